"""Robots, host side: a URDF or MJCF file loaded with MuJoCo's compiler, servos on its joints, and
its collision geoms as DANOs see them (`LinkGeom`)."""

import re
from pathlib import Path

import jax.numpy as jnp
import mujoco
import numpy as np

from dano.sim.scene import Robot, SceneError
from dano.sim.world import LinkGeom


def robot_spec(robot: Robot) -> mujoco.MjSpec:
    """Loads the robot with MuJoCo's own compiler: URDF paths resolved, visuals dropped."""
    path = Path(robot.path)
    if not path.is_file():
        raise SceneError(f"robot file {path} not found")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise SceneError(f"robot file {path} cannot be read: {e}") from None
    if path.suffix.lower() == ".urdf":
        for name, folder in robot.package_dirs:
            text = text.replace(f"package://{name}/", f"{Path(folder).resolve()}/")
        unresolved = sorted(set(re.findall(r"package://([^/\"]+)", text)))
        if unresolved:
            raise SceneError(
                f"robot file {path} uses package(s) {unresolved} that package_dirs does not give: pass "
                f"package_dirs=(({unresolved[0]!r}, FOLDER),)"
            )
        text = re.sub(r'filename="(?!/)([^"]+)"', lambda m: f'filename="{(path.parent / m.group(1)).resolve()}"', text)
        missing = [f for f in re.findall(r'filename="([^"]+)"', text) if not Path(f).is_file()]
        if missing:
            raise SceneError(f"robot file {path}: mesh file {missing[0]} not found ({len(missing)} missing)")
        compiler = '<mujoco><compiler discardvisual="true" balanceinertia="true" fusestatic="false"/></mujoco>'
        text = re.sub(r"(<robot[^>]*>)", r"\1" + compiler, text, count=1)
        return _parse_robot(path, lambda: mujoco.MjSpec.from_string(text))
    return _parse_robot(path, lambda: mujoco.MjSpec.from_file(str(path)))


def world_spec(path: str) -> mujoco.MjSpec:
    """Loads an MJCF world with MuJoCo's own compiler (`Scene.mjcf`), as it is."""
    if not Path(path).is_file():
        raise SceneError(f"MJCF world {path} not found")
    try:
        return mujoco.MjSpec.from_file(str(path))
    except ValueError as e:
        raise SceneError(f"MJCF world {path}: MuJoCo cannot load it: {' '.join(str(e).split())}") from None


def world_geoms(model: mujoco.MjModel, skip_bodies: set[int]) -> list[int]:
    """An MJCF world's colliding geoms (`Scene.mjcf`): every geom with a contact type or affinity,
    but the scene's own ground and the geoms of `skip_bodies` (the DANOs', the primitives')."""
    ground = model.geom("ground").id if "ground" in [model.geom(g).name for g in range(model.ngeom)] else -1
    return [g for g in range(model.ngeom) if g != ground and model.geom_bodyid[g] not in skip_bodies
            and (model.geom_contype[g] or model.geom_conaffinity[g])]  # fmt: skip


def _parse_robot(path, parse) -> mujoco.MjSpec:
    try:
        return parse()
    except ValueError as e:  # MuJoCo's parser: bad XML, a missing mesh of an MJCF, ...
        raise SceneError(f"robot file {path}: MuJoCo cannot load it: {' '.join(str(e).split())}") from None


def prepare_robot(spec: mujoco.MjSpec, robot: Robot) -> list[str]:
    """Places the robot and adds a position servo per joint; returns the robot's body names."""
    root = spec.worldbody.first_body()
    root.pos, root.quat = list(robot.base_pos), list(robot.base_quat)
    bodies = [body.name for body in spec.bodies if body.name != "world"]
    for body in spec.bodies:
        if robot.gravity_compensation and body.name != "world":
            body.gravcomp = 1.0
    for joint in spec.joints:
        if joint.type in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE):
            act = spec.add_actuator(name=f"{joint.name}_servo", target=joint.name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
            act.set_to_position(kp=float(robot.kp), kv=float(robot.kv))
            if robot.armature is not None:
                joint.armature = float(robot.armature)
    return bodies


def check_servo_damping(model: mujoco.MjModel, qpos: np.ndarray) -> None:
    """Raises `SceneError` where a joint servo's damping (kv = -biasprm[2]) is explicitly unstable
    at `qpos`: kv h / M_jj >= 2 under Euler (`implicitfast` integrates it implicitly)."""
    if model.opt.integrator == mujoco.mjtIntegrator.mjINT_IMPLICITFAST:
        return
    data = mujoco.MjData(model)
    data.qpos[:] = qpos
    mujoco.mj_forward(model, data)
    M = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, data, M)
    for a in range(model.nu):
        if model.actuator_trntype[a] != mujoco.mjtTrn.mjTRN_JOINT:
            continue
        joint = int(model.actuator_trnid[a, 0])
        dof = int(model.jnt_dofadr[joint])
        kv = -float(model.actuator_biasprm[a, 2])
        ratio = kv * model.opt.timestep / M[dof, dof]
        if ratio >= 2.0:
            raise SceneError(
                f"the servo of joint {model.joint(joint).name!r} is unstable: kv h / M = {kv:g} x "
                f"{model.opt.timestep:g} s / {M[dof, dof]:.3g} = {ratio:.2f} >= 2 (MuJoCo integrates its "
                "damping explicitly); give the robot an armature, a smaller kv, a smaller time step, or use "
                'integrator = "implicit"'
            )


def robot_geoms(model: mujoco.MjModel, bodies: list[str], robot: Robot | None) -> list[int]:
    """The robot's geoms that touch DANOs (`robot.contact_bodies`, else all), with MuJoCo's own
    collisions switched off for every robot geom: DANOs see them instead."""
    ids = {model.body(name).id for name in bodies}
    geoms = [g for g in range(model.ngeom) if model.geom_bodyid[g] in ids]
    for g in geoms:
        model.geom_contype[g] = model.geom_conaffinity[g] = 0
    if robot is not None and robot.contact_bodies:
        touching = {model.body(name).id for name in robot.contact_bodies}
        geoms = [g for g in geoms if model.geom_bodyid[g] in touching]
    return geoms


_LINK_KINDS = {
    mujoco.mjtGeom.mjGEOM_PLANE: "mesh",  # one half-space
    mujoco.mjtGeom.mjGEOM_BOX: "box",
    mujoco.mjtGeom.mjGEOM_SPHERE: "sphere",
    mujoco.mjtGeom.mjGEOM_CAPSULE: "capsule",
    mujoco.mjtGeom.mjGEOM_MESH: "mesh",
    mujoco.mjtGeom.mjGEOM_CYLINDER: "cylinder",
    mujoco.mjtGeom.mjGEOM_HFIELD: "hfield",
}


def link_geom(model: mujoco.MjModel, g: int) -> LinkGeom:
    """The DANO-side view of a robot collision geom (convex meshes as half-space intersections)."""
    from scipy.spatial import ConvexHull

    body = int(model.geom_bodyid[g])
    kind = _LINK_KINDS.get(mujoco.mjtGeom(model.geom_type[g]))
    if kind is None:
        name, kind_name = model.geom(g).name or f"number {g}", mujoco.mjtGeom(model.geom_type[g]).name
        raise SceneError(f"geom {name} of type {kind_name} cannot touch DANOs (box, sphere, capsule, cylinder, "
                         "convex mesh, plane and height field can): give it contype=0 conaffinity=0")  # fmt: skip
    size = tuple(float(v) for v in model.geom_size[g])
    normals = offsets = None
    if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_PLANE:  # z <= 0 in its frame; no broad phase
        return LinkGeom(g, body, int(model.body_rootid[body]), "mesh", size, 0.0, jnp.array([[0.0, 0.0, 1.0]]),
                        jnp.zeros(1))  # fmt: skip
    if kind == "mesh":
        m = model.geom_dataid[g]
        vert = model.mesh_vert[model.mesh_vertadr[m] : model.mesh_vertadr[m] + model.mesh_vertnum[m]]
        planes = np.unique(np.round(ConvexHull(vert).equations, 6), axis=0)  # n . x + c <= 0 inside
        normals, offsets = jnp.asarray(planes[:, :3]), jnp.asarray(-planes[:, 3])
        radius = float(np.max(np.linalg.norm(vert, axis=1)))
    elif kind == "hfield":  # MuJoCo's size (x, y, top, base): heights = data (0..1) x top
        h = model.geom_dataid[g]
        rows, cols, adr = model.hfield_nrow[h], model.hfield_ncol[h], model.hfield_adr[h]
        size = tuple(float(v) for v in model.hfield_size[h])
        heights = np.asarray(model.hfield_data[adr : adr + rows * cols], float).reshape(rows, cols) * size[2]
        radius = float(np.linalg.norm([size[0], size[1], max(size[2], size[3])]))
        return LinkGeom(g, body, int(model.body_rootid[body]), kind, size, radius, heights=jnp.asarray(heights))
    else:
        radius = float(np.linalg.norm(model.geom_size[g])) + (size[1] if kind == "capsule" else 0.0)
    return LinkGeom(g, body, int(model.body_rootid[body]), kind, size, radius, normals, offsets)
