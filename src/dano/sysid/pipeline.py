"""Files in, identified parameters out: what `dano sysid` runs."""

import dataclasses
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from dano.sim.scene import Scene
from dano.sim.toml import load_scene
from dano.sysid.configs import SysidConfig, SysidError
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
from dano.sysid.params import canonical
from dano.sysid.problem import Problem, make_problem, named_after_scene
from dano.sysid.solve import Identification, identify
from dano.sysid.windows import Recording


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
        # one structure for every candidate: the first one's compiled functions serve them all
        problems.append(build(scene, lying(poses[k], yaw)))
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
