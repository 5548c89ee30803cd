"""A URDF robot (the Franka Panda of example-robot-data) in a DANO scene."""

import dataclasses
import importlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dano
from dano.assets import panda
from dano.fields import BoxField
from dano.sim import DanoBody, Robot, Scene
from dano.sim.run import Simulation
from dano.sim.world import pairs
from helpers import with_value


@pytest.fixture(scope="module")
def cube():
    return dano.build_dano(BoxField([0.06, 0.06, 0.06], width=0.002), n_points=2000, mass=0.3, log2_samples=13)


def test_panda_loads_with_its_collision_geometry(cube):
    sim = Simulation.from_scene(Scene(bodies=(DanoBody("cube", cube, pos=(0.5, 0, 0.1)),), robot=panda()))
    model = sim.model
    assert model.nu == 9 and model.njnt == 10  # 7 arm + 2 finger joints, and the cube's free joint
    kinds = [link.kind for link in sim.world.links]
    assert kinds.count("mesh") == 9 and kinds.count("box") == 8  # 9 STL links, 8 finger boxes
    assert all(
        link.normals is not None and link.normals.shape[0] >= 100 for link in sim.world.links if link.kind == "mesh"
    )
    assert np.all(model.geom_contype[[link.geom for link in sim.world.links]] == 0)  # DANO model only


@pytest.mark.slow
def test_panda_link_sweeps_and_pushes_the_dano(cube):
    # The arm's hand sweeps from +y to -y at ~3 cm above the floor (base yaw joint driven by its
    # position servo) through a cube resting at y = 0.05: the cube must be pushed along -y.
    z = -float(jnp.min(cube.body_points[:, 2]))
    q0 = np.array([0.35, 0.7, 0.0, -2.0, 0.0, 2.6, 0.785, 0.02, 0.02])
    sim = Simulation.from_scene(
        Scene(bodies=(DanoBody("cube", cube, pos=(0.58, 0.05, z)),), robot=panda(qpos=tuple(q0)))
    )
    n = 200
    targets = np.repeat(q0[None], n, axis=0)
    targets[:, 0] = np.linspace(0.35, -0.1, n)
    traj = sim.run(n, ctrl=jnp.asarray(targets))
    a = sim.world.dano_qpos[0]
    start, end = np.asarray(traj.qpos[0, a : a + 3]), np.asarray(traj.qpos[-1, a : a + 3])
    assert end[1] < start[1] - 0.03  # pushed along -y by the sweeping hand
    assert abs(end[2] - start[2]) < 0.005  # still on the floor
    # The servo follows its ramp with the PD lag kv * speed / kp = 30 * 1.125 / 300 = 0.11 rad.
    assert float(traj.qpos[-1, 0]) == pytest.approx(-0.1 + 0.11, abs=0.05)


def test_mjcf_robot_with_primitive_links(cube, tmp_path):
    # A one-joint MJCF arm: a capsule along +x at the cube's height, swung about z by its servo
    # into a cube on its +y side.
    (tmp_path / "arm.xml").write_text(
        """<mujoco><worldbody><body name="link" pos="0 0 0.2">
        <joint name="hinge" type="hinge" axis="0 0 1"/>
        <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.02" mass="0.5"/>
        </body></worldbody></mujoco>"""
    )
    z = -float(jnp.min(cube.body_points[:, 2]))
    robot = Robot(str(tmp_path / "arm.xml"), base_pos=(0.0, 0.0, z))  # the root body's pose
    sim = Simulation.from_scene(Scene(bodies=(DanoBody("cube", cube, pos=(0.25, 0.08, z)),), robot=robot))
    assert [link.kind for link in sim.world.links] == ["capsule"] and sim.model.nu == 1
    traj = sim.run(150, ctrl=jnp.full((150, 1), 1.2))  # swing the capsule towards +y
    a = sim.world.dano_qpos[0]
    assert float(traj.qpos[-1, a + 1]) > 0.08 + 0.02  # the cube was swept along +y


def test_a_servo_too_stiff_for_its_joint_is_refused(cube):
    # Without the armature, the hand's joint (M = 0.0067 kg m²) under kv = 30 at 0.5 ms steps has
    # kv h / M = 2.2: MuJoCo's explicit damping would ring up, so the scene is refused by name.
    from dano.sim.compile import compile_scene
    from dano.sim.scene import SceneError

    body = DanoBody("cube", cube, pos=(0.5, 0, 0.1))
    scene = Scene(bodies=(body,), robot=panda(armature=None), integrator="explicit")
    with pytest.raises(SceneError, match="panda_joint7"):
        compile_scene(scene)
    compile_scene(Scene(bodies=scene.bodies, robot=panda(), integrator="explicit"))  # 0.1 kg m² by default: accepted
    # The implicit step compiles MuJoCo's implicitfast integrator (servo damping implicit): the same
    # bare hand at one 2 ms step holds its pose instead of ringing up.
    sim = Simulation.from_scene(dataclasses.replace(scene, integrator="implicit", substeps=1))
    n = 200  # as many frames as the sweep above: the same compiled program
    traj = sim.run(n, ctrl=jnp.tile(sim.data.qpos[: sim.model.nu], (n, 1)))
    assert np.all(np.isfinite(np.asarray(traj.qpos))) and float(jnp.max(jnp.abs(traj.qvel[-1, : sim.model.nu]))) < 0.1


GROUPED_ARM = """<mujoco><asset>
  <mesh name="long" vertex="0.03 0 0  -0.03 0 0  0 0.018 0  0 -0.018 0  0 0 0.012  0 0 -0.012"/>
  <mesh name="octa" vertex="0.02 0 0  -0.02 0 0  0 0.02 0  0 -0.02 0  0 0 0.02  0 0 -0.02"/>
</asset><worldbody><body name="arm">
  <joint name="yaw" type="hinge" axis="0 0 1" damping="1"/>
  <geom name="east" type="box" pos="0.048 0 0.03" size="0.02 0.02 0.02" mass="0.2"/>
  <geom name="west" type="box" pos="-0.046 0.01 0.03" size="0.018 0.025 0.015" euler="0 0 20" mass="0.2"/>
  <geom name="far" type="box" pos="0.6 0.6 0.03" size="0.02 0.02 0.02" mass="0.2"/>
  <geom name="north" type="mesh" mesh="long" pos="0.005 0.0465 0.025" euler="0 10 0" mass="0.1"/>
  <geom name="south" type="mesh" mesh="octa" pos="0 -0.048 0.03" mass="0.1"/>
  <geom name="top" type="capsule" fromto="-0.02 0 0.0645 0.02 0 0.0645" size="0.007" mass="0.1"/>
</body></worldbody></mujoco>"""


@pytest.mark.slow
def test_link_pairs_computed_as_groups_equal_pair_by_pair(cube, tmp_path, monkeypatch):
    # A one-joint arm whose boxes, capsule and two convex meshes (octahedra of 8 planes) press
    # into a tilted cube from every side, and a box far away. The step computes
    # the boxes as one group, the meshes as another (`pair_groups`); pair by pair it must give the
    # same wrench per link (the implicit and the explicit step's), where the solve's answer shows.
    # The grouped step's derivative w.r.t. friction against central differences.
    from dano.sim import implicit

    step_module = importlib.import_module("dano.sim.step")  # `dano.sim.step` is also the step function
    from dano.sim.step import scaled_model

    (tmp_path / "arm.xml").write_text(GROUPED_ARM)
    z = -float(jnp.min(cube.body_points[:, 2]))
    body = DanoBody("cube", cube, pos=(0.0, 0.0, z), quat=(0.999, 0.02, -0.03, 0.01))
    sim = Simulation.from_scene(Scene(bodies=(body,), robot=Robot(str(tmp_path / "arm.xml"))))
    world = sim.world
    assert [link.kind for link in world.links] == ["box", "box", "box", "mesh", "mesh", "capsule"]
    mu0 = jnp.asarray(0.4)

    def step(mu):
        contact = tuple(dataclasses.replace(p, sliding_friction=mu) for p in sim.params.contact)
        params = dataclasses.replace(sim.params, contact=contact)
        d = implicit.implicit_step(world, params, scaled_model(world, params, sim.mjx_model), sim.data)
        return jnp.concatenate([d.qpos, d.qvel])

    def contacts():
        m = scaled_model(world, sim.params, sim.mjx_model)
        both = (implicit.implicit_contacts, step_module.explicit_contacts)
        return jax.jit(lambda: [f(world, sim.params, m, sim.data) for f in both])()

    (wrench, point), explicit = contacts()
    derivative = jax.jit(jax.jacfwd(with_value(step), has_aux=True))
    jac, x = derivative(mu0)
    eps = 1e-6
    fd = (derivative(mu0 + eps)[1] - derivative(mu0 - eps)[1]) / (2 * eps)
    alone = lambda pair_list, *_, **__: tuple((j,) for j in range(len(pair_list)))  # noqa: E731
    monkeypatch.setattr(implicit, "pair_groups", alone)
    monkeypatch.setattr(step_module, "pair_groups", alone)
    (wrench1, point1), explicit1 = contacts()

    for w in (wrench, explicit[0]):
        force = [float(np.linalg.norm(w[j, :3])) for j, (_, kind, _) in enumerate(pairs(world)) if kind == "link"]
        assert force[2] == 0.0 and min(force[:2] + force[3:]) > 0.1, force  # the far box alone has none
    np.testing.assert_allclose(wrench, wrench1, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(point, point1, rtol=1e-9, atol=1e-12)
    assert np.all(np.isfinite(np.asarray(x)))
    for a, b in zip(explicit, explicit1, strict=True):  # the explicit step's pairs (eqs. 11-16), grouped alike
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-12)
    assert np.max(np.abs(np.asarray(jac))) > 1e-3  # friction matters to the step
    np.testing.assert_allclose(jac, fd, rtol=1e-4, atol=1e-6 * float(np.max(np.abs(fd))))
