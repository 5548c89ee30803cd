"""The settings of system identification and their enumerations (no JAX: the command line reads
them to build `dano sysid`'s options, and `dano --help` stays instant)."""

import dataclasses
import enum
from collections.abc import Sequence
from typing import Literal

from dano import validate as V
from dano.errors import DanoError


class SysidError(DanoError):
    """A system identification problem that cannot be set up as asked."""


class Initial(enum.StrEnum):
    """Which parts of each window's initial state are unknowns: `none` (read from the data),
    `velocity`, or `state` (pose and velocity)."""

    none = "none"
    velocity = "velocity"
    state = "state"


class Interval(enum.StrEnum):
    """How a parameter's confidence interval is found: `gauss_newton` θ ± z·stderr (free), or
    `profile` the profile likelihood (about 3 refits per parameter and side; honest where the loss is
    rough, flat or asymmetric)."""

    gauss_newton = "gauss-newton"
    profile = "profile"


class Loss(enum.StrEnum):
    """The loss on pose residuals (`dano.sysid.objective.robust`): `l2` least squares; `huber` and
    `cauchy` for data with outliers (impacts the model misses, tracking failures)."""

    l2 = "l2"
    huber = "huber"
    cauchy = "cauchy"


class Orientation(enum.StrEnum):
    """Where the rotations come from: `track` the files' quaternions; `resting` none the tracker could
    trust: the object lies on one of its stable faces (`resting_poses`) at one of `YAWS`."""

    track = "track"
    resting = "resting"


@dataclasses.dataclass(frozen=True)
class SysidConfig:
    """What to fit and how to read the data (the `dano sysid` options).

    Attributes:
        fit: parameter names as the user writes them (`friction`, `mass_scale`, any contact key).
        fps: frame rate for files without a `t` column.
        scale: metres per tracker unit (positions only; the scene's DANOs are taken as metric).
        size: the object's real longest dimension along its principal axes, m: the scene's DANO and
            the positions share the tracker's units and are both scaled by size / (the DANO's
            longest principal extent, `dano info`).
        gravity: None (the scene's gravity and ground), a direction (3,) in the data's frame, or
            "fit" (the normal of the plane of motion, the sign that fits better at the initial guess).
        body: the scene body that files without a `body` column observe.
        window: frame intervals per shooting window (None: whole trajectories).
        initial: "none", "velocity" or "state": initial-state parts fitted per window (`dano sysid
            --masks`: state unless given).
        sigma: tracking noise, m.
        init, bounds: initial guesses and (low, high) bounds by name as given in `fit`.
        max_steps: Levenberg-Marquardt iterations at most.
        rotation_weight: multiplies the rotation residuals (0: positions only).
        settle: m; a body within this of the ground at a window's start is put on it (None: 3 sigma,
            0: the data as they are; `make_problem`).
        frames: (first, stop) rows of every file to fit (0-based, stop excluded; None: all).
        interval: "profile": refit with each parameter held, to where the loss rises by the
            chi-square quantile (honest on rough or flat losses; ~6 refits per parameter);
            "gauss-newton": the estimate +/- z stderr, free (`identify`).
        loss: "l2" least squares, or a robust loss for outliers (impacts, tracking failures): frames
            off by more than 2.8 sigma pull less ("huber") or hardly at all ("cauchy")
            (`identify`, `dano.sysid.objective.robust`).
        orientation: "track" (the files' quaternions), or "resting": the tracker could not resolve
            rotation; the object lies on one of its stable faces (`resting_poses`) at one of
            `YAWS`, the pair that fits best at the initial guess, positions only.
        level: confidence level of the intervals.
    """

    fit: tuple[str, ...]
    fps: float | None = None
    scale: float | None = None
    size: float | None = None
    gravity: Sequence[float] | Literal["fit"] | None = None
    body: str | None = None
    window: int | None = None
    initial: Initial | str = Initial.none
    sigma: float = 1e-3
    init: dict = dataclasses.field(default_factory=dict)
    bounds: dict = dataclasses.field(default_factory=dict)
    max_steps: int = 50
    rotation_weight: float = 1.0
    settle: float | None = None
    interval: Interval | str = Interval.gauss_newton
    level: float = 0.95
    frames: tuple[int, int | None] | None = None
    loss: Loss | str = Loss.l2
    orientation: Orientation | str = Orientation.track

    def __post_init__(self):
        for name, kind in (("initial", Initial), ("interval", Interval), ("loss", Loss), ("orientation", Orientation)):
            object.__setattr__(self, name, V.option(getattr(self, name), name, SysidError, kind))
        V.settings(self, SysidError, whole={"max_steps": 1}, positive=["sigma"], nonnegative=["rotation_weight"])
        if not 0.0 < self.level < 1.0:
            raise SysidError(f"level must be between 0 and 1, got {self.level}")
