"""Identification (paper Problem (17)) by projected Levenberg-Marquardt, with exact Jacobians from JAX.

Why not optimistix' `LevenbergMarquardt`: it has no bounds (a sigmoid reparameterisation makes a
parameter at its bound, a friction of 0, unreachable and flattens the loss near it) and it takes
the Jacobian of the whole residual vector with respect to every unknown. With multiple shooting
and fitted initial states the unknowns are θ plus a few per window, and window i's state touches
only window i's residuals: here each window is differentiated forward in θ and its own state only
(`dano.sysid.objective`), and the normal equations are assembled from those blocks. The iteration
is `dano.sysid.lm`; the intervals `dano.sysid.intervals`. `bench/sysid.py` measures both Jacobian
modes on the same problem.
"""

import dataclasses
import time

import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from dano import validate as V
from dano.results import AbstractSolution, Result, finish
from dano.sysid.configs import Interval, SysidError
from dano.sysid.intervals import gauss_newton_intervals, profile_intervals
from dano.sysid.lm import Objective, Point, Tolerances, levenberg_marquardt, logger
from dano.sysid.objective import Jacobian, Loss, assemble, compiled
from dano.sysid.params import DEFAULT_BOUNDS, canonical, current_values
from dano.sysid.problem import Problem


@dataclasses.dataclass(frozen=True)
class Identification(AbstractSolution):
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
    interval: Interval = Interval.gauss_newton
    level: float = 0.95
    flags: tuple[str, ...] = ()
    adjustments: dict = dataclasses.field(default_factory=dict)
    loss_function: Loss = Loss.l2
    rms_observation: float | None = None

    @property
    def value(self) -> dict[str, float]:
        """The estimate, `params`."""
        return self.params

    @property
    def stats(self) -> dict[str, float | int]:
        return super().stats | {"loss": self.loss[-1]}

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
    jac: Jacobian | str = Jacobian.auto,
    progress: bool = True,
    interval: Interval | str = Interval.gauss_newton,
    level: float = 0.95,
    loss: Loss | str = Loss.l2,
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
    interval = V.option(interval, "interval", SysidError, Interval)
    jac = V.option(jac, "jac", SysidError, Jacobian)
    loss = V.option(loss, "the loss", SysidError, Loss)
    if not 0.0 < level < 1.0:
        raise SysidError(f"the confidence level must be between 0 and 1, got {level}")
    if loss != "l2" and problem.observation is not None:
        raise SysidError(f"the {loss!r} loss is for pose residuals; a problem fitted to masks uses 'l2'")
    names = problem.names
    labels = names if labels is None else tuple(labels)
    p, n, s = len(names), problem.n_windows, problem.n_state
    lo, hi = resolve_bounds(names, bounds)
    theta, clipped = _initial_guess(problem, init, bounds)
    adjustments = {**problem.adjustments, **({"init_clipped_to_bounds": clipped} if clipped else {})}
    objective = _objective(problem, lo, hi, jac, loss)
    start = time.perf_counter()
    y = np.concatenate([theta, np.zeros(n * s)])
    point = Point(y, *objective.evaluate(y))
    if not np.isfinite(point.loss):
        raise SysidError("the loss is not finite at the initial guess: the simulation blows up there")
    tol = Tolerances(gtol, ftol, rtol, xtol)
    point, result, message, history = _staged(point, objective, p, s, max_steps, tol, progress)
    finish(result, f"identification {result.value}: {message}", throw)
    stderr = _stderr(point.H, point.loss, problem, p)
    fit = objective, tol, problem.n_residuals, s == 0 and p == 1
    intervals, flags = (profile_intervals if interval == Interval.profile else gauss_newton_intervals)(
        point, fit, labels, stderr, lo, hi, level
    )
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


def _objective(problem: Problem, lo: np.ndarray, hi: np.ndarray, jac: Jacobian, loss: Loss) -> Objective:
    """The loss over every unknown y = (θ, the windows' initial-state corrections δ), as LM sees it:
    its residuals and normal equations, the loss alone, and the bounds of y."""
    p, n, s = len(problem.names), problem.n_windows, problem.n_state
    s_lo, s_hi = problem.state_bounds()
    y_lo = np.concatenate([lo, s_lo.reshape(-1)])
    y_hi = np.concatenate([hi, s_hi.reshape(-1)])
    if jac == Jacobian.auto:
        per_window = problem.n_residuals / max(n, 1)
        jac = Jacobian.rev if p + s > per_window else Jacobian.fwd
    loss_fn, normal_fn = compiled(problem, jac, loss)

    def split(y):
        return jnp.asarray(y[:p]), jnp.asarray(y[p:].reshape(n, s))

    def evaluate(y):
        r, parts = normal_fn(*split(y), problem.windows)
        return (r, *assemble(p, n, s, parts))

    return Objective(evaluate, lambda y: float(loss_fn(*split(y), problem.windows)), y_lo, y_hi)


def _staged(
    point: Point, objective: Objective, p: int, s: int, max_steps: int, tol: Tolerances, progress: bool
) -> tuple[Point, Result, str, list[float]]:
    """LM from `point` in two stages: θ with the initial states held as read from the data, then
    everything. From a poor θ, fitting states at once can wander into a wrong basin (e.g. a fast
    spin that mimics low friction); started from stage 1's θ the joint fit stays in the right one.
    Returns the last iterate, how and why it stopped, and the loss history."""
    history = [point.loss]
    result, message = Result.max_steps_reached, ""
    size = point.y.size
    stages = [np.arange(size) >= p, np.zeros(size, bool)] if s else [np.zeros(size, bool)]
    with tqdm(total=max_steps, desc="sysid", disable=None if progress else True, leave=False) as bar:
        for hold in stages:
            point, result, message = levenberg_marquardt(
                point, objective, hold, max_steps - (len(history) - 1), tol, logger(history, bar)
            )
    return point, result, message, history


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
