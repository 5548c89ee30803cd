"""The simulation step: DANO contact wrenches -> `xfrc_applied` -> `mjx.step`, and rollouts.

One frame is `world.substeps` MuJoCo steps; before each, every DANO pair's wrench is computed at
the current configuration and velocity and written to `xfrc_applied` (force and torque about each
body's centre of mass, world frame). A rollout is a `lax.scan` over frames with the frame step
under `jax.checkpoint`, so reverse-mode gradients of long rollouts keep only one state per frame.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float
from mujoco import mjx

from dano.contact import Box, Capsule, HalfSpace, Polytope, Sphere, expected_overlap
from dano.contact.overlap import outward_normal
from dano.contact.wrench import ContactParams, contact_wrench
from dano.math import normalize, quat_to_mat, safe_norm
from dano.sim.scene import DanoState, LinkGeom, Params, World, pairs


class Frame(eqx.Module):
    """Pose and velocity of a rigid body, world frame: centre of mass x (3,), rotation R (3, 3),
    velocity v (3,), angular velocity w (3,)."""

    x: Float[Array, " 3"]
    R: Float[Array, "3 3"]
    v: Float[Array, " 3"]
    w: Float[Array, " 3"]


def free_frame(qpos: Array, qvel: Array, a: int, v: int) -> Frame:
    """Frame of a free-joint body from MuJoCo state (its angular qvel is in the body frame)."""
    R = quat_to_mat(qpos[a + 3 : a + 7])
    return Frame(qpos[a : a + 3], R, qvel[v : v + 3], R @ qvel[v + 3 : v + 6])


def _static_frame(pos, quat) -> Frame:
    z = jnp.zeros(3)
    return Frame(jnp.asarray(pos, dtype=float), quat_to_mat(jnp.asarray(quat, dtype=float)), z, z)


def primitive_frame(world: World, k: int, d: mjx.Data, mocap_vel: Array | None = None) -> Frame:
    mode = world.prim_mode[k]
    if mode == "free":
        return free_frame(d.qpos, d.qvel, world.prim_qpos[k], world.prim_qvel[k])
    if mode == "actuated":  # three slides along world x, y, z: no rotation
        a, v = world.prim_qpos[k], world.prim_qvel[k]
        z = jnp.zeros(3)
        pos = jnp.asarray(world.prim_pos[k], dtype=float) + d.qpos[a : a + 3]
        return Frame(pos, quat_to_mat(jnp.asarray(world.prim_quat[k], dtype=float)), d.qvel[v : v + 3], z)
    if mode == "mocap":
        i = world.prim_mocap[k]
        z = jnp.zeros(3)
        v = z if mocap_vel is None else mocap_vel[i]
        return Frame(d.mocap_pos[i], quat_to_mat(d.mocap_quat[i]), v, z)
    return _static_frame(world.prim_pos[k], world.prim_quat[k])


def primitive_shape(world: World, k: int, f: Frame):
    size = world.prim_size[k]
    kind = world.prim_kind[k]
    if kind == "sphere":
        return Sphere(f.x, jnp.asarray(size[0]))
    if kind == "capsule":
        axis = f.R[:, 2] * size[1]
        return Capsule(f.x - axis, f.x + axis, jnp.asarray(size[0]))
    return Box(f.x, f.R, jnp.asarray(size, dtype=float))


class Body(eqx.Module):
    """A DANO's contact data at the current scales: body-frame points (3, n), weights (n,) kg,
    mass kg, inertia about the centre of mass (3, 3) body frame, and its `DanoState`."""

    points: Float[Array, "3 n"]
    weights: Float[Array, " n"]
    mass: Float[Array, ""]
    inertia: Float[Array, "3 3"]
    state: DanoState


def inverse_effective_mass(body: Body, a: Frame, at: Array, normal: Array) -> Array:
    """1 / effective mass of a body at world point `at` along `normal`: 1/m + (r x n)^T I^-1 (r x n)."""
    rn = jnp.cross(at - a.x, normal)
    return 1.0 / body.mass + rn @ (a.R @ jnp.linalg.solve(body.inertia, a.R.T @ rn))


def implicit_damper(p: ContactParams, psi, inv_m_eff, dt: float) -> ContactParams:
    """Contact parameters with the damper made linearly implicit: c_d / (1 + dt c_d psi / m_eff).

    An explicit damper c_d psi is unstable once dt c_d psi / m_eff > 2 (deep or wide contacts);
    the backward-Euler factor makes the damping force at most the one that stops the normal
    relative motion in one step, smoothly, and changes nothing when dt c_d psi << m_eff.
    m_eff is the effective mass of the contact along the normal at chi (both bodies).
    """
    factor = 1.0 + dt * p.impact_damper * psi * inv_m_eff
    return eqx.tree_at(lambda q: q.impact_damper, p, p.impact_damper / factor)


def pair_wrench(p: ContactParams, shape, body: Body, a: Frame, b: Frame, mode: str, other_inv_mass: float, dt: float):
    """Wrench on DANO `a` from primitive `shape` carried by frame `b` (eqs. 7-8, 11-16).

    Returns:
        force (3,) and torque about a's centre of mass (3,), world frame.
    """
    P = a.R @ body.points + a.x[:, None]
    o = expected_overlap(shape, P, body.weights, p.indicator_width)
    p = implicit_damper(p, o.psi, inverse_effective_mass(body, a, o.chi, o.normal) + other_inv_mass, dt)
    if mode == "centroid":
        at, psi, normal = o.chi[:, None], o.psi[None], o.normal[:, None]
    elif isinstance(shape, HalfSpace):
        at, psi, normal = P, o.inside, o.normal[:, None]
    else:
        at, psi, normal = P, o.inside, jax.vmap(outward_normal, (None, 1), 1)(shape, P)
    return _apply(p, at, psi, normal, a, b)


def _apply(p: ContactParams, at: Array, psi: Array, normal: Array, a: Frame, b: Frame):
    """`contact_wrench` on DANO `a` from body `b`: (force, torque about a's centre of mass)."""
    w = contact_wrench(p, psi, at, normal, a.x, a.v, a.w, b.x, b.v, b.w)
    return w.force, w.torque


def occupancy(state: DanoState, frame: Frame, world_points: Float[Array, "3 k"]) -> Float[Array, " k"]:
    """How much each world point is inside a DANO: its field there over its peak, in [0, 1]."""
    local = frame.R.T @ (world_points - frame.x[:, None]) + state.com[:, None]
    return jnp.clip(state.field(local.T) / state.peak, 0.0, 1.0)


def dano_pair_wrench(p: ContactParams, A: Body, B: Body, a: Frame, b: Frame, mode: str, dt: float):
    """Wrench on DANO A from DANO B (eqs. 9-10 and the normal after them).

    Each body's surface points count with their weight times the other body's occupancy there
    (its density over its peak): in kg, like the primitive case, whose occupancy is the indicator.
    The normal (from B towards A) is the overlap-weighted sum of B's outward normals at B's points
    minus A's at A's points. Returns the force on A and its torque about A's centre of mass.
    """
    PA = a.R @ A.points + a.x[:, None]
    PB = b.R @ B.points + b.x[:, None]
    psi_a = A.weights * occupancy(B.state, b, PA)
    psi_b = B.weights * occupancy(A.state, a, PB)
    at = jnp.concatenate([PA, PB], axis=1)
    psi = jnp.concatenate([psi_a, psi_b])
    n_bar = (b.R @ B.state.normals) @ psi_b - (a.R @ A.state.normals) @ psi_a
    normal = normalize(n_bar)
    total = jnp.sum(psi)
    chi = at @ psi / jnp.where(total > 0, total, 1.0)
    inv_m = inverse_effective_mass(A, a, chi, normal) + inverse_effective_mass(B, b, chi, normal)
    p = implicit_damper(p, total, inv_m, dt)
    if mode == "centroid":
        return _apply(p, chi[:, None], total[None], normal[:, None], a, b)
    return _apply(p, at, psi, normal[:, None], a, b)


def link_frame(link: LinkGeom, kin: mjx.Data) -> Frame:
    """Pose of a robot collision geom (current kinematics) and the velocity of its body.

    `kin` comes from `link_motion`: `cvel` (angular; linear at the subtree centre of mass of the
    body's root) of the current qpos and qvel. (`d.cvel` would be the last forward pass's, one
    substep old, and for a state set from outside, as trajectory optimisation does, stale.)
    """
    x = kin.geom_xpos[link.geom]
    w = kin.cvel[link.body, :3]
    v = kin.cvel[link.body, 3:] + jnp.cross(w, x - kin.subtree_com[link.root])
    return Frame(x, kin.geom_xmat[link.geom].reshape(3, 3), v, w)


def link_shape(link: LinkGeom, f: Frame):
    if link.kind == "mesh":
        return Polytope(f.x, f.R, link.normals, link.offsets)
    if link.kind == "sphere":
        return Sphere(f.x, jnp.asarray(link.size[0]))
    if link.kind == "capsule":
        axis = f.R[:, 2] * link.size[1]
        return Capsule(f.x - axis, f.x + axis, jnp.asarray(link.size[0]))
    return Box(f.x, f.R, jnp.asarray(link.size, dtype=float))


def _broad_phase(fn, a: Frame, body: Body, centre: Array, radius: float):
    """Runs `fn()` only when the DANO's bounding sphere meets one of `radius` around `centre`."""
    reach = jnp.max(safe_norm(body.points, axis=0)) + radius
    near = safe_norm(a.x - centre) < reach
    zero = (jnp.zeros(3), jnp.zeros(3))
    return jax.lax.cond(near, fn, lambda: zero)


def contact_xfrc(
    world: World,
    params: Params,
    d: mjx.Data,
    mocap_vel: Float[Array, "k 3"] | None = None,
    m: mjx.Model | None = None,
) -> Float[Array, "nbody 6"]:
    """Sum of all DANO contact wrenches, as MuJoCo's `xfrc_applied` (nbody, 6).

    Args:
        mocap_vel: velocities of the mocap bodies (driven primitives), world, m/s; zero if None.
        m: the model, needed when the world has a robot (for its link poses).
    """
    xfrc = jnp.zeros_like(d.xfrc_applied)
    kin = link_motion(m, d) if world.links else None
    frames = [free_frame(d.qpos, d.qvel, a, v) for a, v in zip(world.dano_qpos, world.dano_qvel, strict=True)]
    bodies = [
        Body(
            s.points,
            s.shares * s.mass * params.mass_scale[i],
            s.mass * params.mass_scale[i],
            s.inertia * params.mass_scale[i] * params.inertia_scale[i],
            s,
        )
        for i, s in enumerate(world.danos)
    ]
    for p, (i, kind, k) in zip(params.contact, pairs(world), strict=True):
        a = frames[i]
        if kind == "ground":
            n = jnp.asarray(world.ground_normal)
            b = _static_frame(tuple(world.ground_height * v for v in world.ground_normal), (1.0, 0.0, 0.0, 0.0))
            shape, other, inv_mass = HalfSpace(n, b.x), None, 0.0
        elif kind == "primitive":
            b = primitive_frame(world, k, d, mocap_vel)
            shape = primitive_shape(world, k, b)
            other = world.prim_body[k] if world.prim_mode[k] in ("free", "actuated") else None
            inv_mass = 1.0 / world.prim_mass[k]
        elif kind == "link":
            link = world.links[k]
            b = link_frame(link, kin)
            shape = link_shape(link, b)

            def touch(shape=shape, a=a, b=b, p=p, body=bodies[i]):
                return pair_wrench(p, shape, body, a, b, world.force_mode, 0.0, world.dt)

            force, torque = _broad_phase(touch, a, bodies[i], b.x, link.radius)
            xfrc = xfrc.at[world.dano_body[i]].add(jnp.concatenate([force, torque]))
            reaction = -(torque + jnp.cross(a.x - kin.xipos[link.body], force))
            xfrc = xfrc.at[link.body].add(jnp.concatenate([-force, reaction]))
            continue
        else:
            b = frames[k]
            force, torque = dano_pair_wrench(p, bodies[i], bodies[k], a, b, world.force_mode, world.dt)
            xfrc = xfrc.at[world.dano_body[i]].add(jnp.concatenate([force, torque]))
            reaction = -(torque + jnp.cross(a.x - b.x, force))
            xfrc = xfrc.at[world.dano_body[k]].add(jnp.concatenate([-force, reaction]))
            continue
        force, torque = pair_wrench(p, shape, bodies[i], a, b, world.force_mode, inv_mass, world.dt)
        xfrc = xfrc.at[world.dano_body[i]].add(jnp.concatenate([force, torque]))
        if other is not None:
            reaction = -(torque + jnp.cross(a.x - b.x, force))
            xfrc = xfrc.at[other].add(jnp.concatenate([-force, reaction]))
    return xfrc


def scaled_model(world: World, params: Params, m: mjx.Model) -> mjx.Model:
    """The model with each DANO's mass and inertia multiplied by its mass and inertia scales."""
    body = jnp.asarray(world.dano_body, dtype=jnp.int32)
    mass_factor = jnp.ones_like(m.body_mass).at[body].set(params.mass_scale)
    inertia_factor = jnp.ones_like(m.body_mass).at[body].set(params.mass_scale * params.inertia_scale)
    return m.replace(body_mass=m.body_mass * mass_factor, body_inertia=m.body_inertia * inertia_factor[:, None])


def mjx_kinematics(m: mjx.Model, d: mjx.Data) -> mjx.Data:
    """`mjx.kinematics` under standard promotion (see `mjx_step`)."""
    with jax.numpy_dtype_promotion("standard"), jax.numpy_rank_promotion("allow"):
        return mjx.kinematics(m, d)


def link_motion(m: mjx.Model, d: mjx.Data) -> mjx.Data:
    """Poses and velocities (`cvel`, `subtree_com`) of the bodies at d's qpos and qvel."""
    with jax.numpy_dtype_promotion("standard"), jax.numpy_rank_promotion("allow"):
        return mjx.com_vel(m, mjx.com_pos(m, mjx.kinematics(m, d)))


def mjx_step(m: mjx.Model, d: mjx.Data) -> mjx.Data:
    """`mjx.step` under JAX's standard promotion rules, which MJX is written for (our own code and
    tests run with strict dtype and rank promotion)."""
    with jax.numpy_dtype_promotion("standard"), jax.numpy_rank_promotion("allow"):
        return mjx.step(m, d)


def step(
    world: World,
    params: Params,
    m: mjx.Model,
    d: mjx.Data,
    mocap_target: Float[Array, "k 3"] | None = None,
    external: Float[Array, "nbody 6"] | None = None,
) -> mjx.Data:
    """One frame: `world.substeps` MuJoCo steps, each with fresh DANO contact wrenches.

    Args:
        m: the model, already `scaled_model(world, params, m)`.
        mocap_target: where the mocap bodies are at the end of the frame; they move in a straight
            line at constant velocity (which the contact damper and friction see).
        external: known external wrenches (force, torque about the centre of mass; world), added to
            the contact wrenches in `xfrc_applied`.
    """
    start = d.mocap_pos
    vel = None if mocap_target is None else (mocap_target - start) / (world.dt * world.substeps)

    def sub(d, i):
        if mocap_target is not None:
            d = d.replace(mocap_pos=start + (i + 1) / world.substeps * (mocap_target - start))
        xfrc = contact_xfrc(world, params, d, vel, m)
        d = d.replace(xfrc_applied=xfrc if external is None else xfrc + external)
        return mjx_step(m, d), None

    d, _ = jax.lax.scan(sub, d, jnp.arange(world.substeps))
    return d


class Trajectory(eqx.Module):
    """qpos (T+1, nq) and qvel (T+1, nv) at every frame, the initial state first."""

    qpos: Float[Array, "t nq"]
    qvel: Float[Array, "t nv"]


def rollout(
    world: World,
    params: Params,
    m: mjx.Model,
    d: mjx.Data,
    n_frames: int,
    ctrl: Float[Array, "t nu"] | None = None,
    mocap_pos: Float[Array, "t k 3"] | None = None,
    external: Float[Array, "t nbody 6"] | None = None,
    checkpoint: bool = True,
) -> Trajectory:
    """Simulates `n_frames` frames from `d` (a `lax.scan`; jit-, grad- and vmap-able).

    Args:
        ctrl: optional actuator controls per frame.
        mocap_pos: optional mocap body positions at the end of each frame (driven end effectors);
            they move at constant velocity within a frame.
        external: optional known external wrenches per frame (see `step`).
        checkpoint: rematerialise each frame in reverse mode (memory: one state per frame) at the
            cost of a second forward pass; turn off for short rollouts differentiated forward
            (`jax.linearize` would otherwise recompute every frame for every tangent).
    """
    m = scaled_model(world, params, m)

    def frame(d, inputs):
        c, mp, ext = inputs
        if c is not None:
            d = d.replace(ctrl=c)
        d = step(world, params, m, d, mp, ext)
        return d, (d.qpos, d.qvel)

    if checkpoint:
        frame = jax.checkpoint(frame)
    _, (qpos, qvel) = jax.lax.scan(frame, d, (ctrl, mocap_pos, external), length=n_frames)
    return Trajectory(jnp.concatenate([d.qpos[None], qpos]), jnp.concatenate([d.qvel[None], qvel]))
