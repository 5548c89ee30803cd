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

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from dano._mjx import mjx
from dano.contact import active
from dano.contact.friction import Patch, patch_terms
from dano.contact.overlap import signed_distance
from dano.contact.pairs import Frame
from dano.contact.pairs import reaction as reaction_of
from dano.contact.support import Support, dano_support, normal_terms, normal_velocity, overlap, primitive_support
from dano.math import cross_matrix, normalize, quat_exp, quat_mul, quat_to_mat
from dano.sim.newton import minimize_convex, newton, run_if, solve_implicit
from dano.sim.step import (
    Partner,
    dano_bodies,
    dano_frames,
    link_motion,
    mjx_step,
    partners,
    primitive_frame,
    primitive_shape,
    scatter,
)
from dano.sim.world import Params, World, pairs

PASSES = 3
"""Solves per step: the first without friction, each next one with friction at the normal forces
the previous one delivered (so that they include the support's answer to friction's own torque)."""


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


class _Sets(eqx.Module):
    """Each pair's support and patch, the damper's lagged overlaps and the normal velocities at V~:
    all the points, or their active sets."""

    supports: tuple
    patches: tuple
    psi0: tuple
    u_n0: tuple


def friction_normal(N: Float[Array, " k"]) -> Float[Array, " k"]:
    """The points' normal forces that friction scales with: the positive parts of N (k,), scaled
    to add up to the pair's total. A point's spring and damper may pull (N < 0) while the pair
    pushes; clipping alone then counts more support than the pair gives (in the first version of
    this step, 10x for a box placed 0.5 mm into the floor, which lost a third of its 1 m/s in one
    step). So the positive parts give where the support is, the total how much; a pair whose net
    normal force pulls has no friction.
    """
    positive = jnp.maximum(N, 0.0)
    total, raw = jnp.maximum(jnp.sum(N), 0.0), jnp.sum(positive)
    return positive * (total / jnp.where(raw > 0, raw, 1.0))


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


def _support(world: World, p, mate, bodies, i: int, a: Frame, b: Frame, h: float) -> Support:
    """Pair i's support at the predicted frames (a: the DANO's; b: a DANO partner's predicted frame,
    else the partner's current one), broad phase included (`_within_reach`: a DANO far from a
    primitive costs no point evaluation)."""
    if mate.dano >= 0:
        return dano_support(bodies[i], bodies[mate.dano], a, b)
    fn = lambda: primitive_support(mate.shape, bodies[i], a, p.indicator_width)  # noqa: E731

    def far() -> Support:
        """No point can touch: weightless, held (gain 0) and outside the law's support (s0 = -2), so
        the active set counts none of them as live."""
        sup = jax.eval_shape(fn)
        zero = lambda x: jnp.zeros(x.shape, x.dtype)  # noqa: E731
        s0 = jnp.full(sup.s0.shape, -2.0, sup.s0.dtype)
        return Support(zero(sup.at), zero(sup.normal), zero(sup.weight), s0, zero(sup.gain), sup.smooth)

    reach = world.danos[i].reach
    return jax.lax.cond(_within_reach(mate.shape, reach, a, b, h, p.indicator_width), fn, far)


def _within_reach(shape, reach: float, a: Frame, b: Frame, h: float, delta) -> Array:
    """Broad phase of a DANO (predicted frame a) and a primitive (current frame b, moving over the
    step h): whether a point of the DANO can be within the indicator width `delta` plus `BROAD_MARGIN`
    of it. Signed distances are 1-Lipschitz, so no point of the DANO (within `reach` of its centre)
    is nearer than sd(centre) - reach (`DanoState.reach`, computed once); the partner's points
    approach by at most h |u_b|."""
    gap = signed_distance(shape, a.x[:, None])[0] - reach
    sweep = h * (jnp.linalg.norm(b.v) + jnp.linalg.norm(b.w) * (jnp.linalg.norm(a.x - b.x) + reach))
    return gap - sweep < delta + BROAD_MARGIN


def _centroid(patch: Patch, psi: Array) -> Patch:
    """The paper's centroid mode for friction: one point at chi carrying the whole pair."""
    total = jnp.sum(psi)
    mean = lambda x: (x @ psi / jnp.where(total > 0, total, 1.0))[:, None]  # noqa: E731
    normal = patch.normal if patch.normal.shape[1] == 1 else normalize(mean(patch.normal)[:, 0])[:, None]
    return Patch(mean(patch.r_a), mean(patch.r_b), mean(patch.u_b), patch.w_b, normal, total[None], patch.joint)


def implicit_step(
    world: World,
    params: Params,
    m: mjx.Model,
    d: mjx.Data,
    mocap_vel: Float[Array, "k 3"] | None = None,
    external: Float[Array, "nbody 6"] | None = None,
) -> mjx.Data:
    """One step of `world.dt` (module docstring). `m` is already `scaled_model(...)`.

    One long function on purpose (~270 lines): its inner functions (the pairs' slots, sets,
    objective, the solve's passes and the reactions) close over the step's pairs, frames, masses
    and the free motion, and are traced once inside its `lax.cond` branches; as module functions
    each would take a dozen of those as arguments. Read it top down: the free motion V~, the
    partners, the objective over each pair's active set, the solve (`solved`: passes of
    `minimize_convex`, the exact check of the dropped points, the dense fallback), the
    reactions, then MuJoCo's step and the DANOs' own integration.
    """
    h = world.dt
    n = len(world.danos)
    bodies, frames = dano_bodies(world, params), dano_frames(world, d)
    quats = [d.qpos[a + 3 : a + 7] for a in world.dano_qpos]
    pair_list = pairs(world)
    kin = link_motion(m, d) if world.links else None
    mates = partners(world, d, mocap_vel, kin)
    # The unknowns V: 6 velocities per DANO, then per free or actuated primitive (solved jointly,
    # see above; an actuated one slides without turning, so its 3 angular velocities are held at 0).
    free = tuple(k for k, p in enumerate(world.prims) if p.moving)
    slot = {k: n + s for s, k in enumerate(free)}
    prim_body = [world.prims[k].body for k in free]
    frames_all = list(frames) + [primitive_frame(world, k, d) for k in free]
    masses = [b.mass for b in bodies] + [m.body_mass[b] for b in prim_body]
    inertia_body = [b.inertia for b in bodies] + [jnp.diag(m.body_inertia[b]) for b in prim_body]
    inertia_w = [f.R @ J @ f.R.T for f, J in zip(frames_all, inertia_body, strict=True)]
    M = _block_diag([blk for mass, J in zip(masses, inertia_w, strict=True) for blk in (mass * jnp.eye(3), J)])
    n_all = len(frames_all)
    body_ids = list(world.dano_body) + prim_body
    locked = np.zeros(6 * n_all, bool)
    V_free = []
    for i, f in enumerate(frames_all):
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
    V_free = jnp.concatenate(V_free)

    # The geometry, frozen at the pose the free motion reaches (so a contact that the step would
    # reach acts in that step), and each pair's points' lever arms and partner velocities.
    start = [_moved(f, h * V_free[6 * i : 6 * i + 6], V_free[6 * i : 6 * i + 6]) for i, f in enumerate(frames_all)]
    # Where each pair's partner sits in V (a DANO or a free primitive), or -1 (moves at a known velocity).
    other = [
        mate.dano if mate.dano >= 0 else slot.get(k, -1) if kind == "primitive" else -1
        for (_, kind, k), mate in zip(pair_list, mates, strict=True)
    ]
    supports, patches = [], []
    for j, (p, (i, _, k), mate) in enumerate(zip(params.contact, pair_list, mates, strict=True)):
        a = start[i]
        b = start[other[j]] if other[j] >= 0 else mate.frame
        if other[j] >= 0 and mate.dano < 0:  # a free primitive, at the pose its free motion reaches
            mate = Partner(b, primitive_shape(world, k, b), mate.body, -1, mate.inv_mass, mate.radius)
        sup = _support(world, p, mate, bodies, i, a, b, h)
        zero = jnp.zeros_like(sup.at)
        if other[j] >= 0:
            patch = Patch(
                sup.at - a.x[:, None], sup.at - b.x[:, None], zero, jnp.zeros(3), sup.normal, sup.weight, True
            )
        else:
            u_b = b.v[:, None] + jnp.cross(b.w[:, None], sup.at - b.x[:, None], axis=0)
            patch = Patch(sup.at - a.x[:, None], zero, u_b, b.w, sup.normal, sup.weight)
            # the partner's own motion over the step brings it nearer (n . u_b > 0) or takes it away
            ahead = sup.gain * h * jnp.sum(jnp.broadcast_to(sup.normal, u_b.shape) * u_b, axis=0)
            sup = Support(sup.at, sup.normal, sup.weight, sup.s0 + ahead, sup.gain, sup.smooth)
        supports.append(sup)
        patches.append(patch)

    def slots(j) -> list[int]:
        """Where pair j's velocity vector (V_a, or (V_a, V_b) with a partner in V) sits in V."""
        i, o = pair_list[j][0], other[j]
        return list(range(6 * i, 6 * i + 6)) + (list(range(6 * o, 6 * o + 6)) if o >= 0 else [])

    def pair_velocity(j, V):
        return V[jnp.asarray(slots(j))]

    def scatter_pair(j, g, H):
        """A pair's gradient (m,) and Hessian (m, m) into the (6N,) and (6N, 6N) of all unknowns."""
        idx = jnp.asarray(slots(j))
        size = 6 * n_all
        return jnp.zeros(size).at[idx].add(g), jnp.zeros((size, size)).at[idx[:, None], idx[None, :]].add(H)

    centroid = world.force_mode == "centroid"  # friction and damper at chi (the spring per point)

    def point_sets(sups, pts) -> _Sets:
        u_n0 = tuple(normal_velocity(pt, pair_velocity(j, V_free))[0] for j, pt in enumerate(pts))
        # The damper's overlaps, lagged: at the pose the free motion reaches.
        return _Sets(tuple(sups), tuple(pts), tuple(overlap(sup, sup.s0) for sup in sups), u_n0)

    def with_friction(sets: _Sets, V, on):
        """Each pair's friction patch at the normal forces delivered at the velocities V, times
        `on` (0: no friction, 1)."""
        out = []
        for j, (p, sup, pt) in enumerate(zip(params.contact, sets.supports, sets.patches, strict=True)):
            _, _, _, s, u_n = normal_terms(p, sup, pt, sets.psi0[j], sets.u_n0[j], h, pair_velocity(j, V), centroid)
            N = on * friction_normal(p.impact_spring * overlap(sup, s) - p.impact_damper * sets.psi0[j] * u_n)
            fr = Patch(pt.r_a, pt.r_b, pt.u_b, pt.w_b, pt.normal, N, pt.joint)
            out.append(_centroid(fr, N) if centroid else fr)
        return out

    def pair_terms(sets: _Sets, j, friction, V):
        """Pair j's U + h R + h D (D with the friction patches, a list) at V, with its
        gradient and Hessian w.r.t. the pair's velocity vector."""
        Vj = pair_velocity(j, V)
        p = params.contact[j]
        sup, pt = sets.supports[j], sets.patches[j]
        value, g, H, _, _ = normal_terms(p, sup, pt, sets.psi0[j], sets.u_n0[j], h, Vj, centroid)
        fv, fg, fH = patch_terms(p, friction[j], Vj)
        return value + h * fv, g + h * fg, H + h * fH

    def objective(sets: _Sets, friction):
        def f(V):
            e = V - V_free
            value, g, H = 0.5 * e @ M @ e, M @ e, M
            for j in range(len(pair_list)):
                vj, gj, Hj = pair_terms(sets, j, friction, V)
                gj, Hj = scatter_pair(j, gj, Hj)
                value, g, H = value + vj, g + gj, H + Hj
            if locked.any():  # held velocities: no gradient, a unit Hessian (Newton leaves them at 0)
                g = jnp.where(locked, 0.0, g)
                H = jnp.where(locked[:, None] | locked[None, :], jnp.eye(6 * n_all), H)
            return value, g, H

        return f

    def solved():
        """The pairs' contact solved: over each pair's active set, checked, or over all points; the
        passes are one traced pass run PASSES times (they differ only in their data)."""

        def full():  # all the points' sets, formed only where they are used (inside the branches)
            return point_sets(supports, patches)

        # The active set of each pair (`dano.contact.active`), where its budget is below its points.
        budgets = [
            world.danos[i].budget + (world.danos[mate.dano].budget if mate.dano >= 0 else 0)
            for (i, _, _), mate in zip(pair_list, mates, strict=True)
        ]
        actives = [
            active.choose(sup, k) if 0 < k < sup.s0.shape[0] else None for sup, k in zip(supports, budgets, strict=True)
        ]
        triples = list(zip(supports, patches, actives, strict=True))
        taken = [active.take(sup, pt, a) if a is not None else (sup, pt) for sup, pt, a in triples]
        sparse = point_sets([t[0] for t in taken], [t[1] for t in taken])
        drops = [active.dropped(sup, pt, a) if a is not None else None for sup, pt, a in triples]
        started_over = jnp.any(jnp.asarray([a.overflow for a in actives if a is not None] or [False]))

        # Every point's normal velocity at V~, for the exact check (once per step, not per pass).
        u_n0 = [normal_velocity(pt, pair_velocity(j, V_free))[0] for j, pt in enumerate(patches)]

        def missed(V) -> Array:
            """Whether a point that the active sets dropped is live at V (`dano.contact.active`)."""
            out = started_over
            for j, (a, drop) in enumerate(zip(actives, drops, strict=True)):
                if a is None or drop is None:  # both or neither
                    continue
                dV = pair_velocity(j, V) - pair_velocity(j, V_free)

                def exact(j=j, a=a):
                    return active.missed(supports[j], patches[j], a, u_n0[j], pair_velocity(j, V), h)

                # the exact check under a once-or-never loop: in a batch, only when some element needs it
                safe = active.bound_holds(supports[j], drop, dV, h)
                out = out | run_if(~safe, lambda _, exact=exact: exact(), jnp.zeros((), bool))
            return out

        total_mass = sum(masses)
        tol = 1e-20 * total_mass
        # The first friction solve starts from the velocities the step starts with, not from the
        # frictionless answer: a body that friction holds is near them, while without friction it
        # may slip and turn (a resting box: 1.5 mm/s at its face, far out on the Coulomb law's flat
        # part, where Newton needs ~20 damped steps to come back instead of ~4).
        V_now = jnp.concatenate([jnp.concatenate([f.v, f.w]) for f in frames_all])
        sparse_step = any(a is not None for a in actives)

        def one_pass(carry, k):
            """Solve k: friction at the normal forces of solve k - 1 (none in the first, `PASSES`), over
            the active sets, or over all points once a dropped point turns out live (`missed`)."""
            V_before, over = carry
            x0 = jnp.where(k == 1, V_now, V_before)
            on = (k > 0).astype(V_before.dtype)
            if not sparse_step:
                sets = full()
                return (minimize_convex(objective(sets, with_friction(sets, V_before, on)), x0, tol), over), V_before
            small = objective(sparse, with_friction(sparse, V_before, on))

            def dense():
                sets = full()
                return objective(sets, with_friction(sets, V_before, on))

            def forward(x):
                """Over the active sets, then over all points once a dropped point turns out live (once
                over, the rest of the step is dense: its friction needs all the points)."""
                trial = newton(small, x, tol)
                now_over = over | missed(trial)
                return run_if(now_over, lambda x: newton(dense(), x, tol), trial), now_over

            def solved_over(V, now_over):  # the objective that was minimised
                return jax.lax.cond(now_over, lambda V: dense()(V), small, V)

            return solve_implicit(forward, solved_over, x0), V_before

        last_on = jnp.asarray(float(PASSES > 1), V_free.dtype)

        def reactions(V_next, V_before, over):
            """The pairs' reactions on MuJoCo bodies, as `xfrc_applied` (the pair's force on the DANO
            is -dT/dV_a / h)."""
            xfrc = jnp.zeros_like(d.xfrc_applied)
            for s, body in enumerate(prim_body):  # a free primitive: the wrench that takes it to V'
                e = slice(6 * (n + s), 6 * (n + s) + 6)
                xfrc = scatter(xfrc, body, M[e, e] @ (V_next[e] - V_free[e]) / h)
            for j, ((i, kind, _), mate) in enumerate(zip(pair_list, mates, strict=True)):
                if mate.body < 0 or other[j] >= 0:
                    continue
                if sparse_step:  # solved over the active sets, or over all points if they overflowed

                    def grad_of(sets, j=j):
                        return pair_terms(sets, j, with_friction(sets, V_before, last_on), V_next)[1]

                    g = jax.lax.cond(over, lambda: grad_of(full()), lambda: grad_of(sparse))
                else:
                    sets = full()
                    g = pair_terms(sets, j, with_friction(sets, V_before, last_on), V_next)[1]
                if kind == "link":
                    assert kin is not None  # `link_motion` ran: the world has links
                    centre = kin.xipos[mate.body]
                else:
                    centre = mate.frame.x
                xfrc = scatter(xfrc, mate.body, reaction_of(-g[:6] / h, frames[i].x, centre))
            return xfrc

        (V_next, over), befores = jax.lax.scan(one_pass, (V_free, jnp.zeros((), bool)), jnp.arange(PASSES))
        return V_next, over, reactions(V_next, befores[-1], over)

    def untouched():
        """No point of any pair is live where the free motion goes: V~ is the minimiser (every
        contact term is flat there), no check and no reaction."""
        return V_free, jnp.zeros((), bool), jnp.zeros_like(d.xfrc_applied)

    V_next, over, xfrc = untouched()
    if pair_list:
        touching = jnp.any(jnp.stack([jnp.any(active.live(sup, sup.s0)) for sup in supports]))
        V_next, over, xfrc = jax.lax.cond(touching, solved, untouched)
    if external is not None:
        keep = jnp.ones(xfrc.shape[0]).at[jnp.asarray(world.dano_body)].set(0.0)
        xfrc = xfrc + external * keep[:, None]
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
        f, b = frames[i], bodies[i]
        q1, w_body = _rotate(quats[i], f.R, b.inertia, inertia_w[i] @ V_next[i, 3:], h)
        qpos = qpos.at[a : a + 3].set(f.x + h * V_next[i, :3]).at[a + 3 : a + 7].set(q1)
        qvel = qvel.at[v : v + 3].set(V_next[i, :3]).at[v + 3 : v + 6].set(w_body)
    d = d.replace(qpos=qpos, qvel=qvel)
    if world.fallback_slot >= 0:
        d = d.replace(userdata=d.userdata.at[world.fallback_slot].add(over.astype(d.userdata.dtype)))
    return d
