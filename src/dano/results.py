"""How every solver reports: one enumeration of how it stopped (`Result`, after Optimistix's
`RESULTS`), `throw=` to raise instead of report (`SolverError`), and one JSON shape (`dano sysid
--json`, `dano trajopt --json`).

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

import enum

from dano.errors import DanoError


class Result(enum.Enum):
    """How a solver stopped; the value is its message for people. Only `successful` converged."""

    successful = "converged"
    max_steps_reached = "did not converge: iteration limit reached"
    stalled = "did not converge: no step lowers the objective (line search failed at the regularisation limit)"
    penalty_limit = "did not converge: penalty limit reached with the constraints violated"
    max_outer_reached = "did not converge: multiplier updates exhausted with the constraints violated"

    @property
    def converged(self) -> bool:
        return self is Result.successful


class SolverError(DanoError):
    """A solver that did not converge, raised where `throw=True` asked for an error instead of a report."""


def finish(result: Result, message: str, throw: bool) -> None:
    """Raises `SolverError(message)` where `throw` and the solver did not converge."""
    if throw and not result.converged:
        raise SolverError(message)


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
