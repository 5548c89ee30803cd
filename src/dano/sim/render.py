"""Rendering rollouts to MP4/GIF with MuJoCo's own renderer, headless (EGL or OSMesa).

DANOs have no MuJoCo geoms. By default each is drawn as its surface (`dano.surface.surface_mesh`,
marching cubes of its density grid, added to a copy of the scene's model as a visual mesh, as the
paper's Fig. 8e draws them); `style="points"` draws its surface points as small spheres instead (a
subsample, coloured per body), and a DANO with no density grid (a reference collider) is always
drawn so. The camera frames everything that moves: the DANOs over the whole trajectory, and the
moving primitives and robot links. `make_renderer` picks the OpenGL backend when a renderer
is made, not at import: the user's `MUJOCO_GL` if set, MuJoCo's own choice where a display exists
(or off Linux), else EGL and then OSMesa (headless Linux).
"""

import contextlib
import enum
import os
import platform
from pathlib import Path

import imageio.v3 as iio
import mujoco
import numpy as np
from tqdm.auto import tqdm

from dano import validate as V
from dano.errors import DanoError
from dano.io import atomic_write

_COLOURS = np.array([[0.85, 0.55, 0.35, 1], [0.35, 0.6, 0.85, 1], [0.5, 0.8, 0.4, 1], [0.8, 0.4, 0.7, 1]])


class Style(enum.StrEnum):
    """How a DANO is drawn."""

    surface = "surface"
    """its surface mesh (marching cubes of its density grid)"""
    points = "points"
    """its surface points, as small spheres"""


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
    style: Style | str = Style.surface,
    contacts=None,
) -> Path:
    """Renders a trajectory to `path` (.mp4 via ffmpeg, or .gif), written atomically.

    Args:
        sim: the `Simulation` that produced `traj`.
        traj: the `Trajectory`.
        fps: frames per second of the video; simulation frames are subsampled to match.
        max_points: points drawn per DANO drawn as points.
        style: `Style.surface` (default) or `Style.points` (module docstring).
        contacts: the trajectory's `dano.sim.contacts.ContactForces`, drawn as red arrows from where
            each pair's force acts (`contact_arrows`; the DANOs' surfaces then see-through, as the
            force on a body acts on its face and points into it), or None.
    """
    path = Path(path)
    if path.suffix.lower() not in (".mp4", ".gif"):
        raise DanoError(f"video must be .mp4 or .gif, got {path.name}")
    qpos = np.asarray(traj.qpos)
    if contacts is not None and contacts.force.shape[0] != len(qpos):
        raise DanoError(f"the contact forces have {contacts.force.shape[0]} frames, the trajectory {len(qpos)}")
    every = max(1, int(round(1.0 / (fps * sim.scene.timestep))))
    model, clouds = scene_model(sim, style, max_points, alpha=1.0 if contacts is None else SEE_THROUGH)
    renderer = make_renderer(model, height, width, max_geom=10000)
    data = mujoco.MjData(model)
    camera = frame_camera(model, qpos[::every], sim, width / height)
    arrows = None if contacts is None else contact_arrows(sim, contacts)
    frames = []
    for t in tqdm(range(0, len(qpos), every), desc="render", disable=not progress, unit="frame"):
        frame_arrows = None if arrows is None else arrows[t]
        frames.append(draw_frame(renderer, model, data, qpos[t], camera, sim, clouds, frame_arrows))
    renderer.close()
    with atomic_write(path, suffix=path.suffix) as tmp:
        if path.suffix.lower() == ".gif":
            iio.imwrite(tmp, np.stack(frames), duration=1000 / fps, loop=0)
        else:
            iio.imwrite(tmp, np.stack(frames), fps=fps, codec="libx264", plugin="pyav")
    return path


def coverage(sim, traj, width: int = 640, height: int = 480, style: Style | str = Style.surface) -> dict[str, float]:
    """The fraction of `render_video`'s last picture that each DANO covers (its surface drawn; from
    MuJoCo's segmentation render), by body name: how well the camera frames the objects."""
    model, clouds = scene_model(sim, style)
    qpos = np.asarray(traj.qpos)
    renderer = make_renderer(model, height, width, max_geom=10000)
    renderer.enable_segmentation_rendering()
    seg = draw_frame(renderer, model, mujoco.MjData(model), qpos[-1], frame_camera(model, qpos, sim, width / height),
                     sim, clouds)  # fmt: skip
    renderer.close()
    geoms = np.where(seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM), seg[..., 0], -1)
    return {
        b.name: float(np.mean(geoms == model.geom(f"{b.name}_surface").id))
        for b, c in zip(sim.scene.bodies, clouds, strict=True)
        if c is None
    }


SEE_THROUGH = 0.45
"""The DANOs' surfaces' opacity where contact arrows are drawn."""


def scene_model(sim, style: Style | str = Style.surface, max_points: int = 1500, alpha: float = 1.0):
    """The model to draw the simulation's scene with, and the points to draw per DANO (None for a
    DANO drawn as its surface mesh, which the model then holds as a visual geom of its body, of
    opacity `alpha`)."""
    from dano.sim.compile import add_mesh_geom, scene_spec
    from dano.surface import surface_mesh

    style = V.option(style, "style", DanoError, Style)
    rng = np.random.default_rng(0)
    spec, clouds = None, []
    for i, (body, state) in enumerate(zip(sim.scene.bodies, sim.world.danos, strict=True)):
        if style is Style.surface and body.dano.grid is not None:
            spec = spec or scene_spec(sim.scene)[0]
            rgba = [*_COLOURS[i % len(_COLOURS)][:3].tolist(), alpha]
            add_mesh_geom(spec, body.name, f"{body.name}_surface", surface_mesh(body.dano), collide=False, rgba=rgba)
            clouds.append(None)
            continue
        pts = np.asarray(state.points).T
        clouds.append(pts[rng.choice(len(pts), size=min(max_points, len(pts)), replace=False)])
    model = sim.model if spec is None else spec.compile()
    if model.nq != sim.model.nq:  # an invariant: visual geoms add no joints
        raise AssertionError("the render model's joints differ from the simulation's")
    # Software GL renders thousands of small spheres: coarse spheres and no shadows keep it ~20x faster.
    model.vis.quality.numslices, model.vis.quality.numstacks = 8, 4
    return model, clouds


def draw_frame(renderer, model, data, qpos, camera, sim, clouds, arrows=None) -> np.ndarray:
    """One picture of the state `qpos` (the renderer's pixels, or its segmentation when enabled),
    with `model` and `clouds` from `scene_model` and this frame's `arrows` (k, 2, 3) from
    `contact_arrows`, if any."""
    data.qpos[:] = qpos
    mujoco.mj_forward(model, data)
    renderer.update_scene(data, camera)
    renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
    for i, (a, pts) in enumerate(zip(sim.world.dano_qpos, clouds, strict=True)):
        if pts is not None:
            _add_points(renderer.scene, qpos[a : a + 3], qpos[a + 3 : a + 7], pts, _COLOURS[i % len(_COLOURS)])
    for start, end, width in () if arrows is None else arrows:
        scene = renderer.scene
        if width[0] > 0 and scene.ngeom < scene.maxgeom:
            g = scene.geoms[scene.ngeom]
            mujoco.mjv_initGeom(g, mujoco.mjtGeom.mjGEOM_ARROW, np.zeros(3), np.zeros(3), np.eye(3).ravel(), ARROW_RGBA)
            mujoco.mjv_connector(g, mujoco.mjtGeom.mjGEOM_ARROW, width[0], start, end)  # pyright: ignore[reportAttributeAccessIssue]
            g.category = mujoco.mjtCatBit.mjCAT_DECOR  # pyright: ignore[reportAttributeAccessIssue]
            scene.ngeom += 1
    return renderer.render().copy()


ARROW_RGBA = np.array([0.9, 0.1, 0.1, 1.0], np.float32)
"""The colour of the contact force arrows."""


def contact_arrows(sim, contacts, scale: float = 0.5) -> np.ndarray:
    """Arrows (T+1, P, 3, 3): per frame and pair, (start, end, (width, 0, 0)) of the pair's force on
    its DANO, from where it acts; a force equal to the DANO's weight is `scale` times the DANO's
    size long (the largest extent of its surface points); forces under 1 % of the weight are not
    drawn (width 0, end at the start: the viewer skips them too)."""
    names = {n: i for i, n in enumerate(sim.world.names)}
    states = [sim.world.danos[names[dano]] for dano, _ in contacts.names]
    size = np.array([float(np.max(np.ptp(np.asarray(st.points), axis=1))) for st in states])
    weight = np.array([float(st.mass) * 9.81 for st in states])
    share = contacts.force / weight[None, :, None]  # of each DANO's weight
    shown = np.linalg.norm(share, axis=-1) > 0.01
    start = contacts.point
    end = np.where(shown[..., None], start + share * (scale * size)[None, :, None], start)  # hidden: no length
    w = np.zeros_like(start)
    w[..., 0] = np.where(shown, 0.04 * size[None, :], 0.0)
    return np.stack([start, end, w], axis=2)


def frame_camera(model: mujoco.MjModel, qpos: np.ndarray, sim, aspect: float = 4 / 3) -> mujoco.MjvCamera:
    """A camera that keeps in view, over the frames `qpos` (T, nq), every DANO (a subsample of its
    surface points) and every moving body's geoms (their bounding spheres: free or actuated
    primitives, robot links), from 135° azimuth and 25° above, looking at the middle of their box,
    as close as the pinhole's field of view allows with an 8 % margin (`aspect`: the picture's width
    over its height)."""
    centres, radii = _extent(model, qpos, sim)
    lo, hi = (centres - radii[:, None]).min(axis=0), (centres + radii[:, None]).max(axis=0)
    cam = mujoco.MjvCamera()
    cam.lookat[:] = 0.5 * (lo + hi)
    cam.azimuth, cam.elevation = 135.0, -25.0
    az, el = np.radians(cam.azimuth), np.radians(cam.elevation)
    forward = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])  # MuJoCo's free camera
    right = np.array([np.sin(az), -np.cos(az), 0.0])
    up = np.cross(right, forward)
    # The camera sits at lookat - distance * forward; a point p (radius r) is in the picture where
    # |(p - lookat) . right| + r <= tan_h (distance + (p - lookat) . forward), and likewise up.
    tan_v = np.tan(np.radians(0.5 * float(model.vis.global_.fovy)))
    rel = centres - cam.lookat
    across = np.maximum((np.abs(rel @ right) + radii) / (tan_v * aspect), (np.abs(rel @ up) + radii) / tan_v)
    cam.distance = float(np.max(1.08 * across - rel @ forward + radii))
    return cam


def _extent(model: mujoco.MjModel, qpos: np.ndarray, sim) -> tuple[np.ndarray, np.ndarray]:
    """What the camera must keep in view over the frames: points (n, 3) and their radii (n,), from
    every DANO's surface points (up to 1000 each per frame) and every moving geom's bounding sphere."""
    data = mujoco.MjData(model)
    danos = {model.body(b.name).id for b in sim.scene.bodies}
    bodies = [model.geom_bodyid[g] for g in range(model.ngeom)]
    moves = [b not in danos and (model.body_weldid[b] > 0 or model.body_mocapid[b] >= 0) for b in bodies]
    moving = [g for g, m in enumerate(moves) if m]
    hulls = [np.asarray(state.points).T[:: max(1, state.points.shape[1] // 1000)] for state in sim.world.danos]
    centres, radii = [np.zeros((0, 3))], [np.zeros(0)]
    for q in qpos:
        data.qpos[:] = q
        mujoco.mj_kinematics(model, data)
        for a, pts in zip(sim.world.dano_qpos, hulls, strict=True):
            R = np.zeros(9)
            mujoco.mju_quat2Mat(R, q[a + 3 : a + 7] / np.linalg.norm(q[a + 3 : a + 7]))
            centres.append(pts @ R.reshape(3, 3).T + q[a : a + 3])
            radii.append(np.zeros(len(pts)))
        centres.append(data.geom_xpos[moving])
        radii.append(model.geom_rbound[moving])
    if sum(len(r) for r in radii) == 0:  # nothing moves and no DANO: the origin's neighbourhood
        return np.zeros((1, 3)), np.array([0.2])
    return np.concatenate(centres), np.concatenate(radii)


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
