"""The implicit contact step: backward Euler in the DANOs' velocities, as one convex minimisation.

A flat face resting on the floor is a very stiff spring: hundreds of surface points enter the floor
within the indicator width, so d(k psi)/dz ~ k m_face / 1 mm ~ 1e7 N/m on a 0.5 kg box, a period
near 1 ms. Integrated explicitly that spring gains energy at any step the default frame allows,
and the explicit friction law must be smoothed to be stable, so it creeps. This step instead
takes the velocities V' (6 per DANO: v, w, world) at the end of the step h as

    V' = argmin_V  (1/2) |V - V~|_M^2 + U(V) + h R(V) + h D(V),

V~ the velocities after gravity and known external wrenches, M the world-frame mass matrices, U
the pairs' spring potential and R their damper's Rayleigh function (`dano.contact.support`: each
point's depth is linear in V with the geometry frozen at the pose V~ reaches, its force law exact),
D friction's dissipation potential (`dano.contact.friction`). The optimality condition is backward
Euler, M (V' - V~) = h F(V'), and every term is convex, so the step is stable for any stiffness,
finds the contact a fast body would reach within the step, only dissipates, and has a unique
answer: damped Newton with a line search, differentiated through the optimality condition
(`solve_implicit`), so gradients are those of the exact minimiser.

The damper's overlaps are lagged (taken at the pose V~ reaches), and so are friction's normal
forces: the first solve has no friction, each next one (`PASSES`) friction at the normal forces
the previous one delivered, so it scales with the support that answers friction's own torque.

The DANOs' rigid motion is then integrated here, not by MuJoCo: v' gives x; the world angular
momentum L' = I_w(q) w' is held over the step while the rotation follows it (explicit midpoint on
SO(3)), so a torque-free body keeps L exactly and its energy to O(h^2). A DANO-DANO pair is solved
jointly (12 x 12), and so is a DANO and a free primitive: the primitive's 6 velocities join V with
its mass and inertia and its free motion V~ under gravity, and MuJoCo is handed the wrench
M (V' - V~) / h that takes it to V' (its own contacts with other MuJoCo geoms come on top). Held
at V~ instead, as a partner moving at a known velocity, a light free sphere hitting a DANO gained
energy: the reaction, integrated explicitly by MuJoCo, was not the force the DANO's solve assumed.
An actuated primitive (three world-axis slides, weight compensated, force motors) is solved the
same way: its V~ is its velocity after its motors' force `ctrl` over the step, its angular
velocities are held at zero. The reactions on robot links (driven by servos, so not free) are the
pairs' forces with opposite sign, applied through `xfrc_applied` before `mjx.step`.
"""

from collections.abc import Sequence
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from dano._mjx import mjx
from dano.contact import active
from dano.contact.friction import Patch
from dano.contact.overlap import signed_distance
from dano.contact.pairs import Body, Frame
from dano.contact.support import Support, dano_support, primitive_support
from dano.math import cross_matrix, normalize, quat_exp, quat_mul, quat_to_mat
from dano.sim.contact_solve import ContactProblem, group_wrench, solve, solved, untouched
from dano.sim.groups import each, member_lookup, pair_groups, points_key, signature, stack
from dano.sim.step import (
    dano_bodies,
    dano_frames,
    link_motion,
    mjx_step,
    partners,
    primitive_frame,
    primitive_shape,
)
from dano.sim.world import Params, World, pairs


def _moved(f: Frame, xi: Float[Array, " 6"], V: Float[Array, " 6"]) -> Frame:
    """The frame displaced by the twist xi (dx, d theta; first order) with velocity V."""
    return Frame(f.x + xi[:3], f.R + cross_matrix(xi[3:]) @ f.R, V[:3], V[3:])


def _block_diag(blocks: list[Array]) -> Array:
    n = sum(b.shape[0] for b in blocks)
    out = jnp.zeros((n, n), blocks[0].dtype)
    i = 0
    for b in blocks:
        out = out.at[i : i + b.shape[0], i : i + b.shape[0]].set(b)
        i += b.shape[0]
    return out


def _rotate(q: Float[Array, " 4"], R: Array, inertia: Array, L: Array, h: float) -> tuple[Array, Array]:
    """The orientation after h with the world angular momentum L held (explicit midpoint on SO(3)),
    and the body-frame angular velocity there. `inertia` is the body-frame tensor."""

    def omega(R):
        return R @ jnp.linalg.solve(inertia, R.T @ L)

    mid = quat_to_mat(quat_mul(quat_exp(0.5 * h * omega(R)), q))
    q1 = normalize(quat_mul(quat_exp(h * omega(mid)), q))
    R1 = quat_to_mat(q1)
    return q1, jnp.linalg.solve(inertia, R1.T @ L)


def mujoco_moves(world: World, m: mjx.Model) -> bool:
    """Whether `mjx.step` moves anything the implicit step does not (`World.mujoco_moves`): a
    robot, a free primitive, one that collides with MuJoCo geoms, a constraint. Where it does not
    (DANOs among static geometry, mocap bodies and non-colliding actuated primitives, which the
    step places or integrates itself), the step skips it."""
    return world.mujoco_moves


BROAD_MARGIN = 0.01
"""m: a primitive partner's points are evaluated when the DANO's bounding sphere comes within this
of it (plus the indicator width and the partner's own motion over the step), at the pose the free
motion reaches: a contact made within one step by another contact's impulse larger than this
margin is seen one step late."""


def _within_reach(shape, reach: float | Array, a: Frame, b: Frame, h: float, delta) -> Array:
    """Broad phase of a DANO (predicted frame a) and a primitive (current frame b, moving over the
    step h): whether a point of the DANO can be within the indicator width `delta` plus `BROAD_MARGIN`
    of it. Signed distances are 1-Lipschitz, so no point of the DANO (within `reach` of its centre)
    is nearer than sd(centre) - reach (`DanoState.reach`, computed once); the partner's points
    approach by at most h |u_b|."""
    gap = signed_distance(shape, a.x[:, None])[0] - reach
    sweep = h * (jnp.linalg.norm(b.v) + jnp.linalg.norm(b.w) * (jnp.linalg.norm(a.x - b.x) + reach))
    return gap - sweep < delta + BROAD_MARGIN


def implicit_step(
    world: World,
    params: Params,
    m: mjx.Model,
    d: mjx.Data,
    mocap_vel: Float[Array, "k 3"] | None = None,
    external: Float[Array, "nbody 6"] | None = None,
) -> mjx.Data:
    """One step of `world.dt` (module docstring). `m` is already `scaled_model(...)`.

    Top down: the free motion V~ of the unknowns (`_free_motion`), the pairs' points at the pose it
    reaches (`_contact_problem`), the solve where a point is live (`dano.sim.contact_solve.solved`:
    passes of the convex minimisation over each pair's active set, checked, or over all points),
    the reactions, then MuJoCo's step and the DANOs' own integration (`_integrate`).
    """
    free, f, c = _step_problem(world, params, m, d, mocap_vel, external)
    V_next, over, xfrc = untouched(c)
    if c.pair_list:
        V_next, over, xfrc = jax.lax.cond(_touching(c), lambda: solved(c), lambda: untouched(c))
    if external is not None:
        keep = jnp.ones(xfrc.shape[0]).at[jnp.asarray(world.dano_body)].set(0.0)
        xfrc = xfrc + external * keep[:, None]
    d = _integrate(world, m, d, f, free, V_next, xfrc)
    if world.fallback_slot >= 0:
        d = d.replace(userdata=d.userdata.at[world.fallback_slot].add(over.astype(d.userdata.dtype)))
    return d


def implicit_contacts(
    world: World,
    params: Params,
    m: mjx.Model,
    d: mjx.Data,
    mocap_vel: Float[Array, "k 3"] | None = None,
    external: Float[Array, "nbody 6"] | None = None,
) -> tuple[Array, Array]:
    """The contact of the implicit step from `d` (`implicit_step`'s arguments): per pair (`pairs`),
    its wrench on its DANO (P, 6: force, torque about the DANO's centre of mass; world) and where its
    normal force acts (P, 3; the DANO's centre where it does not touch)."""
    c = _step_problem(world, params, m, d, mocap_vel, external)[2]
    centres = jnp.stack([c.frames[i].x for i, _, _ in c.pair_list]) if c.pair_list else jnp.zeros((0, 3))
    none = (jnp.zeros((len(c.pair_list), 6)), centres)
    if not c.pair_list:
        return none

    def touching():
        s = solve(c)
        wrenches, points = jnp.zeros((len(c.pair_list), 6)), centres
        for g, group in enumerate(c.groups):
            w, at = group_wrench(c, s, g, point=True)
            assert at is not None  # asked for
            wrenches, points = wrenches.at[jnp.asarray(group)].set(w), points.at[jnp.asarray(group)].set(at)
        return wrenches, points

    return jax.lax.cond(_touching(c), touching, lambda: none)


def _step_problem(world: World, params: Params, m: mjx.Model, d: mjx.Data, mocap_vel, external):
    """The step's moving primitives, free motion and contact problem."""
    free = tuple(k for k, p in enumerate(world.prims) if p.moving)
    f = _free_motion(world, params, m, d, free, external)
    return free, f, _contact_problem(world, params, m, d, mocap_vel, f, free)


def _touching(c: ContactProblem) -> Array:
    """Whether any point of any pair is live where the free motion goes."""
    return jnp.any(jnp.stack([jnp.any(active.live(sup, sup.s0)) for sup in c.supports]))


class _Free(NamedTuple):
    """The unknowns' free motion: the DANOs' bodies, the free primitives' MuJoCo bodies, frames,
    masses, mass matrix M, V~, the velocities held at 0."""

    bodies: Sequence[Body]
    prim_body: list[int]
    frames: list[Frame]
    masses: list
    inertia_body: list[Array]
    inertia_w: list[Array]
    M: Array
    V_free: Array
    locked: np.ndarray


def _free_motion(world: World, params: Params, m: mjx.Model, d: mjx.Data, free, external) -> _Free:
    """The unknowns V: 6 velocities per DANO, then per free or actuated primitive (`free`; solved
    jointly, see the module docstring; an actuated one slides without turning, so its 3 angular
    velocities are held at 0), and where gravity, motors and known external wrenches take them."""
    h, n = world.dt, len(world.danos)
    bodies = dano_bodies(world, params)
    prim_body = [world.prims[k].body for k in free]
    frames = list(dano_frames(world, d)) + [primitive_frame(world, k, d) for k in free]
    masses = [b.mass for b in bodies] + [m.body_mass[b] for b in prim_body]
    inertia_body = [b.inertia for b in bodies] + [jnp.diag(m.body_inertia[b]) for b in prim_body]
    inertia_w = [f.R @ J @ f.R.T for f, J in zip(frames, inertia_body, strict=True)]
    M = _block_diag([blk for mass, J in zip(masses, inertia_w, strict=True) for blk in (mass * jnp.eye(3), J)])
    body_ids = list(world.dano_body) + prim_body
    locked = np.zeros(6 * len(frames), bool)
    V_free = []
    for i, f in enumerate(frames):
        ext = jnp.zeros(6) if external is None else external[body_ids[i]]
        k = free[i - n] if i >= n else -1
        if k >= 0 and world.prims[k].mode == "actuated":  # weight compensated, driven by its motors
            c = world.prims[k].actuator
            force = d.ctrl[c : c + 3] * m.actuator_gear[c : c + 3, 0] + ext[:3]
            V_free.append(jnp.concatenate([f.v + h * force / masses[i], jnp.zeros(3)]))
            locked[6 * i + 3 : 6 * i + 6] = True
            continue
        v = f.v + h * (m.opt.gravity + ext[:3] / masses[i])
        V_free.append(jnp.concatenate([v, f.w + h * jnp.linalg.solve(inertia_w[i], ext[3:])]))
    return _Free(bodies, prim_body, frames, masses, inertia_body, inertia_w, M, jnp.concatenate(V_free), locked)


def _contact_problem(
    world: World, params: Params, m: mjx.Model, d: mjx.Data, mocap_vel, f: _Free, free
) -> ContactProblem:
    """The step's contact problem: the free motion, and each group's points (`_group_points`) with
    the geometry frozen at the pose the free motion reaches (so a contact that the step would reach
    acts in that step), their lever arms and their partners' velocities."""
    h, n = world.dt, len(world.danos)
    pair_list = pairs(world)
    kin = link_motion(m, d) if world.links else None
    mates = partners(world, d, mocap_vel, kin)
    slot = {k: n + s for s, k in enumerate(free)}
    V = f.V_free
    start = [_moved(fr, h * V[6 * i : 6 * i + 6], V[6 * i : 6 * i + 6]) for i, fr in enumerate(f.frames)]
    # Where each pair's partner sits in V (a DANO or a free primitive), or -1 (moves at a known velocity).
    other = [
        mate.dano if mate.dano >= 0 else slot.get(k, -1) if kind == "primitive" else -1
        for (_, kind, k), mate in zip(pair_list, mates, strict=True)
    ]

    def partner(j: int):
        """Pair j's partner frame and shape; one solved for with the DANO at the pose its free motion
        reaches (a DANO has no shape)."""
        o, mate = other[j], mates[j]
        if o < 0:
            return mate.frame, mate.shape
        return start[o], None if mate.dano >= 0 else primitive_shape(world, pair_list[j][2], start[o])

    danos = [(points_key(s), s.budget) for s in world.danos]
    fields = [signature((s.field, s.com, s.peak)) for s in world.danos]
    groups = pair_groups(pair_list, mates, other, danos=danos, fields=fields)
    contact, supports, patches = [], [], []
    for group in groups:
        p = stack([params.contact[j] for j in group])
        frames, shapes = zip(*[partner(j) for j in group], strict=True)
        j, owners, mated = group[0], [pair_list[j][0] for j in group], [mates[j].dano for j in group]
        sup, patch = _group_points(world, f.bodies, owners, other[j], mated, p, stack(shapes), stack(frames), start, h)
        contact.append(p)
        supports.append(sup)
        patches.append(patch)
    return ContactProblem(world, params, h, n, pair_list, mates, groups, other, contact, supports, patches, V, f.M,
                          f.locked, f.frames, f.masses, f.prim_body, kin, jnp.zeros_like(d.xfrc_applied))  # fmt: skip


def _owners(world: World, bodies, owners: list[int], start: list[Frame], field: bool = False):
    """Member m of a group -> its DANO's contact data (without its field unless `field`: the
    partners of a primitive group do not need it), its predicted frame and its bounding radius
    (`DanoState.reach`), by `member_lookup`."""

    def value(i):
        return bodies[i] if field else bodies[i].without_field(), start[i], world.danos[i].reach

    return member_lookup(owners, value)


def _group_points(
    world: World, bodies, owners: list[int], o: int, mated: list[int], p, shapes, frames, start, h: float
):
    """A group's supports and patches (stacked): each member's DANO (`owners`; `start` the DANOs'
    predicted frames) against its partner (shapes and frames stacked; `mated` the members' DANO
    partners, or -1 where they are primitives; `o` >= 0 where the partners are solved for with the
    DANOs), broad phase included (`_within_reach`: a DANO far from all of a group's primitives costs
    no point evaluation)."""
    dano = mated[0]  # the group's kind (`pair_groups`): all DANO partners or none

    def one(p, shape, b: Frame, a: Frame, body: Body, mate: Body | None = None) -> tuple[Support, Patch]:
        if dano >= 0:
            assert mate is not None  # a DANO partner's body is given
            sup = dano_support(body, mate, a, b)
        else:
            sup = primitive_support(shape, body, a, p.indicator_width)
        zero = jnp.zeros_like(sup.at)
        if o >= 0:
            patch = Patch(
                sup.at - a.x[:, None], sup.at - b.x[:, None], zero, jnp.zeros(3), sup.normal, sup.weight, True
            )
            return sup, patch
        u_b = b.v[:, None] + jnp.cross(b.w[:, None], sup.at - b.x[:, None], axis=0)
        patch = Patch(sup.at - a.x[:, None], zero, u_b, b.w, sup.normal, sup.weight)
        # the partner's own motion over the step brings it nearer (n . u_b > 0) or takes it away
        ahead = sup.gain * h * jnp.sum(jnp.broadcast_to(sup.normal, u_b.shape) * u_b, axis=0)
        return Support(sup.at, sup.normal, sup.weight, sup.s0 + ahead, sup.gain, sup.smooth), patch

    members = jnp.arange(len(owners))
    if dano >= 0:  # DANO partners (copies of one object, `pair_groups`): both bodies with their fields
        own, mate_of = _owners(world, bodies, owners, start, True), _owners(world, bodies, mated, start, True)

        def dano_member(q, b, m):  # the partner's frame is `b` (its predicted one)
            body, a, _ = own(m)
            return one(q, None, b, a, body, mate_of(m)[0])

        return each(dano_member, p, frames, members)
    own = _owners(world, bodies, owners, start)

    def far(*args):
        """No point can touch: weightless, held (gain 0) and outside the law's support (s0 = -2), so
        the active set counts none of them as live."""
        zeros = jax.tree_util.tree_map(lambda x: jnp.zeros(x.shape, x.dtype), jax.eval_shape(one, *args))
        return eqx.tree_at(lambda t: t[0].s0, zeros, jnp.full(zeros[0].s0.shape, -2.0, zeros[0].s0.dtype))

    def member(q, shape, b, m):
        """One pair, its points evaluated only where its partner is within reach."""
        body, a, reach = own(m)
        near = _within_reach(shape, reach, a, b, h, q.indicator_width)
        return jax.lax.cond(near, one, far, q, shape, b, a, body)

    # one pair at a time (`each`: a loop), so each keeps its own broad phase
    return each(member, p, shapes, frames, members)


def _integrate(world: World, m: mjx.Model, d: mjx.Data, f: _Free, free, V_next, xfrc) -> mjx.Data:
    """MuJoCo's step with the reactions (or, where it would move nothing but actuated slides, their
    Euler step here), then the DANOs' own: v' gives x, the world angular momentum I_w w' is held
    while the rotation follows it (`_rotate`)."""
    h, n = world.dt, len(world.danos)
    quats = [d.qpos[a + 3 : a + 7] for a in world.dano_qpos]  # at the step's start
    if mujoco_moves(world, m):
        d = mjx_step(m, d.replace(xfrc_applied=xfrc))
        qpos, qvel = d.qpos, d.qvel
    else:  # MuJoCo would move nothing but actuated slides: integrated here, as MuJoCo would, time advances
        d = d.replace(time=d.time + h, xfrc_applied=xfrc)
        qpos, qvel = d.qpos, d.qvel
        for s, k in enumerate(free):  # all actuated (`mujoco_moves`): V' is their velocity, Euler in position
            a, v, lin = world.prims[k].qpos, world.prims[k].qvel, V_next[6 * (n + s) : 6 * (n + s) + 3]
            qpos = qpos.at[a : a + 3].add(h * lin)
            qvel = qvel.at[v : v + 3].set(lin)
    V_next = V_next[: 6 * n].reshape(n, 6)
    for i, (a, v) in enumerate(zip(world.dano_qpos, world.dano_qvel, strict=True)):
        fr, J = f.frames[i], f.inertia_body[i]
        q1, w_body = _rotate(quats[i], fr.R, J, f.inertia_w[i] @ V_next[i, 3:], h)
        qpos = qpos.at[a : a + 3].set(fr.x + h * V_next[i, :3]).at[a + 3 : a + 7].set(q1)
        qvel = qvel.at[v : v + 3].set(V_next[i, :3]).at[v + 3 : v + 6].set(w_body)
    return d.replace(qpos=qpos, qvel=qvel)
