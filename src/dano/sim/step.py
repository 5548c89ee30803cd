"""The simulation step: DANO contact -> MuJoCo MJX, as a column of stages, and rollouts.

One frame is `world.substeps` steps of `world.dt`. Two integrators (`Scene.integrator`):

- "implicit" (default): `implicit_step` (`dano.sim.implicit`): the contact is solved implicitly in
  the DANOs' velocities (backward Euler as one convex minimisation: spring potential, damper, friction),
  and the DANOs' rigid motion is integrated by dano; the reactions on MuJoCo bodies enter through
  `xfrc_applied` and `mjx.step` moves them. Stable at the 2 ms default with one step per frame.
- "explicit": the wrench at the current state written to `xfrc_applied` before each `mjx.step`
  (the paper's "computed explicitly at the current configuration"), with the linearly implicit
  damper; it needs ~0.5 ms steps, and reproduces the reference's stored trajectories.

A rollout is a `lax.scan` over frames with the frame step under `jax.checkpoint`, so reverse-mode
gradients of long rollouts keep only one state per frame.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from dano._mjx import mjx
from dano.contact import Box, Capsule, Cylinder, HalfSpace, HeightField, Polytope, Sphere
from dano.contact.overlap import Primitive
from dano.contact.pairs import Body, Frame, PointSet, dano_points, near, primitive_points, reaction
from dano.contact.wrench import ContactParams, contact_wrench
from dano.math import normalize, quat_to_mat
from dano.sim.groups import each, member_lookup, pair_groups, points_key, stack
from dano.sim.world import LinkGeom, Params, World, pairs


def free_frame(qpos: Array, qvel: Array, a: int, v: int) -> Frame:
    """Frame of a free-joint body from MuJoCo state (its angular qvel is in the body frame)."""
    R = quat_to_mat(qpos[a + 3 : a + 7])
    return Frame(qpos[a : a + 3], R, qvel[v : v + 3], R @ qvel[v + 3 : v + 6])


def _static_frame(pos, quat) -> Frame:
    z = jnp.zeros(3)
    return Frame(jnp.asarray(pos, dtype=float), quat_to_mat(jnp.asarray(quat, dtype=float)), z, z)


def primitive_frame(world: World, k: int, d: mjx.Data, mocap_vel: Array | None = None) -> Frame:
    p = world.prims[k]
    z = jnp.zeros(3)
    if p.mode == "free":
        return free_frame(d.qpos, d.qvel, p.qpos, p.qvel)
    if p.mode == "actuated":  # three slides along world x, y, z: no rotation
        pos = jnp.asarray(p.pos, dtype=float) + d.qpos[p.qpos : p.qpos + 3]
        return Frame(pos, quat_to_mat(jnp.asarray(p.quat, dtype=float)), d.qvel[p.qvel : p.qvel + 3], z)
    if p.mode == "mocap":
        v = z if mocap_vel is None else mocap_vel[p.mocap]
        return Frame(d.mocap_pos[p.mocap], quat_to_mat(d.mocap_quat[p.mocap]), v, z)
    return _static_frame(p.pos, p.quat)


def primitive_shape(world: World, k: int, f: Frame):
    p = world.prims[k]
    if p.kind == "sphere":
        return Sphere(f.x, jnp.asarray(p.size[0]))
    if p.kind == "capsule":
        axis = f.R[:, 2] * p.size[1]
        return Capsule(f.x - axis, f.x + axis, jnp.asarray(p.size[0]))
    return Box(f.x, f.R, jnp.asarray(p.size, dtype=float))


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
        assert link.normals is not None and link.offsets is not None  # `_link_geom` sets them for a mesh
        return Polytope(f.x, f.R, link.normals, link.offsets)
    if link.kind == "sphere":
        return Sphere(f.x, jnp.asarray(link.size[0]))
    if link.kind == "capsule":
        axis = f.R[:, 2] * link.size[1]
        return Capsule(f.x - axis, f.x + axis, jnp.asarray(link.size[0]))
    if link.kind == "cylinder":
        return Cylinder(f.x, f.R, jnp.asarray(link.size[0]), jnp.asarray(link.size[1]))
    if link.kind == "hfield":
        assert link.heights is not None  # `link_geom` sets them for a height field
        return HeightField(f.x, f.R, link.heights, jnp.asarray(link.size[:2]), jnp.asarray(link.size[3]))
    return Box(f.x, f.R, jnp.asarray(link.size, dtype=float))


def dano_bodies(world: World, params: Params) -> tuple[Body, ...]:
    """Each DANO's contact data at the current mass and inertia scales."""
    out = []
    for i, s in enumerate(world.danos):
        mass = s.mass * params.mass_scale[i]
        inertia = s.inertia * params.mass_scale[i] * params.inertia_scale[i]
        out.append(Body(s.points, s.normals, s.shares * mass, mass, inertia, s.field, s.com, s.peak))
    return tuple(out)


def dano_frames(world: World, d: mjx.Data) -> tuple[Frame, ...]:
    return tuple(free_frame(d.qpos, d.qvel, a, v) for a, v in zip(world.dano_qpos, world.dano_qvel, strict=True))


class Partner(eqx.Module):
    """The other body of a pair, as the contact sees it.

    Attributes:
        frame: its pose and velocity (for a DANO partner, from the DANO frames instead).
        shape: its geometry (None for a DANO).
        body: MuJoCo body id that takes the reaction, or -1 (static, mocap, or a DANO: see `dano`).
        dano: the partner's DANO index, or -1.
        inv_mass: 1 / its mass (0 when it does not move under forces).
        radius: broad-phase radius around `frame.x`, or 0 for no broad phase.
    """

    frame: Frame
    shape: Primitive | None
    body: int = eqx.field(static=True)
    dano: int = eqx.field(static=True)
    inv_mass: float = eqx.field(static=True)
    radius: float = eqx.field(static=True)


def _ground(world: World, k: int, d, kin, mocap_vel) -> Partner:
    assert world.ground_height is not None  # a ground pair exists only then (`pairs`)
    n = world.ground_normal
    b = _static_frame(tuple(world.ground_height * v for v in n), (1.0, 0.0, 0.0, 0.0))
    return Partner(b, HalfSpace(jnp.asarray(n), b.x), -1, -1, 0.0, 0.0)


def _primitive(world: World, k: int, d, kin, mocap_vel) -> Partner:
    b = primitive_frame(world, k, d, mocap_vel)
    p = world.prims[k]
    return Partner(b, primitive_shape(world, k, b), p.body if p.moving else -1, -1, 1.0 / p.mass, 0.0)


def _link(world: World, k: int, d, kin, mocap_vel) -> Partner:
    link = world.links[k]
    b = link_frame(link, kin)
    return Partner(b, link_shape(link, b), link.body, -1, 0.0, link.radius)


def _dano(world: World, k: int, d, kin, mocap_vel) -> Partner:
    return Partner(free_frame(d.qpos, d.qvel, world.dano_qpos[k], world.dano_qvel[k]), None, -1, k, 0.0, 0.0)


PARTNERS = {"ground": _ground, "primitive": _primitive, "link": _link, "dano": _dano}
"""How each pair kind's partner is read from the MuJoCo state: one small function per kind."""


def partners(world: World, d: mjx.Data, mocap_vel=None, kin: mjx.Data | None = None) -> tuple[Partner, ...]:
    """Every pair's partner; `kin` is `link_motion(m, d)` when the world has a robot."""
    return tuple(PARTNERS[kind](world, k, d, kin, mocap_vel) for _, kind, k in pairs(world))


def pair_points(
    world: World, p: ContactParams, shape, bodies, i: int, a: Frame, b: Frame, dano: int, radius
) -> PointSet:
    """The contact points of DANO i (frame a) with its partner (frame b; `dano` its DANO index, else
    -1 and `shape` its geometry), broad phase included where `radius` (the partner's bounding
    radius, `Partner.radius`) is not 0."""
    if dano >= 0:
        return dano_points(bodies[i], bodies[dano], a, b, world.force_mode)
    fn = lambda: primitive_points(shape, bodies[i], a, p.indicator_width, world.force_mode)  # noqa: E731
    if isinstance(radius, float) and not radius:
        return fn()
    zero = jax.eval_shape(fn)
    return jax.lax.cond(near(bodies[i], a, b.x, radius), fn, lambda: _zeros(zero))


def _zeros(shapes) -> PointSet:
    return jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)


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


def explicit_pair_wrench(
    world: World, p: ContactParams, shape, b: Frame, inv_mass, radius, dano: int, bodies, frames, i: int
) -> tuple[Float[Array, " 6"], Float[Array, " 3"]]:
    """The explicit step's wrench on DANO i from its partner (frame b; `pair_points` for the rest;
    `inv_mass` 1 / its mass where it is not a DANO) (eqs. 11-16): force and torque about the DANO's
    centre of mass, world, with the damper made linearly implicit; and where it acts (the overlap's
    centroid chi, world; the DANO's centre where there is no overlap)."""
    a = frames[i]
    pts = pair_points(world, p, shape, bodies, i, a, b, dano, radius)
    psi = jnp.sum(pts.psi)
    chi = pts.at @ pts.psi / jnp.where(psi > 0, psi, 1.0)
    normal = pts.normal[:, 0] if pts.normal.shape[1] == 1 else _mean_normal(pts)
    inv_m = inverse_effective_mass(bodies[i], a, chi, normal)
    if dano >= 0:
        inv_m = inv_m + inverse_effective_mass(bodies[dano], b, chi, normal)
    else:
        inv_m = inv_m + inv_mass
    p = implicit_damper(p, psi, inv_m, world.dt)
    w = contact_wrench(p, pts.psi, pts.at, pts.normal, a.x, a.v, a.w, b.x, b.v, b.w)
    return jnp.concatenate([w.force, w.torque]), jnp.where(psi > 0, chi, a.x)


def explicit_groups(world: World, params: Params, d: mjx.Data, mocap_vel=None, kin: mjx.Data | None = None):
    """The explicit step's pairs in groups (`dano.sim.groups`): per group, its pairs' indices (into
    `pairs`), their partners, and their wrenches on their DANO (k, 6) and where they act (k, 3)
    (`explicit_pair_wrench`)."""
    pair_list = pairs(world)
    mates = partners(world, d, mocap_vel, kin)
    frames, bodies = dano_frames(world, d), dano_bodies(world, params)
    # across DANOs whose points agree; a DANO partner alone; links apart from primitives (only links
    # have a broad phase: `Partner.radius`)
    danos = [points_key(s) for s in world.danos]
    apart = [m.radius > 0 for m in mates]
    out = []
    for group in pair_groups(pair_list, mates, [m.dano for m in mates], apart, danos=danos):
        mate = mates[group[0]]
        i, dano, broad = pair_list[group[0]][0], mate.dano, mate.radius > 0
        owner = member_lookup([pair_list[j][0] for j in group], lambda i: (bodies[i].without_field(), frames[i]))

        def one(p, shape, b, inv_mass, radius, m, i=i, dano=dano, broad=broad, owner=owner):
            radius = radius if broad else 0.0  # no broad phase: none traced
            if dano >= 0:  # a DANO partner: a group of its own (`pair_groups`)
                return explicit_pair_wrench(world, p, shape, b, inv_mass, radius, dano, bodies, frames, i)
            body, a = owner(m)
            return explicit_pair_wrench(world, p, shape, b, inv_mass, radius, -1, (body,), (a,), 0)

        shapes = stack([mates[j].shape for j in group]) if dano < 0 else None
        radii = stack([mates[j].radius for j in group])
        inputs = (stack([params.contact[j] for j in group]), shapes, stack([mates[j].frame for j in group]))
        wrench, at = each(one, *inputs, stack([mates[j].inv_mass for j in group]), radii, jnp.arange(len(group)))
        out.append((group, [mates[j] for j in group], wrench, at))
    return frames, out


def _mean_normal(pts: PointSet) -> Array:
    return normalize(pts.normal @ pts.psi)


def scatter(xfrc: Array, body: int, wrench: Array) -> Array:
    """Adds a wrench (force, torque about the body's centre of mass; world) to `xfrc_applied`."""
    return xfrc.at[body].add(wrench) if body >= 0 else xfrc


def contact_xfrc(
    world: World,
    params: Params,
    d: mjx.Data,
    mocap_vel: Float[Array, "k 3"] | None = None,
    m: mjx.Model | None = None,
) -> Float[Array, "nbody 6"]:
    """The explicit step's DANO contact wrenches, as MuJoCo's `xfrc_applied` (nbody, 6).

    Args:
        mocap_vel: velocities of the mocap bodies (driven primitives), world, m/s; zero if None.
        m: the model, needed when the world has a robot (for its link poses).
    """
    xfrc = jnp.zeros_like(d.xfrc_applied)
    kin = None
    if world.links:
        assert m is not None, "a world with a robot needs the model `m` (its link poses)"
        kin = link_motion(m, d)
    frames, groups = explicit_groups(world, params, d, mocap_vel, kin)
    for group, mates, wrench, _ in groups:
        for j, partner, w in zip(group, mates, wrench, strict=True):
            i, kind, _ = pairs(world)[j]
            xfrc = scatter(xfrc, world.dano_body[i], w)
            if partner.dano >= 0:
                xfrc = scatter(xfrc, world.dano_body[partner.dano], reaction(w, frames[i].x, frames[partner.dano].x))
            elif partner.body >= 0:
                if kind == "link":
                    assert kin is not None  # `link_motion` ran: the world has links
                    centre = kin.xipos[partner.body]
                else:
                    centre = partner.frame.x
                xfrc = scatter(xfrc, partner.body, reaction(w, frames[i].x, centre))
    return xfrc


def explicit_contacts(
    world: World, params: Params, m: mjx.Model, d: mjx.Data, mocap_vel: Float[Array, "k 3"] | None = None
) -> tuple[Array, Array]:
    """`dano.sim.implicit.implicit_contacts` for the explicit step: per pair its wrench on its DANO
    (P, 6) and where it acts (P, 3)."""
    kin = link_motion(m, d) if world.links else None
    n = len(pairs(world))
    wrenches, points = jnp.zeros((n, 6)), jnp.zeros((n, 3))
    for group, _, wrench, at in explicit_groups(world, params, d, mocap_vel, kin)[1]:
        wrenches, points = wrenches.at[jnp.asarray(group)].set(wrench), points.at[jnp.asarray(group)].set(at)
    return wrenches, points


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
    """One frame: `world.substeps` steps, each with fresh DANO contacts (module docstring).

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
        if world.integrator == "implicit":
            from dano.sim.implicit import implicit_step

            return implicit_step(world, params, m, d, vel, external), None
        xfrc = contact_xfrc(world, params, d, vel, m)
        d = d.replace(xfrc_applied=xfrc if external is None else xfrc + external)
        return mjx_step(m, d), None

    d, _ = jax.lax.scan(sub, d, jnp.arange(world.substeps))
    return d


class Trajectory(eqx.Module):
    """qpos (T+1, nq) and qvel (T+1, nv) at every frame, the initial state first; `fallbacks`
    (T+1,): how many steps so far had a contact active set overflow and were solved over all
    points (`dano.contact.active`; exact, at the dense cost), or None."""

    qpos: Float[Array, "t nq"]
    qvel: Float[Array, "t nv"]
    fallbacks: Float[Array, " t"] | None = None


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
        return d, (d.qpos, d.qvel, fallbacks(world, d))

    if checkpoint:
        frame = jax.checkpoint(frame)
    _, (qpos, qvel, fell) = jax.lax.scan(frame, d, (ctrl, mocap_pos, external), length=n_frames)
    first = fallbacks(world, d)  # None exactly when `fell` is
    fell = None if fell is None or first is None else jnp.concatenate([first[None], fell])
    return Trajectory(jnp.concatenate([d.qpos[None], qpos]), jnp.concatenate([d.qvel[None], qvel]), fell)


def fallbacks(world: World, d: mjx.Data) -> Float[Array, ""] | None:
    """The steps so far whose contact active sets overflowed (counted in `d.userdata`), or None."""
    return d.userdata[world.fallback_slot] if world.fallback_slot >= 0 else None
