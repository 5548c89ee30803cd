"""The implicit contact step: backward Euler in the DANOs' velocities, friction that sticks.

A flat face resting on the floor is a very stiff spring: hundreds of surface points enter the floor
within the indicator width, so d(k psi)/dz ~ k m_face / 1 mm ~ 1e7 N/m on a 0.5 kg box, a period
near 1 ms. Integrated explicitly that spring gains energy at any step the default frame allows,
and the explicit friction law must be smoothed to be stable, so it creeps. This step instead
solves, for the velocities V' (6 per DANO: v, w, world) at the end of the step h,

    M (V' - V~) = h F_n(q + h V', V') + h F_f(V'),

in two stages (V~ the velocity after gravity and known external wrenches; M the world-frame mass
matrices):

1. **Normal forces, linearised backward Euler** (as MuJoCo's implicit integrators treat
   velocity-dependent forces, plus the position term): with K = dF_n/dq and D = dF_n/dV from one
   forward-mode Jacobian of the contact (12 tangents per DANO),
           (M - h D - h^2 K) dV = h F_n,        V* = V~ + dV,
   all at the predicted end of the step (q + h V~, V~), so a contact the step would reach acts in
   that step.
   It is stable for any stiffness and damping (A-stable), and only dissipates.
2. **Friction, exactly implicit**: V' = argmin (1/2)|V - V*|_A^2 + h D(V) with D the convex
   dissipation potential of `dano.contact.friction`, at the normal forces of stage 1 (linearised
   to the end of the step). Solved by Newton's method with a backtracking line search; its
   derivatives come from the optimality condition (implicit function theorem, `lax.custom_root`),
   so gradients are those of the exact minimiser.

The DANOs' rigid motion is then integrated here, not by MuJoCo: v' gives x; the world angular
momentum L' = I_w(q) w' is held over the step while the rotation follows it (explicit midpoint on
SO(3)), so a torque-free body keeps L exactly and its energy to O(h^2). The reactions on MuJoCo
bodies (free and actuated primitives, robot links) are the same forces with opposite sign, applied
through `xfrc_applied` before `mjx.step` moves them; a DANO-DANO pair is solved jointly (12 x 12).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float
from mujoco import mjx

from dano.contact.friction import Patch, patch_terms
from dano.contact.pairs import Frame, relative_velocity, wrench_about
from dano.contact.pairs import reaction as reaction_of
from dano.math import cross_matrix, normalize, quat_exp, quat_mul, quat_to_mat
from dano.sim.scene import Params, World, pairs
from dano.sim.step import dano_bodies, dano_frames, link_motion, mjx_step, pair_points, partners, scatter

FRICTION_PASSES = 2
"""Friction solves per step: the first at stage 1's normal forces, the next at the normal forces
that the support gives once friction has acted (`friction_solve`)."""

NEWTON_ITERATIONS = 40
"""At most this many Newton steps for the friction stage (it stops when a step moves < 1e-13)."""


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


def minimize_convex(objective, x0: Float[Array, " n"], tol: float | Float[Array, ""]) -> Float[Array, " n"]:
    """argmin of a smooth strongly convex function by damped Newton, differentiable through the
    optimality condition grad f(x*) = 0 (`lax.custom_root`), not through the iterations.

    Args:
        objective: x -> (value, gradient, Hessian).
        x0: the start.
        tol: stop when the Newton decrement -grad . dx (units of the value) is below this.
    """

    def solve(_, x):
        def newton(state):
            k, x, _ = state
            f0, g, H = objective(x)
            dx = -jnp.linalg.solve(H, g)
            slope = g @ dx

            def too_long(t):
                return (objective(x + t * dx)[0] > f0 + 1e-4 * t * slope) & (t > 1e-12)

            small = -slope < tol
            one = jnp.ones((), x.dtype)
            t = jax.lax.cond(small, lambda: one, lambda: jax.lax.while_loop(too_long, lambda t: 0.5 * t, one))
            return k + 1, x + t * dx, small

        def going(state):
            k, _, done = state
            return (k < NEWTON_ITERATIONS) & ~done

        return jax.lax.while_loop(going, newton, (0, x, False))[1]

    def tangent_solve(g, y):
        return jnp.linalg.solve(jax.jacobian(g)(y), y)

    return jax.lax.custom_root(lambda x: objective(x)[1], x0, solve, tangent_solve)


def _at_least(S: Float[Array, "n n"], M: Float[Array, "n n"]) -> Float[Array, "n n"]:
    """The symmetric S with its eigenvalues raised to at least half the smallest of M's (so that the
    friction problem stays strongly convex whatever the geometric stiffness)."""
    # The correction carries no gradient: eigh's derivative is undefined at repeated eigenvalues
    # (m, m, m), and in practice the correction is zero (A = M + dissipative and restoring terms).
    fixed = jax.lax.stop_gradient(S)
    lam, Q = jnp.linalg.eigh(fixed)
    floor = 0.5 * jnp.min(jnp.linalg.eigvalsh(jax.lax.stop_gradient(M)))
    return S + (Q * (jnp.maximum(lam, floor) - lam)[None, :]) @ Q.T


def friction_normal(N: Float[Array, " k"]) -> Float[Array, " k"]:
    """The points' normal forces that friction scales with: the positive parts of stage 1's
    linearised forces N (k,), scaled so that they add up to the pair's total normal force.

    Each point's force is a linear extrapolation over the step from the predicted state, good in
    sum (the total is the impulse stage 1 delivers: M dV / h) but not point by point: where a face
    enters the floor, points in the indicator's ramp extrapolate far above and below zero, and the
    sum of the positive parts was 10x the delivered force (a box placed 0.5 mm into the floor
    lost a third of its 1 m/s in the first step). So the positive parts give where the support is,
    the total how much; a pair whose net normal force pulls has no friction.
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


def implicit_step(
    world: World,
    params: Params,
    m: mjx.Model,
    d: mjx.Data,
    mocap_vel: Float[Array, "k 3"] | None = None,
    external: Float[Array, "nbody 6"] | None = None,
) -> mjx.Data:
    """One step of `world.dt` (module docstring). `m` is already `scaled_model(...)`."""
    h = world.dt
    n = len(world.danos)
    bodies, frames = dano_bodies(world, params), dano_frames(world, d)
    quats = [d.qpos[a + 3 : a + 7] for a in world.dano_qpos]
    pair_list = pairs(world)
    kin = link_motion(m, d) if world.links else None
    mates = partners(world, d, mocap_vel, kin)
    inertia_w = [f.R @ b.inertia @ f.R.T for f, b in zip(frames, bodies, strict=True)]
    M = _block_diag([blk for b, J in zip(bodies, inertia_w, strict=True) for blk in (b.mass * jnp.eye(3), J)])
    V_free = []
    for i, (f, b) in enumerate(zip(frames, bodies, strict=True)):
        ext = jnp.zeros(6) if external is None else external[world.dano_body[i]]
        v = f.v + h * (m.opt.gravity + ext[:3] / b.mass)
        V_free.append(jnp.concatenate([v, f.w + h * jnp.linalg.solve(inertia_w[i], ext[3:])]))
    V_free = jnp.concatenate(V_free)

    def frames_at(z):
        xi, V = z[: 6 * n].reshape(n, 6), z[6 * n :].reshape(n, 6)
        return [_moved(f, xi[i], V[i]) for i, f in enumerate(frames)]

    def normal_forces(z):
        """Stage 1's forces at displacement/velocity z = (xi, V): the total wrench on each DANO
        (6n,), each pair's wrench on its DANO (p, 6) and each point's normal force (p x (k,))."""
        fr = frames_at(z)
        W = jnp.zeros((n, 6))
        per_pair, normal, geometry = [], [], []
        for p, (i, _, _), mate in zip(params.contact, pair_list, mates, strict=True):
            a = fr[i]
            b = fr[mate.dano] if mate.dano >= 0 else mate.frame
            pts = pair_points(world, p, mate, bodies, i, a, b)
            u_n = jnp.sum(relative_velocity(pts, a, b) * pts.normal, axis=0)
            N = pts.psi * (p.impact_spring - p.impact_damper * u_n)
            w = wrench_about(pts, N[None] * pts.normal, a.x)
            W = W.at[i].add(w)
            if mate.dano >= 0:
                W = W.at[mate.dano].add(reaction_of(w, a.x, b.x))
            per_pair.append(w)
            normal.append(N)
            geometry.append(pts)
        out = (W.reshape(-1), tuple(per_pair), tuple(normal))
        return out, (out, tuple(geometry))

    # Linearised at the predicted end of the step (displacement h V~, velocity V~): a contact that
    # the step would reach is felt in that step, so a fast body is stopped at the surface instead
    # of a step's travel inside it.
    z0 = jnp.concatenate([h * V_free, V_free])
    jac, ((W0, w0, N0), geometry) = jax.jacfwd(normal_forces, has_aux=True)(z0)
    J_W, J_w, J_N = jac
    K, D = J_W[:, : 6 * n], J_W[:, 6 * n :]
    A = M - h * D - h * h * K
    dV = jnp.linalg.solve(A, h * W0)
    V_star = V_free + dV
    dz = jnp.concatenate([h * dV, dV])
    N_end = [N + J @ dz for N, J in zip(N0, J_N, strict=True)]
    w_normal = [w + J @ dz for w, J in zip(w0, J_w, strict=True)]

    # Stage 2: friction at the same (predicted) geometry, with the normal forces of stage 1.
    start = frames_at(z0)
    bare = []
    for (i, _, _), mate, pts in zip(pair_list, mates, geometry, strict=True):
        a = start[i]
        b = start[mate.dano] if mate.dano >= 0 else mate.frame
        zero = jnp.zeros_like(pts.at)
        none = jnp.zeros_like(pts.psi)
        if mate.dano >= 0:
            bare.append(Patch(pts.at - a.x[:, None], pts.at - b.x[:, None], zero, jnp.zeros(3), pts.normal, none))
        else:
            u_b = b.v[:, None] + jnp.cross(b.w[:, None], pts.at - b.x[:, None], axis=0)
            bare.append(Patch(pts.at - a.x[:, None], zero, u_b, b.w, pts.normal, none))

    def linearised(values, jacobians, V):
        """Stage 1's linearised forces at the end-of-step velocities V instead of V*."""
        e = V - V_star
        de = jnp.concatenate([h * e, e])
        return [x + J @ de for x, J in zip(values, jacobians, strict=True)]

    def pair_terms(patches, j, V):
        """D of pair j, its gradient (6n,) and Hessian (6n, 6n) at the DANOs' velocities V (6n,)."""
        i, mate = pair_list[j][0], mates[j]
        V_b = V[6 * mate.dano : 6 * mate.dano + 6] if mate.dano >= 0 else jnp.zeros(6)
        value, g, H = patch_terms(params.contact[j], patches[j], V[6 * i : 6 * i + 6], V_b)
        o = 6 * max(mate.dano, 0)
        idx = jnp.concatenate([jnp.arange(6 * i, 6 * i + 6), jnp.arange(o, o + 6)])
        keep = 12 if mate.dano >= 0 else 6
        idx, g, H = idx[:keep], g[:keep], H[:keep, :keep]
        return value, jnp.zeros(6 * n).at[idx].add(g), jnp.zeros((6 * n, 6 * n)).at[idx[:, None], idx[None, :]].add(H)

    # Friction moves the bodies against the stiff normal support, not through free space: its
    # quadratic is stage 1's operator A (symmetric part, no softer than half the bare inertia), so
    # the friction under a box slows it down instead of pitching it into the floor.
    M_f = _at_least(0.5 * (A + A.T), M)
    total_mass = sum(b.mass for b in bodies)

    def friction_solve(V_guess):
        """Friction at the normal forces stage 1's operator gives at V_guess (the support also
        answers friction's own torque: at V* alone a box on a slope felt 0.5 % too little)."""
        patches = [
            eqx.tree_at(lambda q: q.N, base, friction_normal(N))
            for base, N in zip(bare, linearised(N_end, J_N, V_guess), strict=True)
        ]

        def objective(V):
            e = V - V_star
            value, g, H = 0.5 * e @ M_f @ e, M_f @ e, M_f
            for j in range(len(pair_list)):
                vj, gj, Hj = pair_terms(patches, j, V)
                value, g, H = value + h * vj, g + h * gj, H + h * Hj
            return value, g, H

        return minimize_convex(objective, V_guess, 1e-20 * total_mass), patches

    V_next = V_star
    patches = None
    for _ in range(FRICTION_PASSES if pair_list else 0):
        V_next, patches = friction_solve(V_next)
    w_final = linearised(w_normal, J_w, V_next)

    # Reactions on MuJoCo bodies; DANOs are integrated here.
    xfrc = jnp.zeros_like(d.xfrc_applied)
    if external is not None:
        keep = jnp.ones(xfrc.shape[0]).at[jnp.asarray(world.dano_body)].set(0.0)
        xfrc = external * keep[:, None]
    for j, ((i, kind, _), mate) in enumerate(zip(pair_list, mates, strict=True)):
        if mate.body < 0:
            continue
        friction = -pair_terms(patches, j, V_next)[1][6 * i : 6 * i + 6]
        centre = kin.xipos[mate.body] if kind == "link" else mate.frame.x
        xfrc = scatter(xfrc, mate.body, reaction_of(w_final[j] + friction, frames[i].x, centre))
    d = mjx_step(m, d.replace(xfrc_applied=xfrc))

    qpos, qvel = d.qpos, d.qvel
    V_next = V_next.reshape(n, 6)
    for i, (a, v) in enumerate(zip(world.dano_qpos, world.dano_qvel, strict=True)):
        f, b = frames[i], bodies[i]
        q1, w_body = _rotate(quats[i], f.R, b.inertia, inertia_w[i] @ V_next[i, 3:], h)
        qpos = qpos.at[a : a + 3].set(f.x + h * V_next[i, :3]).at[a + 3 : a + 7].set(q1)
        qvel = qvel.at[v : v + 3].set(V_next[i, :3]).at[v + 3 : v + 6].set(w_body)
    return d.replace(qpos=qpos, qvel=qvel)
