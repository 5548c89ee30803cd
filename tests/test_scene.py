import csv
import json

import numpy as np
import pytest

import dano
from dano.cli import main
from dano.fields import BoxField, SphereField
from dano.sim import DanoBody, Scene, SceneError, load_scene
from dano.sim.run import Simulation
from dano.sim.scene import DEFAULT_SUBSTEPS

SCENE = """
[sim]
timestep = 0.002            # s
duration = 0.1              # s
gravity = [0.0, 0.0, -9.81] # m/s^2

[ground]
height = 0.0

[[body]]
name = "ball"
dano = "ball.dano.npz"
pos = [0.0, 0.0, 0.2]
quat = [1.0, 0.0, 0.0, 0.0]
vel = [0.5, 0.0, 0.0]
angvel = [0.0, 0.0, 1.0]

[contact]
impact_spring = 3e4
impact_damper = 3e5
sliding_friction = 0.5
sliding_drag = 0.0
rolling_friction = 0.01
rolling_drag = 0.0
torsional_friction = 0.01
torsional_drag = 0.0

[[pair]]
a = "ball"
b = "ground"
sliding_friction = 0.2
"""


@pytest.fixture(scope="module")
def ball_dir(tmp_path_factory):
    folder = tmp_path_factory.mktemp("scene")
    ball = dano.build_dano(SphereField(0.03), n_points=600, mass=0.2, log2_samples=12, replicates=4)
    dano.save_dano(folder / "ball.dano.npz", ball)
    (folder / "scene.toml").write_text(SCENE)
    return folder


def test_toml_scene_keys_as_documented(ball_dir):
    scene = load_scene(ball_dir / "scene.toml")
    assert scene.timestep == 0.002 and scene.n_steps == 50 and scene.ground_height == 0.0
    (body,) = scene.bodies
    assert body.pos == (0.0, 0.0, 0.2) and body.vel == (0.5, 0.0, 0.0)
    assert float(scene.contact.sliding_friction) == 0.5
    ((names, override),) = scene.pair_contact
    assert names == ("ball", "ground") and float(override.sliding_friction) == 0.2
    assert float(override.impact_spring) == 3e4  # the other keys come from [contact]


@pytest.mark.parametrize(
    "lines, integrator, substeps",
    [("", "implicit", 1), ('integrator = "explicit"', "explicit", 4), ('integrator = "implicit"', "implicit", 1),
     ('integrator = "implicit"\nsubsteps = 3', "implicit", 3),
     ('integrator = "explicit"\nsubsteps = 2', "explicit", 2)],
)  # fmt: skip
def test_toml_substeps_default_to_what_the_integrator_needs(ball_dir, tmp_path, lines, integrator, substeps):
    """The implicit step (the default) runs one step per frame unless the file says otherwise, the
    explicit four; `Scene()` resolves its substeps the same way."""
    (tmp_path / "ball.dano.npz").write_bytes((ball_dir / "ball.dano.npz").read_bytes())
    (tmp_path / "s.toml").write_text(SCENE.replace("[sim]\n", f"[sim]\n{lines}\n", 1))
    scene = load_scene(tmp_path / "s.toml")
    assert (scene.integrator, scene.substeps) == (integrator, substeps)
    assert Scene(integrator=integrator).substeps == DEFAULT_SUBSTEPS[integrator]


@pytest.mark.parametrize(
    "edit, message",
    [
        (("sliding_friction = 0.5", "slidding_friction = 0.5"), "unknown key"),
        (('dano = "ball.dano.npz"', 'dano = "missing.dano.npz"'), "no such file"),
        (("duration = 0.1", "duration = [0.1"), "not valid TOML"),
    ],
)
def test_bad_scene_files_name_the_problem(ball_dir, tmp_path, edit, message):
    (tmp_path / "ball.dano.npz").write_bytes((ball_dir / "ball.dano.npz").read_bytes())
    (tmp_path / "bad.toml").write_text(SCENE.replace(*edit))
    with pytest.raises(SceneError, match=message):
        load_scene(tmp_path / "bad.toml")


def test_simulate_cli_writes_csv_and_gif(ball_dir, tmp_path, capsys):
    out = tmp_path / "traj.csv"
    video, view = str(tmp_path / "v.gif"), str(tmp_path / "v.html")
    assert main(["simulate", str(ball_dir / "scene.toml"), "-o", str(out), "--steps", "30",
                 "--video", video, "--contacts", "--view", view]) == 0  # fmt: skip
    with out.open() as f:
        rows = list(csv.reader(f))
    assert rows[0] == ["t", "body", "x", "y", "z", "qw", "qx", "qy", "qz"]
    assert len(rows) == 1 + 31 and rows[-1][1] == "ball"
    assert float(rows[-1][0]) == pytest.approx(0.06)
    z = [float(r[4]) for r in rows[1:]]
    assert z[-1] < z[0]  # it falls
    assert (tmp_path / "v.gif").stat().st_size > 1000
    assert '"arrows":[' in (tmp_path / "v.html").read_text()  # the view, with its contact forces


def test_two_danos_collide_and_conserve_momentum():
    box = dano.build_dano(BoxField([0.08, 0.08, 0.08], width=0.003), n_points=1500, mass=1.0, log2_samples=12)
    ball = dano.build_dano(SphereField(0.04), n_points=1500, mass=0.4, log2_samples=12)
    bodies = (
        DanoBody("box", box, pos=(0.0, 0.0, 0.0)),
        DanoBody("ball", ball, pos=(-0.2, 0.01, 0.005), vel=(2.0, 0.0, 0.0)),
    )
    sim = Simulation.from_scene(Scene(ground_height=None, gravity=(0, 0, 0), bodies=bodies))
    traj = sim.run(150)
    masses = np.array([1.0, 0.4])
    p0 = masses @ np.asarray(traj.qvel[0]).reshape(2, 6)[:, :3]
    p1 = masses @ np.asarray(traj.qvel[-1]).reshape(2, 6)[:, :3]
    assert float(traj.qvel[-1, 0]) > 0.3  # the box was hit and moves along +x
    assert float(traj.qvel[-1, 6]) < 1.5  # the ball slowed down
    np.testing.assert_allclose(p1, p0, atol=1e-6 * float(np.linalg.norm(p0)))


def test_danos_without_a_field_cannot_touch_each_other(dojo):
    ref = dano.load_reference(dojo / "colliders" / "bunny_collider.npz")
    bodies = (DanoBody("a", ref), DanoBody("b", ref, pos=(2.0, 0, 0)))
    with pytest.raises(SceneError, match="density grid"):
        Simulation.from_scene(Scene(bodies=bodies))


def test_simulate_json_is_one_object_that_matches_the_csv(ball_dir, tmp_path, capsys):
    out = tmp_path / "traj.csv"
    assert main(["simulate", str(ball_dir / "scene.toml"), "-o", str(out), "--steps", "10", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)  # stdout holds the object alone
    with out.open() as f:
        rows = list(csv.reader(f))
    assert summary == {"output": str(out), "frames": 11, "bodies": 1, "video": None}
    assert len(rows) - 1 == summary["frames"] * summary["bodies"]
