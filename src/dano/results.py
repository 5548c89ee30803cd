"""How every solver reports: one shape of solution (`AbstractSolution`: the value found, how the
solver stopped and why, its stats), one enumeration of how it stopped (`Result`, after Optimistix's
`RESULTS`), `throw=` to raise instead of report (`SolverError`), and one JSON shape (`dano sysid
--json`, `dano trajopt --json`).

The solvers: `dano.sysid.identify` (Levenberg-Marquardt), `dano.trajopt.ilqr.solve` (constrained
iLQR), `dano.vision.fit_field` and `dano.vision.track` (Adam, a fixed number of steps). `throw`
defaults to False where an unconverged result is still an estimate worth reading (identification,
trajectory optimisation) and to True where a failed one is not (a fit or track whose loss became
non-finite).

Every result object has the keys of `RESULT_KEYS`, keyed by the names as the user typed them:

- `params`: the values found (identification) or used (trajectory optimisation);
- `stderr`, `intervals`: the uncertainty of what was estimated (empty where nothing was);
- `iterations`, `converged`, `message`: how the solver stopped;
- `rms`: {`position` m, `rotation` rad or null}: how far the result is from its target (the data,
  or the goal); fitted to masks, position and rotation are null and `observation` is the RMS opacity
  error;
- `seconds`: wall time, compilation included when it happened;
- `adjustments`: every change between the input as given and what was solved, by kind.

A command adds its own keys beside these.
"""

import abc
import enum
from collections.abc import Callable
from typing import Any, Generic, TypeVar

from dano.errors import DanoError


class Result(enum.Enum):
    """How a solver stopped; the value is its message for people. Only `successful` converged."""

    successful = "converged"
    completed = "completed its fixed number of steps"
    max_steps_reached = "did not converge: iteration limit reached"
    stalled = "did not converge: no step lowers the objective (line search failed at the regularisation limit)"
    penalty_limit = "did not converge: penalty limit reached with the constraints violated"
    max_outer_reached = "did not converge: multiplier updates exhausted with the constraints violated"
    nonfinite = "failed: the loss became non-finite"

    @property
    def converged(self) -> bool:
        return self is Result.successful

    @property
    def ok(self) -> bool:
        """Converged, or a fixed-step solver that completed its steps."""
        return self in (Result.successful, Result.completed)


class SolverError(DanoError):
    """A solver that did not converge, raised where `throw=True` asked for an error instead of a report."""


def finish(result: Result, message: str, throw: bool) -> None:
    """Raises `SolverError(message)` where `throw` and the solver did not converge (`Result.ok`)."""
    if throw and not result.ok:
        raise SolverError(message)


class AbstractSolution(abc.ABC):
    """What every solver returns.

    Attributes:
        value: what it found (each solver names it too: `params`, `controls`, `field`, `positions`).
        result: how it stopped (`Result`); `converged` where that is `Result.successful`.
        message: why, in words, with the figures.
        iterations: iterations (or optimiser steps) in all.
        seconds: wall time, compilation included when it happened.
        stats: how much work it took, by name (`iterations`, `seconds`, and the solver's own).
    """

    result: Result
    message: str
    iterations: int
    seconds: float

    @property
    @abc.abstractmethod
    def value(self) -> Any: ...

    @property
    def converged(self) -> bool:
        return self.result.converged

    @property
    def stats(self) -> dict[str, float | int]:
        return {"iterations": self.iterations, "seconds": self.seconds}


State = TypeVar("State")


class AbstractIterativeSolver(abc.ABC, Generic[State]):
    """A solver in Optimistix's shape (`optimistix/_iterate.py`): `init` makes the state from a
    start, `step` advances it one iteration, `terminate` says whether it has stopped, how (`Result`)
    and why. `iterate` runs one; the solver itself holds no mutable state."""

    @abc.abstractmethod
    def init(self, start: Any) -> State: ...

    @abc.abstractmethod
    def step(self, state: State) -> State: ...

    @abc.abstractmethod
    def terminate(self, state: State) -> tuple[bool, Result, str]:
        """(stopped, how, why); `how` is read only where `stopped`."""


def iterate(
    solver: AbstractIterativeSolver[State], state: State, max_steps: int, on_step: Callable[[State], None] | None = None
) -> tuple[State, Result, str, int]:
    """Runs `solver` from `state` until it terminates or has taken `max_steps` steps (then
    `Result.max_steps_reached` unless the last state terminates); `on_step` sees each new state (a
    history, a progress bar). Returns the last state, how it stopped, why, and the steps taken."""
    steps = max(int(max_steps), 0)
    for n in range(steps):
        stopped, result, message = solver.terminate(state)
        if stopped:
            return state, result, message, n
        state = solver.step(state)
        if on_step is not None:
            on_step(state)
    stopped, result, message = solver.terminate(state)
    return (state, result, message, steps) if stopped else (state, Result.max_steps_reached, "iteration limit", steps)


RESULT_KEYS = (
    "params", "stderr", "intervals", "iterations", "converged", "message", "rms", "seconds", "adjustments",
)  # fmt: skip


def result_json(
    *,
    params: dict,
    iterations: int,
    converged: bool,
    message: str,
    seconds: float,
    rms_position: float | None,
    rms_rotation: float | None = None,
    rms_observation: float | None = None,
    stderr: dict | None = None,
    intervals: dict | None = None,
    adjustments: dict | None = None,
    **extra,
) -> dict:
    """The shared object (`RESULT_KEYS`) followed by the command's own `extra` keys."""
    clash = set(extra) & set(RESULT_KEYS)
    assert not clash, clash
    return {
        "params": dict(params), "stderr": dict(stderr or {}),
        "intervals": {k: list(v) for k, v in (intervals or {}).items()}, "iterations": int(iterations),
        "converged": bool(converged), "message": message, "rms": {"position": rms_position, "rotation": rms_rotation}
        | ({} if rms_observation is None else {"observation": rms_observation}),
        "seconds": float(seconds), "adjustments": dict(adjustments or {}), **extra,
    }  # fmt: skip
