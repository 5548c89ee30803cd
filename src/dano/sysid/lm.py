"""Projected Levenberg-Marquardt: the iteration `identify` runs, and the profile refits reuse.

The reference's (dojo-dano.md §9.3.1) made a little more careful: Gauss-Newton Hessian JᵀJ plus a
Marquardt term λ·diag(JᵀJ), the step projected onto the bounds with parameters held at an active
bound dropped from the system, a backtracking (Armijo) line search on the projected path, λ divided
by 3 after a success and multiplied by 10 after a failure.
"""

import dataclasses
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
from jaxtyping import Array

from dano.results import AbstractIterativeSolver, Result, iterate


@dataclasses.dataclass(frozen=True)
class Point:
    """An iterate: unknowns y, residuals r, loss ½|r|², gradient g = Jᵀr and Hessian H = JᵀJ."""

    y: np.ndarray
    r: Array
    loss: float
    g: np.ndarray
    H: np.ndarray


class Objective(NamedTuple):
    """The loss as LM sees it: `evaluate(y)` -> (r, loss, g, H); `loss_at(y)` the loss alone; the
    bounds (y_lo, y_hi) the unknowns never leave."""

    evaluate: Callable
    loss_at: Callable[[np.ndarray], float]
    y_lo: np.ndarray
    y_hi: np.ndarray


class Tolerances(NamedTuple):
    """`identify`'s stopping tests (see its docstring)."""

    gtol: float
    ftol: float
    rtol: float
    xtol: float


@dataclasses.dataclass(frozen=True)
class LMState:
    """LM's state: the iterate, the one before the last step (None at the start), the Marquardt
    weight λ, and whether the last step found no decrease."""

    point: Point
    previous: Point | None = None
    lam: float = 1e-3
    failed: bool = False


@dataclasses.dataclass(frozen=True)
class ProjectedLM(AbstractIterativeSolver[LMState]):
    """Projected LM (module docstring) on `objective` with the unknowns in `hold` fixed; stops on
    `tol` (`identify`'s docstring) or when no step along the LM direction lowers the loss."""

    objective: Objective
    hold: np.ndarray
    tol: Tolerances

    def init(self, start: Point) -> LMState:
        return LMState(start)

    def _free(self, point: Point) -> np.ndarray:
        """The unknowns that move: neither held nor pushed by the gradient against an active bound."""
        y, g, lo, hi = point.y, point.g, self.objective.y_lo, self.objective.y_hi
        return ~(self.hold | (y <= lo) & (g > 0) | (y >= hi) & (g < 0))

    def terminate(self, state: LMState) -> tuple[bool, Result, str]:
        point, previous, tol = state.point, state.previous, self.tol
        if state.failed:
            return True, Result.successful, "no decrease along the LM direction (a minimum to working precision)"
        if previous is not None:
            if previous.loss - point.loss <= max(tol.rtol * previous.loss, tol.ftol):
                return True, Result.successful, "loss decrease below ftol"
            if np.all(np.abs(point.y - previous.y) <= tol.xtol * (np.abs(point.y) + tol.xtol)):
                return True, Result.successful, "step below xtol"
        if np.max(np.abs(point.g[self._free(point)]), initial=0.0) <= tol.gtol * max(point.loss, 1e-300):
            return True, Result.successful, "gradient below gtol"
        return False, Result.successful, ""

    def step(self, state: LMState) -> LMState:
        """The LM step for the smallest λ (from the last one, ×10 per failure) along whose projected
        path a backtracking line search lowers the loss; λ ÷ 3 after it."""
        point, lam = state.point, state.lam
        free = self._free(point)
        while lam < 1e12:
            step = _lm_step(point.H, point.g, free, lam)
            for alpha in (1.0, 1 / 3, 1 / 9, 1 / 27):
                y_try = np.clip(point.y + alpha * step, self.objective.y_lo, self.objective.y_hi)
                # The normal equations at every trial, not the loss alone: an accepted trial (most
                # are) needs them next, and the loss alone would be a second compiled program.
                tried = Point(y_try, *self.objective.evaluate(y_try))
                if np.isfinite(tried.loss) and tried.loss <= point.loss + 1e-4 * point.g @ (y_try - point.y):
                    return LMState(tried, point, lam / 3)
            lam = lam * 10
        return LMState(point, state.previous, lam, failed=True)


def logger(history: list[float], bar) -> Callable[[LMState], None]:
    """Records an accepted iterate's loss and shows it."""

    def log(state: LMState) -> None:
        if state.failed:
            return
        history.append(state.point.loss)
        bar.update(1)
        bar.set_postfix(loss=f"{state.point.loss:.4g}")

    return log


def levenberg_marquardt(
    point: Point, objective: Objective, hold: np.ndarray, max_steps: int, tol: Tolerances, log: Callable | None = None
) -> tuple[Point, Result, str]:
    """`ProjectedLM` iterated from `point` (`dano.results.iterate`); `log` sees every new state.
    Returns the last iterate, how it stopped and which test stopped it."""
    solver = ProjectedLM(objective, hold, tol)
    state, result, message, _ = iterate(solver, solver.init(point), max_steps, log)
    return state.point, result, message


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
