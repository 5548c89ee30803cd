"""A dano scene for plain MuJoCo: one MJCF file that `mujoco.MjModel.from_xml_path` loads with no
dano installed.

Each DANO becomes a free body with its mass, centre of mass and full inertia tensor (written at full
precision: MuJoCo's own XML writer keeps 6 digits), a visual mesh (marching cubes of its baked
density grid at the middle of its density window, the surface its points were drawn from) and
collision geoms from the mesh path (that surface's convex decomposition, CoACD or V-HACD). **The
collision geometry is the mesh path's approximation, not the DANO's contact model**: MuJoCo's
contact on convex hulls fills concavities and is a different model (`dano compare` measures how far
the two part). The DANOs' meshes are written inline in the file; files the scene itself refers to
(a robot's meshes) are copied into a folder beside it (`scene.xml` → `scene_assets/`) and referred to
by relative path, so the file and its folder can be moved together. Everything else in the scene
(ground, primitives, robot, options) is what dano compiles for itself.
"""

import shutil
import xml.etree.ElementTree as ET
from pathlib import Path

import mujoco
import numpy as np

from dano.baselines.mesh import convex_decomposition
from dano.errors import DanoError, MeshError
from dano.io import atomic_folder, atomic_write
from dano.sim.compile import add_mesh_geom, scene_spec
from dano.sim.scene import DanoBody, Scene
from dano.surface import surface_mesh


class ExportError(DanoError):
    """A scene that cannot be written for plain MuJoCo as asked."""


def export_scene(
    scene: Scene,
    path: str | Path,
    *,
    method: str = "coacd",
    threshold: float = 0.05,
    resolution: int = 64,
    progress: bool = True,
    trajectory: str | Path | None = None,
) -> Path:
    """Writes `scene` to `path` (.xml) for plain MuJoCo (module docstring) and returns the path.

    Args:
        method, threshold: the convex decomposition (`dano.baselines.mesh.convex_decomposition`).
        resolution: marching-cubes nodes along the longest side of each DANO's grid box.
        trajectory: a `dano simulate` CSV of this scene, written as one keyframe per frame (`<key
            time qpos>`: replay with `mujoco.mj_resetDataKeyframe(model, data, k)`).

    Raises:
        ExportError: a path that is not .xml, a DANO without a grid, or one whose principal moments
            MuJoCo refuses (the triangle inequality); a trajectory that does not fit the scene (a
            body it lacks or has too many, frames of different times, joints other than free
            ones, whose positions a pose CSV does not hold); the file is then not written.
    """
    path = Path(path)
    if path.suffix.lower() != ".xml":
        raise ExportError(f"the MJCF file must end in .xml, got {path.name!r}")
    spec, _ = scene_spec(scene)
    _absolute_files(spec)
    friction = [float(scene.contact.sliding_friction), 0.005, 0.0001]
    for body in scene.bodies:
        _add_geoms(spec, body, friction, method, threshold, resolution, progress)
    root = ET.fromstring(spec.to_xml())
    for body in scene.bodies:
        _write_inertial(root, body)
    if trajectory is not None:
        _add_keyframes(root, spec.compile(), trajectory)
    _check(ET.tostring(root, encoding="unicode"), scene)
    copies = _bundle(root, path)
    if copies:
        with atomic_folder(path.parent / f"{path.stem}_assets") as folder:
            for source, name in copies.items():
                shutil.copyfile(source, folder / name)
    with atomic_write(path) as tmp:
        tmp.write_text(ET.tostring(root, encoding="unicode"))
    return path


def _absolute_files(spec: mujoco.MjSpec) -> None:
    """Every asset file of the spec (a robot's meshes, textures, height fields) by absolute path,
    resolved as MuJoCo would from the file's folder and its compiler's mesh and texture folders."""
    base = Path(spec.modelfiledir or ".")
    for assets, folder in ((spec.meshes, spec.meshdir), (spec.skins, spec.meshdir), (spec.hfields, spec.meshdir),
                           (spec.textures, spec.texturedir)):  # fmt: skip
        for asset in assets:
            if asset.file and not Path(asset.file).is_absolute():
                asset.file = str((base / (folder or "") / asset.file).resolve())
    spec.meshdir = spec.texturedir = ""


def _bundle(root: ET.Element, path: Path) -> dict[Path, str]:
    """Points every `file=` of the MJCF (a robot's meshes, textures) at a copy in `<stem>_assets/`
    beside `path`, by relative path; returns the copies to make (source → name in that folder)."""
    copies: dict[Path, str] = {}
    for element in root.iter():
        if "file" not in element.attrib:
            continue
        source = Path(element.attrib["file"]).resolve()
        if source not in copies:
            taken = set(copies.values())
            copies[source] = source.name if source.name not in taken else f"{len(copies)}_{source.name}"
        element.set("file", f"{path.stem}_assets/{copies[source]}")
    return copies


def _add_geoms(spec: mujoco.MjSpec, body: DanoBody, friction, method, threshold, resolution, progress) -> None:
    """The visual mesh (no collision, group 1) and the convex pieces (collision, invisible group 3)."""
    try:
        surface = surface_mesh(body.dano, resolution)
    except MeshError as e:
        raise ExportError(f"{body.name}: {e}") from None
    pieces = convex_decomposition(surface, method=method, threshold=threshold, progress=progress)
    add_mesh_geom(spec, body.name, f"{body.name}_surface", surface, collide=False, group=1, rgba=[0.85, 0.55, 0.35, 1])
    for i, piece in enumerate(pieces):
        add_mesh_geom(spec, body.name, f"{body.name}_hull{i}", piece, collide=True, group=3, friction=friction)


def _add_keyframes(root: ET.Element, model: mujoco.MjModel, trajectory: str | Path) -> None:
    """One `<key>` per frame of the trajectory CSV: its time and qpos, each free body's from its pose."""
    from dano.sysid.data import read_tracks

    tracks = read_tracks(trajectory)
    free = {}
    for j in range(model.njnt):
        name = model.body(model.jnt_bodyid[j]).name
        if model.jnt_type[j] != mujoco.mjtJoint.mjJNT_FREE:
            raise ExportError(f"{trajectory}: keyframes need the position of joint {model.joint(j).name!r} of "
                              f"{name!r}, which a pose CSV does not hold (free bodies only)")  # fmt: skip
        free[name] = int(model.jnt_qposadr[j])
    if set(tracks) != set(free):
        raise ExportError(f"{trajectory}: the trajectory's bodies {sorted(tracks)} are not the scene's free bodies "
                          f"{sorted(free)}")  # fmt: skip
    t = next(iter(tracks.values())).t
    if any(tr.t.shape != t.shape or not np.allclose(tr.t, t) for tr in tracks.values()):
        raise ExportError(f"{trajectory}: the bodies' rows are not at the same times")
    keyframe = ET.SubElement(root, "keyframe")
    for k in range(len(t)):
        qpos = np.array(model.qpos0, dtype=float)
        for name, a in free.items():
            qpos[a : a + 3], qpos[a + 3 : a + 7] = tracks[name].pos[k], tracks[name].quat[k]
        ET.SubElement(keyframe, "key", {"time": repr(float(t[k])), "qpos": " ".join(f"{v:.12g}" for v in qpos)})


def _write_inertial(root: ET.Element, body: DanoBody) -> None:
    """The DANO's mass and full inertia tensor (body frame) at full precision, replacing what
    MuJoCo's writer kept of them."""
    element = root.find(f".//body[@name='{body.name}']")
    if element is None:  # an invariant: scene_spec adds every DANO
        raise AssertionError(f"no body {body.name!r} in the written MJCF")
    for old in element.findall("inertial"):
        element.remove(old)
    J = np.asarray(body.dano.inertia, dtype=float)
    full = [J[0, 0], J[1, 1], J[2, 2], J[0, 1], J[0, 2], J[1, 2]]
    attrs = {"pos": "0 0 0", "mass": repr(float(body.dano.mass)), "fullinertia": " ".join(repr(float(v)) for v in full)}
    element.insert(0, ET.Element("inertial", attrs))


def _check(xml: str, scene: Scene) -> None:
    """Loads the file as plain MuJoCo would, and checks each DANO's mass and inertia against it."""
    try:
        model = mujoco.MjModel.from_xml_string(xml)
    except ValueError as e:
        raise ExportError(f"MuJoCo refuses the exported scene: {' '.join(str(e).split())}") from None
    for body in scene.bodies:
        i = model.body(body.name).id
        R = np.zeros(9)
        mujoco.mju_quat2Mat(R, model.body_iquat[i])
        R = R.reshape(3, 3)
        J = R @ np.diag(model.body_inertia[i]) @ R.T
        want = np.asarray(body.dano.inertia, dtype=float)
        if abs(model.body_mass[i] - float(body.dano.mass)) > 1e-9 * float(body.dano.mass) or not np.allclose(
            J, want, rtol=0.0, atol=1e-9 * np.abs(want).max()
        ):
            raise AssertionError(f"{body.name}: the exported inertia differs from the DANO's")  # an invariant
