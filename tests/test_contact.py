import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dano
from dano.contact import (
    Box,
    Capsule,
    ContactParams,
    HalfSpace,
    Sphere,
    contact_wrench,
    coulomb_direction,
    expected_overlap,
    signed_distance,
)
from dano.fields import BoxField
from dano.math import quat_to_mat
from helpers import partial_differences

UP = jnp.asarray([0.0, 0.0, 1.0])
ORIGIN = jnp.zeros(3)


@pytest.fixture(scope="module")
def cube():
    return dano.build_dano(BoxField([0.1, 0.1, 0.1], width=0.002), n_points=3000, mass=1.0, log2_samples=13)


def _world(d, z, rotation=None):
    R = jnp.eye(3) if rotation is None else rotation
    return R @ d.body_points.T + jnp.asarray([0.0, 0.0, z])[:, None]


def test_hard_overlap_is_the_weighted_sum_of_points_below(cube):
    pts = _world(cube, 0.0495)
    o = expected_overlap(HalfSpace(UP, ORIGIN), pts, cube.weights, delta=0.0)
    below = np.asarray(pts[2]) <= 0
    w = np.asarray(cube.weights)
    assert float(o.psi) == pytest.approx(w[below].sum(), rel=1e-12)
    np.testing.assert_allclose(o.chi, (np.asarray(pts)[:, below] @ w[below]) / w[below].sum(), rtol=1e-12)
    np.testing.assert_allclose(o.normal, UP)
    far = expected_overlap(HalfSpace(UP, ORIGIN), _world(cube, 0.2), cube.weights)
    assert float(far.psi) == 0.0 and np.all(np.isfinite(far.chi))


def test_signed_distances_of_primitives():
    y = jnp.asarray([[0.3, 0.0, 0.0], [0.0, 0.0, 0.5], [0.05, 0.02, -0.01]]).T
    np.testing.assert_allclose(signed_distance(Sphere(ORIGIN, jnp.asarray(0.1)), y), [0.2, 0.4, np.sqrt(0.003) - 0.1])
    cap = Capsule(jnp.asarray([0.0, 0, -0.2]), jnp.asarray([0.0, 0, 0.2]), jnp.asarray(0.05))
    np.testing.assert_allclose(signed_distance(cap, y), [0.25, 0.25, np.sqrt(0.0029) - 0.05])
    R = quat_to_mat(jnp.asarray([np.cos(np.pi / 8), 0, 0, np.sin(np.pi / 8)]))  # 45 deg about z
    box = Box(ORIGIN, R, jnp.asarray([0.1, 0.1, 0.1]))
    np.testing.assert_allclose(signed_distance(box, y)[:2], [0.3 - 0.1 * np.sqrt(2), 0.4], rtol=1e-12)


@pytest.mark.parametrize(
    "shape",
    [
        Sphere(jnp.asarray([0.0, 0.0, -0.2]), jnp.asarray(0.2)),
        Capsule(jnp.asarray([-0.3, 0.0, -0.1]), jnp.asarray([0.3, 0.0, -0.1]), jnp.asarray(0.1)),
        Box(jnp.asarray([0.0, 0.0, -0.1]), jnp.eye(3), jnp.asarray([0.3, 0.3, 0.1])),
    ],
    ids=["sphere", "capsule", "box"],
)
def test_primitive_below_pushes_up(cube, shape):
    o = expected_overlap(shape, _world(cube, 0.0495), cube.weights)
    assert float(o.psi) > 0
    assert float(o.normal[2]) > 0.99  # from the primitive towards the DANO


def test_resting_wrench_balances_gravity(cube):
    # At rest psi k = m g: the spring holds the weight; the force is vertical with no torque about
    # the centre of mass beyond the offset of chi.
    p = ContactParams()
    o = expected_overlap(HalfSpace(UP, ORIGIN), _world(cube, 0.0495), cube.weights)
    z3 = jnp.zeros(3)
    w = contact_wrench(
        p, o.psi[None], o.chi[:, None], o.normal[:, None], jnp.asarray([0, 0, 0.0495]), z3, z3, z3, z3, z3
    )
    np.testing.assert_allclose(w.force, [0, 0, float(o.psi) * 3e4], rtol=1e-12)
    np.testing.assert_allclose(w.torque, jnp.cross(o.chi - jnp.asarray([0, 0, 0.0495]), w.force), atol=1e-12)


def test_sliding_friction_opposes_slip_and_saturates():
    p = ContactParams(sliding_friction=jnp.asarray(0.4))
    psi, z3 = jnp.asarray(0.01), jnp.zeros(3)
    for speed in (0.01, 1.0, 100.0):
        v = jnp.asarray([speed, 0, 0])
        w = contact_wrench(p, psi[None], z3[:, None], UP[:, None], jnp.asarray([0, 0, 0.01]), v, z3, z3, z3, z3)
        normal = float(w.force[2])
        assert float(w.force[0]) < 0 and float(w.force[1]) == 0
        ratio = -float(w.force[0]) / normal
        expected = 0.4 * (2 / np.pi) * np.arctan(30 * speed) * speed / (1e-3 + speed)
        assert ratio == pytest.approx(expected, rel=1e-12)
    assert ratio == pytest.approx(0.4, rel=1e-3)
    np.testing.assert_allclose(coulomb_direction(z3, 30.0, 1e-3), z3)


def test_wrench_gradients_match_finite_differences(cube):
    """Pose, velocity and parameter gradients of the whole overlap -> wrench map (float64)."""
    R = quat_to_mat(jnp.asarray([0.98, 0.1, -0.15, 0.05]))
    ground = HalfSpace(UP, ORIGIN)

    def force(z, mu, vx, k):
        p = ContactParams(sliding_friction=mu, impact_spring=k, indicator_width=jnp.asarray(2e-3))
        pts = _world(cube, z, R)
        o = expected_overlap(ground, pts, cube.weights, p.indicator_width)
        com = jnp.stack([0.0, 0.0, z])
        v, w3 = jnp.stack([vx, 0.0, -0.01]), jnp.asarray([0.0, 0.3, 0.0])
        z3 = jnp.zeros(3)
        w = contact_wrench(p, o.psi[None], o.chi[:, None], o.normal[:, None], com, v, w3, z3, z3, z3)
        return jnp.sum(w.force * jnp.asarray([0.3, -0.2, 1.0])) + jnp.sum(w.torque)

    x0 = (0.052, 0.5, 0.2, 3e4)
    grads = jax.grad(force, argnums=(0, 1, 2, 3))(*x0)
    for i, (g, fd) in enumerate(zip(grads, partial_differences(force, x0, rel_step=1e-6), strict=True)):
        assert float(g) == pytest.approx(float(fd), rel=1e-5, abs=1e-8 * abs(float(fd)) + 1e-9), i
        assert float(g) != 0.0
