"""Volume rendering of a density field along rays (the paper's reference [2], NeRF's quadrature).

A ray x(t) = o + t d crosses the field's box between `near` and `far`; `n_samples` points split that
interval into equal bins (jittered uniformly inside each bin while training, so the whole interval
is seen). With optical density sigma_i and bin length delta_i, the bin's opacity is
a_i = 1 - exp(-sigma_i delta_i), the light reaching it T_i = prod_{j<i} (1 - a_j), and its weight
w_i = T_i a_i. The pixel's accumulated opacity is sum_i w_i = 1 - T_end: the "transmittance image"
the paper's tracker matches to object masks. Colour is sum_i w_i c_i plus (1 - opacity) times the
background.

Everything is a pure function of arrays, so `jax.grad` reaches the field's parameters (fitting) and
the object's pose (tracking) alike.
"""

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PRNGKeyArray


def ray_box(
    origins: Float[Array, "r 3"], directions: Float[Array, "r 3"], bounds: Float[Array, "2 3"]
) -> tuple[Float[Array, " r"], Float[Array, " r"]]:
    """Entry and exit distances of rays through an axis-aligned box (slab method).

    Rays that miss get near = far (an empty interval, so they render as background). Distances are
    clipped at 0: a ray starting inside the box enters at its origin.
    """
    safe = jnp.where(jnp.abs(directions) < 1e-12, 1e-12, directions)
    t0 = (bounds[0][None, :] - origins) / safe
    t1 = (bounds[1][None, :] - origins) / safe
    near = jnp.maximum(jnp.max(jnp.minimum(t0, t1), axis=-1), 0.0)
    far = jnp.min(jnp.maximum(t0, t1), axis=-1)
    return near, jnp.maximum(far, near)


def sample_distances(
    near: Float[Array, " r"], far: Float[Array, " r"], n_samples: int, key: PRNGKeyArray | None = None
) -> tuple[Float[Array, "r s"], Float[Array, "r s"]]:
    """Sample distances along each ray (bin midpoints, or uniformly jittered in their bins with a key)
    and the bins' lengths."""
    edges = jnp.linspace(0.0, 1.0, n_samples + 1, dtype=near.dtype)
    if key is None:
        u = jnp.broadcast_to(0.5 * (edges[:-1] + edges[1:])[None, :], (near.shape[0], n_samples))
    else:
        u = edges[None, :-1] + jax.random.uniform(key, (near.shape[0], n_samples), dtype=near.dtype) / n_samples
    span = (far - near)[:, None]
    return near[:, None] + span * u, jnp.broadcast_to(span / n_samples, (near.shape[0], n_samples))


def _sample_points(origins, directions, near, far, n_samples: int, key):
    """The sample points (r * s, 3) of every ray, flattened, and their bins' lengths (r, s)."""
    t, delta = sample_distances(near, far, n_samples, key)
    return (origins[:, None, :] + t[..., None] * directions[:, None, :]).reshape(-1, 3), delta


def composite(sigma: Float[Array, "r s"], delta: Float[Array, "r s"]) -> Float[Array, "r s"]:
    """The samples' weights w_i = T_i (1 - exp(-sigma_i delta_i)) (their sum is the opacity)."""
    tau = sigma * delta
    before = jnp.concatenate([jnp.zeros_like(tau[:, :1]), jnp.cumsum(tau[:, :-1], axis=-1)], axis=-1)
    return jnp.exp(-before) * -jnp.expm1(-tau)


def render_opacity(
    sigma_fn,
    origins: Float[Array, "r 3"],
    directions: Float[Array, "r 3"],
    near: Float[Array, " r"],
    far: Float[Array, " r"],
    n_samples: int,
    key: PRNGKeyArray | None = None,
) -> Float[Array, " r"]:
    """Accumulated opacity of each ray: 1 - exp(-integral of sigma), by `n_samples` bins.

    `sigma_fn` maps world points (n, 3) to optical densities (n,) (1/m).
    """
    x, delta = _sample_points(origins, directions, near, far, n_samples, key)
    sigma = sigma_fn(x).reshape(delta.shape)
    return -jnp.expm1(-jnp.sum(sigma * delta, axis=-1))


def render_peak(
    fn,
    origins: Float[Array, "r 3"],
    directions: Float[Array, "r 3"],
    near: Float[Array, " r"],
    far: Float[Array, " r"],
    n_samples: int,
) -> Float[Array, " r"]:
    """The largest value of `fn` (world points (n, 3) -> (n,)) at each ray's `n_samples` bin midpoints.

    The hard-surface limit of accumulated opacity: a ray is opaque where it meets the object at all,
    i.e. where the largest occupancy along it is above one half.

    The derivative of a maximum is the derivative of its largest term, so the samples are searched
    without derivatives and `fn` is differentiated at each ray's largest sample only (the same value
    and derivative as `max` over all of them; under `jvp`/`grad` one tangent evaluation per ray
    instead of `n_samples`).
    """
    t, _ = sample_distances(near, far, n_samples)
    x = origins[:, None, :] + t[..., None] * directions[:, None, :]
    values = fn(jax.lax.stop_gradient(x).reshape(-1, 3)).reshape(t.shape)
    best = jnp.argmax(jax.lax.stop_gradient(values), axis=-1)
    return fn(jnp.take_along_axis(x, best[:, None, None], axis=1)[:, 0, :])


def render_rgb(
    sigma_colour_fn,
    origins: Float[Array, "r 3"],
    directions: Float[Array, "r 3"],
    near: Float[Array, " r"],
    far: Float[Array, " r"],
    n_samples: int,
    background: Float[Array, " 3"],
    key: PRNGKeyArray | None = None,
) -> tuple[Float[Array, "r 3"], Float[Array, " r"]]:
    """Colour (composited over `background`) and accumulated opacity of each ray.

    `sigma_colour_fn` maps world points (n, 3) to (optical densities (n,) in 1/m, colours (n, 3)).
    """
    x, delta = _sample_points(origins, directions, near, far, n_samples, key)
    sigma, colour = sigma_colour_fn(x)
    w = composite(sigma.reshape(delta.shape), delta)
    opacity = jnp.sum(w, axis=-1)
    rgb = jnp.sum(w[..., None] * colour.reshape(*delta.shape, 3), axis=1)
    rgb = rgb + (1.0 - opacity)[:, None] * background[None, :]
    return rgb, opacity
