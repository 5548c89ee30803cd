"""One JSON shape for what a solver reports (`dano sysid --json`, `dano trajopt --json`).

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
