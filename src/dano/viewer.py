"""An interactive 3D view of DANOs in the browser, as one self-contained HTML page (WebGL, no
library, no server): `dano view OBJ.dano.npz -o view.html`, `dano view SCENE.toml [--trajectory
TRAJ.csv] -o view.html`.

Each DANO is shown as its surface (`dano.surface.surface_mesh`), its surface points coloured by
density, their normals and its centre of mass, each switchable; a trajectory adds a timeline to
scrub and play. Drag to orbit, scroll to zoom. The page opens from disk in any browser with WebGL.
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


def write_view(
    path: str | Path,
    danos: dict[str, DANO],
    poses: dict[str, np.ndarray] | None = None,
    frames: Frames | None = None,
    title: str = "dano view",
    max_points: int = 3000,
    resolution: int = 64,
    ground: bool = False,
) -> Path:
    """Writes the page (module docstring) to `path` (.html), atomically, and returns the path.

    Args:
        danos: the objects by name.
        poses: each one's pose (7,) when no `frames` are given (default: at the origin, upright).
        frames: a trajectory to play (`Frames`); every body it names must be in `danos`.
        max_points: surface points shown per DANO (an evenly spread subsample).
        resolution: marching-cubes nodes along the longest side of each DANO's grid.
        ground: draw the plane z = 0 as a grid (a scene's floor).

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
    data = {
        "title": title,
        "scene": ground,
        "bodies": [_body(name, d, max_points, resolution) for name, d in danos.items()],
        "t": np.asarray(frames.t, float).round(6).tolist(),
        "poses": {n: np.asarray(p, float).round(7).tolist() for n, p in frames.poses.items()},
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


def _escape(text: str) -> str:
    import html

    return html.escape(text)


def view_scene(path: str | Path, scene, trajectory: str | Path | None = None, **kwargs) -> Path:
    """`write_view` of a `dano.sim.Scene`'s DANOs at their start poses, or playing a `dano simulate`
    CSV of it (`trajectory`), over the scene's floor."""
    danos = {b.name: b.dano for b in scene.bodies}
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
