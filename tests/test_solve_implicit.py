"""The implicit step's solver (`dano.sim.implicit`): Newton with its line search, and the
derivatives of the exact minimiser (`solve_implicit`) against closed forms and central differences."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dano.sim.newton import minimize_convex, newton, run_if, solve_implicit
from helpers import partial_differences

INDEX = np.array([2, 0, 1, 2])


def _objective(theta):
    """A smooth, strongly convex function of x (3,) with a kink-like term (Coulomb friction's
    sqrt(v_s^2 + x^2)) that Newton's full step overshoots, built from closed-over floats
    (theta) and integers (an index array), as the implicit step's objectives are."""
    index = jnp.asarray(INDEX)
    A = jnp.eye(3) * (1.0 + theta[0]) + 0.3 * jnp.outer(theta[1:4], theta[1:4])
    b = theta[1:4][index][:3] * theta[4]
    vs = 1e-4

    def f(x):
        r = jnp.sqrt(vs * vs + x * x)
        value = 0.5 * x @ A @ x - b @ x + theta[5] * jnp.sum(r - vs)
        grad = A @ x - b + theta[5] * x / r
        hess = A + theta[5] * jnp.diag(vs * vs / r**3)
        return value, grad, hess

    return f


THETA = (0.5, 0.4, -0.7, 0.2, 1.3, 0.6)


def _solve(theta):
    return minimize_convex(_objective(theta), jnp.zeros(3), 1e-28)


def test_newton_finds_the_minimiser_across_a_near_kink():
    """Newton ends where its own step vanishes, two of the coordinates inside the 1e-4-wide kink
    (where the curvature is 1e4 times the rest's) and one outside."""
    f = _objective(jnp.asarray(THETA))
    x = jax.jit(lambda: newton(f, jnp.array([1.0, -1.0, 0.5]), 1e-28))()
    _, g, H = f(x)
    assert np.max(np.abs(np.linalg.solve(np.asarray(H), np.asarray(g)))) < 1e-9
    assert sorted(np.abs(np.asarray(x)) < 1e-3) == [False, True, True]


@pytest.mark.parametrize("mode", ["jacfwd", "jacrev", "vmap_grad"])
def test_derivatives_of_the_minimiser_match_central_differences(mode):
    theta = jnp.asarray(THETA)
    fd = np.stack(partial_differences(lambda *t: np.asarray(jax.jit(_solve)(jnp.asarray(t))), THETA, 1e-6), 1)
    if mode == "jacfwd":
        J = jax.jit(jax.jacfwd(_solve))(theta)
    elif mode == "jacrev":
        J = jax.jit(jax.jacrev(_solve))(theta)
    else:  # one row per output, each a gradient, batched
        J = jax.jit(jax.vmap(lambda e: jax.grad(lambda t: e @ _solve(t))(theta)))(jnp.eye(3))
    np.testing.assert_allclose(np.asarray(J), fd, rtol=1e-6, atol=1e-9)
    assert np.all(np.abs(fd).max(axis=0) > 1e-3)  # every parameter moves the minimiser


def test_a_forward_solve_with_a_switch_differentiates_the_objective_it_chose():
    """`forward` may choose between objectives (the active sets or all points) and say which in
    `aux`; the derivatives are those of the chosen one's minimiser, and aux has none."""
    theta = jnp.asarray(THETA)

    def solve(theta, switch):
        f, g = _objective(theta), _objective(2.0 * theta)

        def forward(x0):
            x = newton(f, x0, 1e-28)
            on = jnp.asarray(switch)
            return run_if(on, lambda x: newton(g, x, 1e-28), x), on

        return solve_implicit(forward, lambda x, s: jax.lax.cond(s, g, f, x), jnp.zeros(3))[0]

    for switch, scale in ((False, 1.0), (True, 2.0)):
        J = np.asarray(jax.jit(jax.jacfwd(solve), static_argnums=1)(theta, switch))
        expected = np.asarray(jax.jacfwd(_solve)(scale * theta)) * scale
        np.testing.assert_allclose(J, expected, rtol=1e-8, atol=1e-12)
