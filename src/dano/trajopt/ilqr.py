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

Every piece is compiled once per problem (`Pieces.call`: JAX's own cache, shared by every solve of
it); the loops run in Python so a progress bar can follow them.
"""

import dataclasses
import time
from collections.abc import Callable
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from dano.results import AbstractIterativeSolver, AbstractSolution, Result, finish, iterate
from dano.trajopt.pieces import (
    OptimalControlProblem,
    Pieces,
    TrajoptError,
    augmented,
    backward,
    compile_ahead,
    expand,
    forward_trials,
    jacobians_along,
    objective,
    open_loop_states,
    pieces,
    violation,
)

LINE_SEARCH_REACH = 4.0
"""A line search starts at the largest step size within this factor of the last one taken: on
contact, where the quadratic model overshoots, the steps taken stay small for many iterations
(the Panda push: 26 of the 45 steps its 76 iterations took were 1/64 or 1/128), and each size
above them costs a rollout that fails (measured: the sphere push 87 rollouts in 23 iterations ->
55 in 20, the Panda 56 iterations instead of 76, to lower costs; README)."""


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
        line_search: step sizes tried, largest first, from the largest within `LINE_SEARCH_REACH` of the
            last step taken (from the first after a search that failed, and in a new inner solve);
            `armijo`: accepted fraction of the predicted decrease.
        jacobian_batch: time steps whose dynamics Jacobians are taken together (`jax.lax.map`'s
            batch size); None: all at once (`jax.vmap`). Vmapping a long simulated step over time
            turns its branches into selects and its loops into the longest one; for a robot arm in
            contact, one step at a time (1) is the fast choice.
        lanes: programs run at once from threads of their own (`dano.lanes.count`): the
            line search's rollouts `lanes` step sizes at a time, the Jacobians in `lanes` chunks
            of frames. None: one per CPU core on the CPU backend, 1 on an accelerator. The
            result is the same for any count (the step sizes are accepted in the same order).
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
    lanes: int | None = None


@dataclasses.dataclass(frozen=True)
class Solution(AbstractSolution):
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
    def value(self) -> np.ndarray:
        """The controls found, `controls` (T, m)."""
        return self.controls

    @property
    def stats(self) -> dict[str, float | int]:
        return super().stats | {"outer": self.outer, "cost": self.cost, "max_violation": self.max_violation}


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


def open_loop(problem: OptimalControlProblem, x0: Float[Array, " n"], controls: Float[Array, "T m"]) -> Array:
    """The states (T+1, n) of the open-loop `controls` from x0, as the solver rolls them out: its
    closed-loop forward pass with no feedback and no step, so the dynamics are compiled once for
    both (a warm start's rollouts and every later `solve` of the problem share the program)."""
    return open_loop_states(problem.flow, x0, controls)


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
    fn = pieces(problem, n, m)
    compile_ahead(fn.flow, n, m, options.jacobian_batch, options.lanes)  # while the first rollout runs
    xs = open_loop(problem, x0, us)
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
            worst_j, c, h = fn.call(violation, it.xs, it.us)
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
        states=np.asarray(it.xs), controls=np.asarray(it.us), cost=float(fn.call(objective, it.xs, it.us)),
        max_violation=float(fn.call(violation, it.xs, it.us)[0]), result=result, message=message,
        iterations=it.iterations, outer=outer, seconds=time.perf_counter() - start, history=history,
        multipliers=(np.asarray(mult.lam), np.asarray(mult.nu)),
    )  # fmt: skip


def _logger(fn: Pieces, history: list, bar, rho: float) -> Callable[["_InnerState"], None]:
    """Records an iteration (cost, violation, accepted step or 0, regularisation) and shows it."""

    def log(state: _InnerState) -> None:
        if state.alpha is None:  # stopped before a line search: nothing was tried
            return
        xs, us, reg, _ = state.it
        worst = float(fn.call(violation, xs, us)[0])
        history.append((float(fn.call(objective, xs, us)), worst, state.alpha, reg))
        if bar is not None:
            bar.update(1)
            bar.set_postfix(cost=f"{history[-1][0]:.4g}", violation=f"{worst:.1e}", rho=f"{rho:.0e}")

    return log


def _inner(fn: Pieces, it: _Iterate, mult: _Multipliers, o: Options, log: Callable) -> tuple[_Iterate, Result]:
    """`_AugmentedILQR` iterated from `it` (`dano.results.iterate`) within the iteration budget."""
    solver = _AugmentedILQR(fn, mult, o)
    state, result, _, _ = iterate(solver, solver.init(it), o.max_iterations - it.iterations, log)
    return state.it, result


class _InnerState(NamedTuple):
    """iLQR's state: the iterate, its augmented cost J, the expansion along it (None: not yet
    taken), the last accepted step size (0: none; None: no line search), and how the last step
    ended the solve (None: it did not)."""

    it: _Iterate
    J: float
    expansion: tuple | None = None
    alpha: float | None = None
    stop: Result | None = None


@dataclasses.dataclass(frozen=True)
class _AugmentedILQR(AbstractIterativeSolver[_InnerState]):
    """iLQR on the augmented cost for fixed multipliers (module docstring): stops when its cost stops
    falling (`successful`) or the line search fails at the regularisation limit (`stalled`)."""

    fn: Pieces
    mult: _Multipliers
    o: Options

    def init(self, start: _Iterate) -> _InnerState:
        return _InnerState(start, float(self.fn.call(augmented, start.xs, start.us, *self.mult)))

    def terminate(self, state: _InnerState) -> tuple[bool, Result, str]:
        return state.stop is not None, state.stop or Result.successful, ""

    def step(self, state: _InnerState) -> _InnerState:
        """Expansion (kept after a rejected step: only the regularisation changes), Riccati pass
        (regularisation raised until Q_uu is positive definite), backtracking line search."""
        fn, o, (xs, us, reg, iterations), J = self.fn, self.o, state.it, state.J
        iterations += 1
        expansion = state.expansion
        if expansion is None:
            # The cost's expansion first: on the first iteration it compiles here while the
            # dynamics Jacobians still compile in the thread `compile_ahead` started, instead of after.
            costs = fn.call(expand, xs, us, *self.mult)
            expansion = (*jacobians_along(fn.flow, xs, us, o.jacobian_batch, o.lanes), *costs)
        A, B, g, H, gT, HT = expansion
        while True:
            k, K, dV, failed = fn.call(backward, A, B, g, H, gT, HT, reg)
            if not bool(failed):
                break
            reg = reg * 10.0
            if reg > o.reg_max:
                return _InnerState(_Iterate(xs, us, o.reg_max, iterations), J, expansion, None, Result.stalled)
        size = float(jnp.max(jnp.abs(k)))  # the feedforward step's largest entry
        step_small = size <= o.gradient_tol * (1.0 + float(jnp.max(jnp.abs(us))))
        top = LINE_SEARCH_REACH * state.alpha if state.alpha else max(o.line_search)
        trials = [a for a in o.line_search if a <= top] or o.line_search[-1:]
        for alpha, (x_new, u_new) in forward_trials(fn.flow, xs, us, k, K, trials, o.lanes):
            if not bool(jnp.all(jnp.isfinite(x_new))):
                continue
            J_new = float(fn.call(augmented, x_new, u_new, *self.mult))
            predicted = -(alpha * float(dV[0]) + alpha**2 * float(dV[1]))
            if J - J_new >= o.armijo * max(predicted, 0.0) and J_new <= J:
                it = _Iterate(x_new, u_new, max(o.reg_min, reg / 10.0), iterations)
                done = step_small or J - J_new <= o.cost_tol * max(abs(J_new), 1e-12)
                return _InnerState(it, J_new, None, alpha, Result.successful if done else None)
        if step_small:
            return _InnerState(_Iterate(xs, us, reg * 10.0, iterations), J, expansion, 0.0, Result.successful)
        reg = _shorter(fn, expansion, reg, size, o.reg_max)
        if reg > o.reg_max:
            return _InnerState(_Iterate(xs, us, o.reg_max, iterations), J, expansion, 0.0, Result.stalled)
        return _InnerState(_Iterate(xs, us, reg, iterations), J, expansion, 0.0)


def _shorter(fn: Pieces, expansion: tuple, reg: float, size: float, reg_max: float) -> float:
    """After a line search that found no decrease along a feedforward step of largest entry `size`:
    the regularisation raised tenfold, and again while that leaves the step as it was (within a
    tenth) and below `reg_max`. A Levenberg term far below Q_uu's scale does not change the step,
    and the next search fails along it again: on the sphere push, searches of 8 rollouts each
    failed at 1e-9, 1e-8, ..., 1e-3 (the step 0.282, 0.282, ..., 0.271 at 1e-4, 0.200 at 1e-3)
    before one at 1e-2 (0.057) found a decrease; now at 1e-9, 1e-3 and 1e-2, the same answer in 23
    iterations instead of 28. The Panda's push never met such a level (its 76 iterations are the
    same, step for step). The Riccati passes this takes cost next to nothing beside a rollout."""
    A, B, g, H, gT, HT = expansion
    reg = reg * 10.0
    while reg <= reg_max:
        k, _, _, failed = fn.call(backward, A, B, g, H, gT, HT, reg)
        if not bool(failed) and float(jnp.max(jnp.abs(k))) <= 0.9 * size:
            break
        reg = reg * 10.0
    return reg


def _bar(progress: bool, total: int):
    if not progress:
        return None
    from tqdm.auto import tqdm

    return tqdm(total=total, desc="iLQR", unit="it", leave=False)
