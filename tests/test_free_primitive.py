"""A DANO and a free MuJoCo primitive are solved jointly by the implicit step (`dano.sim.implicit`):
momentum is conserved and no energy appears, where the primitive's side used to be integrated
explicitly by MuJoCo and a light sphere hitting a box gained energy (the audit raised)."""

import numpy as np
import pytest

import dano
from dano.fields import BoxField
from dano.math import quat_to_mat
from dano.sim import DanoBody, Primitive, Scene
from dano.sim.run import Simulation

MASSES = (1.0, 0.2)


@pytest.fixture(scope="module")
def box():
    return dano.build_dano(BoxField([0.08, 0.06, 0.05], width=0.002), n_points=800, mass=MASSES[0], log2_samples=12)


def _kinetic(qvel: np.ndarray, box) -> float:
    """Kinetic energy of the DANO and the sphere, J (MuJoCo's angular velocities are in the body
    frame, where the inertia is the body-frame tensor)."""
    v, w = qvel[0:3], qvel[3:6]
    inertia = np.asarray(box.inertia)
    sphere_I = 0.4 * MASSES[1] * 0.015**2
    return float(0.5 * MASSES[0] * v @ v + 0.5 * w @ inertia @ w + 0.5 * MASSES[1] * qvel[6:9] @ qvel[6:9]
                 + 0.5 * sphere_I * qvel[9:12] @ qvel[9:12])  # fmt: skip


@pytest.mark.parametrize("offset", [0.0, 0.02])  # head on, and off the centre (it spins the box)
def test_a_free_sphere_hitting_a_dano_in_free_space_conserves_momentum_and_loses_energy(box, offset):
    ball = Primitive("ball", "sphere", (0.015,), pos=(-0.08, offset, 0.0), mode="free", mass=MASSES[1],
                     vel=(1.0, 0.0, 0.0))  # fmt: skip
    scene = Scene(bodies=(DanoBody("box", box),), primitives=(ball,), ground_height=None, gravity=(0, 0, 0))
    sim = Simulation.from_scene(scene)
    traj = sim.run(150)  # 0.3 s: contact at ~0.04 s, then apart (the energy audit runs too)
    qvel = np.asarray(traj.qvel)
    p0 = MASSES[0] * qvel[0, 0:3] + MASSES[1] * qvel[0, 6:9]
    p1 = MASSES[0] * qvel[-1, 0:3] + MASSES[1] * qvel[-1, 6:9]
    assert qvel[-1, 0] > 0.1  # the box was hit
    np.testing.assert_allclose(p1, p0, atol=1e-9)  # equal and opposite impulses, exactly
    e0, e1 = _kinetic(qvel[0], box), _kinetic(qvel[-1], box)
    assert e1 <= e0 * (1 + 1e-9), (e0, e1)  # the implicit contact only dissipates
    qpos = np.asarray(traj.qpos[-1])
    R = np.asarray(quat_to_mat(qpos[3:7]))
    local = R.T @ (qpos[7:10] - qpos[0:3])  # the sphere's centre in the box frame
    assert np.max(np.abs(local) - np.array([0.04, 0.03, 0.025])) > 0.015 - 0.003  # outside: it did not pass through


def test_a_free_sphere_pushes_a_resting_box_without_an_energy_error(box):
    """The scene that failed the energy audit: the box resting on the floor, a 0.2 kg sphere at
    1 m/s rolling into it (the sphere's contact with the floor is MuJoCo's)."""
    lift = -float(np.min(np.asarray(box.body_points)[:, 2]))
    start = float(np.min(np.asarray(box.body_points)[:, 0])) - 0.03
    ball = Primitive("ball", "sphere", (0.015,), pos=(start, 0.0, 0.015), mode="free", mass=MASSES[1],
                     vel=(1.0, 0, 0))  # fmt: skip
    sim = Simulation.from_scene(Scene(bodies=(DanoBody("b", box, pos=(0, 0, lift)),), primitives=(ball,)))
    traj = sim.run(250)  # raises SimulationError if energy appears
    moved = np.linalg.norm(np.asarray(traj.qpos[-1, :2] - traj.qpos[0, :2]))
    assert 1e-3 < moved < 0.05  # pushed a few mm to cm (not thrown)


@pytest.mark.parametrize("push", [0.0, 2.0])  # coasting, and driven by its motors (N along x)
def test_an_actuated_sphere_hitting_a_dano_in_free_space_conserves_momentum(box, push):
    """An actuated primitive (three world slides, force motors) is solved jointly too: the pair's
    momentum changes by exactly the motors' impulse, and a coasting one gives no energy."""
    ball = Primitive("ball", "sphere", (0.015,), pos=(-0.08, 0.01, 0.0), mode="actuated", mass=MASSES[1],
                     vel=(1.0, 0.0, 0.0))  # fmt: skip
    scene = Scene(bodies=(DanoBody("box", box),), primitives=(ball,), ground_height=None, gravity=(0, 0, 0))
    sim = Simulation.from_scene(scene)
    frames = 150
    traj = sim.run(frames, ctrl=np.tile([push, 0.0, 0.0], (frames, 1)))
    qvel = np.asarray(traj.qvel)
    momentum = MASSES[0] * qvel[:, 0:3] + MASSES[1] * qvel[:, 6:9]
    assert qvel[-1, 0] > 0.1  # the box was hit
    impulse = np.array([push * frames * sim.scene.step_size, 0.0, 0.0])
    np.testing.assert_allclose(momentum[-1] - momentum[0], impulse, atol=1e-9)
    if push == 0.0:
        v, w = qvel[-1, 0:3], qvel[-1, 3:6]
        e1 = (
            0.5 * MASSES[0] * v @ v
            + 0.5 * w @ np.asarray(box.inertia) @ w
            + 0.5 * MASSES[1] * qvel[-1, 6:9] @ qvel[-1, 6:9]
        )
        assert e1 <= 0.5 * MASSES[1] * 1.0**2 * (1 + 1e-9)
