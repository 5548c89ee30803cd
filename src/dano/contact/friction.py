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

SPIN_LENGTH = 0.01
"""m: spin sticks below v_s / SPIN_LENGTH rad/s (a point 1 cm from the axis slipping at v_s)."""


class Patch(eqx.Module):
    """A pair's friction data, frozen over the step: lever arms from the DANO's centre `r_a` (3, k)
    and from a DANO partner's `r_b` (3, k) (zeros otherwise), the partner's velocity at each point
    `u_b` (3, k) and angular velocity `w_b` (3,) when it is not solved for (zeros otherwise),
    normals (3, k) or (3, 1), normal forces N (k,) >= 0; `joint`: the partner is a DANO whose
    velocity V_b is solved for with the DANO's (the pair's velocity vector is then (V_a, V_b), 12,
    else V_a, 6)."""

    r_a: Float[Array, "3 k"]
    r_b: Float[Array, "3 k"]
    u_b: Float[Array, "3 k"]
    w_b: Float[Array, " 3"]
    normal: Float[Array, "3 kn"]
    N: Float[Array, " k"]
    joint: bool = eqx.field(static=True, default=False)


def rows(patch: Patch, d: Float[Array, "3 k"]) -> Float[Array, "m k"]:
    """Each point's row of d_i . (relative velocity at the point) w.r.t. the pair's velocity vector:
    (d, r_a x d) for the DANO, (-d, -r_b x d) appended for a joint partner (m = 6 or 12)."""
    out = [d, jnp.cross(patch.r_a, d, axis=0)]
    if patch.joint:
        out += [-d, -jnp.cross(patch.r_b, d, axis=0)]
    return jnp.concatenate(out)


def tangents(n: Float[Array, "3 k"]) -> tuple[Array, Array]:
    """Two unit tangents (3, k) completing unit normals n (3, k) to orthonormal bases (Duff et al.,
    "Building an orthonormal basis, revisited", 2017: no branch, no division by ~0)."""
    sign = jnp.where(n[2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + n[2])
    b = n[0] * n[1] * a
    t1 = jnp.stack([1.0 + sign * n[0] * n[0] * a, sign * b, -sign * n[0]])
    t2 = jnp.stack([b, sign + n[1] * n[1] * a, -n[1]])
    return t1, t2


def _gram(G: Array, c: Array) -> Array:
    """sum_i c_i G_i G_i^T for rows G (m, k) and weights c (k,) (one matrix product)."""
    return (G * c[None]) @ G.T


def _law(coef, drag, a: Array, vs) -> tuple[Array, Array, Array]:
    """Value, gradient factor c and curvature factor e of coef rho(a) + drag |a|^2 / 2 with
    a (3, k) (or (k,) for a scalar): gradient c a, Hessian c I - e a a^T."""
    sq = jnp.sum(a * a, axis=0) if a.ndim == 2 else a * a
    s = jnp.sqrt(vs * vs + sq)
    value = coef * sq / (s + vs) + 0.5 * drag * sq
    return value, coef / s + drag, coef / (s * s * s)


def patch_terms(p: ContactParams, patch: Patch, V: Float[Array, " m"]):
    """D of one pair (module docstring) at the pair's velocity vector V (V_a, 6, or (V_a, V_b), 12,
    for a joint DANO partner), its gradient (m,) and Hessian (m, m), analytically and as a few
    matrix products over the points (the step's friction solve evaluates these many times)."""
    gain = p.coulomb_gain * (jnp.pi / 2)
    vs, ws = p.stiction_velocity, p.stiction_velocity / SPIN_LENGTH
    n, N = patch.normal, patch.N
    V_b = V[6:] if patch.joint else jnp.zeros(6, V.dtype)
    u = (V[:3, None] + jnp.cross(V[3:6, None], patch.r_a, axis=0)) - patch.u_b
    u = u - V_b[:3, None] - jnp.cross(V_b[3:, None], patch.r_b, axis=0)
    w = V[3:6] - V_b[3:] - patch.w_b
    u_t = u - jnp.sum(u * n, axis=0, keepdims=True) * n
    w_n = w @ n
    w_t = w[:, None] - w_n[None] * n
    slide, c_s, e_s = _law(gain * p.sliding_friction, p.sliding_drag, u_t, vs)
    twist, c_n, e_n = _law(gain * p.torsional_friction, p.torsional_drag, w_n, ws)
    roll, c_r, e_r = _law(gain * p.rolling_friction, p.rolling_drag, w_t, ws)
    Nn = jnp.broadcast_to(jnp.sum(N) if n.shape[1] == 1 else N, w_n.shape)  # weights of the spin terms
    value = jnp.sum(N * slide) + jnp.sum(Nn * (twist + roll))

    # Slip: the point's Hessian N c_s (t1 t1^T + t2 t2^T) - N e_s u_t u_t^T (t1, t2 a tangent
    # basis), through each point's rows, as one matrix product.
    t1, t2 = tangents(jnp.broadcast_to(n, u_t.shape))
    grad = rows(patch, u_t) @ (N * c_s)
    G = jnp.concatenate([rows(patch, t1), rows(patch, t2), rows(patch, u_t)], axis=1)
    H = _gram(G, jnp.concatenate([N * c_s, N * c_s, -N * e_s]))
    # Spin (twist about n, roll about the tangents): functions of the relative angular velocity.
    g_w = n @ (Nn * c_n * w_n) + w_t @ (Nn * c_r)
    H_w = (n * (Nn * (c_n - e_n * w_n * w_n))[None]) @ n.T
    H_w = H_w + jnp.sum(Nn * c_r) * jnp.eye(3) - (n * (Nn * c_r)[None]) @ n.T - (w_t * (Nn * e_r)[None]) @ w_t.T
    spin = jnp.zeros((V.shape[0], 3)).at[3:6].set(jnp.eye(3))
    if patch.joint:
        spin = spin.at[9:12].set(-jnp.eye(3))
    return value, grad + spin @ g_w, H + spin @ H_w @ spin.T
