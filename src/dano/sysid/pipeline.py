"""Files in, identified parameters out: what `dano sysid` runs."""

import dataclasses
import enum
from collections.abc import Sequence
from pathlib import Path
from typing import Literal

import numpy as np

from dano import validate as V
from dano.sim.scene import Scene
from dano.sim.toml import load_scene
from dano.sysid.data import MIN_FRAMES, read_tracks
from dano.sysid.frames import (
    RestingPose,
    extent,
    lying_on,
    plane_of_motion,
    resting_poses,
    scaled,
    warn_implausible_units,
    with_gravity,
)
from dano.sysid.intervals import Interval
from dano.sysid.objective import Loss
from dano.sysid.params import Initial, SysidError, canonical
from dano.sysid.problem import Problem, make_problem, named_after_scene
from dano.sysid.solve import Identification, identify
from dano.sysid.windows import Recording


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
        initial: "none", "velocity" or "state": initial-state parts fitted per window.
        sigma: tracking noise, m.
        init, bounds: initial guesses and (low, high) bounds by name as given in `fit`.
        max_steps: Levenberg-Marquardt iterations at most.
        rotation_weight: multiplies the rotation residuals (0: positions only).
        settle: m; a body within this of the ground at a window's start is put on it (None: 3 sigma,
            0: the data as they are; `make_problem`).
        frames: (first, stop) rows of every file to fit (0-based, stop excluded; None: all).
        interval: "profile" or "gauss-newton" (`identify`).
        loss: "l2", "huber" or "cauchy" (`identify`, `dano.sysid.objective.robust`).
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


def load_recordings(
    paths: Sequence[str | Path], fps: float | None, body: str | None, frames: tuple[int, int | None] | None = None
) -> list[Recording]:
    """One `Recording` per file; `body` names the body of files without a `body` column; `frames`
    (first, stop) keeps those rows of every file (0-based, stop excluded)."""
    out = []
    for path in paths:
        tracks = read_tracks(path, fps=fps)
        if frames is not None:
            tracks = {k: t.frames(*frames) for k, t in tracks.items()}
            short = min(t.n_frames for t in tracks.values())
            if short < MIN_FRAMES:
                raise SysidError(f"{path}: frames {frames[0]}:{frames[1] or ''} leave {short} rows; at least 3 needed")
        if body is not None and "" in tracks:
            tracks = {(body if k == "" else k): v for k, v in tracks.items()}
        out.append(Recording(tracks))
    return out


def metric_scale(scene: Scene, config: SysidConfig) -> dict | None:
    """The metric scale `config` asks for: {"m_per_unit", "objects"} (the DANOs scaled too), from
    `scale` (positions only) or `size` (both; see `dano.sysid.frames`); None for neither."""
    if config.scale is not None and config.size is not None:
        raise SysidError("give the scale or the object's size, not both")
    if config.scale is not None:
        return {"m_per_unit": config.scale, "objects": False}
    if config.size is not None:
        return {"m_per_unit": config.size / extent(scene, config.body), "objects": True}
    return None


def prepare(scene: Scene, recordings: list[Recording], config: SysidConfig) -> tuple[Scene, list[Recording]]:
    """Applies the metric scale of `config` (`metric_scale`) and warns when the result still looks
    like mixed units (`UnitsWarning`)."""
    scale = metric_scale(scene, config)
    if scale is not None:
        scene, recordings = scaled(scene, recordings, scale["m_per_unit"], objects_too=scale["objects"])
    warn_implausible_units(scene, recordings)
    return scene, recordings


def canonical_fit(config: SysidConfig) -> tuple[list[str], dict, dict]:
    """The fitted parameters' canonical names, and the initial guesses and bounds keyed by them
    (the user may write either name)."""
    names = [canonical(n) for n in config.fit]
    by_name = dict(zip(config.fit, names, strict=True))
    init = {by_name.get(k, canonical(k)): v for k, v in config.init.items()}
    bounds = {by_name.get(k, canonical(k)): v for k, v in config.bounds.items()}
    return names, init, bounds


def identify_files(
    scene_path: str | Path, traj_paths: Sequence[str | Path], config: SysidConfig, progress: bool = True
) -> tuple[Problem, Identification]:
    """Reads the scene and trajectories, sets up Problem (17) and solves it."""
    if not traj_paths:
        raise SysidError("give at least one trajectory file")
    scene = load_scene(scene_path)
    loaded = load_recordings(traj_paths, config.fps, config.body, config.frames)
    recordings = [named_after_scene(scene, r) for r in loaded]
    scale = metric_scale(scene, config)
    adjustments: dict = {} if scale is None else {"scale": scale}
    if config.frames is not None:
        adjustments["frames"] = list(config.frames)
    scene, recordings = prepare(scene, recordings, config)
    names, init, bounds = canonical_fit(config)

    def build(scene, observed=None):
        return make_problem(
            scene, recordings if observed is None else observed, names, window=config.window,
            initial=config.initial, sigma=config.sigma, settle=config.settle,
            rotation_weight=0.0 if config.orientation == "resting" else config.rotation_weight,
        )  # fmt: skip

    if config.orientation == "resting":
        if config.gravity is not None:
            raise SysidError(
                "--orientation resting needs the table of the scene (its ground): without --gravity, the data "
                "in the scene's frame"
            )
        problem, adjustments["orientation"] = _lying_still(scene, recordings, config, build, init, bounds)
    elif config.gravity is None:
        problem = build(scene)
    elif isinstance(config.gravity, str) and config.gravity == "fit":
        axis = plane_of_motion(recordings)
        candidates = [build(with_gravity(scene, recordings, sign * axis)) for sign in (1.0, -1.0)]
        problem = min(candidates, key=lambda p: _initial_loss(p, init, bounds))
    else:
        problem = build(with_gravity(scene, recordings, np.asarray(config.gravity, dtype=float)))
    if config.gravity is not None:
        adjustments["gravity"] = {
            "vector": list(problem.scene.gravity), "ground_normal": list(problem.scene.ground_normal),
            "ground_height": problem.scene.ground_height, "fitted": config.gravity == "fit",
        }  # fmt: skip
    problem = dataclasses.replace(problem, adjustments={**adjustments, **problem.adjustments})
    result = identify(
        problem, init=init, bounds=bounds, labels=tuple(config.fit), max_steps=config.max_steps, progress=progress,
        interval=config.interval, level=config.level, loss=config.loss,
    )  # fmt: skip
    return problem, result


YAWS = (0.0, 45.0, 90.0, 135.0)
"""deg: headings tried for each resting face (`--orientation resting`)."""


def _lying_still(scene: Scene, recordings: list[Recording], config: SysidConfig, build, init, bounds):
    """The problem with the observed DANO lying on the resting face and heading (`YAWS`) that fit
    best at the initial guess, positions only; and the report of that choice."""
    observed = {name for r in recordings for name in r.tracks}
    bodies = [b for b in scene.bodies if b.name in observed]
    if len(bodies) != 1:
        raise SysidError(f"--orientation resting needs exactly one observed DANO, got {len(bodies)}")
    name = bodies[0].name
    up = np.asarray(scene.ground_normal, dtype=float)
    poses = resting_poses(bodies[0].dano, up=up)

    def lying(pose: RestingPose, yaw: float) -> list[Recording]:
        return [
            dataclasses.replace(r, tracks={**r.tracks, name: lying_on(r.tracks[name], pose, np.radians(yaw), up)})
            for r in recordings
        ]

    candidates = [(k, yaw) for k in range(len(poses)) for yaw in YAWS]
    problems, losses = [], []
    for k, yaw in candidates:
        problem = build(scene, lying(poses[k], yaw))
        # one structure for every candidate: the first one's compiled functions serve them all
        problems.append(problem if not problems else dataclasses.replace(problem, cache=problems[0].cache))
        losses.append(_initial_loss(problems[-1], init, bounds))
    if not np.isfinite(min(losses)):
        raise SysidError("no resting orientation gives a finite loss at the initial guess")
    best = int(np.argmin(losses))
    (k, yaw), problem = candidates[best], problems[best]
    report = {
        "face": k, "normal": list(poses[k].normal), "yaw_deg": yaw, "quat": list(poses[k].quat),
        "height_m": poses[k].height, "candidates": len(candidates), "rotation_weight": 0.0,
    }  # fmt: skip
    return problem, report


def _initial_loss(problem: Problem, init: dict, bounds: dict) -> float:
    """½Σr² at the initial guess (for choosing the sign of a fitted gravity axis)."""
    import jax.numpy as jnp

    from dano.sysid.objective import Jacobian, compiled
    from dano.sysid.solve import initial_guess

    loss_fn, _ = compiled(problem, Jacobian.fwd)
    theta = initial_guess(problem, init, bounds)
    value = float(loss_fn(jnp.asarray(theta), jnp.zeros((problem.n_windows, problem.n_state)), problem.windows))
    return value if np.isfinite(value) else np.inf
