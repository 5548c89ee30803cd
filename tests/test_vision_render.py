"""Volume rendering (`dano.vision.render`): quadrature against closed forms, and its gradients."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dano.vision.render import composite, ray_box, render_opacity, render_rgb, sample_distances

BOX = jnp.asarray([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


def _rays(n=5, seed=0):
    rng = np.random.default_rng(seed)
    origins = jnp.asarray(rng.normal(size=(n, 3)) * 0.2 + [0.0, 0.0, 3.0])
    targets = jnp.asarray(rng.uniform(-0.5, 0.5, size=(n, 3)))
    d = targets - origins
    return origins, d / jnp.linalg.norm(d, axis=-1, keepdims=True)


def test_ray_box_finds_the_slab_interval_and_empty_for_misses():
    origins = jnp.asarray([[0.0, 0.0, 3.0], [0.5, 0.0, 3.0], [5.0, 0.0, 3.0], [0.0, 0.0, 0.0]])
    directions = jnp.asarray([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    near, far = ray_box(origins, directions, BOX)
    np.testing.assert_allclose(near, [2.0, 2.0, float(near[2]), 0.0])
    np.testing.assert_allclose(far, [4.0, 4.0, float(near[2]), 1.0])  # a miss is empty; inside starts at 0


def test_uniform_density_gives_beer_lambert_and_weights_sum_to_opacity():
    origins, directions = _rays()
    near, far = ray_box(origins, directions, BOX)
    sigma = 0.7
    opacity = render_opacity(lambda x: jnp.full(x.shape[0], sigma), origins, directions, near, far, 32)
    np.testing.assert_allclose(opacity, 1 - np.exp(-sigma * (far - near)), rtol=1e-12)
    t, delta = sample_distances(near, far, 32, jax.random.key(0))
    assert bool(jnp.all((t >= near[:, None]) & (t <= far[:, None])))
    w = composite(jnp.full(t.shape, sigma), delta)
    np.testing.assert_allclose(jnp.sum(w, axis=-1), opacity, rtol=1e-12)


def test_colour_is_the_front_surface_over_the_background():
    # An opaque red slab z in [-1, 0] behind a transparent half: the ray from above sees red.
    def field(x):
        dense = jnp.where(x[:, 2] < 0.0, 1e4, 0.0)
        return dense, jnp.broadcast_to(jnp.asarray([1.0, 0.0, 0.0]), x.shape)

    origins = jnp.asarray([[0.0, 0.0, 3.0], [3.0, 3.0, 3.0]])
    directions = jnp.asarray([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]])
    near, far = ray_box(origins, directions, BOX)
    rgb, opacity = render_rgb(field, origins, directions, near, far, 64, jnp.asarray([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(rgb, [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], atol=1e-9)
    np.testing.assert_allclose(opacity, [1.0, 0.0], atol=1e-9)


def test_opacity_gradient_matches_central_differences():
    """d(opacity)/d(blob centre) and d/d(sigma scale): jax.grad against central differences."""
    origins, directions = _rays(4, seed=1)
    near, far = ray_box(origins, directions, BOX)

    def total(params):
        centre, scale = params[:3], params[3]
        fn = lambda x: scale * jnp.exp(-jnp.sum((x - centre[None, :]) ** 2, axis=-1) / 0.18)  # noqa: E731
        return jnp.sum(render_opacity(fn, origins, directions, near, far, 48) ** 2)

    p = jnp.asarray([0.1, -0.2, 0.05, 1.3])
    g = jax.grad(total)(p)
    h = 1e-6
    fd = np.array([(total(p.at[i].add(h)) - total(p.at[i].add(-h))) / (2 * h) for i in range(4)])
    np.testing.assert_allclose(g, fd, rtol=1e-6, atol=1e-9)
    assert np.all(np.abs(fd) > 1e-4)


@pytest.mark.parametrize("n", [2, 7])
def test_bins_tile_the_interval(n):
    near, far = jnp.asarray([0.5, 1.0]), jnp.asarray([2.5, 1.0])
    t, delta = sample_distances(near, far, n)
    np.testing.assert_allclose(jnp.sum(delta, axis=-1), far - near)
    np.testing.assert_allclose(t[:, 0], near + 0.5 * (far - near) / n)
