"""Scenes, compiled: a `Scene` to a MuJoCo model (MjSpec), the `World` the step reads, default
`Params` and the initial state, with the checks that need the compiled model (unknown pairs or
contact bodies, a start the contact cannot resolve, a servo MuJoCo cannot integrate)."""

from collections.abc import Callable
from typing import NamedTuple

import jax.numpy as jnp
import mujoco
import numpy as np
from jaxtyping import Array

from dano.contact import ContactParams, active
from dano.contact.pairs import ForceMode
from dano.sim.robots import (
    check_servo_damping,
    link_geom,
    prepare_robot,
    robot_geoms,
    robot_spec,
    world_geoms,
    world_spec,
)
from dano.sim.scene import DanoBody, Integrator, Primitive, Scene, SceneError
from dano.sim.world import MOVING, DanoState, Params, PrimGeom, World, pair_name, pairs


def principal_frame(inertia) -> tuple[np.ndarray, np.ndarray]:
    """Principal moments (3,) and the quaternion (w, x, y, z) of the principal axes (a proper
    rotation) of an inertia tensor (3, 3) given in the body frame."""
    moments, axes = np.linalg.eigh(np.asarray(inertia, dtype=np.float64))
    if np.linalg.det(axes) < 0:
        axes[:, 0] = -axes[:, 0]
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, axes.ravel())
    return moments, quat


def _add_dano(spec: mujoco.MjSpec, body: DanoBody) -> None:
    """A free body whose inertial frame is the DANO's principal frame.

    The principal frame must be given to the compiler: MuJoCo decides from `ipos`/`iquat` whether
    the inertial frame is the body frame (`body_sameframe`, `body_simple`) and then ignores
    `body_iquat`, so writing the frame into the compiled model afterwards turns the tensor about
    the wrong axes. The moments are written after compiling (`_set_moments`): the compiler rejects
    moments that break the triangle inequality, which the reference DANOs need (`dano.reference`).
    """
    d = body.dano
    _, quat = principal_frame(d.inertia)
    b = spec.worldbody.add_body(name=body.name, pos=list(body.pos), quat=list(body.quat))
    b.add_freejoint(name=f"{body.name}_free")
    b.mass = float(d.mass)
    b.ipos = [0.0, 0.0, 0.0]
    b.iquat = quat.tolist()
    b.inertia = [1.0, 1.0, 1.0]  # replaced after compiling by `_set_moments`
    b.explicitinertial = True


def _set_moments(model: mujoco.MjModel, body: int, inertia: np.ndarray) -> None:
    """Writes the principal moments of a full inertia tensor (body frame) into the compiled model,
    whose inertial frame `_add_dano` already set to the tensor's principal axes."""
    moments, quat = principal_frame(inertia)
    if not np.allclose(np.abs(quat @ model.body_iquat[body]), 1.0, atol=1e-9):
        raise AssertionError("the compiled inertial frame is not the principal frame")  # an invariant
    model.body_inertia[body] = moments


_GEOM = {
    "sphere": mujoco.mjtGeom.mjGEOM_SPHERE,
    "capsule": mujoco.mjtGeom.mjGEOM_CAPSULE,
    "box": mujoco.mjtGeom.mjGEOM_BOX,
}


def add_mesh_geom(spec: mujoco.MjSpec, body: str, name: str, mesh, *, collide: bool, **attrs):
    """A massless geom of a triangle mesh (`trimesh.Trimesh`, written inline as the mesh asset
    `name`) on `body`: a DANO's drawn surface (`collide=False`: no MuJoCo contact) or a convex piece
    of it, for renders and exports. `attrs` are the geom's own (rgba, group, friction)."""
    spec.add_mesh(name=name, uservert=mesh.vertices.ravel().tolist(), userface=mesh.faces.ravel().tolist())
    geom = spec.body(body).add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_MESH, meshname=name, mass=0.0, **attrs)
    if not collide:
        geom.contype = geom.conaffinity = 0
    return geom


def add_primitive(spec: mujoco.MjSpec, p: Primitive, friction: float | None = None) -> None:
    """Adds a primitive to a MuJoCo spec as dano's scenes have it: a static geom, a free or mocap
    body, or an actuated one (three world-axis slides under force motors, weight compensated);
    `friction` sets MuJoCo's own sliding friction on its geom (for MuJoCo C baselines)."""
    mu = {} if friction is None else {"friction": [friction, 0.005, 0.0001]}
    if p.mode == "static":
        spec.worldbody.add_geom(
            name=p.name, type=_GEOM[p.kind], size=_mj_size(p), pos=list(p.pos), quat=list(p.quat), **mu
        )
        return
    b = spec.worldbody.add_body(name=p.name, pos=list(p.pos), quat=list(p.quat), mocap=p.mode == "mocap")
    if p.mode == "free":
        b.add_freejoint(name=f"{p.name}_free")
    if p.mode == "actuated":
        b.gravcomp = 1.0
        R = np.zeros(9)
        mujoco.mju_quat2Mat(R, np.asarray(p.quat, dtype=float) / np.linalg.norm(p.quat))
        for k, axis in enumerate("xyz"):
            local = R.reshape(3, 3).T[:, k]  # world axis k in the body frame
            b.add_joint(name=f"{p.name}_slide{axis}", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=local.tolist())
            spec.add_actuator(name=f"{p.name}_force{axis}", target=f"{p.name}_slide{axis}",
                              trntype=mujoco.mjtTrn.mjTRN_JOINT).set_to_motor()  # fmt: skip
    geom = b.add_geom(type=_GEOM[p.kind], size=_mj_size(p), mass=p.mass if p.mode in MOVING else 0.0, **mu)
    if not p.collide:
        geom.contype = geom.conaffinity = 0


def _add_visuals(spec: mujoco.MjSpec) -> None:
    """A checker floor material and a light (rendering only)."""
    spec.add_texture(
        name="grid", type=mujoco.mjtTexture.mjTEXTURE_2D, builtin=mujoco.mjtBuiltin.mjBUILTIN_CHECKER,
        rgb1=[0.25, 0.28, 0.32], rgb2=[0.18, 0.2, 0.23], width=256, height=256,
    )  # fmt: skip
    material = spec.add_material(name="grid", texrepeat=[10, 10], reflectance=0.1)
    material.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = "grid"
    spec.worldbody.add_light(pos=[0, 0, 3], dir=[0, 0, -1], diffuse=[0.7, 0.7, 0.7])


def _mj_size(p: Primitive) -> list[float]:
    return list(p.size) + [0.0] * (3 - len(p.size))


def _budget(scene: Scene, body: DanoBody) -> int:
    n = body.dano.n_points
    k = scene.contact_budget
    if k is None:
        k = active.budget(np.asarray(body.dano.body_points).T, np.asarray(body.dano.normals).T)
    return min(int(k), n)


def _mujoco_moves(scene: Scene, model: mujoco.MjModel) -> bool:
    """`World.mujoco_moves`: anything but the DANOs' free joints and non-colliding actuated
    primitives' slides and motors (a robot, a free primitive, a colliding one, a constraint)."""
    held = sum(p.mode == "actuated" and not p.collide for p in scene.primitives)
    extra_dof = model.nv - 6 * len(scene.bodies) - 3 * held  # a robot's, a free or colliding primitive's
    return extra_dof > 0 or model.nu > 3 * held or model.neq > 0 or model.ntendon > 0


class Compiled(NamedTuple):
    """A compiled scene: the `mujoco.MjModel` (use `mjx.put_model`), the static `World`, default
    `Params`, and the initial state arrays `qpos` (nq,) and `qvel` (nv,)."""

    model: mujoco.MjModel
    world: World
    params: Params
    qpos: np.ndarray
    qvel: np.ndarray


def compile_scene(scene: Scene, check_start: bool = False) -> Compiled:
    """Builds the MuJoCo model and the `World`, `Params` and initial `qpos`/`qvel` of a scene.

    `check_start` refuses initial states the contact cannot resolve (`_check_start`: a DANO inside
    the ground, or crossing its own size in one step); `Simulation.from_scene` turns it on, while
    identification leaves it off: its initial states come from the data, not from the scene.

    Returns:
        `Compiled(model, world, params, qpos, qvel)`, which unpacks as a tuple.

    Raises:
        SceneError: DANOs that must touch each other without a density field, a robot or scene
            MuJoCo cannot compile, unknown contact bodies or pairs, an unresolvable start.
    """
    _check_dano_pairs(scene)
    spec, robot_bodies = scene_spec(scene)
    try:
        model = spec.compile()
    except ValueError as e:  # e.g. a robot link named like a DANO
        raise SceneError(f"MuJoCo cannot compile the scene: {' '.join(str(e).split())}") from None
    for body in scene.bodies:
        _set_moments(model, model.body(body.name).id, np.asarray(body.dano.inertia))
    world = _world(scene, model, robot_bodies)
    overrides = _pair_overrides(scene, world)
    if check_start:
        _check_start(scene, world, overrides)
    params = Params(
        contact=tuple(overrides.get(pair_name(world, pr), scene.contact) for pr in pairs(world)),
        mass_scale=jnp.ones(len(world.danos)),
        inertia_scale=jnp.ones(len(world.danos)),
    )
    qpos, qvel = _initial_state(scene, model, world, robot_bodies)
    return Compiled(model, world, params, qpos, qvel)


def scene_spec(scene: Scene) -> tuple[mujoco.MjSpec, list[str]]:
    """The scene as an uncompiled MuJoCo spec, and the robot's bodies: its options, ground,
    primitives and robot, each DANO a free body with its mass in its principal frame and no geom
    (its contact is dano's; its moments are written after compiling, `_set_moments`)."""
    if scene.mjcf is not None:
        spec = world_spec(scene.mjcf)
        keys = [(k.name, list(k.qpos), list(k.qvel), list(k.act), list(k.ctrl), k.time) for k in spec.keys]
        for k in list(spec.keys):
            spec.delete(k)
        _add_scene(spec, scene)
        _keep_keys(spec, keys)
        return spec, []
    spec = mujoco.MjSpec() if scene.robot is None else robot_spec(scene.robot)
    robot_bodies = prepare_robot(spec, scene.robot) if scene.robot is not None else []
    _add_scene(spec, scene)
    return spec, robot_bodies


def _keep_keys(spec: mujoco.MjSpec, keys: list) -> None:
    """An MJCF world's keyframes, each extended by the scene's own bodies at their start (the
    DANOs' and primitives' joints come after the world's, at their `qpos0`)."""
    if not keys:
        return
    try:
        model = spec.compile()
    except ValueError as e:
        raise SceneError(f"MuJoCo cannot compile the scene: {' '.join(str(e).split())}") from None
    for name, qpos, qvel, act, ctrl, time in keys:
        key = spec.add_key(name=name, time=time)
        key.qpos = (qpos + model.qpos0[len(qpos) :].tolist()) if qpos else model.qpos0.tolist()
        key.qvel = (qvel + [0.0] * (model.nv - len(qvel))) if qvel else [0.0] * model.nv
        key.ctrl = (ctrl + [0.0] * (model.nu - len(ctrl))) if ctrl else [0.0] * model.nu
        if act:
            key.act = act


def _check_dano_pairs(scene: Scene) -> None:
    if len(scene.bodies) > 1:
        blind = [b.name for b in scene.bodies if b.field is None and b.dano.grid is None]
        if blind:
            raise SceneError(
                f"DANOs {blind} carry no density grid, so they cannot touch other DANOs: rebuild them with "
                "`dano build` from a field (reference colliders have none), or pass field= to DanoBody"
            )


def _add_scene(spec: mujoco.MjSpec, scene: Scene) -> None:
    """The options, the ground, the DANOs' bodies and the primitives, added to `spec`."""
    spec.option.timestep = scene.step_size
    spec.option.gravity = list(scene.gravity)
    if scene.integrator == "implicit":
        # MuJoCo's own velocity-dependent forces (servo damping kv) implicit too, as the contact:
        # at one 2 ms step per frame Euler's explicit damping rings up on a light joint.
        spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    _add_visuals(spec)
    spec.nuserdata += 1  # the last slot counts the steps whose contact active sets overflowed
    if scene.ground_height is not None:
        n = np.asarray(_unit(scene.ground_normal))
        quat = np.zeros(4)
        mujoco.mju_quatZ2Vec(quat, n)
        spec.worldbody.add_geom(
            name="ground", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0, 0, 1], pos=(scene.ground_height * n).tolist(),
            quat=quat.tolist(), material="grid",
        )  # fmt: skip
    for body in scene.bodies:
        _add_dano(spec, body)
    for p in scene.primitives:
        add_primitive(spec, p)


def _dano_state(scene: Scene, b: DanoBody) -> DanoState:
    d = b.dano
    return DanoState(
        points=jnp.asarray(d.body_points.T),
        shares=d.densities / jnp.sum(d.densities),
        mass=jnp.asarray(d.mass),
        inertia=jnp.asarray(d.inertia),
        com=jnp.asarray(d.com),
        field=_contact_field(b),
        peak=jnp.asarray(d.peak if d.peak is not None else jnp.max(d.densities)),
        normals=jnp.asarray(d.normals.T),
        budget=_budget(scene, b),
        reach=float(np.max(np.linalg.norm(np.asarray(d.body_points), axis=1))),
    )


def _contact_field(body: DanoBody) -> Callable[[Array], Array] | None:
    """The field a DANO's partners query: the online field if given, else its baked grid."""
    from dano.fields import GridField

    if body.field is not None:
        return body.field
    grid, bounds = body.dano.grid, body.dano.grid_bounds
    if grid is None or bounds is None:
        return None
    return GridField(jnp.asarray(grid), bounds)


def _joint(model: mujoco.MjModel, name: str) -> int:
    """A body's first joint: a DANO's or free primitive's free joint, an actuated primitive's x slide
    (`_add_dano` and `add_primitive` add them first)."""
    return int(model.body_jntadr[model.body(name).id])


def _prim_geom(model: mujoco.MjModel, p: Primitive) -> PrimGeom:
    moving = p.mode in MOVING
    body = model.body(p.name).id if p.mode != "static" else 0
    j = _joint(model, p.name) if moving else -1
    return PrimGeom(
        name=p.name,
        kind=p.kind,
        size=tuple(float(s) for s in p.size),
        mode=p.mode,
        body=body,
        pos=tuple(float(s) for s in p.pos),
        quat=tuple(float(s) for s in p.quat),
        qpos=int(model.jnt_qposadr[j]) if moving else -1,
        qvel=int(model.jnt_dofadr[j]) if moving else -1,
        mocap=int(model.body_mocapid[body]) if p.mode == "mocap" else -1,
        actuator=int(model.actuator(f"{p.name}_forcex").id) if p.mode == "actuated" else -1,
        mass=float(p.mass) if moving else float("inf"),
    )


def _world(scene: Scene, model: mujoco.MjModel, robot_bodies: list[str]) -> World:
    if scene.robot is not None and scene.robot.contact_bodies:
        unknown = sorted(set(scene.robot.contact_bodies) - set(robot_bodies))
        if unknown:
            raise SceneError(f"contact_bodies {unknown} are not bodies of the robot (it has {robot_bodies})")
    if scene.mjcf is not None:
        scene_bodies = {model.body(b.name).id for b in scene.bodies} | {model.body(p.name).id for p in scene.primitives}
        geoms = world_geoms(model, scene_bodies)
    else:
        geoms = robot_geoms(model, robot_bodies, scene.robot)
    links = tuple(link_geom(model, g) for g in geoms)
    free = [_joint(model, b.name) for b in scene.bodies]
    return World(
        danos=tuple(_dano_state(scene, b) for b in scene.bodies),
        links=links,
        link_names=tuple(model.body(link.body).name for link in links),
        dano_body=tuple(model.body(b.name).id for b in scene.bodies),
        dano_qpos=tuple(int(model.jnt_qposadr[j]) for j in free),
        dano_qvel=tuple(int(model.jnt_dofadr[j]) for j in free),
        names=tuple(b.name for b in scene.bodies),
        prims=tuple(_prim_geom(model, p) for p in scene.primitives),
        ground_height=scene.ground_height,
        ground_normal=_unit(scene.ground_normal),
        substeps=int(scene.substeps),  # pyright: ignore[reportArgumentType]  (`__post_init__` sets it)
        dt=scene.step_size,
        force_mode=ForceMode(scene.force_mode),
        integrator=Integrator(scene.integrator),
        fallback_slot=model.nuserdata - 1,
        mujoco_moves=_mujoco_moves(scene, model),
    )


def _initial_state(
    scene: Scene, model: mujoco.MjModel, world: World, robot_bodies: list[str]
) -> tuple[np.ndarray, np.ndarray]:
    """`qpos` (nq,) and `qvel` (nv,) of the declared start; a robot's servos checked there."""
    qpos, qvel = np.array(model.qpos0), np.zeros(model.nv)
    for b, a, v in zip(scene.bodies, world.dano_qpos, world.dano_qvel, strict=True):
        _set_free(qpos, qvel, a, v, b.pos, b.quat, b.vel, b.angvel)
    for p, g in zip(scene.primitives, world.prims, strict=True):
        if p.mode == "free":
            _set_free(qpos, qvel, g.qpos, g.qvel, p.pos, p.quat, p.vel, p.angvel)
        elif p.mode == "actuated":
            qvel[g.qvel : g.qvel + 3] = p.vel
    if scene.robot is not None:
        ids = {model.body(name).id for name in robot_bodies}
        robot_joints = [j for j in range(model.njnt) if model.jnt_bodyid[j] in ids]
        for j, value in zip(robot_joints, scene.robot.qpos, strict=False):
            qpos[model.jnt_qposadr[j]] = value
        check_servo_damping(model, qpos)
    return qpos, qvel


def _pair_overrides(scene: Scene, world: World) -> dict[tuple[str, str], ContactParams]:
    """`scene.pair_contact` keyed as `pair_name` names the pairs; a pair given in the other order is
    the same pair. A pair that names no contact pair of the scene is an error, not ignored."""
    known = {pair_name(world, pr) for pr in pairs(world)}
    out: dict[tuple[str, str], ContactParams] = {}
    for (a, b), params in scene.pair_contact:
        key = (a, b) if (a, b) in known else (b, a)
        if key not in known:
            hint = ", ".join(f"{x}/{y}" for x, y in sorted(known)) or "none (contact is off)"
            raise SceneError(f"pair {a}/{b} is not a contact pair of this scene (its pairs: {hint})")
        if key in out:
            raise SceneError(f"pair {a}/{b} is given more than once")
        out[key] = params
    return out


START_DEPTH = 0.003
"""m: how deep below the ground a DANO's deepest surface point may start, beyond the spring's own
rest depth (5 g / k). Deeper, the contact spring throws it out (1 cm deep: 4.5 m/s)."""


def _check_start(scene: Scene, world: World, overrides: dict) -> None:
    """Refuses initial states the contact cannot resolve: a DANO started inside the ground, or moving
    so fast that it crosses its own size in one step (it would tunnel through what it should hit)."""
    dt = scene.step_size
    for body, state in zip(scene.bodies, world.danos, strict=True):
        reach = state.reach
        speed = float(np.linalg.norm(body.vel))
        if speed * dt > reach:
            raise SceneError(
                f"body {body.name!r} starts at {speed:g} m/s, moving {speed * dt:.3g} m per step of {dt:g} s, more "
                f"than its own radius {reach:.3g} m: lower its speed or the time step"
            )
        spin = float(np.linalg.norm(body.angvel))
        if spin * dt > 1.0:
            raise SceneError(f"body {body.name!r} starts spinning at {spin:g} rad/s, over 1 rad per step of {dt:g} s")
        if scene.ground_height is None:
            continue
        n = np.asarray(world.ground_normal)
        R = np.zeros(9)
        mujoco.mju_quat2Mat(R, np.asarray(body.quat) / np.linalg.norm(body.quat))
        points = np.asarray(state.points).T @ R.reshape(3, 3).T + np.asarray(body.pos)
        depth = float(scene.ground_height - np.min(points @ n))
        spring = float(overrides.get((body.name, "ground"), scene.contact).impact_spring)
        allowed = START_DEPTH + 5 * float(np.linalg.norm(scene.gravity)) / max(spring, 1e-12)
        if depth > allowed:
            lift = depth + float(np.asarray(body.pos) @ n) - scene.ground_height
            raise SceneError(
                f"body {body.name!r} starts {depth * 1e3:.3g} mm inside the ground (at most {allowed * 1e3:.2g} mm "
                f"allowed): start its centre at least {lift:.4g} m above the ground (along its normal)"
            )


def _unit(v) -> tuple[float, float, float]:
    n = np.asarray(v, dtype=float)
    if n.shape != (3,) or not np.linalg.norm(n) > 0:
        raise SceneError(f"ground normal must be a non-zero 3-vector, got {v}")
    return tuple(float(x) for x in n / np.linalg.norm(n))  # type: ignore[return-value]


def _set_free(qpos, qvel, a, v, pos, quat, vel, angvel) -> None:
    q = np.asarray(quat, dtype=float)
    q = q / np.linalg.norm(q)
    qpos[a : a + 3], qpos[a + 3 : a + 7] = pos, q
    R = np.zeros(9)
    mujoco.mju_quat2Mat(R, q)
    qvel[v : v + 3] = vel
    qvel[v + 3 : v + 6] = R.reshape(3, 3).T @ np.asarray(angvel, dtype=float)  # MuJoCo: body frame
