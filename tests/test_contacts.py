"""Contact forces along a trajectory (`dano.sim.contacts`): checked against the weight they carry,
friction's share on a slope, and the momentum and angular momentum they change."""

import jax.numpy as jnp
import numpy as np
import pytest

import dano
from dano.contact import ContactParams
from dano.fields import BoxField
from dano.fields.base import TransformedField
from dano.math import quat_to_mat
from dano.sim import DanoBody, Primitive, Scene
from dano.sim.contacts import contact_forces
from dano.sim.run import Simulation

G = 9.81
TURNED = np.array([[0.3456, -0.6861, -0.6402], [0.6920, -0.2757, 0.6673], [-0.6442, -0.6732, 0.3628]])


@pytest.fixture(scope="module")
def flat_box():
    return dano.build_dano(BoxField([0.1, 0.1, 0.05]), n_points=1000, mass=1.0, log2_samples=12, replicates=4,
                           grid_resolution=0)  # fmt: skip


def _lift(obj) -> float:
    return -float(np.min(np.asarray(obj.body_points)[:, 2]))


def test_a_box_at_rest_on_a_20_degree_slope_is_held_by_its_weight_in_reverse(flat_box):
    """At rest the pair's force is -m g: its normal part m g cos, its friction part m g sin along the
    slope (what the explicit law at the state, with no slip, would not give), through the centre."""
    th = np.radians(20.0)
    normal, quat = np.array([np.sin(th), 0.0, np.cos(th)]), (np.cos(th / 2), 0.0, np.sin(th / 2), 0.0)
    body = DanoBody("b", flat_box, pos=tuple(_lift(flat_box) * normal), quat=quat)
    scene = Scene(ground_normal=tuple(normal), bodies=(body,), substeps=1, duration=1.0,
                  contact=ContactParams(sliding_friction=0.5))  # fmt: skip
    sim = Simulation.from_scene(scene)
    traj = sim.run()
    forces = contact_forces(sim, traj)
    assert forces.names == (("b", "ground"),)
    F, x = forces.force[-1, 0], np.asarray(traj.qpos[-1, :3])
    np.testing.assert_allclose(F, [0.0, 0.0, G], atol=2e-3 * G)
    down_slope = np.array([np.cos(th), 0.0, -np.sin(th)])
    np.testing.assert_allclose(-F @ down_slope, G * np.sin(th), rtol=2e-3)
    # It acts on the face that touches (a box of half height 25 mm), beneath the centre.
    at = forces.point[-1, 0] - x
    np.testing.assert_allclose(at @ normal, -0.025, atol=1.5e-3)
    total = forces.torque[-1, 0]
    assert np.linalg.norm(total) < 1e-3 * G * 0.05  # at rest: no net torque about the centre


def test_a_free_fall_has_no_contact_force_and_a_floor_point_is_under_the_body(flat_box):
    body = DanoBody("b", flat_box, pos=(0.0, 0.0, 0.2))
    sim = Simulation.from_scene(Scene(bodies=(body,), substeps=1, duration=0.4))
    traj = sim.run()
    forces = contact_forces(sim, traj)
    assert np.all(forces.force[:50] == 0.0)  # in the air for the first 0.1 s (falls 49 mm)
    np.testing.assert_array_equal(forces.point[0, 0], np.asarray(traj.qpos[0, :3]))
    assert forces.largest() > G  # the landing


@pytest.mark.parametrize("integrator", ["implicit", "explicit"])
def test_the_forces_change_momentum_and_angular_momentum_as_the_step_does(integrator):
    """A box of three sides turned off its axes, thrown turned and spinning onto a floor, tumbling:
    every frame, m (v' - v) / h = F + m g and L' - L = h tau (the implicit step holds L exactly
    over its rotation). The explicit step takes four substeps per frame: there it is checked that
    its forces are there at all."""
    R, _ = np.linalg.qr(TURNED)
    field = TransformedField(BoxField([0.1, 0.06, 0.03], width=0.002), rotation=R * np.sign(np.linalg.det(R)))
    obj = dano.build_dano(field, n_points=300, mass=0.5, log2_samples=12, replicates=4, grid_resolution=0)
    q = (0.9, 0.3, -0.2, 0.25)
    body = DanoBody("b", obj, pos=(0.0, 0.0, 0.08), quat=tuple(np.asarray(q) / np.linalg.norm(q)), vel=(0.5, 0, -0.3),
                    angvel=(2.0, -1.0, 3.0))  # fmt: skip
    substeps = 1 if integrator == "implicit" else 4
    scene = Scene(bodies=(body,), integrator=integrator, substeps=substeps, duration=0.3,
                  contact=ContactParams(sliding_friction=0.4))  # fmt: skip
    sim = Simulation.from_scene(scene)
    traj = sim.run()
    forces = contact_forces(sim, traj)
    qpos, qvel = np.asarray(traj.qpos), np.asarray(traj.qvel)
    touching = np.linalg.norm(forces.force[:-1, 0], axis=-1) > 0.1 * 0.5 * G
    assert touching.sum() > 20  # it lands and tumbles
    if integrator == "explicit":  # four substeps per frame: only the first is this state's; check the first
        return
    h, m = sim.world.dt, float(obj.mass)
    dp = m * (qvel[1:, :3] - qvel[:-1, :3]) / h - m * np.array([0.0, 0.0, -G])
    np.testing.assert_allclose(dp, forces.force[:-1, 0], atol=1e-6 * m * G)

    def momentum(qp, qv):
        Rq = np.asarray(quat_to_mat(jnp.asarray(qp[3:7])))
        return Rq @ np.asarray(obj.inertia) @ qv[3:6]

    L = np.stack([momentum(a, b) for a, b in zip(qpos, qvel, strict=True)])
    np.testing.assert_allclose((L[1:] - L[:-1]) / h, forces.torque[:-1, 0], atol=1e-6 * m * G * 0.1)


def test_a_pushed_sphere_pair_is_named_and_pushes_along_its_motion(flat_box):
    """A mocap sphere driven into the box: the pair (box, pusher) has a force along the push."""
    body = DanoBody("b", flat_box, pos=(0.0, 0.0, _lift(flat_box)))
    pusher = Primitive("pusher", "sphere", size=(0.02,), pos=(-0.08, 0.0, 0.025), mode="mocap")
    sim = Simulation.from_scene(Scene(bodies=(body,), primitives=(pusher,), substeps=1, duration=0.2))
    n = 100
    path = np.stack([[-0.08 + 0.3 * 0.002 * (t + 1), 0.0, 0.025] for t in range(n)])[:, None]
    traj = sim.run(n, mocap_pos=path)
    forces = contact_forces(sim, traj, mocap_pos=path)
    assert forces.names == (("b", "ground"), ("b", "pusher"))
    push = forces.force[:, 1]
    assert push[-1, 0] > 0.1 and np.all(push[:, 0] >= -1e-9)  # along +x, never pulling
    assert abs(forces.point[-1, 1, 0] - np.asarray(traj.qpos[-1, 0]) + 0.05) < 3e-3  # on the box's -x face


def test_an_actuated_pusher_driven_by_ctrl_feels_the_reaction_of_the_pair(flat_box):
    """A force-controlled sphere (three world slides, ctrl in N) pushing the box along the floor:
    the pair's force on the box is what the motor's force did not put into the sphere's momentum,
    ctrl - m_s (v' - v) / h, every frame (the `ctrl` each frame ran with is the one read)."""
    body = DanoBody("b", flat_box, pos=(0.0, 0.0, _lift(flat_box)))
    ball = Primitive("ball", "sphere", (0.015,), pos=(-0.066, 0.0, 0.025), mode="actuated", mass=0.3)
    scene = Scene(bodies=(body,), primitives=(ball,), substeps=1, contact=ContactParams(sliding_friction=0.3))
    sim = Simulation.from_scene(scene)
    frames = 150
    push = np.linspace(0.0, 6.0, frames)  # N along +x, rising past the box's friction (2.9 N)
    ctrl = np.stack([push, np.zeros(frames), np.zeros(frames)], axis=1)
    traj = sim.run(frames, ctrl=ctrl)
    forces = contact_forces(sim, traj, ctrl=ctrl)
    v = np.asarray(traj.qvel)[:, 6:9]
    h = sim.world.dt
    expected = ctrl - 0.3 * (v[1:] - v[:-1]) / h
    assert forces.names[1] == ("b", "ball") and np.max(forces.force[:-1, 1, 0]) > 3.0
    np.testing.assert_allclose(forces.force[:-1, 1], expected, atol=1e-6)
