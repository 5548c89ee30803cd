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
