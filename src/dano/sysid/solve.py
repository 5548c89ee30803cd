"""Projected Levenberg-Marquardt for Problem (17), with exact Jacobians from JAX.

Why not optimistix' `LevenbergMarquardt`: it has no bounds (a sigmoid reparameterisation makes a
parameter at its bound, a friction of 0, unreachable and flattens the loss near it) and it takes
the Jacobian of the whole residual vector with respect to every unknown. With multiple shooting
and fitted initial states the unknowns are θ plus a few per window, and window i's state touches
only window i's residuals: here each window is differentiated forward in θ and its own state only
(`jacfwd` under `vmap`: p + s tangents per window instead of p + n·s), and the normal equations
are assembled from those blocks. `bench/sysid.py` measures both on the same problem.

The iteration is the reference's (dojo-dano.md §9.3.1) made a little more careful: Gauss-Newton
Hessian JᵀJ plus a Marquardt term λ·diag(JᵀJ), the step projected onto the bounds with parameters
held at an active bound dropped from the system, a backtracking (Armijo) line search on the
projected path, λ divided by 3 after a success and multiplied by 10 after a failure.
"""

import dataclasses
import time
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float
from scipy.stats import chi2
from tqdm.auto import tqdm

from dano.results import Result, finish
from dano.sysid.problem import (
    DEFAULT_BOUNDS,
    Problem,
    SysidError,
    canonical,
    current_values,
    over_windows,
    residuals,
    window_residuals,
)


@dataclasses.dataclass(frozen=True)
class Identification:
    """The result of `identify`.

    Attributes:
        params: estimate per parameter, keyed by the names as given.
        stderr: standard error per parameter from the Gauss-Newton Hessian, s² (JᵀJ)⁻¹ with
            s² = Σr² / (N − P) the residual variance (so a wrong `sigma` does not bias it).
        loss: ½ Σ r² at the initial guess and after every accepted iteration (r in units of σ).
        seconds: wall time, JIT compilation included when it happened.
        iterations: accepted iterations.
        result: how it stopped (`dano.results.Result`): `successful` when a stopping test passed,
            `max_steps_reached` at the iteration limit.
        message: which test stopped it.
        theta: (p,) the estimate in `problem.names` order.
        delta: (n, s) the fitted initial-state corrections per window (empty unless fitted).
        rms_position: root mean square position error at the estimate, m (None when fitted to an
            observation other than poses).
        rms_rotation: root mean square rotation error at the estimate, rad (None when the rotation
            residuals were weighted out, `rotation_weight=0`).
        intervals: (low, high) per parameter at `level`: the profile-likelihood interval (refit with
            the parameter held; where the loss rises by the χ² quantile) or θ ± z·stderr clipped to
            the bounds (`interval="gauss-newton"`).
        interval: how `intervals` were found, "profile" or "gauss-newton".
        level: their confidence level.
        flags: what the numbers above do not say: an interval that reaches a bound, a Gauss-Newton
            stderr more than 2× off the profile interval, a lower loss found while profiling.
        adjustments: every change between the data as given and the simulation, by kind
            (`Problem.adjustments`, and `init` clipped into the bounds).
        loss_function: "l2", "huber" or "cauchy" (`robust`).
        rms_observation: the observation's own RMS error when fitted to one (masks: opacity), or None.
    """

    params: dict[str, float]
    stderr: dict[str, float]
    loss: list[float]
    seconds: float
    iterations: int
    result: Result
    message: str
    theta: np.ndarray
    delta: np.ndarray
    rms_position: float | None
    rms_rotation: float | None
    intervals: dict[str, tuple[float, float]]
    interval: str = "gauss-newton"
    level: float = 0.95
    flags: tuple[str, ...] = ()
    adjustments: dict = dataclasses.field(default_factory=dict)
    loss_function: str = "l2"
    rms_observation: float | None = None

    @property
    def converged(self) -> bool:
        return self.result.converged

    def summary(self) -> dict:
        """The `dano sysid --json` object (`dano.results`), with the intervals' method and level, the
        loss history and the flags."""
        from dano.results import result_json

        return result_json(
            params=self.params, stderr=self.stderr, intervals=self.intervals, iterations=self.iterations,
            converged=self.converged, message=self.message, seconds=self.seconds, rms_position=self.rms_position,
            rms_rotation=self.rms_rotation, adjustments=self.adjustments,
            interval={"method": self.interval, "level": self.level}, loss=self.loss, flags=list(self.flags),
            loss_function=self.loss_function, rms_observation=self.rms_observation,
        )  # fmt: skip


ROBUST_SCALE = 2.795
"""σ: where the robust losses start to discount a frame's position (or rotation) error, the 95 %
quantile of the norm of a 3-vector of unit Gaussian noise (√χ²₃(0.95)): inliers keep their weight."""


def robust(r: Float[Array, "... 6"], loss: str, c: float = ROBUST_SCALE) -> Float[Array, "... 6"]:
    """Residuals whose squares sum to the robust loss: each frame's position and rotation error e
    (3-vectors, in σ) scaled by √(ρ(|e|²) / |e|²), so ½Σ|r|² = ½Σρ(|e|²) and Gauss-Newton on r is
    the "square-rooted" robust fit (Triggs et al., Bundle adjustment, §4.3).

    ρ: "l2" u; "huber" u up to c², then 2c√u − c² (linear growth: an outlier pulls with constant
    force); "cauchy" c² log(1 + u/c²) (an outlier's pull fades). Smooth, with the gradient of the
    identity at 0.
    """
    if loss == "l2":
        return r
    e = r.reshape(*r.shape[:-1], 2, 3)
    u = jnp.sum(e * e, axis=-1, keepdims=True)
    small = u < 1e-12 * c * c
    safe = jnp.where(small, c * c, u)  # the double `where`: no NaN gradient at e = 0
    if loss == "huber":
        ratio = jnp.where(u <= c * c, 1.0, (2.0 * c * jnp.sqrt(safe) - c * c) / safe)
    elif loss == "cauchy":
        ratio = jnp.where(small, 1.0, c * c * jnp.log1p(safe / (c * c)) / safe)
    else:
        raise SysidError(f"the loss must be 'l2', 'huber' or 'cauchy', got {loss!r}")
    return (e * jnp.sqrt(ratio)).reshape(r.shape)


def _compiled(problem: Problem, jac: str, loss_name: str = "l2"):
    """(loss, residuals and normal equations) functions of (θ, δ, windows), jitted once per problem
    structure. The residuals returned are the plain ones (for the RMS errors); the loss and the
    normal equations are those of `robust(r, loss_name)`."""
    key = ("fns", jac, loss_name)
    if key in problem.cache:
        return problem.cache[key]

    def loss(theta, delta, windows):
        r = residuals(problem, theta, delta, windows)
        r = r if loss_name == "l2" else robust(r, loss_name)  # robust: pose residuals only
        return 0.5 * jnp.sum(r * r)

    def normal_equations(theta, delta, windows):
        def one(dl, w):
            def f(th, d_):
                plain = window_residuals(problem, th, d_, w).reshape(-1)
                r = plain if loss_name == "l2" else robust(plain.reshape(-1, 6), loss_name).reshape(-1)
                return r, (plain, r)

            if jac == "fwd" and theta.shape[0] + dl.shape[0] == 1:  # one tangent: a jvp, nothing batched
                (r, (plain, _)), (dr, _) = jax.jvp(f, (theta, dl), (jnp.ones_like(theta), jnp.ones_like(dl)))
                column = dr[:, None]
                return plain, r, column[:, : theta.shape[0]], column[:, theta.shape[0] :]
            differentiate = jax.jacfwd if jac == "fwd" else jax.jacrev
            (Jt, Jd), (plain, r) = differentiate(f, argnums=(0, 1), has_aux=True)(theta, dl)
            return plain, r, Jt, Jd

        plain, r, Jt, Jd = over_windows(one, delta, windows)
        return plain, (
            0.5 * jnp.sum(r * r),
            jnp.einsum("nm,nmp->p", r, Jt),
            jnp.einsum("nm,nms->ns", r, Jd),
            jnp.einsum("nmp,nmq->pq", Jt, Jt),
            jnp.einsum("nmp,nms->nps", Jt, Jd),
            jnp.einsum("nms,nmt->nst", Jd, Jd),
        )

    opts = problem.compiler_options
    fns = tuple(jax.jit(f, compiler_options=opts) for f in (loss, normal_equations))
    problem.cache[key] = fns
    return fns


def _assemble(p: int, n: int, s: int, parts) -> tuple[float, np.ndarray, np.ndarray]:
    """Dense loss, gradient (P,) and Hessian (P, P) over y = (θ, δ₁, …, δₙ) from the blocks."""
    loss, g_t, g_d, H_tt, H_td, H_dd = (np.asarray(x) for x in parts)
    P = p + n * s
    H = np.zeros((P, P))
    H[:p, :p] = H_tt
    for i in range(n):
        sl = slice(p + i * s, p + (i + 1) * s)
        H[:p, sl] = H_td[i]
        H[sl, :p] = H_td[i].T
        H[sl, sl] = H_dd[i]
    return float(loss), np.concatenate([g_t, g_d.reshape(-1)]), H


def by_canonical_name(values: dict | None, names, what: str) -> dict:
    """`values` keyed by canonical parameter names (`friction` -> `sliding_friction`); a name that
    is not fitted is an error, not silently ignored (an `init` that names an alias once was)."""
    out: dict = {}
    for key, value in (values or {}).items():
        name = canonical(key)
        if name not in names:
            raise SysidError(f"{what} names {key!r}, which is not fitted (fitting {', '.join(names)})")
        if name in out:
            raise SysidError(f"{what} gives {name!r} twice (as {key!r} and another name)")
        out[name] = value
    return out


def resolve_bounds(names, given: dict | None) -> tuple[np.ndarray, np.ndarray]:
    given = by_canonical_name(given, names, "bounds")
    lo = np.array([given.get(n, DEFAULT_BOUNDS[n])[0] for n in names], dtype=float)
    hi = np.array([given.get(n, DEFAULT_BOUNDS[n])[1] for n in names], dtype=float)
    bad = ~(lo <= hi) | ~np.isfinite(lo) | ~np.isfinite(hi)
    if bad.any():
        k = int(np.argmax(bad))
        raise SysidError(f"bounds for {names[k]!r} must be finite with low <= high, got [{lo[k]}, {hi[k]}]")
    return lo, hi


def initial_guess(problem: Problem, init: dict | None, bounds: dict | None) -> np.ndarray:
    """θ to start from: `init` where given, else the scene's values; clipped into the bounds."""
    return _initial_guess(problem, init, bounds)[0]


def _initial_guess(problem: Problem, init: dict | None, bounds: dict | None) -> tuple[np.ndarray, dict]:
    """`initial_guess` and what clipping changed ({name: {"given", "used"}})."""
    lo, hi = resolve_bounds(problem.names, bounds)
    theta = current_values(problem.params, problem.names)
    init = by_canonical_name(init, problem.names, "init")
    for k, name in enumerate(problem.names):
        if name in init:
            value = float(init[name])
            if not np.isfinite(value):
                raise SysidError(f"the initial guess for {name!r} is not finite")
            theta[k] = value
    clipped = np.clip(theta, lo, hi)
    pairs = zip(problem.names, theta, clipped, strict=True)
    changed = {n: {"given": float(a), "used": float(b)} for n, a, b in pairs if a != b}
    return clipped, changed


def identify(
    problem: Problem,
    init: dict[str, float] | None = None,
    bounds: dict[str, tuple[float, float]] | None = None,
    labels: tuple[str, ...] | None = None,
    max_steps: int = 50,
    gtol: float = 1e-9,
    ftol: float = 1e-3,
    rtol: float = 1e-9,
    xtol: float = 1e-8,
    jac: str = "auto",
    progress: bool = True,
    interval: str = "gauss-newton",
    level: float = 0.95,
    loss: str = "l2",
    throw: bool = False,
) -> Identification:
    """Fits `problem.names` (and the windows' initial states if the problem asks) by projected LM.

    Example:
        >>> problem = make_problem(scene, [Recording({"soap": track})], fit=["friction"], initial="velocity")
        >>> result = identify(problem, init={"sliding_friction": 0.1})
        >>> result.params, result.stderr

    Args:
        init: initial guesses by canonical name (default: the scene's values), clipped into the bounds.
        bounds: (low, high) by canonical name (default `DEFAULT_BOUNDS`); estimates never leave them.
        labels: names to key the result by (default `problem.names`), e.g. as typed by the user.
        max_steps: LM iterations (Jacobian evaluations) at most.
        gtol: stop when the projected gradient's largest entry, relative to the loss, is below this.
        ftol: stop when an accepted step lowers the loss by less than this (r is in units of σ, so
            1e-3 is a change of χ² far inside the estimate's standard error: more steps would
            fit noise, not data).
        rtol: ... or by less than this fraction of it.
        xtol: stop when an accepted step moves every unknown by less than xtol · (|value| + xtol).
        jac: "fwd" (forward mode, one tangent per unknown), "rev" (reverse mode, one cotangent per
            residual of a window), or "auto" (reverse when a window has more unknowns than residuals).
        progress: show a progress bar.
        interval: "gauss-newton" (θ ± z·stderr, free) or "profile": each parameter's profile-likelihood
            interval, where ½Σr² refitted with the parameter held rises by ½ χ²₁(level) · s² (s² the
            residual variance, as in the stderr). It costs about 3 refits per parameter and side, and
            it is honest where the loss is rough, flat or asymmetric: the stderr, a local curvature,
            is flagged where it disagrees with it by more than 2×.
        level: confidence level of the intervals.
        loss: "l2" (least squares), or "huber" or "cauchy" for data with outliers (impacts the model
            misses, tracking failures): see `robust`. The stderr and intervals then follow the
            robust loss as if it were a likelihood (an approximation).
        throw: raise `SolverError` where the fit stops without converging (else it is reported in
            `Identification.result`).

    Raises:
        SysidError: bad settings, or a loss that is not finite at the initial guess.
        SolverError: `throw` and the fit did not converge.
    """
    if interval not in ("gauss-newton", "profile"):
        raise SysidError(f"interval must be 'gauss-newton' or 'profile', got {interval!r}")
    if not 0.0 < level < 1.0:
        raise SysidError(f"the confidence level must be between 0 and 1, got {level}")
    robust(jnp.zeros((1, 6)), loss)  # a bad name is refused before any work
    if loss != "l2" and problem.observation is not None:
        raise SysidError(f"the {loss!r} loss is for pose residuals; a problem fitted to masks uses 'l2'")
    names = problem.names
    labels = names if labels is None else tuple(labels)
    p, n, s = len(names), problem.n_windows, problem.n_state
    lo, hi = resolve_bounds(names, bounds)
    theta, clipped = _initial_guess(problem, init, bounds)
    adjustments = {**problem.adjustments, **({"init_clipped_to_bounds": clipped} if clipped else {})}
    y = np.concatenate([theta, np.zeros(n * s)])
    s_lo, s_hi = problem.state_bounds()
    y_lo = np.concatenate([lo, s_lo.reshape(-1)])
    y_hi = np.concatenate([hi, s_hi.reshape(-1)])
    if jac == "auto":
        per_window = problem.n_residuals / max(n, 1)
        jac = "rev" if p + s > per_window else "fwd"
    loss_fn, normal_fn = _compiled(problem, jac, loss)

    def split(y):
        return jnp.asarray(y[:p]), jnp.asarray(y[p:].reshape(n, s))

    def evaluate(y):
        r, parts = normal_fn(*split(y), problem.windows)
        return (r, *_assemble(p, n, s, parts))

    start = time.perf_counter()
    point = _Point(y, *evaluate(y))
    if not np.isfinite(point.loss):
        raise SysidError("the loss is not finite at the initial guess: the simulation blows up there")
    history = [point.loss]
    bar = tqdm(total=max_steps, desc="sysid", disable=None if progress else True, leave=False)
    tol = _Tolerances(gtol, ftol, rtol, xtol)
    objective = _Objective(evaluate, lambda y: float(loss_fn(*split(y), problem.windows)), y_lo, y_hi)
    result, message = Result.max_steps_reached, ""
    # Stage 1 fits θ with the initial states held as read from the data; stage 2 frees them. From a
    # poor θ, fitting states at once can wander into a wrong basin (e.g. a fast spin that mimics low
    # friction); started from stage 1's θ the joint fit stays in the right one.
    stages = [np.arange(y.size) >= p, np.zeros(y.size, bool)] if s else [np.zeros(y.size, bool)]
    for hold in stages:
        point, result, message = _levenberg_marquardt(
            point, objective, hold, max_steps - (len(history) - 1), tol, _logger(history, bar)
        )
    bar.close()
    finish(result, f"identification {result.value}: {message}", throw)
    stderr = _stderr(point.H, point.loss, problem, p)
    q = float(np.sqrt(chi2.ppf(level, 1)))
    flags: list[str] = []
    if interval == "profile":
        variance = 2.0 * point.loss / max(problem.n_residuals - y.size, 1)
        refit = _Refit(point, objective, only_theta=s == 0 and p == 1, tol=tol)
        bounds_found = []
        for k in range(p):
            deviance = lambda v, k=k: 2.0 * (refit(k, v) - point.loss) / max(variance, 1e-300)  # noqa: E731
            sides = [profile_bound(deviance, point.y[k], d, q * stderr[k], (lo[k], hi[k])[d > 0], q) for d in (-1, 1)]
            bounds_found.append((sides[0].value, sides[1].value))
            flags += _flags(labels[k], point.y[k], stderr[k], q, sides)
        intervals = dict(zip(labels, bounds_found, strict=True))
    else:
        intervals = {
            lab: (max(float(t - q * e), float(lo[k])), min(float(t + q * e), float(hi[k])))
            for k, (lab, t, e) in enumerate(zip(labels, point.y[:p], stderr, strict=True))
        }
    seconds = time.perf_counter() - start
    theta, delta = point.y[:p], point.y[p:].reshape(n, s)
    return Identification(
        params={lab: float(v) for lab, v in zip(labels, theta, strict=True)},
        stderr=dict(zip(labels, stderr, strict=True)),
        loss=history, seconds=seconds, iterations=len(history) - 1, result=result, message=message,
        theta=theta, delta=delta, **_rms(problem, np.asarray(point.r)),  # pyright: ignore[reportArgumentType]
        intervals=intervals, interval=interval, level=level, flags=tuple(flags), adjustments=adjustments,
        loss_function=loss,
    )  # fmt: skip


class _Refit:
    """½Σr² minimised over every unknown but θ_k = v (the profile), warm-started from the last
    refit; with θ alone unknown and one parameter, just the loss at v."""

    def __init__(self, best: "_Point", objective: "_Objective", only_theta: bool, tol: "_Tolerances"):
        self.best, self.objective, self.only_theta, self.tol = best, objective, only_theta, tol
        self.last: dict = {}

    def __call__(self, k: int, v: float) -> float:
        start = self.last.get((k, v > self.best.y[k]), self.best).y.copy()
        start[k] = v
        if self.only_theta:
            return self.objective.loss_at(start)
        point = _Point(start, *self.objective.evaluate(start))
        hold = np.zeros(start.size, bool)
        hold[k] = True
        point, _, _ = _levenberg_marquardt(point, self.objective, hold, 20, self.tol, lambda point: None)
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


@dataclasses.dataclass(frozen=True)
class _Point:
    """An iterate: unknowns y, residuals r, loss ½|r|², gradient g = Jᵀr and Hessian H = JᵀJ."""

    y: np.ndarray
    r: object
    loss: float
    g: np.ndarray
    H: np.ndarray


class _Objective(NamedTuple):
    """The loss as LM sees it: `evaluate(y)` -> (r, loss, g, H); `loss_at(y)` the loss alone; the
    bounds (y_lo, y_hi) the unknowns never leave."""

    evaluate: Callable
    loss_at: Callable[[np.ndarray], float]
    y_lo: np.ndarray
    y_hi: np.ndarray


class _Tolerances(NamedTuple):
    """`identify`'s stopping tests (see its docstring)."""

    gtol: float
    ftol: float
    rtol: float
    xtol: float


def _logger(history: list[float], bar) -> Callable[["_Point"], None]:
    """Records an accepted iterate's loss and shows it."""

    def log(point: "_Point") -> None:
        history.append(point.loss)
        bar.update(1)
        bar.set_postfix(loss=f"{point.loss:.4g}")

    return log


def _levenberg_marquardt(
    point: _Point, objective: _Objective, hold: np.ndarray, max_steps: int, tol: _Tolerances, log: Callable
) -> tuple[_Point, Result, str]:
    """Projected LM iterations from `point` with the unknowns in `hold` fixed; `log` sees every
    accepted iterate. Returns the last iterate, how it stopped and which test stopped it."""
    lam = 1e-3
    y_lo, y_hi = objective.y_lo, objective.y_hi
    for _ in range(max(max_steps, 0)):
        y, g = point.y, point.g
        free = ~(hold | (y <= y_lo) & (g > 0) | (y >= y_hi) & (g < 0))
        if np.max(np.abs(g[free]), initial=0.0) <= tol.gtol * max(point.loss, 1e-300):
            return point, Result.successful, "gradient below gtol"
        accepted = False
        while not accepted and lam < 1e12:
            step = _lm_step(point.H, g, free, lam)
            for alpha in (1.0, 1 / 3, 1 / 9, 1 / 27):
                y_try = np.clip(y + alpha * step, y_lo, y_hi)
                loss_try = objective.loss_at(y_try)
                if np.isfinite(loss_try) and loss_try <= point.loss + 1e-4 * g @ (y_try - y):
                    accepted = True
                    break
            lam = lam / 3 if accepted else lam * 10
        if not accepted:
            return point, Result.successful, "no decrease along the LM direction (a minimum to working precision)"
        previous = point
        point = _Point(y_try, *objective.evaluate(y_try))
        log(point)
        if previous.loss - point.loss <= max(tol.rtol * previous.loss, tol.ftol):
            return point, Result.successful, "loss decrease below ftol"
        if np.all(np.abs(y_try - y) <= tol.xtol * (np.abs(y_try) + tol.xtol)):
            return point, Result.successful, "step below xtol"
    return point, Result.max_steps_reached, "iteration limit"


def _lm_step(H: np.ndarray, g: np.ndarray, free: np.ndarray, lam: float) -> np.ndarray:
    """Solves (H + λ diag H) Δ = −g over the free unknowns (the others stay put)."""
    Hf = H[np.ix_(free, free)]
    d = np.diag(Hf).copy()
    d = np.maximum(d, 1e-12 * max(float(np.max(d, initial=0.0)), 1e-300))
    step = np.zeros_like(g)
    try:
        step[free] = np.linalg.solve(Hf + lam * np.diag(d), -g[free])
    except np.linalg.LinAlgError:
        step[free] = -np.linalg.lstsq(Hf + lam * np.diag(d), g[free], rcond=None)[0]
    return step


def _stderr(H: np.ndarray, loss: float, problem: Problem, p: int) -> list[float]:
    dof = max(problem.n_residuals - H.shape[0], 1)
    variance = 2.0 * loss / dof
    cov = variance * np.linalg.pinv(H, hermitian=True)
    return [float(np.sqrt(max(cov[k, k], 0.0))) for k in range(p)]


def _rms(problem: Problem, r: np.ndarray) -> dict[str, float | None]:
    if problem.observation is not None:  # no poses to compare with: the observation's own RMS
        rms = problem.observation.rms(r.reshape(problem.n_windows, problem.n_frames, -1), problem.windows)
        return {"rms_position": None, "rms_rotation": None, "rms_observation": rms}
    r = r.reshape(problem.windows.target_pos.shape[:3] + (6,)) * problem.sigma
    mask = np.asarray(problem.windows.mask) > 0
    free = np.array([o.kind == "free" and o.weight > 0 for o in problem.observed])
    scale = np.array([o.length * o.weight for o in problem.observed])
    pos = r[..., :3][mask]
    rot = r[..., 3:][mask][:, free] / scale[free][None, :, None]
    no_rotation = not free.any() and any(o.kind == "free" for o in problem.observed)  # weighted out: unknown
    return {
        "rms_position": float(np.sqrt(np.mean(np.sum(pos**2, axis=-1)))),
        "rms_rotation": None if no_rotation else float(np.sqrt(np.mean(np.sum(rot**2, axis=-1)))) if rot.size else 0.0,
    }
