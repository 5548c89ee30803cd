"""An interactive 3D view of DANOs in the browser, as one self-contained HTML page (WebGL, no
library, no server): `dano view OBJ.dano.npz -o view.html`, `dano view SCENE.toml [--trajectory
TRAJ.csv] -o view.html`.

Each DANO is shown as its surface (`dano.surface.surface_mesh`), its surface points coloured by
density, their normals and its centre of mass, each switchable; the scene's other geoms (a table,
a robot's links: `Solid`) beside them; a trajectory adds a timeline to scrub and play, and its
contact forces as red arrows (`dano simulate SCENE.toml --view VIEW.html --contacts`). Drag to
orbit, scroll to zoom. The page opens from disk in any browser with WebGL.
"""

import dataclasses
import json
from pathlib import Path

import numpy as np

from dano.errors import DanoError, MeshError
from dano.io import atomic_write
from dano.types import DANO

_TEMPLATE = Path(__file__).with_name("viewer.html")


class ViewerError(DanoError):
    """A view that cannot be written as asked."""


@dataclasses.dataclass(frozen=True)
class Frames:
    """Poses to play: `t` (T,) seconds and, per body name, (T, 7) rows x, y, z, qw, qx, qy, qz
    (centre of mass, object frame to world)."""

    t: np.ndarray
    poses: dict[str, np.ndarray]


@dataclasses.dataclass(frozen=True)
class Solid:
    """A geom of the scene that is not a DANO, as a triangle mesh in its own frame: `vertices`
    (n, 3) m, `faces` (m, 3), `rgba` (4,), and its poses (T, 7) (x, y, z, qw, qx, qy, qz) per frame."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    rgba: np.ndarray
    poses: np.ndarray


def write_view(
    path: str | Path,
    danos: dict[str, DANO],
    poses: dict[str, np.ndarray] | None = None,
    frames: Frames | None = None,
    title: str = "dano view",
    max_points: int = 3000,
    resolution: int = 64,
    ground: bool = False,
    solids: tuple[Solid, ...] = (),
    arrows: np.ndarray | None = None,
) -> Path:
    """Writes the page (module docstring) to `path` (.html), atomically, and returns the path.

    Args:
        danos: the objects by name.
        poses: each one's pose (7,) when no `frames` are given (default: at the origin, upright).
        frames: a trajectory to play (`Frames`); every body it names must be in `danos`.
        max_points: surface points shown per DANO (an evenly spread subsample).
        resolution: marching-cubes nodes along the longest side of each DANO's grid.
        ground: draw the plane z = 0 as a grid (a scene's floor).
        solids: the scene's other geoms (`scene_solids`), drawn in their colours.
        arrows: contact forces per frame (T, k, 2, 3): start and end (world, m) of each arrow
            (`dano.sim.render.contact_arrows`); an arrow with start == end is not drawn.

    Raises:
        ViewerError: a path that is not .html, no DANO, or frames naming a body that is not there.
    """
    path = Path(path)
    if path.suffix.lower() != ".html":
        raise ViewerError(f"the view must end in .html, got {path.name!r}")
    if not danos:
        raise ViewerError("nothing to view: no DANO")
    if frames is not None and set(frames.poses) - set(danos):
        raise ViewerError(f"the trajectory's bodies {sorted(set(frames.poses) - set(danos))} are not in the scene")
    upright = np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
    if frames is None:
        frames = Frames(np.zeros(1), {n: np.asarray((poses or {}).get(n, upright), float)[None] for n in danos})
    if arrows is not None and len(arrows) != len(frames.t):
        raise ViewerError(f"{len(arrows)} frames of contact forces for {len(frames.t)} frames of poses")
    data = {
        "title": title,
        "scene": ground,
        "bodies": [_body(name, d, max_points, resolution) for name, d in danos.items()],
        "t": np.asarray(frames.t, float).round(6).tolist(),
        "poses": {n: np.asarray(p, float).round(7).tolist() for n, p in frames.poses.items()},
        "solids": [_solid(sol) for sol in solids],
        "arrows": None if arrows is None else [_segments(a) for a in np.asarray(arrows, float)],
    }
    page = _TEMPLATE.read_text(encoding="utf-8").replace("/*DATA*/null", json.dumps(data, separators=(",", ":")))
    with atomic_write(path) as tmp:
        tmp.write_text(page.replace("<title></title>", f"<title>{_escape(title)}</title>"), encoding="utf-8")
    return path


def _body(name: str, d: DANO, max_points: int, resolution: int) -> dict:
    """One body's geometry in its body frame (origin at the centre of mass), rounded to 0.01 mm."""
    from dano.surface import surface_mesh

    points, normals = np.asarray(d.body_points), np.asarray(d.normals)
    densities = np.asarray(d.densities)
    keep = np.linspace(0, len(points) - 1, min(max_points, len(points))).round().astype(int)
    body = {
        "name": name,
        "points": points[keep].round(5).ravel().tolist(),
        "normals": normals[keep].round(4).ravel().tolist(),
        "density": ((densities[keep] - densities.min()) / max(float(np.ptp(densities)), 1e-12)).round(3).tolist(),
        "vertices": [],
        "faces": [],
        "size": float(np.max(np.ptp(points, axis=0))),
    }
    try:
        mesh = surface_mesh(d, resolution)
    except MeshError:  # no grid (a reference collider): its points only
        return body
    body["vertices"] = np.asarray(mesh.vertices).round(5).ravel().tolist()
    body["faces"] = np.asarray(mesh.faces).ravel().tolist()
    return body


def _solid(sol: Solid) -> dict:
    v = np.asarray(sol.vertices, float)
    size = float(np.max(np.ptp(v, axis=0))) if len(v) else 0.0
    return {
        "name": sol.name,
        "vertices": v.round(5).ravel().tolist(),
        "faces": np.asarray(sol.faces, int).ravel().tolist(),
        "rgba": [float(c) for c in np.asarray(sol.rgba)[:3]],
        "poses": np.asarray(sol.poses, float).round(7).tolist(),
        "size": size,
    }


def _segments(frame_arrows: np.ndarray) -> list:
    """One frame's arrows (k, 2, 3) as a flat list of the drawn ones' (start, end)."""
    drawn = frame_arrows[np.linalg.norm(frame_arrows[:, 1] - frame_arrows[:, 0], axis=-1) > 0]
    return drawn.round(5).ravel().tolist()


def scene_solids(model, qpos: np.ndarray, skip_bodies=()) -> tuple[Solid, ...]:
    """Every visible geom of a MuJoCo `model` (boxes, spheres, capsules, cylinders, ellipsoids,
    meshes, height fields' surfaces; planes are the view's floor grid) but those of `skip_bodies`
    (names: the DANOs), with its poses over the states `qpos` (T, nq)."""
    import mujoco
    import trimesh

    skip = {model.body(n).id for n in skip_bodies}
    G = mujoco.mjtGeom
    shapes = {
        int(G.mjGEOM_BOX): lambda s, _: trimesh.creation.box(extents=2 * s),
        int(G.mjGEOM_SPHERE): lambda s, _: trimesh.creation.icosphere(2, radius=s[0]),
        int(G.mjGEOM_CAPSULE): lambda s, _: trimesh.creation.capsule(height=2 * s[1], radius=s[0], count=(12, 12)),
        int(G.mjGEOM_CYLINDER): lambda s, _: trimesh.creation.cylinder(radius=s[0], height=2 * s[1], sections=16),
        int(G.mjGEOM_ELLIPSOID): lambda s, _: trimesh.creation.icosphere(2).apply_scale(s),
        int(G.mjGEOM_MESH): lambda _, g: _mesh_of(model, g),
        int(G.mjGEOM_HFIELD): lambda _, g: _height_field_of(model, g),
    }
    geoms = [
        g
        for g in range(model.ngeom)
        if model.geom_bodyid[g] not in skip and int(model.geom_type[g]) in shapes and model.geom_rgba[g, 3] > 0
    ]
    data = mujoco.MjData(model)
    poses = np.zeros((len(qpos), len(geoms), 7))
    for t, q in enumerate(np.asarray(qpos)):
        data.qpos[:] = q
        mujoco.mj_kinematics(model, data)
        for k, g in enumerate(geoms):
            mujoco.mju_mat2Quat(poses[t, k, 3:], data.geom_xmat[g])
            poses[t, k, :3] = data.geom_xpos[g]
    out = []
    for k, g in enumerate(geoms):
        m = shapes[int(model.geom_type[g])](np.asarray(model.geom_size[g], float), g)
        name = model.geom(g).name or model.body(model.geom_bodyid[g]).name or f"world geom {g}"
        out.append(Solid(name, np.asarray(m.vertices), np.asarray(m.faces), model.geom_rgba[g].copy(), poses[:, k]))
    return tuple(out)


def _mesh_of(model, g: int):
    import trimesh

    m = model.geom_dataid[g]
    v0, nv, f0, nf = model.mesh_vertadr[m], model.mesh_vertnum[m], model.mesh_faceadr[m], model.mesh_facenum[m]
    return trimesh.Trimesh(model.mesh_vert[v0 : v0 + nv], model.mesh_face[f0 : f0 + nf], process=False)


def _height_field_of(model, g: int):
    """A height field's surface as a triangle mesh (its nodes, two triangles per cell)."""
    import trimesh

    h = model.geom_dataid[g]
    rows, cols, adr = model.hfield_nrow[h], model.hfield_ncol[h], model.hfield_adr[h]
    rx, ry, top, _ = model.hfield_size[h]
    z = np.asarray(model.hfield_data[adr : adr + rows * cols], float).reshape(rows, cols) * top
    x, y = np.meshgrid(np.linspace(-rx, rx, cols), np.linspace(-ry, ry, rows))
    k = np.arange(rows * cols).reshape(rows, cols)
    a, b, c, d = k[:-1, :-1].ravel(), k[:-1, 1:].ravel(), k[1:, :-1].ravel(), k[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, d], axis=1), np.stack([a, d, c], axis=1)])
    return trimesh.Trimesh(np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1), faces, process=False)


def view_simulation(path: str | Path, sim, traj, contacts=None, **kwargs) -> Path:
    """`write_view` of a rollout of a `dano.sim.run.Simulation`: its DANOs and every other geom of
    its scene (`scene_solids`) moving as they did, over the floor, and with `contacts` (the
    rollout's `dano.sim.contacts.ContactForces`) its contact forces as arrows."""
    from dano.sim.run import body_poses

    qpos = np.asarray(traj.qpos)
    danos = {b.name: b.dano for b in sim.scene.bodies}
    t = np.arange(len(qpos)) * sim.scene.timestep
    poses = {n: p for n, p in body_poses(traj, sim).items() if n in danos}
    solids = scene_solids(sim.model, qpos, skip_bodies=danos)
    arrows = None
    if contacts is not None:
        from dano.sim.render import contact_arrows

        arrows = contact_arrows(sim, contacts)[:, :, :2]
    ground = sim.scene.ground_height is not None
    return write_view(path, danos, frames=Frames(t, poses), ground=ground, solids=solids, arrows=arrows, **kwargs)


def _escape(text: str) -> str:
    import html

    return html.escape(text)


def view_scene(path: str | Path, scene, trajectory: str | Path | None = None, **kwargs) -> Path:
    """`write_view` of a `dano.sim.Scene`'s DANOs at their start poses, or playing a `dano simulate`
    CSV of it (`trajectory`), over the scene's floor, with the scene's other geoms where they start
    (a CSV holds the DANOs' poses only: `view_simulation` shows everything moving)."""
    from dano.sim.compile import compile_scene

    danos = {b.name: b.dano for b in scene.bodies}
    model, _, _, qpos, _ = compile_scene(scene)
    kwargs.setdefault("solids", scene_solids(model, np.asarray(qpos)[None], skip_bodies=danos))
    if trajectory is None:
        poses = {b.name: np.array([*b.pos, *b.quat], float) for b in scene.bodies}
        return write_view(path, danos, poses=poses, ground=True, **kwargs)
    from dano.sysid.data import read_tracks

    tracks = read_tracks(trajectory)
    if not tracks or any(tr.t.shape != next(iter(tracks.values())).t.shape for tr in tracks.values()):
        raise ViewerError(f"{trajectory}: the bodies' rows are not at the same times")
    t = next(iter(tracks.values())).t
    frames = Frames(t, {n: np.concatenate([tr.pos, tr.quat], axis=1) for n, tr in tracks.items()})
    return write_view(path, danos, frames=frames, ground=True, **kwargs)
