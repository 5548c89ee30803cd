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

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from dano.sysid.problem import (
    DEFAULT_BOUNDS,
    Problem,
    SysidError,
    canonical,
    current_values,
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
        converged: a stopping test passed (not the iteration limit or a stalled line search).
        message: which test stopped it.
        theta: (p,) the estimate in `problem.names` order.
        delta: (n, s) the fitted initial-state corrections per window (empty unless fitted).
        rms_position: root mean square position error at the estimate, m.
        rms_rotation: root mean square rotation error at the estimate, rad (None when the rotation
            residuals were weighted out, `rotation_weight=0`).
    """

    params: dict[str, float]
    stderr: dict[str, float]
    loss: list[float]
    seconds: float
    iterations: int
    converged: bool
    message: str
    theta: np.ndarray
    delta: np.ndarray
    rms_position: float
    rms_rotation: float | None

    def summary(self) -> dict:
        """The `dano sysid --json` object: estimates and standard errors keyed by the names as given,
        the loss history, iterations, whether and why it stopped, the RMS errors (position in m,
        rotation in rad) and the wall time."""
        return {
            "params": self.params, "stderr": self.stderr, "loss": self.loss, "iterations": self.iterations,
            "converged": self.converged, "message": self.message,
            "rms": {"position": self.rms_position, "rotation": self.rms_rotation}, "seconds": self.seconds,
        }  # fmt: skip


def _compiled(problem: Problem, jac: str):
    """(loss, residuals and normal equations) functions of (θ, δ, windows), jitted once per problem structure."""
    key = ("fns", jac)
    if key in problem.cache:
        return problem.cache[key]

    def loss(theta, delta, windows):
        r = residuals(problem, theta, delta, windows)
        return 0.5 * jnp.sum(r * r)

    def normal_equations(theta, delta, windows):
        def one(dl, w):
            def f(th, d_):
                r = window_residuals(problem, th, d_, w).reshape(-1)
                return r, r

            differentiate = jax.jacfwd if jac == "fwd" else jax.jacrev
            (Jt, Jd), r = differentiate(f, argnums=(0, 1), has_aux=True)(theta, dl)
            return r, Jt, Jd

        r, Jt, Jd = jax.vmap(one)(delta, windows)
        return r, (
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
    lo, hi = resolve_bounds(problem.names, bounds)
    theta = current_values(problem.params, problem.names)
    init = by_canonical_name(init, problem.names, "init")
    for k, name in enumerate(problem.names):
        if name in init:
            value = float(init[name])
            if not np.isfinite(value):
                raise SysidError(f"the initial guess for {name!r} is not finite")
            theta[k] = value
    return np.clip(theta, lo, hi)


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
    """
    names = problem.names
    labels = names if labels is None else tuple(labels)
    p, n, s = len(names), problem.n_windows, problem.n_state
    lo, hi = resolve_bounds(names, bounds)
    theta = initial_guess(problem, init, bounds)
    y = np.concatenate([theta, np.zeros(n * s)])
    s_lo, s_hi = problem.state_bounds()
    y_lo = np.concatenate([lo, s_lo.reshape(-1)])
    y_hi = np.concatenate([hi, s_hi.reshape(-1)])
    if jac == "auto":
        per_window = problem.n_residuals / max(n, 1)
        jac = "rev" if p + s > per_window else "fwd"
    loss_fn, normal_fn = _compiled(problem, jac)

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
    tolerances = dict(gtol=gtol, ftol=ftol, rtol=rtol, xtol=xtol)
    loss_at = lambda y: float(loss_fn(*split(y), problem.windows))  # noqa: E731
    message, converged = "", False
    # Stage 1 fits θ with the initial states held as read from the data; stage 2 frees them. From a
    # poor θ, fitting states at once can wander into a wrong basin (e.g. a fast spin that mimics low
    # friction); started from stage 1's θ the joint fit stays in the right one.
    stages = [np.arange(y.size) >= p, np.zeros(y.size, bool)] if s else [np.zeros(y.size, bool)]
    for hold in stages:
        point, message, converged = _levenberg_marquardt(
            point, evaluate, loss_at, y_lo, y_hi, hold, max_steps - (len(history) - 1), history, bar, **tolerances
        )
    bar.close()
    seconds = time.perf_counter() - start
    theta, delta = point.y[:p], point.y[p:].reshape(n, s)
    return Identification(
        params={lab: float(v) for lab, v in zip(labels, theta, strict=True)},
        stderr=dict(zip(labels, _stderr(point.H, point.loss, problem, p), strict=True)),
        loss=history, seconds=seconds, iterations=len(history) - 1, converged=converged, message=message,
        theta=theta, delta=delta, **_rms(problem, np.asarray(point.r)),  # pyright: ignore[reportArgumentType]
    )  # fmt: skip


@dataclasses.dataclass(frozen=True)
class _Point:
    """An iterate: unknowns y, residuals r, loss ½|r|², gradient g = Jᵀr and Hessian H = JᵀJ."""

    y: np.ndarray
    r: object
    loss: float
    g: np.ndarray
    H: np.ndarray


def _levenberg_marquardt(point, evaluate, loss_at, y_lo, y_hi, hold, max_steps, history, bar, gtol, ftol, rtol, xtol):
    """Projected LM iterations from `point` with the unknowns in `hold` fixed; appends to `history`."""
    lam = 1e-3
    for _ in range(max(max_steps, 0)):
        y, g = point.y, point.g
        free = ~(hold | (y <= y_lo) & (g > 0) | (y >= y_hi) & (g < 0))
        if np.max(np.abs(g[free]), initial=0.0) <= gtol * max(point.loss, 1e-300):
            return point, "gradient below gtol", True
        accepted = False
        while not accepted and lam < 1e12:
            step = _lm_step(point.H, g, free, lam)
            for alpha in (1.0, 1 / 3, 1 / 9, 1 / 27):
                y_try = np.clip(y + alpha * step, y_lo, y_hi)
                loss_try = loss_at(y_try)
                if np.isfinite(loss_try) and loss_try <= point.loss + 1e-4 * g @ (y_try - y):
                    accepted = True
                    break
            lam = lam / 3 if accepted else lam * 10
        if not accepted:
            return point, "no decrease along the LM direction (a minimum to working precision)", True
        previous = point
        point = _Point(y_try, *evaluate(y_try))
        history.append(point.loss)
        bar.update(1)
        bar.set_postfix(loss=f"{point.loss:.4g}")
        if previous.loss - point.loss <= max(rtol * previous.loss, ftol):
            return point, "loss decrease below ftol", True
        if np.all(np.abs(y_try - y) <= xtol * (np.abs(y_try) + xtol)):
            return point, "step below xtol", True
    return point, "iteration limit", False


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
