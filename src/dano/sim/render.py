"""Rendering rollouts to MP4/GIF with MuJoCo's own renderer, headless (EGL or OSMesa).

DANOs have no MuJoCo geoms, so each frame adds their surface points as small spheres to the
MuJoCo scene (a subsample, coloured per body). `make_renderer` picks the OpenGL backend when a renderer
is made, not at import: the user's `MUJOCO_GL` if set, MuJoCo's own choice where a display exists
(or off Linux), else EGL and then OSMesa (headless Linux).
"""

import contextlib
import os
import platform
from pathlib import Path

import imageio.v3 as iio
import mujoco
import numpy as np
from tqdm.auto import tqdm

from dano.errors import DanoError
from dano.io import atomic_write

_COLOURS = np.array([[0.85, 0.55, 0.35, 1], [0.35, 0.6, 0.85, 1], [0.5, 0.8, 0.4, 1], [0.8, 0.4, 0.7, 1]])


class RenderError(DanoError):
    """No headless OpenGL context could be made (install EGL or OSMesa, or set MUJOCO_GL)."""


def headless_backends() -> tuple[str | None, ...]:
    """The OpenGL backends `make_renderer` tries, in order (None: MuJoCo's own choice, `MUJOCO_GL`)."""
    if os.environ.get("MUJOCO_GL") or platform.system() != "Linux":
        return (None,)
    if os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"):
        return (None, "egl", "osmesa")
    return ("egl", "osmesa")


def make_renderer(model: mujoco.MjModel, height: int, width: int, **kwargs) -> mujoco.Renderer:
    """MuJoCo's offscreen renderer on the first OpenGL backend that works (`headless_backends`).

    MuJoCo fixes its backend from `MUJOCO_GL` when it is imported; dano sets no environment variable
    at import, so here the backend's context class is swapped in only while this renderer is made.

    Raises:
        RenderError: no backend could make a context (names each backend's reason).
    """
    from mujoco.rendering.classic import gl_context

    reasons = []
    for backend in headless_backends():
        try:
            with _gl_backend(gl_context, backend):
                return mujoco.Renderer(model, height, width, **kwargs)
        except Exception as e:  # MuJoCo raises several kinds when no GL context can be made
            reasons.append(f"{backend or os.environ.get('MUJOCO_GL') or 'default'}: {type(e).__name__}: {e}")
    raise RenderError(f"cannot render: no OpenGL context ({'; '.join(reasons)}); install EGL or OSMesa")


@contextlib.contextmanager
def _gl_backend(gl_context, backend: str | None):
    if backend is None:
        yield
        return
    if backend == "egl":
        from mujoco.egl import GLContext
    else:
        from mujoco.osmesa import GLContext
    saved = getattr(gl_context, "GLContext", None)
    gl_context.GLContext = GLContext
    try:
        yield
    finally:
        gl_context.GLContext = saved


def render_video(
    sim,
    traj,
    path: str | Path,
    width: int = 640,
    height: int = 480,
    fps: float = 30.0,
    max_points: int = 1500,
    progress: bool = True,
) -> Path:
    """Renders a trajectory to `path` (.mp4 via ffmpeg, or .gif), written atomically.

    Args:
        sim: the `Simulation` that produced `traj`.
        traj: the `Trajectory`.
        fps: frames per second of the video; simulation frames are subsampled to match.
        max_points: points drawn per DANO.
    """
    path = Path(path)
    if path.suffix.lower() not in (".mp4", ".gif"):
        raise DanoError(f"video must be .mp4 or .gif, got {path.name}")
    model = sim.model
    # Software GL renders thousands of small spheres: coarse spheres and no shadows keep it ~20x faster.
    model.vis.quality.numslices, model.vis.quality.numstacks = 8, 4
    renderer = make_renderer(model, height, width, max_geom=10000)
    data = mujoco.MjData(model)
    qpos = np.asarray(traj.qpos)
    every = max(1, int(round(1.0 / (fps * sim.scene.timestep))))
    rng = np.random.default_rng(0)
    clouds = []
    for state in sim.world.danos:
        pts = np.asarray(state.points).T
        clouds.append(pts[rng.choice(len(pts), size=min(max_points, len(pts)), replace=False)])
    camera = _camera(qpos, sim)
    frames = []
    for t in tqdm(range(0, len(qpos), every), desc="render", disable=not progress, unit="frame"):
        data.qpos[:] = qpos[t]
        mujoco.mj_forward(model, data)
        renderer.update_scene(data, camera)
        renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
        for i, (a, pts) in enumerate(zip(sim.world.dano_qpos, clouds, strict=True)):
            _add_points(renderer.scene, qpos[t, a : a + 3], qpos[t, a + 3 : a + 7], pts, _COLOURS[i % len(_COLOURS)])
        frames.append(renderer.render().copy())
    renderer.close()
    with atomic_write(path, suffix=path.suffix) as tmp:
        if path.suffix.lower() == ".gif":
            iio.imwrite(tmp, np.stack(frames), duration=1000 / fps, loop=0)
        else:
            iio.imwrite(tmp, np.stack(frames), fps=fps, codec="libx264", plugin="pyav")
    return path


def _camera(qpos: np.ndarray, sim) -> mujoco.MjvCamera:
    centres = [qpos[:, a : a + 3] for a in sim.world.dano_qpos] or [np.zeros((1, 3))]
    allc = np.concatenate(centres)
    cam = mujoco.MjvCamera()
    cam.lookat[:] = allc.mean(axis=0)
    size = max([float(np.max(np.ptp(np.asarray(s.points), axis=1))) for s in sim.world.danos] or [0.2])
    cam.distance = 1.5 * float(np.max(np.ptp(allc, axis=0))) + 4.0 * size
    cam.azimuth, cam.elevation = 135.0, -25.0
    return cam


def _add_points(scene: mujoco.MjvScene, x: np.ndarray, quat: np.ndarray, pts: np.ndarray, rgba: np.ndarray) -> None:
    R = np.zeros(9)
    mujoco.mju_quat2Mat(R, quat / np.linalg.norm(quat))
    world = pts @ R.reshape(3, 3).T + x
    radius = 0.6 * float(np.max(np.ptp(pts, axis=0))) / np.sqrt(len(pts))
    eye = np.eye(3).ravel()
    for p in world:
        if scene.ngeom >= scene.maxgeom:
            return
        mujoco.mjv_initGeom(scene.geoms[scene.ngeom], mujoco.mjtGeom.mjGEOM_SPHERE, np.full(3, radius), p, eye, rgba)
        scene.ngeom += 1
