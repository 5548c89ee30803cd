"""Quaternion helpers of dano.math against scipy, and their gradients (at the identity too)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dano.math import quat_conj, quat_exp, quat_log, quat_mul, quat_to_mat
from helpers import partial_differences, rel_err

_conj = jax.vmap(quat_conj)  # quat_conj itself refuses a batch under strict rank promotion (see below)


def _wxyz(rot: Rotation) -> np.ndarray:
    return np.asarray(rot.as_quat())[..., [3, 0, 1, 2]]


def _scipy(q) -> Rotation:
    return Rotation.from_quat(np.asarray(q)[..., [1, 2, 3, 0]])


def _rotvecs(n: int, seed: int, max_angle: float = 3.0) -> np.ndarray:
    """Random rotation vectors with uniform directions and angles in [0, max_angle] (< π)."""
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    return axis * rng.uniform(0.0, max_angle, size=(n, 1))


def test_log_and_exp_are_inverse():
    r = _rotvecs(200, seed=0)
    q = quat_exp(r)
    np.testing.assert_allclose(jnp.linalg.norm(q, axis=-1), 1.0, rtol=1e-14)
    np.testing.assert_allclose(quat_log(q), r, rtol=0, atol=1e-12)
    np.testing.assert_allclose(q, _wxyz(Rotation.from_rotvec(r)) * np.sign(_wxyz(Rotation.from_rotvec(r))[:, :1]))
    # and the other way round, from random quaternions of any norm
    qs = _wxyz(Rotation.random(200, random_state=1)) * np.random.default_rng(2).uniform(0.2, 5.0, size=(200, 1))  # pyright: ignore[reportCallIssue]
    back = quat_exp(quat_log(qs))
    unit = qs / np.linalg.norm(qs, axis=1, keepdims=True)
    np.testing.assert_allclose(np.abs(np.sum(np.asarray(back) * unit, axis=1)), 1.0, rtol=1e-13)
    np.testing.assert_allclose(quat_log(qs), Rotation.from_quat(qs[:, [1, 2, 3, 0]]).as_rotvec(), atol=1e-12)


@pytest.mark.parametrize("angle", [0.0, 1e-9, 5e-7, 9.99e-7, 1.001e-6, 2e-6, 1e-3, 1.0, 3.1])
def test_log_and_exp_near_the_series_switch(angle):
    """Both sides of the s < 1e-6 / angle < 1e-6 switch to Taylor series agree with scipy."""
    r = np.array([0.48, -0.6, 0.64]) * angle
    q = quat_exp(r)
    np.testing.assert_allclose(q, _wxyz(Rotation.from_rotvec(r)), rtol=0, atol=1e-15)
    np.testing.assert_allclose(quat_log(q), r, rtol=1e-12, atol=1e-20)


def test_log_angle_is_the_geodesic_distance():
    a = _wxyz(Rotation.random(100, random_state=3))  # pyright: ignore[reportCallIssue]
    b = _wxyz(Rotation.random(100, random_state=4))  # pyright: ignore[reportCallIssue]
    rel = quat_mul(_conj(a), b)
    angle = np.linalg.norm(quat_log(rel), axis=-1)
    expected = (_scipy(a).inv() * _scipy(b)).magnitude()
    np.testing.assert_allclose(angle, expected, rtol=0, atol=1e-12)
    assert np.all(angle <= np.pi + 1e-12)
    np.testing.assert_allclose(quat_log(quat_mul(_conj(a), a)), 0.0, atol=1e-15)


def test_log_of_minus_q_is_log_of_q():
    q = _wxyz(Rotation.random(100, random_state=5)) * np.random.default_rng(6).uniform(0.5, 2.0, size=(100, 1))  # pyright: ignore[reportCallIssue]
    np.testing.assert_allclose(quat_log(-q), quat_log(q), rtol=0, atol=1e-14)
    assert np.any(q[:, 0] < 0) and np.any(q[:, 0] > 0)  # both signs of w were exercised
    np.testing.assert_array_equal(quat_log(jnp.array([-1.0, 0.0, 0.0, 0.0])), jnp.zeros(3))


def test_quat_mul_matches_scipy_composition():
    p = _wxyz(Rotation.random(50, random_state=7))  # pyright: ignore[reportCallIssue]
    q = _wxyz(Rotation.random(50, random_state=8))  # pyright: ignore[reportCallIssue]
    pq = np.asarray(quat_mul(p, q))
    expected = _wxyz(_scipy(p) * _scipy(q))  # scipy's p * q: apply q, then p
    np.testing.assert_allclose(pq * np.sign(np.sum(pq * expected, axis=1, keepdims=True)), expected, atol=1e-14)
    assert np.min(np.abs(np.sum(pq * expected, axis=1))) == pytest.approx(1.0, rel=1e-14)
    qp = np.asarray(quat_mul(q, p))
    assert np.all(np.abs(np.sum(qp * expected, axis=1)) < 1 - 1e-6)  # the order matters: the test sees it
    np.testing.assert_allclose(quat_to_mat(pq), quat_to_mat(p) @ quat_to_mat(q), atol=1e-14)
    np.testing.assert_allclose(quat_to_mat(p), _scipy(p).as_matrix(), atol=1e-14)
    np.testing.assert_allclose(quat_mul(p, _conj(p)), np.tile([1.0, 0.0, 0.0, 0.0], (50, 1)), atol=1e-15)


def test_quat_conj_of_one_quaternion():
    np.testing.assert_array_equal(quat_conj(jnp.array([0.5, 0.1, -0.2, 0.3])), jnp.array([0.5, -0.1, 0.2, -0.3]))


def test_quat_conj_of_a_batch():
    q = _wxyz(Rotation.random(5, random_state=9))  # pyright: ignore[reportCallIssue]
    np.testing.assert_array_equal(quat_conj(q), q * np.array([1.0, -1.0, -1.0, -1.0]))


def test_quat_mul_is_the_hamilton_product():
    i, j, k, one = (jnp.eye(4)[n] for n in (1, 2, 3, 0))
    np.testing.assert_array_equal(quat_mul(i, j), k)
    np.testing.assert_array_equal(quat_mul(j, k), i)
    np.testing.assert_array_equal(quat_mul(k, i), j)
    np.testing.assert_array_equal(quat_mul(j, i), -k)
    np.testing.assert_array_equal(quat_mul(i, i), -one)


def _linear_of_log(c):
    f = jax.jit(lambda q: jnp.dot(c, quat_log(q)))
    return lambda *q: float(f(jnp.array(q)))


@pytest.mark.parametrize(
    "q0",
    [
        (0.7, -0.2, 0.5, 0.4),  # generic, not unit
        (-0.3, 0.9, 0.1, -0.2),  # w < 0: the sign flip branch
        (1.0, 0.0, 0.0, 0.0),  # exactly the identity
        (2.5, 0.0, 0.0, 0.0),  # the identity, not unit
        (-1.0, 0.0, 0.0, 0.0),  # the identity as -1
    ],
)
def test_grad_of_log_matches_finite_differences(q0):
    c = jnp.array([0.3, -1.2, 0.8])
    f = _linear_of_log(c)
    grad = jax.jit(jax.grad(lambda q: jnp.dot(c, quat_log(q))))(jnp.array(q0))
    assert np.all(np.isfinite(grad))
    fd = np.array(partial_differences(f, q0, rel_step=1e-6))
    np.testing.assert_allclose(grad, fd, rtol=0, atol=1e-7 * max(1.0, float(np.abs(fd).max())))


def test_grad_of_log_at_the_identity_is_exact():
    """d log / d v = 2 I / |q| and d log / d w = 0 at q = (w, 0, 0, 0), w > 0."""
    jac = jax.jit(jax.jacrev(quat_log))(jnp.array([1.0, 0.0, 0.0, 0.0]))
    np.testing.assert_array_equal(jac, np.concatenate([np.zeros((3, 1)), 2.0 * np.eye(3)], axis=1))
    jac2 = jax.jit(jax.jacfwd(quat_log))(jnp.array([2.0, 0.0, 0.0, 0.0]))
    np.testing.assert_allclose(jac2, np.concatenate([np.zeros((3, 1)), np.eye(3)], axis=1), rtol=1e-15)


def test_grad_of_squared_geodesic_distance():
    """The loss |log(a⁻¹ ⊗ b)|² a fit uses: finite gradient, 0 at b = a, matches differences elsewhere."""
    a = jnp.asarray(_wxyz(Rotation.from_rotvec([0.3, -0.2, 1.0])))

    def loss(b):
        r = quat_log(quat_mul(quat_conj(a), b))
        return jnp.dot(r, r)

    grad = jax.jit(jax.grad(loss))
    np.testing.assert_allclose(grad(a), 0.0, atol=1e-15)
    assert np.all(np.isfinite(jax.jit(jax.hessian(loss))(a)))
    b0 = _wxyz(Rotation.from_rotvec([0.1, 0.5, -0.4]))
    jloss = jax.jit(loss)
    fd = np.array(partial_differences(lambda *b: float(jloss(jnp.array(b))), tuple(b0), rel_step=1e-6))
    assert rel_err(grad(jnp.asarray(b0)), fd) < 1e-7


def test_jacobian_of_exp_at_zero_is_exact():
    expected = np.concatenate([np.zeros((1, 3)), 0.5 * np.eye(3)], axis=0)
    for jacobian in (jax.jacfwd, jax.jacrev):
        jac = jax.jit(jacobian(quat_exp))(jnp.zeros(3))
        assert jac.shape == (4, 3) and np.all(np.isfinite(jac))
        np.testing.assert_array_equal(jac, expected)


def test_jacobian_of_exp_matches_finite_differences():
    r0 = (0.4, -0.9, 0.3)
    jac = jax.jit(jax.jacfwd(quat_exp))(jnp.array(r0))
    exp = jax.jit(quat_exp)
    fd = np.stack(partial_differences(lambda *r: np.asarray(exp(jnp.array(r))), r0, rel_step=1e-6), axis=1)
    np.testing.assert_allclose(jac, fd, rtol=0, atol=1e-9)
