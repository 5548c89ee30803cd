"""From a tracker's frame to the simulator's: metric scale, gravity, and the table.

A pose tracker that renders the object's density field reports poses in the field's own units and
in the camera's frame. To simulate them we need three facts the images do not give: the metric
scale (metres per unit: `scale`, or the object's real size), the direction of gravity in the
camera frame (given, or fitted from the plane the object slides in), and where the table is (put
under the object, touching it). Rather than rotating the data, the scene is posed in the camera
frame: gravity along the given direction and the ground plane normal to it.
"""

import dataclasses
import warnings

import numpy as np

from dano.build import scale_lengths
from dano.sim.scene import Scene
from dano.sysid.configs import SysidError
from dano.sysid.data import Track, motion_plane_normal, to_metric
from dano.sysid.windows import Recording

STANDARD_GRAVITY = 9.81


def extent(scene: Scene, name: str | None = None) -> float:
    """A DANO's longest dimension along its principal axes (`DANO.principal_extents`), in the scene's
    units: what a ruler laid along the object measures, whatever frame its field was built in."""
    return longest_extent(scene_dano(scene, name).dano)


def longest_extent(dano) -> float:
    """The largest of `DANO.principal_extents`, in the DANO's units."""
    return float(np.max(np.asarray(dano.principal_extents())))


class UnitsWarning(UserWarning):
    """The track and the DANO look as if they were in different units (or neither in metres): an
    object of implausible size, or a track that spans too many of the object's own lengths. A slide
    alone cannot tell (friction and scale trade off: positions ×3 fit μ ×3), so check `dano info`'s
    principal extents and give `--scale` or `--size`."""


SIZE_RANGE = (0.005, 3.0)
"""m: longest principal extents of objects a tabletop experiment plausibly holds."""

MAX_SPAN = 100.0
"""A track that spans more than this many of the object's longest extents is suspect."""


def warn_implausible_units(scene: Scene, recordings: list[Recording]) -> None:
    """Warns (`UnitsWarning`) for each observed DANO whose longest principal extent is outside
    `SIZE_RANGE` or whose track spans more than `MAX_SPAN` of it."""
    sizes = {b.name: longest_extent(b.dano) for b in scene.bodies}
    advice = "are the DANO and the track both in metres? (dano info prints the DANO's extents; --scale, --size)"
    for name, size in sizes.items():
        if not SIZE_RANGE[0] <= size <= SIZE_RANGE[1]:
            warnings.warn(f"the DANO {name!r} is {size:.3g} m long along its principal axes: {advice}", UnitsWarning, 3)
    for r in recordings:
        for name, track in r.tracks.items():
            if name not in sizes:
                continue
            pos = np.asarray(track.pos)
            span = float(np.max(np.ptp(pos, axis=0)))
            if span > MAX_SPAN * sizes[name]:
                warnings.warn(
                    f"the track of {name!r} spans {span:.3g} m, {span / sizes[name]:.0f} times the DANO's "
                    f"{sizes[name]:.3g} m: {advice}",
                    UnitsWarning,
                    3,
                )


def scene_dano(scene: Scene, name: str | None, what: str = "the size refers to"):
    """The scene's DANO called `name`, or its only one (None); `what` ends the message asking for a name."""
    if name is None:
        if len(scene.bodies) != 1:
            raise SysidError(f"the scene has {len(scene.bodies)} DANOs: name the one {what}")
        return scene.bodies[0]
    for b in scene.bodies:
        if b.name == name:
            return b
    raise SysidError(f"the scene has no DANO {name!r}")


def scaled(scene: Scene, recordings: list[Recording], scale: float, objects_too: bool) -> tuple[Scene, list]:
    """Positions in the recordings × scale; with `objects_too`, the scene's DANOs as well (their field
    shares the tracker's units, e.g. both come from one NeRF)."""
    if not (np.isfinite(scale) and scale > 0):
        raise SysidError(f"the scale must be a positive number of metres per unit, got {scale}")
    recs = [dataclasses.replace(r, tracks={k: to_metric(t, scale) for k, t in r.tracks.items()}) for r in recordings]
    if objects_too:
        bodies = tuple(dataclasses.replace(b, dano=scale_lengths(b.dano, scale)) for b in scene.bodies)
        scene = dataclasses.replace(scene, bodies=bodies)
    return scene, recs


def with_gravity(scene: Scene, recordings: list[Recording], down: np.ndarray) -> Scene:
    """The scene posed in the data's frame: gravity along `down` (|g| kept, 9.81 if the scene has
    none) and the ground plane normal to it, touching the observed DANOs from below (the median,
    over all frames, of their lowest surface point along `down`). Tracks are keyed by the scene's
    body names (see `named_after_scene`)."""
    from scipy.spatial.transform import Rotation

    down = np.asarray(down, dtype=float)
    if down.shape != (3,) or not np.linalg.norm(down) > 0:
        raise SysidError(f"the gravity direction must be a non-zero 3-vector, got {down}")
    down = down / np.linalg.norm(down)
    up = -down
    g = float(np.linalg.norm(scene.gravity)) or STANDARD_GRAVITY
    lows = []
    for r in recordings:
        for name, tr in r.tracks.items():
            body = next((b for b in scene.bodies if b.name == name), None)
            if body is None:
                continue
            R = Rotation.from_quat(tr.quat[:, [1, 2, 3, 0]]).as_matrix()  # (T, 3, 3)
            points = np.asarray(body.dano.body_points)  # (k, 3) about the centre of mass
            heights = np.einsum("j,tjk,nk->tn", up, R, points) + (tr.pos @ up)[:, None]
            lows.append(heights.min(axis=1))
    if not lows:
        raise SysidError("no observed DANO to put the table under")
    return dataclasses.replace(
        scene, gravity=tuple(float(v) for v in g * down), ground_normal=tuple(float(v) for v in up),
        ground_height=float(np.median(np.concatenate(lows))),
    )  # fmt: skip


def plane_of_motion(recordings: list[Recording]) -> np.ndarray:
    """The gravity axis (unit, sign undetermined) from the plane the observed bodies move in."""
    tracks: list[Track] = [t for r in recordings for t in r.tracks.values()]
    return motion_plane_normal(tracks)


@dataclasses.dataclass(frozen=True)
class RestingPose:
    """A way the object can lie still on a table: `quat` (w, x, y, z) turns the body so that the face
    with outward `normal` (body frame) faces down the table's normal, `height` is then the centre of
    mass's height above the table (m)."""

    quat: tuple[float, float, float, float]
    normal: tuple[float, float, float]
    height: float


def resting_poses(dano, up=(0.0, 0.0, 1.0), separation_deg: float = 10.0) -> list[RestingPose]:
    """The DANO's stable resting poses on a plane with normal `up`, lowest centre of mass first.

    A face of the convex hull of the surface points is one the object can rest on when the centre of
    mass's perpendicular foot on its plane falls inside it (the potential energy is then at a local
    minimum). A noisy hull splits a flat face into many facets: poses whose face normals are within
    `separation_deg` are one, the lowest kept.
    """
    from scipy.spatial import ConvexHull
    from scipy.spatial.transform import Rotation

    points = np.asarray(dano.body_points, dtype=np.float64)
    hull = ConvexHull(points)
    found: list[tuple[float, np.ndarray]] = []
    for simplex, (*normal, offset) in zip(hull.simplices, hull.equations, strict=True):
        n = np.asarray(normal)
        foot = -offset * n  # the centre of mass (the origin) dropped onto the facet's plane
        a, b, c = points[simplex]
        # barycentric test of the foot in the triangle abc
        v0, v1, v2 = b - a, c - a, foot - a
        d00, d01, d11, d20, d21 = v0 @ v0, v0 @ v1, v1 @ v1, v2 @ v0, v2 @ v1
        det = d00 * d11 - d01 * d01
        if det <= 0:
            continue
        beta, gamma = (d11 * d20 - d01 * d21) / det, (d00 * d21 - d01 * d20) / det
        if beta >= -1e-9 and gamma >= -1e-9 and beta + gamma <= 1 + 1e-9:
            found.append((float(-offset), n))
    found.sort(key=lambda f: f[0])
    cos = np.cos(np.radians(separation_deg))
    kept: list[tuple[float, np.ndarray]] = []
    for height, n in found:
        if all(n @ m < cos for _, m in kept):
            kept.append((height, n))
    up = np.asarray(up, dtype=float) / np.linalg.norm(up)
    poses = []
    for height, n in kept:
        turn = Rotation.align_vectors(-up[None], n[None])[0]  # the face's normal onto -up
        x, y, z, w = (float(v) for v in turn.as_quat())
        poses.append(RestingPose((w, x, y, z), (float(n[0]), float(n[1]), float(n[2])), height))
    return poses


def lying_on(track: Track, pose: RestingPose, yaw: float, up=(0.0, 0.0, 1.0)) -> Track:
    """The track with its orientation replaced by `pose` turned by `yaw` (rad) about `up`, constant
    over the frames (for a tracker that could not resolve rotation; fit positions only)."""
    from scipy.spatial.transform import Rotation

    up = np.asarray(up, dtype=float) / np.linalg.norm(up)
    w, x, y, z = pose.quat
    q = (Rotation.from_rotvec(yaw * up) * Rotation.from_quat([x, y, z, w])).as_quat()
    quat = np.tile(np.array([q[3], q[0], q[1], q[2]]), (track.n_frames, 1))
    return dataclasses.replace(track, quat=quat)
