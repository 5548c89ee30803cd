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

from dano.results import Result


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


def logger(history: list[float], bar) -> Callable[["Point"], None]:
    """Records an accepted iterate's loss and shows it."""

    def log(point: "Point") -> None:
        history.append(point.loss)
        bar.update(1)
        bar.set_postfix(loss=f"{point.loss:.4g}")

    return log


def levenberg_marquardt(
    point: Point, objective: Objective, hold: np.ndarray, max_steps: int, tol: Tolerances, log: Callable
) -> tuple[Point, Result, str]:
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
        point = Point(y_try, *objective.evaluate(y_try))
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
