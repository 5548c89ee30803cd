"""DANOs in the user's own MJCF world (`Scene.mjcf`): the world's bodies, joints, actuators and
contacts kept; its geoms touch the DANOs through the DANO contact model."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dano import build_dano
from dano.fields import BoxField
from dano.sim import DanoBody, Robot, Scene
from dano.sim.run import Simulation
from dano.sim.scene import SceneError
from dano.sim.step import rollout
from helpers import partial_differences, with_value

TOP = 0.22  # the table's top
WORLD = """<mujoco>
  <worldbody>
    <geom name="floor" type="plane" size="2 2 0.1"/>
    <body name="table" pos="0 0 0.2"><geom name="top" type="box" size="0.4 0.3 0.02"/></body>
    <body name="shelf" pos="0 0.5 0.4"><geom name="board" type="box" size="0.3 0.1 0.01"/></body>
    <body name="lid" pos="-0.3 -0.45 0.3">
      <joint name="hinge" type="hinge" axis="1 0 0" damping="0.05"/>
      <geom name="lid" type="box" size="0.1 0.05 0.005" pos="0 0.05 0" mass="0.1"/>
    </body>
    <body name="crate" pos="0.15 0 0.25">
      <freejoint/><geom name="crate" type="box" size="0.03 0.03 0.03" mass="0.05"/>
    </body>
  </worldbody>
  <actuator><position name="lid_motor" joint="hinge" kp="2" kv="0.1"/></actuator>
  KEYFRAME
</mujoco>"""


@pytest.fixture(scope="module")
def soap():
    return build_dano(BoxField(size=(0.06, 0.04, 0.03)), mass=0.1, n_points=300)


def _world(tmp_path, keyframe: str = "") -> str:
    (tmp_path / "world.xml").write_text(WORLD.replace("KEYFRAME", keyframe))
    return str(tmp_path / "world.xml")


def _still_world(tmp_path) -> str:
    """The world's table and floor alone: nothing of it moves, so the step skips MuJoCo's (a world
    body that moves costs an `mjx.step` per step: minutes for the slow tests that solve in it)."""
    text = WORLD.replace("KEYFRAME", "")
    for name in ("shelf", "crate", "lid"):
        start = text.index(f'<body name="{name}"')
        text = text[:start] + text[text.index("</body>", start) + len("</body>") :]
    start = text.index("<actuator>")
    (tmp_path / "still.xml").write_text(text[:start] + text[text.index("</actuator>") + len("</actuator>") :])
    return str(tmp_path / "still.xml")


def test_a_dano_slides_on_the_worlds_table_into_its_free_crate_while_the_lid_follows_its_motor(soap, tmp_path):
    # The soap, dropped 2 cm onto the table at 1.5 m/s, slides 0.23 m (mu = 0.5) into the crate. The
    # crate sits on the table by MuJoCo's own contact; the soap touches the table, the crate and the
    # floor through the DANO model; the lid's position servo (the world's actuator) follows ctrl.
    start = (-0.05, 0.0, TOP + 0.015 + 0.02)
    scene = Scene(mjcf=_world(tmp_path), ground_height=None, duration=1.0,
                  bodies=(DanoBody("soap", soap, pos=start, vel=(1.5, 0.0, 0.0)),))  # fmt: skip
    sim = Simulation.from_scene(scene)
    assert sim.world.link_names == ("world", "table", "shelf", "lid", "crate") and sim.model.nu == 1
    traj = sim.run(scene.n_steps, ctrl=jnp.full((scene.n_steps, 1), 0.8))
    q, m = np.asarray(traj.qpos), sim.model
    a = sim.world.dano_qpos[0]
    crate = int(m.jnt_qposadr[m.body("crate").jntadr[0]])
    assert q[-1, crate] > 0.15 + 0.005  # pushed along +x by the soap
    assert q[-1, crate + 2] == pytest.approx(TOP + 0.03, abs=2e-3)  # still on the table (MuJoCo's contact)
    assert q[-1, a + 2] == pytest.approx(TOP + 0.015, abs=2e-3)  # the soap rests on the table (DANO contact)
    assert np.abs(np.asarray(traj.qvel[-1, sim.world.dano_qvel[0] : sim.world.dano_qvel[0] + 6])).max() < 1e-2
    # The lid: 0.1 kg, its centre 5 cm out: gravity holds it below the target by m g l cos(q) / kp.
    hinge = float(q[-1, m.jnt_qposadr[m.joint("hinge").id]])
    assert hinge == pytest.approx(0.8 - 0.1 * 9.81 * 0.05 * np.cos(0.8) / 2.0, abs=0.01)


@pytest.mark.slow
def test_the_stanford_bunny_slides_on_the_worlds_table_into_its_crate(tmp_path, bunny_field):
    """The same world with a DANO of the Stanford bunny (0.3 kg, 15 cm), dropped 2 cm onto the
    table at 1.85 m/s: it hits the crate, which slides along the table on MuJoCo's contact and stays
    on it; the bunny comes to rest on the table (its lowest point on the top); the lid follows."""
    bunny = build_dano(bunny_field, n_points=500, mass=0.3, log2_samples=12, replicates=4)
    lift = -float(np.min(np.asarray(bunny.body_points)[:, 2]))
    body = DanoBody("bunny", bunny, pos=(-0.25, 0.0, TOP + lift + 0.02), vel=(1.85, 0.0, 0.0))
    scene = Scene(mjcf=_world(tmp_path), ground_height=None, duration=1.5, bodies=(body,))
    sim = Simulation.from_scene(scene)
    traj = sim.run(scene.n_steps, ctrl=jnp.full((scene.n_steps, 1), 0.8))
    q, m = np.asarray(traj.qpos), sim.model
    a, va = sim.world.dano_qpos[0], sim.world.dano_qvel[0]
    crate = int(m.jnt_qposadr[m.body("crate").jntadr[0]])
    assert q[-1, crate] > 0.15 + 0.02 and q[-1, crate + 2] == pytest.approx(TOP + 0.03, abs=2e-3)
    assert q[-1, a + 2] == pytest.approx(TOP + lift, abs=3e-3)  # resting upright on the table top
    assert np.abs(np.asarray(traj.qvel[-1, va : va + 6])).max() < 1e-2
    hinge = float(q[-1, m.jnt_qposadr[m.joint("hinge").id]])
    assert hinge == pytest.approx(0.8 - 0.1 * 9.81 * 0.05 * np.cos(0.8) / 2.0, abs=0.01)


def test_gradients_through_a_world_rollout_match_central_differences(soap, tmp_path):
    """d(where the soap and the crate end)/d(friction, initial speed), 150 frames: the soap's
    friction on the table and its hit on the crate, against central differences in float64."""
    start = (-0.02, 0.0, TOP + 0.015)
    scene = Scene(mjcf=_world(tmp_path), ground_height=None, bodies=(DanoBody("soap", soap, pos=start),))
    sim = Simulation.from_scene(scene)
    m = sim.model
    crate = int(m.jnt_qposadr[m.body("crate").jntadr[0]])
    v = sim.world.dano_qvel[0]

    def final(theta):
        mu, vx = theta
        contact = tuple(dataclasses.replace(c, sliding_friction=mu) for c in sim.params.contact)
        d = sim.data.replace(qvel=sim.data.qvel.at[v].set(vx))
        ctrl = jnp.zeros((150, 1))
        q = rollout(sim.world, dataclasses.replace(sim.params, contact=contact), sim.mjx_model, d, 150, ctrl).qpos[-1]
        return jnp.stack([q[sim.world.dano_qpos[0]], q[crate]])

    theta = (0.5, 1.4)
    # One compiled program: the Jacobian with the value beside it, which gives the differences too.
    jac = jax.jit(jax.jacfwd(with_value(final), has_aux=True))
    fd = np.stack(partial_differences(lambda *t: jac(jnp.asarray(t))[1], theta, rel_step=1e-5), axis=1)
    J = np.asarray(jac(jnp.asarray(theta))[0])
    np.testing.assert_allclose(J, fd, rtol=2e-3, atol=1e-6 * np.abs(fd).max())
    assert np.abs(fd[1]).max() > 1e-3  # the crate's end depends on the soap: the hit is in the gradient


def test_a_worlds_keyframes_are_kept_and_extended_by_the_scenes_bodies(soap, tmp_path):
    key = '<keyframe><key name="open" qpos="1.2  0.15 0 0.25 1 0 0 0" ctrl="1.2"/></keyframe>'
    scene = Scene(mjcf=_world(tmp_path, key), ground_height=None, duration=0.01,
                  bodies=(DanoBody("soap", soap, pos=(0.0, 0.0, TOP + 0.015)),))  # fmt: skip
    m = Simulation.from_scene(scene).model
    assert m.nkey == 1 and m.key("open").qpos.shape == (m.nq,)
    np.testing.assert_allclose(m.key("open").qpos[:8], [1.2, 0.15, 0, 0.25, 1, 0, 0, 0])
    np.testing.assert_allclose(m.key("open").qpos[8:11], [0.0, 0.0, TOP + 0.015])  # the soap where it starts


def test_bad_worlds_are_named_errors(soap, tmp_path):
    body = (DanoBody("soap", soap, pos=(0.0, 0.0, 0.5)),)
    with pytest.raises(SceneError, match="MJCF world .*missing.xml not found"):
        Simulation.from_scene(Scene(mjcf=str(tmp_path / "missing.xml"), bodies=body))
    with pytest.raises(SceneError, match="a robot or an MJCF world, not both"):
        Scene(mjcf=_world(tmp_path), robot=Robot(str(tmp_path / "world.xml")), bodies=body)
    (tmp_path / "egg.xml").write_text('<mujoco><worldbody><geom name="egg" type="ellipsoid" size="0.05 0.04 0.1"/>'
                                      "</worldbody></mujoco>")  # fmt: skip
    with pytest.raises(SceneError, match="geom egg of type mjGEOM_ELLIPSOID cannot touch DANOs"):
        Simulation.from_scene(Scene(mjcf=str(tmp_path / "egg.xml"), bodies=body))
    (tmp_path / "broken.xml").write_text("<mujoco><worldbody><body></mujoco>")
    with pytest.raises(SceneError, match="MuJoCo cannot load it"):
        Simulation.from_scene(Scene(mjcf=str(tmp_path / "broken.xml"), bodies=body))


def test_a_dano_rests_on_the_worlds_floor_plane_and_a_scene_file_names_its_world(soap, tmp_path):
    from dano.io import save_dano
    from dano.sim import load_scene

    _world(tmp_path)
    save_dano(tmp_path / "soap.dano.npz", soap)
    (tmp_path / "scene.toml").write_text(
        '[sim]\nduration = 0.4\n[world]\nmjcf = "world.xml"\n'
        '[[body]]\nname = "soap"\ndano = "soap.dano.npz"\npos = [1.0, 1.0, 0.03]\n'
    )  # fmt: skip
    scene = load_scene(tmp_path / "scene.toml")
    assert scene.mjcf == str(tmp_path / "world.xml") and scene.ground_height is None
    sim = Simulation.from_scene(scene)
    traj = sim.run()
    a = sim.world.dano_qpos[0]
    assert float(traj.qpos[-1, a + 2]) == pytest.approx(0.015, abs=1e-3)  # on the world's plane (DANO contact)


@pytest.mark.slow
def test_friction_is_identified_from_a_slide_on_the_worlds_table(soap, tmp_path):
    from dano.contact import ContactParams
    from dano.sysid import Recording, identify, make_problem
    from dano.sysid.experiments import slide_track

    body = DanoBody("object", soap, pos=(-0.25, 0.0, TOP + 0.015), vel=(1.0, 0.0, 0.0))
    truth = Scene(  # on the world's table; its moving bodies left out (`_still_world`)
        mjcf=_still_world(tmp_path), ground_height=None, contact=ContactParams(sliding_friction=0.4), bodies=(body,)
    )
    track = slide_track(truth, fps=120.0, n_frames=25, lead=2)
    guess = dataclasses.replace(truth, contact=ContactParams(sliding_friction=0.2))
    problem = make_problem(guess, [Recording({"object": track})], ["friction"], initial="velocity")
    result = identify(problem, init={"sliding_friction": 0.2})
    assert result.converged and result.params["sliding_friction"] == pytest.approx(0.4, rel=1e-3)


@pytest.mark.slow
@pytest.mark.optimized
def test_a_sphere_pushes_the_dano_to_its_goal_on_the_worlds_table(soap, tmp_path):
    """Trajectory optimisation in the world: the soap stood on the table top (what the world has
    under the point asked for), pushed 5 cm by the force-controlled sphere, ends at its goal and
    still on the table. The world here is its table and floor (`_still_world`: with the lid's hinge,
    255 s in CI instead of ~60 s); a world's own actuators are held first in `ctrl` (`_full_ctrl`,
    checked below)."""
    import dano.trajopt.push as P

    world = _still_world(tmp_path)
    push = P.push_problem(soap, "sphere", P.PushTask(goal=(0.05, 0.0), horizon=8), world=world, at=(-0.15, 0.1))
    a = push.sim.world.dano_qpos[0]
    assert push.sim.model.nu == 3 and push.x0[a + 2] == pytest.approx(TOP + 0.015, abs=1e-3)  # on the table top
    result = P.solve_push(push, P.default_options("sphere"), progress=False)
    end = np.asarray(result.replay.qpos[-1, a : a + 3])
    assert result.final_error_m < 3e-3 and result.replay_gap_m < 1e-9
    np.testing.assert_allclose(end[:2], push.goal_world, atol=3e-3)
    assert end[2] == pytest.approx(TOP + 0.015, abs=2e-3)
    held = P._full_ctrl(push.pusher, jnp.asarray([0.8]), jnp.ones((2, 3)))  # a world motor held at 0.8
    np.testing.assert_array_equal(held, [[0.8, 1.0, 1.0, 1.0]] * 2)


def test_a_push_where_the_world_has_nothing_is_a_named_error(soap, tmp_path, capsys):
    from dano.cli import main
    from dano.trajopt.pieces import TrajoptError
    from dano.trajopt.push import PushTask, push_problem

    world = _world(tmp_path)
    with pytest.raises(TrajoptError, match=r"nothing under \(5, 5\) to stand the object on"):
        push_problem(soap, "sphere", PushTask(goal=(0.05, 0.0), horizon=4), world=world, at=(5.0, 5.0))
    (tmp_path / "bad.xml").write_text("<mujoco><worldbody><geom type='box'/></worldbody>")
    with pytest.raises(TrajoptError, match="MuJoCo cannot load the world"):
        push_problem(soap, "sphere", PushTask(goal=(0.05, 0.0), horizon=4), world=tmp_path / "bad.xml")
    assert main(["trajopt", "push", "--world", str(tmp_path / "missing.xml")]) == 2
    assert "argument --world: no file" in capsys.readouterr().err


RAMP = """<mujoco><asset><hfield name="ramp" nrow="2" ncol="2" size="0.5 0.3 0.2 0.05" elevation="0 1 0 1"/></asset>
<worldbody><geom name="ramp" type="hfield" hfield="ramp" pos="0 0 0.1"/>
<geom name="post" type="cylinder" size="0.05 0.1" pos="1 0 0.1"/></worldbody></mujoco>"""


@pytest.mark.slow
def test_a_dano_slides_down_a_height_field_at_g_sin_minus_mu_cos_and_rests_on_a_cylinder(soap, tmp_path):
    """The world's height field (a 2 x 2 grid rising 0.2 m over 1 m: a plane at atan 0.2 = 11.3°)
    and an upright cylinder: the soap placed on the slope with mu = 0.1 < tan slides down at
    g (sin - mu cos) (the closed form); another on the cylinder's flat top rests there."""
    from dano.contact import ContactParams
    from dano.viewer import scene_solids

    (tmp_path / "ramp.xml").write_text(RAMP)
    th, mu, x0 = np.arctan(0.2), 0.1, 0.3
    normal = np.array([-np.sin(th), 0.0, np.cos(th)])
    lift = -float(np.min(np.asarray(soap.body_points)[:, 2]))
    on_slope = np.array([x0, 0.0, 0.1 + 0.2 * (x0 + 0.5)]) + (lift + 1e-4) * normal
    bodies = (
        DanoBody("slider", soap, pos=tuple(on_slope), quat=(np.cos(-th / 2), 0.0, np.sin(-th / 2), 0.0)),
        DanoBody("resting", soap, pos=(1.0, 0.0, 0.2 + lift + 1e-4)),
    )
    scene = Scene(mjcf=str(tmp_path / "ramp.xml"), ground_height=None, duration=0.6, bodies=bodies,
                  contact=ContactParams(sliding_friction=mu))  # fmt: skip
    sim = Simulation.from_scene(scene)
    assert [link.kind for link in sim.world.links] == ["hfield", "cylinder"]
    traj = sim.run()
    q, v = np.asarray(traj.qpos), np.asarray(traj.qvel)
    down = np.array([-np.cos(th), 0.0, -np.sin(th)])
    accel = np.polyfit(np.arange(100, 300) * 0.002, v[100:300, :3] @ down, 1)[0]
    np.testing.assert_allclose(accel, 9.81 * (np.sin(th) - mu * np.cos(th)), rtol=2e-3)
    assert q[-1, 9] == pytest.approx(0.2 + lift, abs=1e-3) and np.abs(v[-1, 6:12]).max() < 1e-3
    solids = {s.name: s for s in scene_solids(sim.model, q[-1:])}  # in the viewer: the ramp's surface, the post
    np.testing.assert_allclose(np.ptp(solids["ramp"].vertices, axis=0), [1.0, 0.6, 0.2], atol=1e-6)
    np.testing.assert_allclose(np.ptp(solids["post"].vertices, axis=0), [0.1, 0.1, 0.2], atol=1e-6)
    # d(where the slider is after 0.12 s)/d(friction, its initial speed along the slope) through the
    # height field's contact, against central differences in float64.
    sim = Simulation.from_scene(dataclasses.replace(scene, bodies=bodies[:1]))  # the slider alone
    a, va = sim.world.dano_qpos[0], sim.world.dano_qvel[0]

    def final(theta):
        contact = tuple(dataclasses.replace(c, sliding_friction=theta[0]) for c in sim.params.contact)
        d = sim.data.replace(qvel=sim.data.qvel.at[va : va + 3].set(theta[1] * jnp.asarray(down)))
        return rollout(sim.world, dataclasses.replace(sim.params, contact=contact), sim.mjx_model, d, 60).qpos[-1, a]

    theta = (mu, 0.3)
    program = jax.jit(jax.value_and_grad(final))  # one program: the differences from its values
    fd = np.asarray(partial_differences(lambda *t: program(jnp.asarray(t))[0], theta, rel_step=1e-5))
    J = np.asarray(program(jnp.asarray(theta))[1])
    np.testing.assert_allclose(J, fd, rtol=2e-3)
    assert fd[0] > 0.01  # more friction: it ends higher up the slope (at larger x)


def test_the_cylinder_signed_distance_matches_a_fine_mesh_of_it():
    """Against trimesh's signed distance to a 512-sided cylinder (an independent computation), at
    random points inside, beside, above and off the rims of a cylinder turned off the axes."""
    import trimesh

    from dano.contact import Cylinder, signed_distance
    from dano.math import quat_to_mat

    r, half = 0.05, 0.08
    R = np.asarray(quat_to_mat(jnp.asarray([0.8, 0.3, -0.4, 0.33]) / np.linalg.norm([0.8, 0.3, -0.4, 0.33])))
    centre = np.array([0.1, -0.2, 0.3])
    mesh = trimesh.creation.cylinder(radius=r, height=2 * half, sections=512)
    local = np.random.default_rng(0).uniform(-0.12, 0.12, size=(400, 3))
    expected = -trimesh.proximity.signed_distance(mesh, local)  # trimesh: positive inside
    world = local @ R.T + centre
    got = signed_distance(Cylinder(jnp.asarray(centre), jnp.asarray(R), jnp.asarray(r), jnp.asarray(half)),
                          jnp.asarray(world.T))  # fmt: skip
    np.testing.assert_allclose(np.asarray(got), expected, atol=r * 5e-4)  # the mesh: within 25 µm
