"""Friction as a dissipation potential, for the implicit step (paper eqs. 12-14, solved implicitly).

The paper's friction (eqs. 12-14) opposes slip with |F_n| (mu v/|v| + d v). Integrated explicitly it
cannot hold a body still: the force must reverse within a step, so it is smoothed, and a smoothed
law creeps (paper Sec. IV). Here friction is instead the gradient of a convex potential of the
velocities at the end of the step,

    D(V) = sum_i N_i [ g mu_s rho(u_t,i) + d_s |u_t,i|^2 / 2        sliding (eq. 12)
                     + g mu_t rho(W_n,i) + d_t |W_n,i|^2 / 2        torsion (eq. 13)
                     + g mu_r rho(W_t,i) + d_r |W_t,i|^2 / 2 ]      rolling (eq. 14)
    rho(a) = sqrt(v_s^2 + |a|^2) - v_s,      grad rho(a) = a / sqrt(v_s^2 + |a|^2),

with N_i each point's normal force, u_t,i its tangential slip, W the relative angular velocity
(normal and tangential parts at the point's normal), g = coulomb_gain pi / 2 (1 by default) and v_s
= `stiction_velocity` (for spin, v_s / SPIN_LENGTH in rad/s). The step's velocities minimise (1/2)|V
- V*|_A^2 + h D(V) (`dano.sim.implicit`; a strongly convex problem: friction is the proximal step of
its own dissipation, as in optimisation-based contact). Above v_s the force is mu N to within (v_s /
|u|)^2 / 2, the exact Coulomb force; below, it is a stiff viscous force that the implicit solve
keeps stable, so a body held by friction slips at about v_s (1e-5 m/s by default) instead of the
explicit law's centimetres per second.
"""

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from dano.contact.wrench import ContactParams
from dano.math import cross_matrix

SPIN_LENGTH = 0.01
"""m: spin sticks below v_s / SPIN_LENGTH rad/s (a point 1 cm from the axis slipping at v_s)."""


class Patch(eqx.Module):
    """A pair's friction data, frozen over the step: lever arms from the DANO's centre `r_a` (3, k)
    and from a DANO partner's `r_b` (3, k) (zeros otherwise), the partner's velocity at each point
    `u_b` (3, k) and angular velocity `w_b` (3,) when it is not solved for (zeros otherwise),
    normals (3, k) or (3, 1), normal forces N (k,) >= 0."""

    r_a: Float[Array, "3 k"]
    r_b: Float[Array, "3 k"]
    u_b: Float[Array, "3 k"]
    w_b: Float[Array, " 3"]
    normal: Float[Array, "3 kn"]
    N: Float[Array, " k"]


def _law(coef, drag, a: Array, vs) -> tuple[Array, Array, Array]:
    """Value, gradient factor c and curvature factor e of coef rho(a) + drag |a|^2 / 2 with
    a (3, k) (or (k,) for a scalar): gradient c a, Hessian c I - e a a^T."""
    sq = jnp.sum(a * a, axis=0) if a.ndim == 2 else a * a
    s = jnp.sqrt(vs * vs + sq)
    value = coef * sq / (s + vs) + 0.5 * drag * sq
    return value, coef / s + drag, coef / (s * s * s)


def patch_terms(p: ContactParams, patch: Patch, V_a: Float[Array, " 6"], V_b: Float[Array, " 6"]):
    """D of one pair (module docstring) at the DANO's velocity V_a and a DANO partner's V_b (zeros
    for other partners), its gradient w.r.t. (V_a, V_b) (12,) and Hessian (12, 12), analytically
    (a few passes over the points: the step's friction solve evaluates these many times)."""
    gain = p.coulomb_gain * (jnp.pi / 2)
    vs, ws = p.stiction_velocity, p.stiction_velocity / SPIN_LENGTH
    n, N = patch.normal, patch.N
    u = (V_a[:3, None] + jnp.cross(V_a[3:, None], patch.r_a, axis=0)) - patch.u_b
    u = u - V_b[:3, None] - jnp.cross(V_b[3:, None], patch.r_b, axis=0)
    w = V_a[3:] - V_b[3:] - patch.w_b
    u_t = u - jnp.sum(u * n, axis=0, keepdims=True) * n
    w_n = w @ n
    w_t = w[:, None] - w_n[None] * n
    slide, c_s, e_s = _law(gain * p.sliding_friction, p.sliding_drag, u_t, vs)
    twist, c_n, e_n = _law(gain * p.torsional_friction, p.torsional_drag, w_n, ws)
    roll, c_r, e_r = _law(gain * p.rolling_friction, p.rolling_drag, w_t, ws)
    k = N.shape[0]
    Nn = jnp.broadcast_to(jnp.sum(N) if n.shape[1] == 1 else N, w_n.shape)  # weights of the spin terms
    value = jnp.sum(N * slide) + jnp.sum(Nn * (twist + roll))
    g_u = (N * c_s)[None] * u_t  # (3, k) dD/du
    g_w = (Nn * c_n * w_n) @ n.T + jnp.sum((Nn * c_r)[None] * w_t, axis=1)  # (3,) dD/dw
    eye = jnp.eye(3)
    P = eye[None] - jnp.einsum("ik,jk->kij", n, n)  # (k or 1, 3, 3) tangent projectors
    H_u = (N * c_s)[:, None, None] * P - (N * e_s)[:, None, None] * jnp.einsum("ik,jk->kij", u_t, u_t)
    H_u = jnp.broadcast_to(H_u, (k, 3, 3))
    nn = jnp.einsum("ik,jk->kij", n, n)
    H_w = jnp.sum((Nn * (c_n - e_n * w_n * w_n))[:, None, None] * nn, axis=0)
    roll_t = jnp.einsum("ik,jk->kij", w_t, w_t)
    H_w = H_w + jnp.sum((Nn * c_r)[:, None, None] * P - (Nn * e_r)[:, None, None] * roll_t, axis=0)

    def blocks(r_x, r_y):
        """sum_i J_x^T H_u J_y with J = [I, -[r]x] (velocity of a point at lever r)."""
        Rx, Ry = cross_matrix(r_x.T), cross_matrix(r_y.T)
        vv = jnp.sum(H_u, axis=0)
        vw = -jnp.sum(H_u @ Ry, axis=0)
        wv = jnp.sum(Rx @ H_u, axis=0)
        ww = -jnp.sum(Rx @ H_u @ Ry, axis=0)
        return jnp.block([[vv, vw], [wv, ww]])

    rot = jnp.zeros((6, 6)).at[3:, 3:].set(H_w)
    H_aa = blocks(patch.r_a, patch.r_a) + rot
    H_ab = -blocks(patch.r_a, patch.r_b) - rot
    H_bb = blocks(patch.r_b, patch.r_b) + rot
    grad_a = jnp.concatenate([jnp.sum(g_u, axis=1), jnp.sum(jnp.cross(patch.r_a, g_u, axis=0), axis=1) + g_w])
    grad_b = -jnp.concatenate([jnp.sum(g_u, axis=1), jnp.sum(jnp.cross(patch.r_b, g_u, axis=0), axis=1) + g_w])
    H = jnp.block([[H_aa, H_ab], [H_ab.T, H_bb]])
    return value, jnp.concatenate([grad_a, grad_b]), H
