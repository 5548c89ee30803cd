"""Confidence intervals of identified parameters: θ ± z·stderr (`gauss_newton_intervals`), or the
profile likelihood (`profile_intervals`): each parameter held at trial values while everything else
is refitted (`Refit`), the deviance followed out to the χ² quantile on each side
(`profile_bound`), and what the numbers do not say flagged (`_flags`)."""

import dataclasses

import numpy as np
from scipy.stats import chi2

from dano.sysid.lm import Objective, Point, Tolerances, levenberg_marquardt


class Refit:
    """½Σr² minimised over every unknown but θ_k = v (the profile), warm-started from the last
    refit; with θ alone unknown and one parameter, just the loss at v."""

    def __init__(self, best: Point, objective: Objective, only_theta: bool, tol: Tolerances):
        self.best, self.objective, self.only_theta, self.tol = best, objective, only_theta, tol
        self.last: dict = {}

    def __call__(self, k: int, v: float) -> float:
        start = self.last.get((k, v > self.best.y[k]), self.best).y.copy()
        start[k] = v
        if self.only_theta:
            return self.objective.loss_at(start)
        point = Point(start, *self.objective.evaluate(start))
        hold = np.zeros(start.size, bool)
        hold[k] = True
        point, _, _ = levenberg_marquardt(point, self.objective, hold, 20, self.tol)
        self.last[(k, v > self.best.y[k])] = point
        return point.loss


@dataclasses.dataclass(frozen=True)
class ProfileBound:
    """One end of a profile interval: `value`; `at_limit` when the deviance stayed below the
    threshold up to the bound (the interval is cut there); `lowest`, the smallest deviance met on the
    way and `lowest_at` where (negative: the profile found a lower loss than the fit)."""

    value: float
    at_limit: bool
    lowest: float
    lowest_at: float


def profile_bound(deviance, start: float, direction: int, step: float, limit: float, q: float, evals: int = 16):
    """Where the signed root deviance √deviance(v) first reaches `q` going from `start` towards `limit`.

    The root deviance of a well-behaved fit is close to linear in v (|v − start| / stderr), so each
    trial extrapolates to q from the last point inside (growing the step at most 4×), then regula
    falsi (Illinois) on the bracket, to 1 % of q or of the bracket (an end to ~1 % of the interval's
    half-width). A rough profile is handled as it is met: the first crossing counts. `deviance(start)` is taken as 0.
    """
    step = abs(step) if np.isfinite(step) and step > 0 else 1e-3 * max(abs(limit - start), 1e-6)
    clip = (lambda v: max(v, limit)) if direction < 0 else (lambda v: min(v, limit))  # noqa: E731
    inside, z_in = start, 0.0
    lowest, lowest_at = 0.0, start
    v = clip(start + direction * step)
    outside = None
    for _ in range(evals):
        dev = float(deviance(v))
        if dev < lowest:
            lowest, lowest_at = dev, v
        z = float(np.sqrt(max(dev, 0.0)))
        if z >= q:
            outside = (v, z)
            break
        inside, z_in = v, z
        if v == limit:
            return ProfileBound(float(limit), True, lowest, lowest_at)
        grow = 4.0 if z < 0.25 * q else float(np.clip(1.05 * q / z, 1.2, 4.0))
        v = clip(start + (v - start) * grow)
    if outside is None:  # never reached q in `evals` trials: the interval is at least this wide
        return ProfileBound(float(inside), True, lowest, lowest_at)
    v_out, z_out = outside
    f_in, f_out, moved = z_in - q, z_out - q, 0  # f < 0 inside; `moved`: the end replaced last
    for _ in range(evals):
        if abs(v_out - inside) <= 1e-2 * abs(v_out - start):
            break
        v = inside + float(np.clip(f_in / (f_in - f_out), 0.05, 0.95)) * (v_out - inside)
        dev = float(deviance(v))
        if dev < lowest:
            lowest, lowest_at = dev, v
        f = float(np.sqrt(max(dev, 0.0))) - q
        if abs(f) < 1e-2 * q:
            return ProfileBound(float(v), False, lowest, lowest_at)
        if f >= 0:  # Illinois: an end kept twice has its value halved, so the bracket closes from both sides
            v_out, f_out, f_in, moved = v, f, f_in * (0.5 if moved > 0 else 1.0), 1
        else:
            inside, f_in, f_out, moved = v, f, f_out * (0.5 if moved < 0 else 1.0), -1
    v = inside + float(np.clip(f_in / (f_in - f_out), 0.0, 1.0)) * (v_out - inside)
    return ProfileBound(float(v), False, lowest, lowest_at)


def _flags(name: str, estimate: float, stderr: float, q: float, sides: list[ProfileBound]) -> list[str]:
    """What a reader of (estimate, stderr) would get wrong, from the two ends of the profile."""
    out = []
    for side, bound in zip(("low", "high"), sides, strict=True):
        if bound.lowest < -1e-6:
            out.append(
                f"{name}: the profile found a lower loss at {bound.lowest_at:.6g} than at the estimate "
                f"{estimate:.6g}: the fit stopped in a local minimum"
            )
        if bound.at_limit:
            out.append(f"{name}: the {side} end of the interval is cut at {bound.value:.6g} (a bound or the search)")
            continue
        width, gn = abs(bound.value - estimate), q * stderr
        if not (0.5 <= width / max(gn, 1e-300) <= 2.0):
            out.append(
                f"{name}: the Gauss-Newton stderr {stderr:.3g} is {'too small' if width > gn else 'too large'}: "
                f"the profile's {side} end is {width:.3g} from the estimate, {width / max(gn, 1e-300):.3g} times "
                f"the {q:.3g} stderr it predicts; trust the interval"
            )
    return out


Fit = tuple[Objective, Tolerances, int, bool]
"""What a refit needs: the objective, the tolerances, the residuals' count N, and whether θ is the
one unknown (then the profile is the loss itself, no refit)."""


def gauss_newton_intervals(point: Point, fit: Fit, labels, stderr, lo, hi, level: float):
    """θ ± z·stderr at `level`, clipped to the bounds (lo, hi); no flags."""
    q = float(np.sqrt(chi2.ppf(level, 1)))
    intervals = {
        lab: (max(float(t - q * e), float(lo[k])), min(float(t + q * e), float(hi[k])))
        for k, (lab, t, e) in enumerate(zip(labels, point.y[: len(labels)], stderr, strict=True))
    }
    return intervals, []


def profile_intervals(point: Point, fit: Fit, labels, stderr, lo, hi, level: float):
    """Each parameter's profile-likelihood interval at `level` (where ½Σr² refitted with the
    parameter held rises by ½ χ²₁(level) · s², s² the residual variance), and the flags."""
    objective, tol, n_residuals, only_theta = fit
    q = float(np.sqrt(chi2.ppf(level, 1)))
    variance = 2.0 * point.loss / max(n_residuals - point.y.size, 1)
    refit = Refit(point, objective, only_theta=only_theta, tol=tol)
    found, flags = [], []
    for k in range(len(labels)):
        deviance = lambda v, k=k: 2.0 * (refit(k, v) - point.loss) / max(variance, 1e-300)  # noqa: E731
        sides = [profile_bound(deviance, point.y[k], d, q * stderr[k], (lo[k], hi[k])[d > 0], q) for d in (-1, 1)]
        found.append((sides[0].value, sides[1].value))
        flags += _flags(labels[k], point.y[k], stderr[k], q, sides)
    return dict(zip(labels, found, strict=True)), flags
