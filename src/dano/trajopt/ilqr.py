"""Constrained iLQR: augmented-Lagrangian iLQR in the style of ALTRO (Howell, Jackson & Manchester 2019).

Problem, for a horizon of T steps from a given x₀:

    minimise    Σₜ ℓ(xₜ, uₜ, t) + ℓ_T(x_T)
    subject to  xₜ₊₁ = f(xₜ, uₜ, t)
                c(xₜ, uₜ, t) ≤ 0        t = 0 … T−1   (state and input limits)
                h(x_T) = 0                              (goal)

The outer loop adds to the cost the augmented-Lagrangian terms λᵀc + ½ ρ‖c‖² (inequalities, only
where active: c > 0 or λ > 0) and νᵀh + ½ ρ‖h‖², solves that by iLQR, then updates the multipliers
λ ← max(0, λ + ρ c), ν ← ν + ρ h and raises ρ until the largest violation is below the tolerance.

The inner iLQR: the dynamics linearised by `jax.jacfwd` (vmapped over time), the cost expanded to
second order by `jax.hessian` and the Lagrangian terms by Gauss-Newton (ρ CᵀC, C the active
constraints' Jacobian); a Riccati backward pass with Levenberg regularisation of
Q_uu (raised when Q_uu is not positive definite or a step fails, lowered after a good one); a
backtracking line search on the closed-loop rollout accepting a step when the cost falls by a
fraction of the quadratic model's prediction.

Every piece is jitted once per problem (`compiled`, shared by every solve of it); the loops run in
Python so a progress bar can follow them.
"""

import dataclasses
import functools
import time
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from dano.errors import DanoError
from dano.results import Result, finish


class TrajoptError(DanoError):
    """A trajectory optimisation problem that cannot be set up as asked."""


@dataclasses.dataclass(frozen=True, eq=False)
class OptimalControlProblem:
    """x' = f(x, u, t) with costs and constraints (see the module docstring); all pure JAX functions.
    Hashed by identity: its compiled pieces are kept per problem (`compiled`).

    Attributes:
        dynamics: f(x (n,), u (m,), t) -> (n,).
        cost: ℓ(x, u, t) -> scalar, t = 0 … T-1.
        terminal_cost: ℓ_T(x) -> scalar.
        horizon: T.
        constraints: c(x, u, t) -> (p,), feasible where ≤ 0; or None.
        terminal_constraints: h(x) -> (q,), feasible where = 0; or None.
        compiler_options: XLA options for jitting the solver's pieces, e.g.
            `dano.sim.run.compiler_options(world)`: the same as the forward simulator's, so that an
            open-loop replay there repeats the optimiser's arithmetic.
    """

    dynamics: Callable
    cost: Callable
    terminal_cost: Callable
    horizon: int
    constraints: Callable | None = None
    terminal_constraints: Callable | None = None
    compiler_options: dict | None = None


@dataclasses.dataclass(frozen=True)
class Options:
    """Solver settings.

    Attributes:
        max_iterations: iLQR iterations in all (inner iterations summed over outer ones).
        max_outer: augmented-Lagrangian updates.
        constraint_tol: largest constraint violation accepted at a solution.
        cost_tol: an inner solve stops when the cost falls by less than this fraction.
        gradient_tol: ... or when the feedforward step is this small relative to the controls.
        penalty: initial ρ; `penalty_scale` multiplies it at each update, up to `penalty_max`.
        regularization: initial Levenberg term on Q_uu, kept in [reg_min, reg_max].
        line_search: step sizes tried, largest first; `armijo`: accepted fraction of the predicted decrease.
        jacobian_batch: time steps whose dynamics Jacobians are taken together (`jax.lax.map`'s
            batch size); None: all at once (`jax.vmap`). Vmapping a long simulated step over time
            turns its branches into selects and its loops into the longest one; for a robot arm in
            contact, one step at a time (1) is the fast choice.
    """

    max_iterations: int = 300
    max_outer: int = 12
    constraint_tol: float = 1e-4
    cost_tol: float = 1e-4
    gradient_tol: float = 1e-5
    penalty: float = 10.0
    penalty_scale: float = 10.0
    penalty_max: float = 1e9
    regularization: float = 1e-6
    reg_min: float = 1e-9
    reg_max: float = 1e8
    line_search: tuple[float, ...] = (1.0, 0.5, 0.25, 0.125, 0.0625, 0.03125, 0.015625, 0.0078125)
    armijo: float = 1e-4
    jacobian_batch: int | None = None


@dataclasses.dataclass(frozen=True)
class Solution:
    """What `solve` found.

    Attributes:
        states: (T+1, n); controls: (T, m).
        cost: the objective ∑ℓ + ℓ_T at the solution (without the Lagrangian terms).
        max_violation: the largest constraint violation (inequality excess or |h|).
        result: how it stopped (`dano.results.Result`): `successful` when the constraints are
            within tolerance and the last inner solve converged.
        message: why it stopped, in words, with the figures.
        iterations: iLQR iterations in all; outer: multiplier updates.
        seconds: wall time (JIT compilation included).
        history: per iteration (cost, max violation, accepted step size or 0, regularisation).
        multipliers: λ (T, p) and ν (q,) at the end.
    """

    states: np.ndarray
    controls: np.ndarray
    cost: float
    max_violation: float
    result: Result
    message: str
    iterations: int
    outer: int
    seconds: float
    history: list[tuple[float, float, float, float]]
    multipliers: tuple[np.ndarray, np.ndarray]

    @property
    def converged(self) -> bool:
        return self.result.converged


class _Iterate(NamedTuple):
    """The inner loop's state: states (T+1, n), controls (T, m), the regularisation, iterations so far."""

    xs: Array
    us: Array
    reg: float
    iterations: int


class _Multipliers(NamedTuple):
    """The augmented Lagrangian's λ (T, p), ν (q,) and penalty ρ."""

    lam: Array
    nu: Array
    rho: float


def rollout(problem: OptimalControlProblem, x0: Float[Array, " n"], controls: Float[Array, "T m"]) -> Array:
    """States (T+1, n) of the open-loop controls from x0."""

    def step(x, ut):
        u, t = ut
        x_next = problem.dynamics(x, u, t)
        return x_next, x_next

    _, xs = jax.lax.scan(step, x0, (controls, jnp.arange(problem.horizon)))
    return jnp.concatenate([x0[None], xs], axis=0)


def _width(fn, *args) -> int:
    """Length of the vector `fn(*args)` returns (0 for no function), without evaluating it."""
    return 0 if fn is None else int(jax.eval_shape(fn, *args).shape[0])


@functools.lru_cache(maxsize=8)
def compiled(problem: OptimalControlProblem, n: int, m: int) -> "_Compiled":
    """The jitted pieces of `problem` for states of size n and controls of size m, built once per
    problem: a warm start's rollouts and every later `solve` of the same problem share them (and
    their compiled programs)."""
    return _Compiled(problem, n, m)


@dataclasses.dataclass(frozen=True, eq=False)
class _Pieces:
    """A problem's functions as the solver's pieces use them: constraints that are empty vectors
    where the problem has none, the time indices, the state and control sizes."""

    problem: OptimalControlProblem
    c: Callable  # c(x, u, t) -> (p,)
    h: Callable  # h(x) -> (q,)
    ts: Array  # (T,)
    n: int
    m: int

    def running(self, x, u, t, lam, rho, active):
        c = self.c(x, u, t)
        return self.problem.cost(x, u, t) + lam @ c + 0.5 * rho * jnp.sum(active * c**2)

    def terminal(self, x, nu, rho):
        h = self.h(x)
        return self.problem.terminal_cost(x) + nu @ h + 0.5 * rho * h @ h

    def constraints(self, xs, us):
        return jax.vmap(self.c)(xs[:-1], us, self.ts)


def _active_set(c, lam):
    return ((c > 0) | (lam > 0)).astype(c.dtype)


def _objective(f: _Pieces, xs, us):
    """∑ℓ + ℓ_T, without the Lagrangian terms."""
    return jnp.sum(jax.vmap(f.problem.cost)(xs[:-1], us, f.ts)) + f.problem.terminal_cost(xs[-1])


def _violation(f: _Pieces, xs, us):
    """The largest violation (inequality excess or |h|), and c (T, p), h (q,)."""
    c = f.constraints(xs, us)
    h = f.h(xs[-1])
    worst_c = jnp.max(jnp.maximum(c, 0.0), initial=0.0)
    worst_h = jnp.max(jnp.abs(h), initial=0.0)
    return jnp.maximum(worst_c, worst_h), c, h


def _augmented(f: _Pieces, xs, us, lam, nu, rho):
    """The augmented-Lagrangian cost."""
    active = _active_set(f.constraints(xs, us), lam)
    run = jax.vmap(f.running, in_axes=(0, 0, 0, 0, None, 0))(xs[:-1], us, f.ts, lam, rho, active)
    return jnp.sum(run) + f.terminal(xs[-1], nu, rho)


def _expand(f: _Pieces, xs, us, lam, nu, rho, jacobian_batch):
    """Dynamics Jacobians and the augmented cost's gradients and Hessians along (xs, us)."""
    problem, n, ts = f.problem, f.n, f.ts
    jac = jax.jacfwd(problem.dynamics, argnums=(0, 1))
    if jacobian_batch is None:
        A, B = jax.vmap(jac)(xs[:-1], us, ts)
    else:
        batch = None if jacobian_batch == 1 else jacobian_batch  # 1: a plain scan, branches kept
        A, B = jax.lax.map(lambda a: jac(*a), (xs[:-1], us, ts), batch_size=batch)
    c = f.constraints(xs, us)
    active = _active_set(c, lam)
    z = jnp.concatenate([xs[:-1], us], axis=1)

    def cost_z(zt, t):
        return problem.cost(zt[:n], zt[n:], t)

    def c_z(zt, t):
        return f.c(zt[:n], zt[n:], t)

    # The Lagrangian terms to first order in c (Gauss-Newton, as ALTRO): their Hessian is
    # rho C^T C over the active rows. Their exact Hessian adds (lam + rho c) * c'', which is
    # indefinite for a nonlinear constraint (a link's height, a torque through the state)
    # and would be met only by regularisation so large that the step vanishes.
    C = jax.vmap(jax.jacfwd(c_z))(z, ts)  # (T, p, n + m)
    g = jax.vmap(jax.grad(cost_z))(z, ts) + jnp.einsum("tpz,tp->tz", C, lam + rho * active * c)
    H = jax.vmap(jax.hessian(cost_z))(z, ts) + rho * jnp.einsum("tpz,tp,tpy->tzy", C, active, C)
    h = f.h(xs[-1])
    Ch = jax.jacfwd(f.h)(xs[-1])  # (q, n)
    gT = jax.grad(problem.terminal_cost)(xs[-1]) + Ch.T @ (nu + rho * h)
    HT = jax.hessian(problem.terminal_cost)(xs[-1]) + rho * Ch.T @ Ch
    return A, B, g, H, gT, HT


def _backward(f: _Pieces, A, B, g, H, gT, HT, reg):
    """Riccati recursion; returns gains, the predicted decrease terms and a failure flag."""
    n, m = f.n, f.m

    def step(carry, inputs):
        Vx, Vxx, failed = carry
        A_t, B_t, g_t, H_t = inputs
        Qx = g_t[:n] + A_t.T @ Vx
        Qu = g_t[n:] + B_t.T @ Vx
        Qxx = H_t[:n, :n] + A_t.T @ Vxx @ A_t
        Quu = H_t[n:, n:] + B_t.T @ Vxx @ B_t
        Qux = H_t[n:, :n] + B_t.T @ Vxx @ A_t
        Quu_reg = Quu + reg * jnp.eye(m)
        L = jnp.linalg.cholesky(0.5 * (Quu_reg + Quu_reg.T))
        bad = ~jnp.all(jnp.isfinite(L))
        solve = lambda r: jax.scipy.linalg.cho_solve((L, True), r)  # noqa: E731
        k = -solve(Qu)
        K = -solve(Qux)
        Vx = Qx + K.T @ Quu @ k + K.T @ Qu + Qux.T @ k
        Vxx = Qxx + K.T @ Quu @ K + K.T @ Qux + Qux.T @ K
        Vxx = 0.5 * (Vxx + Vxx.T)
        dV = jnp.stack([k @ Qu, 0.5 * k @ Quu @ k])
        return (Vx, Vxx, failed | bad), (k, K, dV)

    (_, _, failed), (k, K, dV) = jax.lax.scan(step, (gT, HT, jnp.zeros((), bool)), (A, B, g, H), reverse=True)
    failed = failed | ~jnp.all(jnp.isfinite(k)) | ~jnp.all(jnp.isfinite(K))
    return k, K, jnp.sum(dV, axis=0), failed


def _forward(f: _Pieces, xs, us, k, K, alpha):
    """The closed-loop rollout u = ū + α k + K (x − x̄)."""

    def step(x, inputs):
        x_ref, u_ref, k_t, K_t, t = inputs
        u = u_ref + alpha * k_t + K_t @ (x - x_ref)
        x_next = f.problem.dynamics(x, u, t)
        return x_next, (x_next, u)

    _, (x_new, u_new) = jax.lax.scan(step, xs[0], (xs[:-1], us, k, K, f.ts))
    return jnp.concatenate([xs[:1], x_new], axis=0), u_new


class _Compiled:
    """The jitted pieces of one problem (built once; shapes fixed by x0 and the controls)."""

    def __init__(self, problem: OptimalControlProblem, n: int, m: int):
        T = problem.horizon
        self.p = _width(problem.constraints, jnp.zeros(n), jnp.zeros(m), 0)
        self.q = _width(problem.terminal_constraints, jnp.zeros(n))
        given_c, given_h = problem.constraints, problem.terminal_constraints  # not None where p, q > 0
        c_fn = given_c if self.p and given_c is not None else (lambda x, u, t: jnp.zeros(0))
        h_fn = given_h if self.q and given_h is not None else (lambda x: jnp.zeros(0))
        f = _Pieces(problem, c_fn, h_fn, jnp.arange(T), n, m)

        def jit(fn, **kw):
            return jax.jit(functools.partial(fn, f), compiler_options=problem.compiler_options, **kw)

        self.objective = jit(_objective)
        self.violation = jit(_violation)
        self.augmented = jit(_augmented)
        self.expand = jit(_expand, static_argnums=5)
        self.backward = jit(_backward)
        self.forward = jit(_forward)
        self._zeros = (jnp.zeros((T + 1, n)), jnp.zeros((T, m)), jnp.zeros((T, m, n)))

    def rollout(self, x0: Array, us: Array) -> Array:
        """The open-loop rollout (T+1, n): the closed-loop one with no feedback and no step, so the
        dynamics are compiled once for both."""
        xs, k, K = self._zeros
        return self.forward(xs.at[0].set(x0), us, k, K, 0.0)[0]


def solve(
    problem: OptimalControlProblem,
    x0: Float[Array, " n"],
    controls: Float[Array, "T m"],
    options: Options = Options(),
    progress: bool = False,
    throw: bool = False,
) -> Solution:
    """Solves `problem` from x0, starting from the open-loop `controls` (T, m).

    A problem it cannot solve is reported, not raised (`Solution.result` says how it stopped,
    `message` why: iteration limit, penalty limit, a line search that found no decrease), unless
    `throw`.

    Raises:
        TrajoptError: controls of the wrong shape, or a non-finite x0 or initial rollout.
        SolverError: `throw` and the solve did not converge.
    """
    start = time.perf_counter()
    x0 = jnp.asarray(x0)
    us = jnp.asarray(controls)
    T = problem.horizon
    if us.ndim != 2 or us.shape[0] != T:
        raise TrajoptError(f"controls must be (horizon={T}, m), got {tuple(us.shape)}")
    if not bool(jnp.all(jnp.isfinite(x0))):
        raise TrajoptError("the initial state is not finite")
    n, m = x0.shape[0], us.shape[1]
    fn = compiled(problem, n, m)
    xs = fn.rollout(x0, us)
    if not bool(jnp.all(jnp.isfinite(xs))):
        raise TrajoptError("the initial controls' rollout is not finite")
    it = _Iterate(xs, us, options.regularization, 0)
    mult = _Multipliers(jnp.zeros((T, fn.p)), jnp.zeros(fn.q), options.penalty)
    history: list[tuple[float, float, float, float]] = []
    result, message, worst, outer = Result.max_outer_reached, "", float("inf"), 0
    bar = _bar(progress, options.max_iterations)
    try:
        for outer in range(1, options.max_outer + 1):  # noqa: B007 (reported after the loop)
            it, inner = _inner(fn, it, mult, options, _logger(fn, history, bar, mult.rho))
            worst_j, c, h = fn.violation(it.xs, it.us)
            worst = float(worst_j)
            if worst <= options.constraint_tol and inner.converged:
                result, message = Result.successful, f"constraint violation {worst:.2e} <= {options.constraint_tol:g}"
                break
            if it.iterations >= options.max_iterations:
                result, message = (
                    Result.max_steps_reached,
                    f"{options.max_iterations} iterations, the last inner solve {inner.name}",
                )
                break
            if mult.rho >= options.penalty_max:
                result, message = Result.penalty_limit, f"constraint violation {worst:.2e}"
                break
            mult = _Multipliers(
                jnp.maximum(0.0, mult.lam + mult.rho * c),
                mult.nu + mult.rho * h,
                min(mult.rho * options.penalty_scale, options.penalty_max),
            )
        else:
            message = f"{options.max_outer} multiplier updates, constraint violation {worst:.2e}"
    finally:
        if bar is not None:
            bar.close()
    message = f"{result.value}: {message}"
    finish(result, f"iLQR {message}", throw)
    return Solution(
        states=np.asarray(it.xs), controls=np.asarray(it.us), cost=float(fn.objective(it.xs, it.us)),
        max_violation=float(fn.violation(it.xs, it.us)[0]), result=result, message=message,
        iterations=it.iterations, outer=outer, seconds=time.perf_counter() - start, history=history,
        multipliers=(np.asarray(mult.lam), np.asarray(mult.nu)),
    )  # fmt: skip


def _logger(fn: "_Compiled", history: list, bar, rho: float) -> Callable:
    """Records an iteration (cost, violation, accepted step or 0, regularisation) and shows it."""

    def log(xs, us, alpha: float, reg: float) -> None:
        worst = float(fn.violation(xs, us)[0])
        history.append((float(fn.objective(xs, us)), worst, alpha, reg))
        if bar is not None:
            bar.update(1)
            bar.set_postfix(cost=f"{history[-1][0]:.4g}", violation=f"{worst:.1e}", rho=f"{rho:.0e}")

    return log


def _inner(fn: "_Compiled", it: _Iterate, mult: _Multipliers, o: Options, log: Callable) -> tuple[_Iterate, Result]:
    """iLQR on the augmented cost for fixed multipliers, from `it` until its cost stops falling
    (`successful`), the line search fails at the regularisation limit (`stalled`) or the
    iteration limit (`max_steps_reached`)."""
    xs, us, reg, iterations = it
    J = float(fn.augmented(xs, us, *mult))
    expansion = None
    while iterations < o.max_iterations:
        iterations += 1
        if expansion is None:  # kept after a rejected step: only the regularisation changes
            expansion = fn.expand(xs, us, *mult, o.jacobian_batch)
        A, B, g, H, gT, HT = expansion
        while True:
            k, K, dV, failed = fn.backward(A, B, g, H, gT, HT, reg)
            if not bool(failed):
                break
            reg = reg * 10.0
            if reg > o.reg_max:
                return _Iterate(xs, us, o.reg_max, iterations), Result.stalled
        step_small = float(jnp.max(jnp.abs(k))) <= o.gradient_tol * (1.0 + float(jnp.max(jnp.abs(us))))
        accepted = False
        for alpha in o.line_search:
            x_new, u_new = fn.forward(xs, us, k, K, alpha)
            if not bool(jnp.all(jnp.isfinite(x_new))):
                continue
            J_new = float(fn.augmented(x_new, u_new, *mult))
            predicted = -(alpha * float(dV[0]) + alpha**2 * float(dV[1]))
            if J - J_new >= o.armijo * max(predicted, 0.0) and J_new <= J:
                accepted = True
                break
        if accepted:
            decrease = J - J_new
            xs, us, J, expansion = x_new, u_new, J_new, None
            reg = max(o.reg_min, reg / 10.0)
        else:
            decrease = 0.0
            reg = reg * 10.0
        log(xs, us, alpha if accepted else 0.0, reg)
        if step_small or (accepted and decrease <= o.cost_tol * max(abs(J), 1e-12)):
            return _Iterate(xs, us, reg, iterations), Result.successful
        if not accepted and reg > o.reg_max:
            return _Iterate(xs, us, o.reg_max, iterations), Result.stalled
    return _Iterate(xs, us, reg, iterations), Result.max_steps_reached


def _bar(progress: bool, total: int):
    if not progress:
        return None
    from tqdm.auto import tqdm

    return tqdm(total=total, desc="iLQR", unit="it", leave=False)
