"""The normal contact as a potential, for the implicit step (paper eqs. 7-11, solved implicitly).

Each point i of a pair pushes the DANO along its normal n_i with the spring force k w_i sigma(s_i):
w_i its weight (kg), s_i how deep it is. Against a primitive s_i = -f(P_i) / delta and sigma is the
indicator's smootherstep (so k w_i sigma is the paper's k psi_i, per point); against another DANO s_i
is the partner's occupancy at the point and sigma clips it to [0, 1]. Over one step of length h the
geometry is frozen at the predicted pose (normals, lever arms), and each point's further approach is
linear in the end-of-step velocities V:

    d_i(V) = -h (u_n,i(V) - u_n,i(V~)),     s_i(V) = s0_i + gain_i d_i(V),

u_n,i the normal relative velocity at the point, V~ the velocities the step starts from (after
gravity), s0 the depth at the pose V~ reaches, gain = ds/dd (1/delta for a primitive, the occupancy's
slope along the normal for a DANO). sigma does not decrease, so the spring is the gradient of the
convex potential

    U(V) = sum_i k w_i (Phi(s_i(V)) - Phi(s0_i)) / gain_i,      Phi' = sigma,

and the damper -c psi_i u_n,i (psi_i = w_i sigma, lagged) of the convex Rayleigh function
h sum_i c psi_i u_n,i^2 / 2. Backward Euler in the normal forces is then the minimum of a strongly
convex function (`dano.sim.implicit`): stable for any stiffness, and it cannot create energy.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from dano.contact.friction import Patch, rows
from dano.contact.overlap import Primitive, outward_normal, signed_distance
from dano.contact.pairs import Body, Frame, occupancy, world_points
from dano.contact.wrench import ContactParams
from dano.math import normalize

MIN_GAIN = 1.0
"""1/m: a DANO-DANO point whose occupancy slope is below this (flat there: saturated, or outside
the partner) has its force held at s0 over the step (gain 0), as the hard indicator's: over a step
its depth changes by less than a micron's worth of the law, and a point outside the partner then
exerts no force at all, so the active set (`dano.contact.active`) can leave it out."""


class Support(eqx.Module):
    """A pair's points at the predicted pose: world points `at` (3, k), unit normals from the partner
    towards the DANO (3, k) or (3, 1), weights (k,) kg, depths s0 (k,) and gains (k,) 1/m (0: the
    force is held at s0 over the step, the hard indicator's); `smooth`: the primitive's
    smootherstep law (True) or the DANO occupancy's clip (False)."""

    at: Float[Array, "3 k"]
    normal: Float[Array, "3 kn"]
    weight: Float[Array, " k"]
    s0: Float[Array, " k"]
    gain: Float[Array, " k"]
    smooth: bool = eqx.field(static=True)


def law(s: Array, smooth: bool) -> tuple[Array, Array, Array]:
    """Phi(s), sigma(s) = Phi'(s) and sigma'(s): the smootherstep on [-1, 1] (`dano.math`), or
    clip(s, 0, 1)."""
    if smooth:
        u = jnp.clip((s + 1.0) / 2.0, 0.0, 1.0)
        ramp = 2.0 * u**4 * (u * (u - 3.0) + 2.5)  # 2 * integral of 6u^5 - 15u^4 + 10u^3
        phi = ramp + jnp.maximum(s - 1.0, 0.0)
        return phi, u**3 * (u * (6.0 * u - 15.0) + 10.0), 15.0 * u * u * (u - 1.0) ** 2
    c = jnp.clip(s, 0.0, 1.0)
    phi = jnp.where(s < 1.0, 0.5 * c * c, s - 0.5)
    return phi, c, ((s > 0.0) & (s < 1.0)).astype(s.dtype)


def overlap(support: Support, s: Array) -> Array:
    """psi_i = w_i sigma(s_i), kg."""
    return support.weight * law(s, support.smooth)[1]


def primitive_support(shape: Primitive, body: Body, a: Frame, delta) -> Support:
    """A DANO against a primitive {f <= 0}: s = -f / delta, gain 1 / delta, normals grad f.

    delta = 0 is the hard inside test: each point's force is then a step in its depth, so it is
    taken at the predicted pose and held over the step (gain 0; `normal_terms`), as Dojo does."""
    P = world_points(body, a)
    safe = jnp.where(delta > 0, delta, 1e-9)  # delta = 0, the hard indicator, is the limit
    s0 = -signed_distance(shape, P) / safe
    normal = jax.vmap(outward_normal, (None, 1), 1)(shape, P)
    gain = jnp.where(delta > 0, 1.0 / safe, 0.0)
    return Support(P, normal, body.weights, s0, jnp.full_like(s0, gain), True)


def dano_support(A: Body, B: Body, a: Frame, b: Frame) -> Support:
    """DANO A against DANO B (eqs. 9-10): A's points in B's occupancy and B's in A's, all pushing A
    along one normal (from B towards A; as in `dano.contact.pairs.dano_points`). A point's gain is its
    occupancy's slope as the bodies approach along that normal (0, held, below `MIN_GAIN`)."""
    PA, PB = world_points(A, a), world_points(B, b)
    occ_b, occ_a = occupancy(B, b, PA), occupancy(A, a, PB)
    n = normalize((b.R @ B.normals) @ (B.weights * occ_a) - (a.R @ A.normals) @ (A.weights * occ_b))
    # A moving along -n goes into B; B's points then move along +n relative to A.
    slope_a = jax.jvp(lambda P: occupancy(B, b, P), (PA,), (jnp.broadcast_to(-n[:, None], PA.shape),))[1]
    slope_b = jax.jvp(lambda P: occupancy(A, a, P), (PB,), (jnp.broadcast_to(n[:, None], PB.shape),))[1]
    slope = jnp.concatenate([slope_a, slope_b])
    return Support(
        jnp.concatenate([PA, PB], axis=1),
        n[:, None],
        jnp.concatenate([A.weights, B.weights]),
        jnp.concatenate([occ_b, occ_a]),
        jnp.where(slope >= MIN_GAIN, slope, 0.0),
        False,
    )


def normal_velocity(patch: Patch, V: Float[Array, " m"]) -> tuple[Array, Array]:
    """Each point's normal relative velocity u_n (k,) = n . (v_a + w_a x r_a - u_b - v_b - w_b x r_b)
    at the pair's velocity vector V (V_a, or (V_a, V_b) for a joint DANO partner), and its rows
    d u_n / dV (m, k)."""
    n = jnp.broadcast_to(patch.normal, patch.r_a.shape)
    J = rows(patch, n)
    return J.T @ V - jnp.sum(n * patch.u_b, axis=0), J


def normal_terms(
    p: ContactParams,
    support: Support,
    patch: Patch,
    psi: Array,
    u_n0: Array,
    h,
    V: Float[Array, " m"],
    centroid: bool = False,
):
    """The pair's spring potential U plus h times its damper's Rayleigh function (module docstring)
    at the pair's velocity vector V (m = 6, or 12 for a joint DANO partner), with gradient (m,) and
    Hessian (m, m). `patch` gives the points' lever arms and the partner's velocity (its N is not
    used), `psi` (k,) the damper's lagged overlaps, `u_n0` (k,) the normal velocities at V~.
    `centroid`: the paper's centroid mode, the damper -c psi u_n(chi) acting at the overlap centroid
    chi (u_n(chi) the psi-weighted mean of the points' u_n), not at each point: the same force, but
    it does not damp rocking about chi.

    Also returns each point's spring depth s (k,) and normal velocity u_n (k,) at V."""
    u_n, J = normal_velocity(patch, V)
    # gain 0: a force that is a step in the depth (the hard indicator) is held at s0 over the step;
    # its potential is then linear in V (k w sigma(s0) d), Newton's Hessian has no spring part.
    held = support.gain <= 0.0
    gain = jnp.maximum(support.gain, MIN_GAIN)
    d = -h * (u_n - u_n0)  # each point's further approach over the step
    s = jnp.where(held, support.s0, support.s0 + gain * d)
    phi, sigma, slope = law(s, support.smooth)
    phi0 = law(support.s0, support.smooth)[0]
    k, c = p.impact_spring, p.impact_damper
    value = jnp.sum(k * support.weight * jnp.where(held, sigma * d, (phi - phi0) / gain))
    d1 = -h * k * support.weight * sigma  # d value / d u_n
    d2 = jnp.where(held, 0.0, h * h * k * support.weight * slope * gain)
    if centroid:
        total = jnp.sum(psi)
        share = psi / jnp.where(total > 0, total, 1.0)
        u_chi, J_chi = share @ u_n, J @ share  # u_n at chi and its row d u_n(chi) / dV
        value = value + 0.5 * h * c * total * u_chi * u_chi
        grad = J @ d1 + h * c * total * u_chi * J_chi
        hess = (J * d2[None]) @ J.T + h * c * total * jnp.outer(J_chi, J_chi)
        return value, grad, hess, s, u_n
    value = value + 0.5 * h * c * jnp.sum(psi * u_n * u_n)
    d1 = d1 + h * c * psi * u_n
    d2 = d2 + h * c * psi
    return value, J @ d1, (J * d2[None]) @ J.T, s, u_n
