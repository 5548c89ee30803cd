"""Small grad-safe helpers shared by fields, mass properties and contact.

Every function here is pure and written for arrays of any batch shape.
"""

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float


def safe_norm(x: Float[ArrayLike, "... d"], axis: int = -1) -> Float[Array, "..."]:
    """Euclidean norm whose gradient is 0 (not NaN) at x = 0.

    The double-`where` keeps the NaN of d/dx sqrt(0) out of the backward pass.
    """
    x = jnp.asarray(x)
    sq = jnp.sum(x * x, axis=axis)
    positive = sq > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, sq, 1.0)), 0.0)


def normalize(x: Float[ArrayLike, "... d"], axis: int = -1) -> Float[Array, "... d"]:
    """x / |x|, and 0 where x = 0 (grad-safe)."""
    x = jnp.asarray(x)
    n = safe_norm(x, axis=axis)
    return x / jnp.expand_dims(jnp.where(n > 0, n, 1.0), axis)


def smootherstep(t: Float[ArrayLike, "..."]) -> Float[Array, "..."]:
    """Perlin's C2 step: 0 for t <= -1, 1 for t >= 1, 6u^5 - 15u^4 + 10u^3 between, u = (t+1)/2.

    It is odd about its midpoint, S(t) + S(-t) = 1, so the 1/2 level of a field built from it lies
    exactly on the zero of the signed distance.
    """
    u = jnp.clip((jnp.asarray(t) + 1.0) / 2.0, 0.0, 1.0)
    return u * u * u * (u * (6.0 * u - 15.0) + 10.0)


def cross_matrix(r: Float[ArrayLike, "... 3"]) -> Float[Array, "... 3 3"]:
    """[r]x, the matrix with [r]x a = r x a, for vectors of any batch shape."""
    r = jnp.asarray(r)
    z = jnp.zeros_like(r[..., 0])
    x, y, w = r[..., 0], r[..., 1], r[..., 2]
    rows = [jnp.stack([z, -w, y], -1), jnp.stack([w, z, -x], -1), jnp.stack([-y, x, z], -1)]
    return jnp.stack(rows, -2)


def quat_to_mat(q: Float[ArrayLike, "... 4"]) -> Float[Array, "... 3 3"]:
    """Rotation matrix of a quaternion (w, x, y, z); q need not be unit (it is normalised)."""
    q = normalize(q)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


def quat_mul(p: Float[ArrayLike, "... 4"], q: Float[ArrayLike, "... 4"]) -> Float[Array, "... 4"]:
    """Hamilton product p ⊗ q of quaternions (w, x, y, z): rotate by q, then by p."""
    p, q = jnp.asarray(p), jnp.asarray(q)
    pw, pv = p[..., :1], p[..., 1:]
    qw, qv = q[..., :1], q[..., 1:]
    w = pw * qw - jnp.sum(pv * qv, axis=-1, keepdims=True)
    v = pw * qv + qw * pv + jnp.cross(pv, qv)
    return jnp.concatenate([w, v], axis=-1)


def quat_conj(q: Float[ArrayLike, "... 4"]) -> Float[Array, "... 4"]:
    """The inverse rotation of a unit quaternion (w, -x, -y, -z)."""
    q = jnp.asarray(q)
    return jnp.concatenate([q[..., :1], -q[..., 1:]], axis=-1)


def quat_log(q: Float[ArrayLike, "... 4"]) -> Float[Array, "... 3"]:
    """Rotation vector (axis × angle, rad, angle in [0, π]) of a quaternion (w, x, y, z), any norm.

    q and -q give the same vector (the shorter way round). |quat_log(conj(a) ⊗ b)| is the geodesic
    distance between rotations a and b. Grad-safe at the identity, where it is 2 v / w.
    """
    q = normalize(q)
    q = jnp.where(q[..., :1] < 0, -q, q)
    w, v = q[..., 0], q[..., 1:]
    s = safe_norm(v)
    small = s < 1e-6
    # 2 atan2(s, w) / s, and its Taylor series 2/w (1 - s²/(3 w²)) near s = 0
    series = 2.0 / w * (1.0 - s * s / (3.0 * w * w))
    ratio = jnp.where(small, series, 2.0 * jnp.arctan2(s, w) / jnp.where(small, 1.0, s))
    return v * ratio[..., None]


def quat_exp(r: Float[ArrayLike, "... 3"]) -> Float[Array, "... 4"]:
    """Unit quaternion of a rotation vector r (axis × angle, rad); inverse of `quat_log`. Grad-safe at 0."""
    r = jnp.asarray(r)
    angle = safe_norm(r)
    small = angle < 1e-6
    half = 0.5 * angle
    # sin(θ/2)/θ, and its Taylor series 1/2 - θ²/48 near 0
    sinc = jnp.where(small, 0.5 - angle * angle / 48.0, jnp.sin(half) / jnp.where(small, 1.0, angle))
    return jnp.concatenate([jnp.cos(half)[..., None], r * sinc[..., None]], axis=-1)
