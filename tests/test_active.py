"""The active set (`dano.contact.active`): the implicit step over K points per pair equals the step
over all of them, in value and derivative, with and without overflow, under jit, vmap and grad."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dano
import dano.math
from dano.contact import active
from dano.fields import BoxField
from dano.sim import DanoBody, Primitive, Scene
from dano.sim.run import Simulation
from dano.sim.step import rollout
from helpers import partial_differences, with_value

TURN = (0.8924, 0.2391, -0.3696, 0.1167)  # a unit quaternion: no axis of the bunny along a world axis


@pytest.fixture(scope="module")
def bunny(bunny_field):
    return dano.build_dano(bunny_field, n_points=600, log2_samples=13)


@pytest.fixture(scope="module")
def boxes():
    return dano.build_dano(BoxField([0.06, 0.04, 0.03]), n_points=600, mass=0.3, log2_samples=12, grid_resolution=24)


def _lowest(obj, quat=(1.0, 0.0, 0.0, 0.0)) -> float:
    R = np.asarray(dano.math.quat_to_mat(jnp.asarray(quat)))
    return float(np.min(np.asarray(obj.body_points) @ R.T[:, 2]))


def _scenes(bunny, boxes):
    """Every partner kind: a bunny turned off its axes landing and sliding on a tilted static box;
    a box DANO landing turned on another (DANO-DANO) that rests on the ground and is hit by a free
    sphere (a primitive that takes the reaction)."""
    lift = -_lowest(bunny, TURN)
    slab = Primitive("slab", "box", (0.2, 0.2, 0.02), pos=(0, 0, -0.02), quat=(0.9962, 0.0872, 0.0, 0.0))
    body = DanoBody("b", bunny, pos=(0, 0, lift + 0.002), quat=TURN, vel=(0.4, 0.1, -0.5), angvel=(1.0, 2.0, -3.0))
    yield "bunny on a box", Scene(ground_height=None, primitives=(slab,), bodies=(body,))
    low = -_lowest(boxes)
    ball = Primitive("ball", "sphere", (0.02,), pos=(-0.085, 0.0, 0.02), mode="free", mass=0.2, vel=(1.0, 0, 0))
    over = DanoBody("over", boxes, pos=(0.01, 0.005, 3 * low + 5e-4), vel=(0.1, 0, -0.3), angvel=(0.5, -0.4, 0.2))
    bodies = (DanoBody("under", boxes, pos=(0, 0, low)), over)
    yield "box on a box, and a ball", Scene(primitives=(ball,), bodies=bodies)


def _run(scene: Scene, budget: int | None, frames: int):
    sim = Simulation.from_scene(dataclasses.replace(scene, contact_budget=budget))
    return jax.jit(lambda d: rollout(sim.world, sim.params, sim.mjx_model, d, frames))(sim.data)


def test_steps_over_the_active_set_equal_steps_over_all_points(bunny, boxes):
    """Both scenes, 25 frames: the default budget, a budget of 1 point (contact steps overflow
    and are solved over all points) and all points give one trajectory."""
    for name, scene in _scenes(bunny, boxes):
        n = sum(b.dano.n_points for b in scene.bodies)
        dense, default, tiny = (_run(scene, k, 25) for k in (n, None, 1))
        assert float(dense.fallbacks[-1]) == 0.0  # no active set at all
        assert float(tiny.fallbacks[-1]) > 0, name  # overflowed, and said so
        assert float(default.fallbacks[-1]) < 25, name
        assert np.abs(np.asarray(dense.qvel[-1] - dense.qvel[0])).max() > 0.05, name  # the contacts acted
        for traj in (default, tiny):
            np.testing.assert_allclose(traj.qpos, dense.qpos, rtol=0, atol=1e-10, err_msg=name)
            np.testing.assert_allclose(traj.qvel, dense.qvel, rtol=0, atol=1e-8, err_msg=name)


def test_derivatives_over_the_active_set_equal_those_over_all_points(bunny):
    """jacfwd and grad of the final pose w.r.t. friction and the initial velocity of a bunny landing
    turned and sliding: the default budget, an overflowing one and all points agree, and match
    central differences."""
    lift = -_lowest(bunny, TURN)
    body = DanoBody("b", bunny, pos=(0, 0, lift + 5e-4), quat=TURN, vel=(0.5, 0.0, -0.2), angvel=(0, 0, 2.0))

    def final(budget):
        sim = Simulation.from_scene(Scene(bodies=(body,), contact_budget=budget))

        def f(theta):
            contact = dataclasses.replace(sim.params.contact[0], sliding_friction=theta[0])
            params = dataclasses.replace(sim.params, contact=(contact,))
            d = sim.data.replace(qvel=sim.data.qvel.at[0].set(theta[1]))
            q = rollout(sim.world, params, sim.mjx_model, d, 20).qpos[-1]
            return jnp.stack([q[0], q[1], q[6]])

        return f

    theta = jnp.asarray([0.4, 0.5])
    # each with the value beside it: the default budget's program gives the central differences too
    programs = {k: jax.jit(jax.jacfwd(with_value(final(k)), has_aux=True)) for k in (bunny.n_points, None, 1)}
    jacobians = {k: np.asarray(fn(theta)[0]) for k, fn in programs.items()}
    for k in (None, 1):
        np.testing.assert_allclose(jacobians[k], jacobians[bunny.n_points], rtol=1e-7, atol=1e-12)
    f = final(None)
    grad = np.asarray(jax.jit(jax.grad(lambda t: f(t)[0]))(theta))
    np.testing.assert_allclose(grad, jacobians[None][0], rtol=1e-8, atol=1e-14)
    value = lambda *t: programs[None](jnp.asarray(t))[1]  # noqa: E731
    fd = np.stack(partial_differences(value, tuple(map(float, theta)), rel_step=1e-5), axis=1)
    np.testing.assert_allclose(jacobians[None], fd, rtol=2e-4, atol=1e-6 * np.abs(fd).max())
    assert np.abs(fd[0]).min() > 1e-4  # friction and the start both move the bunny


def test_a_batch_where_one_environment_overflows_equals_each_run_alone(bunny):
    """vmap: an environment in contact with a budget too small falls back to all points; the one in
    the air does not need it; each equals its own run."""
    lift = -_lowest(bunny, TURN)
    body = DanoBody("b", bunny, pos=(0, 0, lift - 2e-3), quat=TURN)  # pressed 2 mm in: several points live
    sim = Simulation.from_scene(Scene(bodies=(body,), contact_budget=1))
    heights = jnp.asarray([lift - 2e-3, lift + 0.5])
    batch = jax.vmap(lambda z: sim.data.replace(qpos=sim.data.qpos.at[2].set(z)))(heights)

    def roll(d):
        return rollout(sim.world, sim.params, sim.mjx_model, d, 10)

    together = jax.jit(jax.vmap(roll))(batch)
    assert float(together.fallbacks[0, -1]) > 0 and float(together.fallbacks[1, -1]) == 0
    for i in range(2):
        alone = jax.jit(roll)(jax.tree.map(lambda x, i=i: x[i], batch))
        np.testing.assert_allclose(together.qpos[i], alone.qpos, rtol=0, atol=1e-12)


def test_budget_holds_a_flat_face_and_a_round_body_needs_few():
    """The budget is at least the points of a box's largest face, whatever its orientation, and a
    sphere needs at most a few percent of its points."""
    box = dano.build_dano(BoxField([0.1, 0.06, 0.02]), n_points=2000, mass=1.0, log2_samples=12, grid_resolution=0)
    P, N = np.asarray(box.body_points).T, np.asarray(box.normals).T
    face = int(np.sum(P[2] < P[2].min() + 1.5e-3))  # the 0.2 x 0.12 face
    assert face > 0.3 * box.n_points
    R, _ = np.linalg.qr(np.random.default_rng(1).normal(size=(3, 3)))
    for rot in (np.eye(3), R):
        k = active.budget(rot @ P, rot @ N)
        assert face <= k <= box.n_points
    ball = dano.build_dano(dano.fields.SphereField(0.05), n_points=2000, log2_samples=12, grid_resolution=0)
    assert active.budget(np.asarray(ball.body_points).T, np.asarray(ball.normals).T) <= 0.05 * ball.n_points


def test_frequent_overflow_is_said_and_a_rare_one_only_counted(boxes):
    """`Simulation.run` warns (`ContactBudgetWarning`) when more than `FALLBACK_SHARE` of the steps
    fell back to all points: a box resting on its face with a budget of 8 points overflows every
    step; at its own budget none does, and no warning is raised."""
    from dano.sim.run import ContactBudgetWarning

    body = DanoBody("box", boxes, pos=(0, 0, -_lowest(boxes) - 2e-4))
    small = Simulation.from_scene(Scene(bodies=(body,), contact_budget=8))
    with pytest.warns(ContactBudgetWarning, match="20 of 20 steps"):
        traj = small.run(20)
    assert traj.fallbacks is not None and float(traj.fallbacks[-1]) == 20
    own = Simulation.from_scene(Scene(bodies=(body,))).run(20)  # the suite turns warnings into errors
    assert own.fallbacks is not None and float(own.fallbacks[-1]) == 0
    np.testing.assert_allclose(own.qpos, traj.qpos, rtol=0, atol=1e-10)


def test_the_broad_phase_changes_no_step(bunny, boxes, monkeypatch):
    """Both scenes (a bunny turned off its axes landing on a tilted box; a box DANO landing turned on
    another, hit by a free sphere), 25 frames: with every primitive's points evaluated at every step
    the trajectory is the same to rounding (the bounding-sphere test against each primitive's signed distance
    skips only points that cannot touch)."""
    from dano.sim import implicit

    for name, scene in _scenes(bunny, boxes):
        broad = _run(scene, None, 25)
        monkeypatch.setattr(implicit, "_within_reach", lambda *args: jnp.asarray(True))
        every = _run(scene, None, 25)
        monkeypatch.undo()
        # the same to rounding (two programs, compiled apart); a missed contact would differ by mm
        np.testing.assert_allclose(broad.qpos, every.qpos, rtol=0, atol=1e-12, err_msg=name)
        np.testing.assert_allclose(broad.qvel, every.qvel, rtol=0, atol=1e-10, err_msg=name)
