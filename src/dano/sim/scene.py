"""Scenes, host side: declare DANOs, primitives and a ground, compile once to MuJoCo/MJX.

A DANO becomes a MuJoCo body with a free joint whose frame is the object frame moved to the centre
of mass (so `qpos` holds the centre of mass and the object-to-world quaternion), with the DANO's
mass and full inertia tensor (MuJoCo diagonalises it into `body_inertia`/`body_iquat`). It has no
collision geoms: its contacts are computed by `dano.contact` and enter through `xfrc_applied`.
Primitives are ordinary MuJoCo geoms (static, free, or mocap-driven) and collide with each other in
MuJoCo; with DANOs they collide through the DANO contact model.
"""

import dataclasses
from typing import Literal

import equinox as eqx
import jax.numpy as jnp
import mujoco
import numpy as np
from jaxtyping import Array, Float

from dano.contact import ContactParams
from dano.types import DANO

Number = float | int
Vec3 = tuple[Number, Number, Number]
Quat = tuple[Number, Number, Number, Number]
PrimitiveKind = Literal["sphere", "capsule", "box"]
Mode = Literal["static", "free", "mocap"]


@dataclasses.dataclass(frozen=True)
class DanoBody:
    """A DANO placed in the world.

    Attributes:
        name: unique body name.
        dano: the object.
        pos: (3,) initial centre of mass, world, m.
        quat: (4,) initial orientation w, x, y, z, object frame -> world.
        vel: (3,) initial velocity of the centre of mass, world, m/s.
        angvel: (3,) initial angular velocity, world, rad/s.
    """

    name: str
    dano: DANO
    pos: Vec3 = (0.0, 0.0, 0.0)
    quat: Quat = (1.0, 0.0, 0.0, 0.0)
    vel: Vec3 = (0.0, 0.0, 0.0)
    angvel: Vec3 = (0.0, 0.0, 0.0)


@dataclasses.dataclass(frozen=True)
class Primitive:
    """A sphere, capsule (along its local z) or box, static, free or driven by mocap.

    Attributes:
        size: sphere (radius,); capsule (radius, half_length); box (hx, hy, hz) half extents; m.
        mass: kg, for free primitives (inertia of a solid of that shape).
    """

    name: str
    kind: PrimitiveKind
    size: tuple[Number, ...]
    pos: Vec3 = (0.0, 0.0, 0.0)
    quat: Quat = (1.0, 0.0, 0.0, 0.0)
    mode: Mode = "static"
    mass: Number = 1.0
    vel: Vec3 = (0.0, 0.0, 0.0)
    angvel: Vec3 = (0.0, 0.0, 0.0)


@dataclasses.dataclass(frozen=True)
class Scene:
    """Everything a simulation needs (see README for the TOML form).

    Attributes:
        timestep: s, one recorded frame.
        substeps: MuJoCo steps per frame (the penalty contact is stiff; see `dano.sim.step`).
        duration: s.
        gravity: (3,) m/s^2.
        ground_height: the plane z = height with normal +z, or None for no ground.
        bodies: DANOs.
        primitives: MuJoCo primitives.
        contact: default contact parameters of every pair.
        pair_contact: overrides per pair, keyed by (dano name, other name); the ground is "ground".
        force_mode: "points" applies each sampled point's own force at the point; "centroid" applies
            the total at the overlap centroid chi, as in the paper.
    """

    timestep: Number = 0.002
    substeps: int = 4
    duration: Number = 1.0
    gravity: Vec3 = (0.0, 0.0, -9.81)
    ground_height: Number | None = 0.0
    bodies: tuple[DanoBody, ...] = ()
    primitives: tuple[Primitive, ...] = ()
    contact: ContactParams = dataclasses.field(default_factory=ContactParams)
    pair_contact: tuple[tuple[tuple[str, str], ContactParams], ...] = ()
    force_mode: Literal["points", "centroid"] = "points"

    @property
    def n_steps(self) -> int:
        return int(round(self.duration / self.timestep))


class DanoState(eqx.Module):
    """Per-DANO constant data used inside the step: points (3, n) in the body frame (m) and
    the normalised densities (n,) (weights are these times the current mass)."""

    points: Float[Array, "3 n"]
    shares: Float[Array, " n"]
    mass: Float[Array, ""]
    inertia: Float[Array, "3 3"]


class World(eqx.Module):
    """The compiled scene: static indices and constant arrays that the jitted step reads."""

    danos: tuple[DanoState, ...]
    dano_body: tuple[int, ...] = eqx.field(static=True)
    dano_qpos: tuple[int, ...] = eqx.field(static=True)
    dano_qvel: tuple[int, ...] = eqx.field(static=True)
    names: tuple[str, ...] = eqx.field(static=True)
    prim_kind: tuple[str, ...] = eqx.field(static=True)
    prim_body: tuple[int, ...] = eqx.field(static=True)
    prim_mode: tuple[str, ...] = eqx.field(static=True)
    prim_names: tuple[str, ...] = eqx.field(static=True)
    prim_size: tuple[tuple[float, ...], ...] = eqx.field(static=True)
    prim_pos: tuple[tuple[float, ...], ...] = eqx.field(static=True)
    prim_quat: tuple[tuple[float, ...], ...] = eqx.field(static=True)
    prim_qpos: tuple[int, ...] = eqx.field(static=True)
    prim_qvel: tuple[int, ...] = eqx.field(static=True)
    prim_mocap: tuple[int, ...] = eqx.field(static=True)
    ground_height: float | None = eqx.field(static=True)
    prim_mass: tuple[float, ...] = eqx.field(static=True)
    substeps: int = eqx.field(static=True)
    dt: float = eqx.field(static=True)
    force_mode: str = eqx.field(static=True)


class Params(eqx.Module):
    """Differentiable simulation parameters.

    Attributes:
        contact: one `ContactParams` per DANO pair, in `pairs(world)` order.
        mass_scale: (n_dano,) multiplies each DANO's mass, inertia and contact weights.
        inertia_scale: (n_dano,) multiplies each DANO's inertia only.
    """

    contact: tuple[ContactParams, ...]
    mass_scale: Float[Array, " d"]
    inertia_scale: Float[Array, " d"]


def pairs(world: World) -> tuple[tuple[int, str, int], ...]:
    """Contact pairs (dano index, other kind, other index); kinds: ground, primitive, dano (i < j)."""
    out: list[tuple[int, str, int]] = []
    for i in range(len(world.danos)):
        if world.ground_height is not None:
            out.append((i, "ground", 0))
        out.extend((i, "primitive", k) for k in range(len(world.prim_kind)))
        out.extend((i, "dano", j) for j in range(i + 1, len(world.danos)))
    return tuple(out)


def _pair_name(world: World, pair: tuple[int, str, int]) -> tuple[str, str]:
    i, kind, k = pair
    other = {"ground": lambda: "ground", "primitive": lambda: world.prim_names[k], "dano": lambda: world.names[k]}
    return world.names[i], other[kind]()


def _add_dano(spec: mujoco.MjSpec, body: DanoBody) -> None:
    d = body.dano
    b = spec.worldbody.add_body(name=body.name, pos=list(body.pos), quat=list(body.quat))
    b.add_freejoint(name=f"{body.name}_free")
    J = np.asarray(d.inertia, dtype=np.float64)
    b.mass = float(d.mass)
    b.ipos = [0.0, 0.0, 0.0]
    b.iquat = [1.0, 0.0, 0.0, 0.0]
    b.fullinertia = [J[0, 0], J[1, 1], J[2, 2], J[0, 1], J[0, 2], J[1, 2]]
    b.explicitinertial = True


_GEOM = {
    "sphere": mujoco.mjtGeom.mjGEOM_SPHERE,
    "capsule": mujoco.mjtGeom.mjGEOM_CAPSULE,
    "box": mujoco.mjtGeom.mjGEOM_BOX,
}


def _add_primitive(spec: mujoco.MjSpec, p: Primitive) -> None:
    if p.mode == "static":
        spec.worldbody.add_geom(name=p.name, type=_GEOM[p.kind], size=_mj_size(p), pos=list(p.pos), quat=list(p.quat))
        return
    b = spec.worldbody.add_body(name=p.name, pos=list(p.pos), quat=list(p.quat), mocap=p.mode == "mocap")
    if p.mode == "free":
        b.add_freejoint(name=f"{p.name}_free")
    b.add_geom(type=_GEOM[p.kind], size=_mj_size(p), mass=p.mass if p.mode == "free" else 0.0)


def _mj_size(p: Primitive) -> list[float]:
    return list(p.size) + [0.0] * (3 - len(p.size))


def compile_scene(scene: Scene):
    """Builds the MuJoCo model and the `World`, `Params` and initial `qpos`/`qvel` of a scene.

    Returns:
        (mj_model, world, params, qpos0, qvel0): the `mujoco.MjModel` (use `mjx.put_model`), the
        static world, default parameters, and the initial state arrays.
    """
    names = [b.name for b in scene.bodies] + [p.name for p in scene.primitives]
    if len(set(names)) != len(names) or "ground" in names:
        raise ValueError(f"body names must be unique and not 'ground', got {names}")
    spec = mujoco.MjSpec()
    spec.option.timestep = scene.timestep / scene.substeps
    spec.option.gravity = list(scene.gravity)
    if scene.ground_height is not None:
        spec.worldbody.add_geom(name="ground", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0, 0, 1],
                                pos=[0, 0, scene.ground_height])  # fmt: skip
    for body in scene.bodies:
        _add_dano(spec, body)
    for p in scene.primitives:
        _add_primitive(spec, p)
    model = spec.compile()

    def jnt(name):
        return model.joint(f"{name}_free").id

    danos = tuple(
        DanoState(
            points=jnp.asarray(b.dano.body_points.T),
            shares=b.dano.densities / jnp.sum(b.dano.densities),
            mass=jnp.asarray(b.dano.mass),
            inertia=jnp.asarray(b.dano.inertia),
        )
        for b in scene.bodies
    )
    world = World(
        danos=danos,
        dano_body=tuple(model.body(b.name).id for b in scene.bodies),
        dano_qpos=tuple(int(model.jnt_qposadr[jnt(b.name)]) for b in scene.bodies),
        dano_qvel=tuple(int(model.jnt_dofadr[jnt(b.name)]) for b in scene.bodies),
        names=tuple(b.name for b in scene.bodies),
        prim_kind=tuple(p.kind for p in scene.primitives),
        prim_body=tuple(model.body(p.name).id if p.mode != "static" else 0 for p in scene.primitives),
        prim_mode=tuple(p.mode for p in scene.primitives),
        prim_names=tuple(p.name for p in scene.primitives),
        prim_size=tuple(tuple(float(s) for s in p.size) for p in scene.primitives),
        prim_pos=tuple(tuple(float(s) for s in p.pos) for p in scene.primitives),
        prim_quat=tuple(tuple(float(s) for s in p.quat) for p in scene.primitives),
        prim_qpos=tuple(int(model.jnt_qposadr[jnt(p.name)]) if p.mode == "free" else -1 for p in scene.primitives),
        prim_qvel=tuple(int(model.jnt_dofadr[jnt(p.name)]) if p.mode == "free" else -1 for p in scene.primitives),
        prim_mocap=tuple(
            int(model.body_mocapid[model.body(p.name).id]) if p.mode == "mocap" else -1 for p in scene.primitives
        ),
        ground_height=scene.ground_height,
        prim_mass=tuple(float(p.mass) if p.mode == "free" else float("inf") for p in scene.primitives),
        substeps=scene.substeps,
        dt=scene.timestep / scene.substeps,
        force_mode=scene.force_mode,
    )
    overrides = dict(scene.pair_contact)
    params = Params(
        contact=tuple(overrides.get(_pair_name(world, pr), scene.contact) for pr in pairs(world)),
        mass_scale=jnp.ones(len(danos)),
        inertia_scale=jnp.ones(len(danos)),
    )
    qpos, qvel = np.array(model.qpos0), np.zeros(model.nv)
    for b, a, v in zip(scene.bodies, world.dano_qpos, world.dano_qvel, strict=True):
        _set_free(model, qpos, qvel, a, v, b.pos, b.quat, b.vel, b.angvel)
    for p, a, v in zip(scene.primitives, world.prim_qpos, world.prim_qvel, strict=True):
        if p.mode == "free":
            _set_free(model, qpos, qvel, a, v, p.pos, p.quat, p.vel, p.angvel)
    return model, world, params, qpos, qvel


def _set_free(model, qpos, qvel, a, v, pos, quat, vel, angvel) -> None:
    q = np.asarray(quat, dtype=float)
    q = q / np.linalg.norm(q)
    qpos[a : a + 3], qpos[a + 3 : a + 7] = pos, q
    R = np.zeros(9)
    mujoco.mju_quat2Mat(R, q)
    qvel[v : v + 3] = vel
    qvel[v + 3 : v + 6] = R.reshape(3, 3).T @ np.asarray(angvel, dtype=float)  # MuJoCo: body frame
