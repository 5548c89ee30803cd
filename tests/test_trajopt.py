"""Constrained iLQR (augmented Lagrangian): the LQ solution, constraints, infeasibility, and the push task."""

import jax.numpy as jnp
import numpy as np
import pytest

import dano
from dano.cli import main
from dano.fields import BoxField
from dano.results import Result, SolverError
from dano.trajopt import (
    OptimalControlProblem,
    Options,
    PushTask,
    TrajoptError,
    push_problem,
    rollout,
    solve,
)
from helpers import central_difference

N, M, T = 4, 2, 20


@pytest.fixture(scope="module")
def lq():
    rng = np.random.default_rng(0)
    A = np.eye(N) + 0.1 * rng.normal(size=(N, N))
    B = rng.normal(size=(N, M))
    Q, R, QT = np.diag([1.0, 2.0, 0.5, 1.0]), 0.1 * np.eye(M), 10.0 * np.eye(N)
    Aj, Bj, Qj, Rj, QTj = map(jnp.asarray, (A, B, Q, R, QT))
    problem = OptimalControlProblem(
        dynamics=lambda x, u, t: Aj @ x + Bj @ u,
        cost=lambda x, u, t: 0.5 * x @ Qj @ x + 0.5 * u @ Rj @ u,
        terminal_cost=lambda x: 0.5 * x @ QTj @ x,
        horizon=T,
    )
    return problem, (A, B, Q, R, QT), jnp.asarray(rng.normal(size=N))


@pytest.fixture(scope="module")
def pendulum():
    """A pendulum (θ = 0 hanging) swung up towards θ = π in 3 s, its torque bounded below the
    weight's (4 vs 9.81 N m per unit inertia, so it must swing), the goal a terminal cost."""
    h, g, limit, goal = 0.05, 9.81, 4.0, jnp.asarray([jnp.pi, 0.0])

    def dynamics(x, u, t):
        w = x[1] + h * (u[0] - g * jnp.sin(x[0]))
        return jnp.stack([x[0] + h * w, w])

    problem = OptimalControlProblem(
        dynamics=dynamics,
        cost=lambda x, u, t: 1e-2 * u @ u,
        terminal_cost=lambda x: 100.0 * (x - goal) @ (x - goal),
        horizon=60,
        constraints=lambda x, u, t: jnp.concatenate([u - limit, -u - limit]),
    )
    return problem, jnp.zeros(2)


def riccati_controls(A, B, Q, R, QT, x0):
    """The finite-horizon discrete LQR by the textbook recursion (numpy, independent of the solver)."""
    P, gains = QT, []
    for _ in range(T):
        K = np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)
        gains.append(K)
        P = Q + A.T @ P @ (A - B @ K)
    x, us = np.asarray(x0), []
    for K in reversed(gains):
        us.append(-K @ x)
        x = A @ x + B @ us[-1]
    return np.array(us)


def test_ilqr_solves_linear_quadratic_problem_to_the_riccati_solution(lq):
    problem, matrices, x0 = lq
    sol = solve(problem, x0, jnp.zeros((T, M)))
    assert sol.converged, sol.message
    np.testing.assert_allclose(sol.controls, riccati_controls(*matrices, x0=x0), atol=1e-9)
    assert sol.iterations <= 3  # one Newton step, then the convergence check


def test_jacobians_compiled_ahead_are_the_dynamics_matrices(lq):
    """`compile_ahead` compiles the dynamics Jacobians in a thread once per dynamics and shapes;
    `jacobians_along` then gives A and B of the linear dynamics, on one lane or in chunks of frames
    on several (3 lanes: 7 + 7 + 6 frames, the last chunk padded). A compilation that fails there
    (a state of the wrong size) raises nowhere: the call that needs a program compiles its own."""
    from dano.trajopt import pieces as P

    problem, (A, B, *_), x0 = lq
    flow = problem.flow
    for n in (N, N, N + 1):
        P.compile_ahead(flow, n, M, None, 1)
    # one compilation per state size (the solves of other tests may have asked for other chunks)
    assert sorted(k[2] for k in P._AHEAD[problem.dynamics] if k[0] == T and k[3:] == (M, None)) == [N, N + 1]
    us = jnp.asarray(np.random.default_rng(2).normal(size=(T, M)))
    for lanes in (1, 3, T + 5):
        JA, JB = P.jacobians_along(flow, rollout(problem, x0, us), us, None, lanes)
        np.testing.assert_allclose(JA, np.broadcast_to(A, (T, N, N)), rtol=0, atol=1e-14)
        np.testing.assert_allclose(JB, np.broadcast_to(B, (T, N, M)), rtol=0, atol=1e-14)
    P._finish_compiling()  # the failing one has finished too


def test_the_same_solve_on_one_lane_and_on_several(pendulum):
    """The line search's step sizes tried several at a time and the Jacobians taken in chunks on
    parallel lanes give the solve one lane gives, iteration for iteration: a pendulum swung up
    under a torque bound, whose line searches back off (steps below 1 are taken)."""
    problem, x0 = pendulum
    one, three = (solve(problem, x0, jnp.full((problem.horizon, 1), 0.5), Options(lanes=k)) for k in (1, 3))
    assert one.converged, one.message
    assert one.states[-1, 0] > 2.9 and np.max(np.abs(one.controls)) <= 4.0 + 1e-4  # swung up, within the bound
    assert min(h[2] for h in one.history) < 1.0  # some searches tried more than one step size
    assert one.history == three.history
    np.testing.assert_array_equal(one.controls, three.controls)


def test_a_failed_search_raises_the_regularisation_until_the_step_shortens(lq):
    """After a failed line search the next Levenberg term is the first tenfold level whose
    feedforward step is at most 0.9 of the failed one's: the level below it leaves the step within
    a tenth, so a search along it would repeat the failure. Checked against the Riccati pass itself
    on the LQ problem, from 1e-9 (far below its Q_uu, ~0.1 to 10) and from a level that already
    shortens it."""
    from dano.trajopt.ilqr import _shorter
    from dano.trajopt.pieces import backward, expand, jacobians, pieces

    problem, _, x0 = lq
    fn = pieces(problem, N, M)
    us = jnp.zeros((T, M))
    xs = rollout(problem, x0, us)
    expansion = (
        *fn.flow.call(jacobians, xs[:-1], us, jnp.arange(T), None),
        *fn.call(expand, xs, us, jnp.zeros((T, 0)), jnp.zeros(0), 10.0),
    )

    def size(reg):
        k, _, _, failed = fn.call(backward, *expansion, reg)
        assert not bool(failed)
        return float(jnp.max(jnp.abs(k)))

    reg = _shorter(fn, expansion, 1e-9, size(1e-9), 1e8)
    assert reg > 1e-8  # levels that changed nothing were passed over
    assert size(reg) <= 0.9 * size(1e-9) < size(reg / 10)
    assert _shorter(fn, expansion, 10.0, size(10.0), 1e8) == pytest.approx(100.0)  # tenfold was enough
    assert size(100.0) <= 0.9 * size(10.0)
    assert _shorter(fn, expansion, 1e8, size(1e8), 1e8) > 1e8  # past the limit: the solve stalls


@pytest.mark.parametrize("batch", [1, 3])
def test_jacobians_taken_in_time_batches_give_the_same_solution(lq, batch):
    problem, matrices, x0 = lq
    sol = solve(problem, x0, jnp.zeros((T, M)), Options(jacobian_batch=batch))
    assert sol.converged, sol.message
    np.testing.assert_allclose(sol.controls, riccati_controls(*matrices, x0=x0), atol=1e-9)


def test_input_bounds_and_goal_constraint_hold_at_the_solution(lq):
    problem, _, x0 = lq
    bounded = OptimalControlProblem(
        problem.dynamics, problem.cost, problem.terminal_cost, T,
        constraints=lambda x, u, t: jnp.concatenate([u - 0.3, -u - 0.3]),
        terminal_constraints=lambda x: x[:2],
    )  # fmt: skip
    sol = solve(bounded, x0, jnp.zeros((T, M)))
    assert sol.converged, sol.message
    assert sol.max_violation <= 1e-4
    assert np.max(np.abs(sol.controls)) <= 0.3 + 1e-4
    assert np.max(np.abs(sol.states[-1, :2])) <= 1e-4
    assert np.max(np.abs(sol.controls)) > 0.29  # the bound is active: the unconstrained optimum exceeds it
    np.testing.assert_allclose(np.asarray(rollout(bounded, x0, jnp.asarray(sol.controls))), sol.states, atol=1e-12)


def test_infeasible_goal_is_reported_not_raised(lq):
    problem, _, x0 = lq
    impossible = OptimalControlProblem(
        problem.dynamics, problem.cost, problem.terminal_cost, T,
        constraints=lambda x, u, t: jnp.concatenate([u - 1e-3, -u - 1e-3]),
        terminal_constraints=lambda x: x[:2] - 100.0,
    )  # fmt: skip
    sol = solve(impossible, x0, jnp.zeros((T, M)), Options(max_iterations=60))
    assert not sol.converged
    assert sol.message.startswith("did not converge")
    assert sol.max_violation > 1.0
    assert np.all(np.isfinite(sol.states)) and np.all(np.isfinite(sol.controls))
    assert sol.result is not Result.successful
    with pytest.raises(SolverError, match=r"^iLQR did not converge: .*constraint violation"):
        solve(impossible, x0, jnp.zeros((T, M)), Options(max_iterations=60), throw=True)


def test_wrong_control_shape_is_a_named_error(lq):
    problem, _, x0 = lq
    with pytest.raises(TrajoptError, match="horizon"):
        solve(problem, x0, jnp.zeros((T + 1, M)))


@pytest.fixture(scope="module")
def cube():
    return dano.build_dano(BoxField(size=(0.06, 0.06, 0.06)), mass=0.3, n_points=150, seed=0)


def test_push_dynamics_jacobian_matches_central_differences(cube):
    """The solver's own frame Jacobians (`jacobians_along`, compiled ahead while the push was set
    up), chained over the horizon, against central differences of the rolled-out final position."""
    from dano.trajopt.pieces import jacobians_along
    from dano.trajopt.push import default_options

    push = push_problem(cube, "sphere", PushTask(goal=(0.05, 0.0), horizon=4))
    x0, us = jnp.asarray(push.x0), jnp.asarray(push.initial_controls)
    a = push.sim.world.dano_qpos[0]

    def final(u):
        return rollout(push.problem, x0, u)[-1, a : a + 2]

    direction = jnp.asarray(np.random.default_rng(1).normal(size=us.shape))
    xs = rollout(push.problem, x0, us)
    A, B = jacobians_along(push.problem.flow, xs, us, default_options("sphere").jacobian_batch)
    dx = jnp.zeros(x0.shape[0])
    for t in range(us.shape[0]):  # the linearised rollout
        dx = A[t] @ dx + B[t] @ direction[t]
    exact = dx[a : a + 2]
    assert float(jnp.linalg.norm(exact)) > 1e-4  # the warm start is in contact: controls move the cube
    numeric = central_difference(lambda s: final(us + s * direction), 0.0, 1e-4)
    np.testing.assert_allclose(exact, numeric, rtol=1e-4, atol=1e-9)


# The sphere pushing a 100-point bunny 8 cm to its goal (converged, < 1 cm, violation <= 1e-4, exact
# replay) is `dano demo`'s push: tests/test_demo.py asserts it, rather than solving it twice.


def test_cli_refuses_a_goal_at_the_start(capsys, tmp_path, cube):
    from dano.io import save_dano

    save_dano(tmp_path / "cube.dano.npz", cube)
    code = main(["trajopt", "push", "--dano", str(tmp_path / "cube.dano.npz"), "--goal", "0", "0", "--json"])
    assert code == 2
    assert "TrajoptError" in capsys.readouterr().err
