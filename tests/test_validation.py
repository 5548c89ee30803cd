"""Every input is checked at the boundary, before any work: one test per class of bad input.

Each bad input gets a named `DanoError` with a one-line message (exit status 2 on the command line)
and leaves earlier output untouched. The property-based versions are in `test_fuzz.py`.
"""

import json
import subprocess
import sys

import numpy as np
import pytest

import dano
from dano.cli import main
from dano.contact import ContactParams
from dano.errors import InvalidValueError, NonFiniteFieldError
from dano.fields import SphereField, as_field
from dano.sim import DanoBody, Primitive, Robot, Scene, SceneError, load_scene
from dano.sim.compile import compile_scene
from dano.sim.world import pair_name, pairs

SCENE = """
[sim]
timestep = 0.002
duration = 0.02

[ground]
height = 0.0

[[body]]
name = "ball"
dano = "ball.dano.npz"
pos = [0.0, 0.0, 0.03]

[[primitive]]
name = "wall"
type = "box"
size = [0.01, 0.1, 0.1]
pos = [0.2, 0.0, 0.1]

[[pair]]
a = "ball"
b = "ground"
sliding_friction = 0.2
"""


@pytest.fixture(scope="module")
def ball():
    return dano.build_dano(SphereField(0.03), n_points=300, mass=0.2, log2_samples=10, replicates=4)


@pytest.fixture(scope="module")
def folder(tmp_path_factory, ball):
    out = tmp_path_factory.mktemp("validation")
    dano.save_dano(out / "ball.dano.npz", ball)
    (out / "scene.toml").write_text(SCENE)
    return out


def _write(folder, text: str):
    path = folder / f"s{abs(hash(text))}.toml"
    path.write_text(text)
    return path


def _one_line_exit_2(capsys, argv: list[str]) -> str:
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("dano ") and "Traceback" not in err
    return err


# --- silently accepted nonsense ----------------------------------------------------------------


def test_a_pair_naming_no_pair_is_refused_and_one_in_the_other_order_is_applied(folder, ball):
    misspelt = _write(folder, SCENE.replace('a = "ball"', 'a = "bal"'))
    with pytest.raises(SceneError, match=r"pair bal/ground is not a contact pair of this scene \(its pairs: "):
        compile_scene(load_scene(misspelt))
    reversed_ = load_scene(_write(folder, SCENE.replace('a = "ball"\nb = "ground"', 'a = "ground"\nb = "ball"')))
    _, world, params, _, _ = compile_scene(reversed_)
    frictions = {
        pair_name(world, p): float(c.sliding_friction) for p, c in zip(pairs(world), params.contact, strict=True)
    }
    assert frictions == {("ball", "ground"): 0.2, ("ball", "wall"): 0.5}  # the user's 0.2 reaches the ground pair
    twice = Scene(bodies=(DanoBody("ball", ball),), pair_contact=((("ball", "ground"), ContactParams()),) * 2)
    with pytest.raises(SceneError, match="more than once"):
        compile_scene(twice)


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (("sliding_friction = 0.2", "sliding_friction = -0.2"), "sliding_friction must be finite and >= 0, got -0.2"),
        (("sliding_friction = 0.2", "sliding_friction = nan"), "sliding_friction must be finite"),
        (("sliding_friction = 0.2", "impact_spring = -3e4"), "impact_spring must be finite and >= 0"),
        (("duration = 0.02", 'duration = 0.02\nforce_mode = "pointz"'), "force_mode must be one of 'points'"),
        (("pos = [0.2, 0.0, 0.1]", 'pos = [0.2, 0.0, 0.1]\nmode = "flying"'), "mode must be one of 'static'"),
    ],
)
def test_nonsense_values_are_refused(folder, edit, message):
    with pytest.raises(SceneError, match=message.replace("(", r"\(").replace(")", r"\)")):
        load_scene(_write(folder, SCENE.replace(*edit)))


def test_a_body_started_inside_the_ground_or_too_fast_is_refused(ball):
    depth = 0.01  # the ball's surface points reach 3 cm below its centre
    with pytest.raises(SceneError, match=r"'ball' starts 10.\d* mm inside the ground .* at least 0.03\d* m above"):
        compile_scene(Scene(bodies=(DanoBody("ball", ball, pos=(0, 0, 0.03 - depth)),)), check_start=True)
    compile_scene(Scene(bodies=(DanoBody("ball", ball, pos=(0, 0, 0.0295)),)), check_start=True)  # resting depth: fine
    with pytest.raises(SceneError, match="starts at 500 m/s, moving 1 m per step"):
        compile_scene(Scene(bodies=(DanoBody("ball", ball, pos=(0, 0, 1), vel=(500, 0, 0)),)), check_start=True)
    with pytest.raises(SceneError, match="spinning at 1000 rad/s"):
        compile_scene(Scene(bodies=(DanoBody("ball", ball, pos=(0, 0, 1), angvel=(0, 0, 1000)),)), check_start=True)


def test_an_inertia_that_is_not_positive_definite_is_refused(tmp_path, ball, capsys):
    import equinox as eqx

    negated = eqx.tree_at(lambda d: d.inertia, ball, -ball.inertia)  # tree_at bypasses the DANO's own check
    with pytest.raises(SceneError, match="inertia is not positive definite"):
        DanoBody("ball", negated)
    with pytest.raises(InvalidValueError, match="DANO.inertia is not positive definite"):
        type(ball)(**{**{f: getattr(ball, f) for f in ball.__dataclass_fields__}, "inertia": -ball.inertia})
    arrays = dict(np.load(_saved(tmp_path, ball)))
    arrays["inertia"] = np.diag([1.0, 1.0, -1.0]) * 1e-4
    np.savez(tmp_path / "bad.dano.npz", **arrays)
    err = _one_line_exit_2(capsys, ["info", str(tmp_path / "bad.dano.npz")])
    assert "DanoFileError" in err and "not positive definite" in err


def _saved(tmp_path, obj):
    dano.save_dano(tmp_path / "good.dano.npz", obj)
    return tmp_path / "good.dano.npz"


# --- tracebacks that are now named errors ------------------------------------------------------


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (("timestep = 0.002", "timestep = 0"), "timestep must be > 0, got 0"),
        (("timestep = 0.002", "timestep = -0.002"), "timestep must be > 0"),
        (("timestep = 0.002", 'timestep = "fast"'), "timestep must be a number, got 'fast'"),
        (("duration = 0.02", "duration = 0.02\nsubsteps = 0"), "substeps must be a whole number >= 1"),
        (("duration = 0.02", "duration = -1"), "duration must be > 0"),
        (("pos = [0.0, 0.0, 0.03]", "pos = [0.0, 0.03]"), "pos must be 3 numbers, got 2"),
        (("duration = 0.02", "duration = 0.02\ngravity = [0, -9.81]"), "gravity must be 3 numbers, got 2"),
        (('name = "wall"', 'name = "ball"'), r"\['ball'\] appear more than once"),
        (('name = "wall"', 'name = "ground"'), "'ground' names the ground"),
        (("[[body]]", "[[bodies]]"), "unknown table"),
        (("size = [0.01, 0.1, 0.1]", "size = [0.01, 0.1, 0.1]\nmass = -1"), "mass must be > 0"),
        (("size = [0.01, 0.1, 0.1]", "size = [0.01, 0.0, 0.1]"), "size hy must be > 0"),
        (("size = [0.01, 0.1, 0.1]", "size = [0.01, 0.1]"), r"size \(hx, hy, hz\) must be 3 numbers"),
        (('type = "box"', 'type = "cone"'), "type must be one of 'sphere', 'capsule', 'box'"),
        (('name = "wall"\n', ""), r"\[\[primitive\]\] #1 needs 'name'"),
        (("quat = [1.0, 0.0, 0.0, 0.0]", ""), ""),  # (absent key: the default; not an error)
    ],
)
def test_bad_scene_values_are_named_one_line_errors_before_any_work(folder, tmp_path, capsys, edit, message):
    text = SCENE.replace(*edit)
    if not message:
        load_scene(_write(folder, text))
        return
    csv = tmp_path / "traj.csv"
    csv.write_text("earlier output\n")
    err = _one_line_exit_2(capsys, ["simulate", str(_write(folder, text)), "-o", str(csv)])
    assert "SceneError" in err and ".toml" in err
    assert message == "" or __import__("re").search(message, err), err
    assert csv.read_text() == "earlier output\n"


def test_a_scene_with_no_bodies_is_refused(folder):
    start, end = SCENE.index("[[body]]"), SCENE.index("[[primitive]]")
    with pytest.raises(SceneError, match="no \\[\\[body\\]\\]: a scene needs at least one DANO"):
        load_scene(_write(folder, SCENE[:start] + SCENE[end:].replace('a = "ball"', 'a = "x"')))


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["simulate", "S", "-o", "O.csv", "--steps", "-1"], "argument --steps: must be a whole number >= 1, got -1"),
        (
            ["build", "sphere:r=0.05", "-o", "O.dano.npz", "--seed", "-1"],
            "argument --seed: must be a whole number >= 0",
        ),
        (["trajopt", "push", "--dt", "0"], "argument --dt: must be > 0, got 0"),
        (
            ["track", "V", "--field", "F", "--camera", "C", "--masks", "M", "-o", "O.csv", "--fps", "0"],
            "--fps: must be > 0",
        ),
        (
            ["track", "V", "--field", "F", "--camera", "C", "--masks", "M", "-o", "O.csv", "--init", "a,b,c"],
            "--init: takes 7 comma-separated numbers",
        ),
        (
            ["track", "V", "--field", "F", "--camera", "C", "--masks", "M", "-o", "O.csv", "--init", "0,0,0,0,0,0,0"],
            "the quaternion of '0,0,0,0,0,0,0' is zero",
        ),
        (["render-views", "M.ply", "-o", "OUT", "--views", "0"], "argument --views: must be a whole number >= 1"),
        (["build", "sphere:r=0.05", "-o", "O.dano.npz", "--points", "0"], "argument --points: must be a whole number"),
        (["build", "sphere:r=0.05", "-o", "O.dano.npz", "--scale", "-2"], "argument --scale: must be > 0, got -2"),
        (
            ["sysid", "S", "--traj", "T", "--fit", "friction", "--sigma", "0"],
            "argument --sigma: must be > 0",
        ),
        (["simulate", "S", "-o", "O.csv", "--video", "O.avi"], "argument --video: 'O.avi' must end with .mp4 or .gif"),
        (["simulate", "S", "-o", "missing/O.csv"], "folder 'missing' of 'missing/O.csv' does not exist"),
        (["simulate", "S", "-o", "."], "'.' is a folder; give a file name"),
        (
            ["simulate", "S", "-o", "O.csv", "--contacts"],
            "--contacts draws the contact forces in the video or the view",
        ),
        (["build", "sphere:r=0.05", "-o", "O.dano.npz", "--mass", "nan"], "argument --mass: must be finite"),
    ],
)
def test_bad_command_line_values_are_one_line_usage_errors(tmp_path, monkeypatch, capsys, argv, message):
    monkeypatch.chdir(tmp_path)
    err = _one_line_exit_2(capsys, argv)
    assert "UsageError" in err and message in err, err
    assert list(tmp_path.iterdir()) == []  # nothing written


def test_negative_comma_values_need_no_equals_sign(capsys):
    err = _one_line_exit_2(capsys, ["sysid", "S", "--traj", "T", "--fit", "friction",
                                    "--gravity", "-0.27,-0.27,-0.92", "--sigma", "-1"])  # fmt: skip
    assert "argument --sigma" in err  # --gravity itself parsed


URDF = """<robot name="r"><link name="base"><collision><geometry><mesh filename="{mesh}"/></geometry></collision>
<inertial><mass value="1"/><inertia ixx="1" iyy="1" izz="1" ixy="0" ixz="0" iyz="0"/></inertial></link></robot>"""


@pytest.mark.parametrize(
    ("mesh", "message"),
    [
        ("meshes/missing.stl", r"mesh file .*missing.stl not found"),
        ("package://mypkg/meshes/base.stl", r"uses package\(s\) \['mypkg'\] that package_dirs does not give"),
    ],
)
def test_robot_files_with_missing_meshes_name_them(tmp_path, ball, mesh, message):
    (tmp_path / "r.urdf").write_text(URDF.format(mesh=mesh))
    scene = Scene(bodies=(DanoBody("ball", ball, pos=(0, 0, 1)),), robot=Robot(str(tmp_path / "r.urdf")))
    with pytest.raises(SceneError, match=message):
        compile_scene(scene)


# --- the right cause named ---------------------------------------------------------------------


def test_each_non_physical_input_names_its_own_cause(ball):
    with pytest.raises(InvalidValueError, match="impact_spring must be finite and >= 0, got -1"):
        ContactParams(impact_spring=-1.0)
    with pytest.raises(InvalidValueError, match="sliding_friction must be finite"):
        ContactParams(sliding_friction=float("nan"))
    with pytest.raises(SceneError, match="quat must not be all zeros"):
        DanoBody("ball", ball, quat=(0, 0, 0, 0))
    with pytest.raises(SceneError, match="5\\d.\\d* mm inside the ground"):
        compile_scene(Scene(bodies=(DanoBody("ball", ball, pos=(0, 0, -0.02)),)), check_start=True)
    with pytest.raises(SceneError, match="primitive 'p': mass must be > 0"):
        Primitive("p", "sphere", (0.1,), mode="free", mass=0.0)
    with pytest.raises(SceneError, match="timestep must be > 0"):
        Scene(timestep=0)


def test_a_field_nan_in_part_of_its_box_is_named_non_finite_not_empty():
    import jax.numpy as jnp

    def density(x):
        inside = jnp.where(jnp.linalg.norm(x, axis=1) < 0.08, 1000.0, 0.0)
        return jnp.where(x[:, 0] > 0.05, jnp.nan, inside)

    field = as_field(density, bounds=((-0.1, -0.1, -0.1), (0.1, 0.1, 0.1)))
    with pytest.raises(NonFiniteFieldError, match="NaN or Inf"):
        dano.mass_properties(field, mass=1.0)


# --- output that tools can parse ---------------------------------------------------------------


def test_json_output_is_the_only_thing_on_stdout(folder):
    out = subprocess.run([sys.executable, "-m", "dano.cli", "info", str(folder / "ball.dano.npz"), "--json"],
                         capture_output=True, text=True, check=True)  # fmt: skip
    assert json.loads(out.stdout)["n_points"] == 300


def test_a_blow_up_names_the_body_and_the_step(ball):
    """With the inputs checked up front, what is left to blame is the step: the report names the
    frame, the body whose speed ran away, and the step (a NaN planted in a real trajectory)."""
    import equinox as eqx
    import jax.numpy as jnp

    from dano.sim.run import Simulation, SimulationError, check_trajectory

    sim = Simulation.from_scene(Scene(bodies=(DanoBody("ball", ball, pos=(0, 0, 1)),)))
    traj = sim.run(3)
    broken = eqx.tree_at(lambda t: t.qvel, traj, jnp.asarray(traj.qvel).at[2, 4].set(jnp.nan))
    with pytest.raises(SimulationError, match=r"frame 2 \(t = 0.004 s\): body 'ball' reached inf .* step of 0.002 s"):
        check_trajectory(broken, sim.scene, sim.world)


def test_identification_guesses_and_bounds_accept_aliases_and_refuse_what_is_not_fitted():
    from dano.sysid.configs import SysidError
    from dano.sysid.solve import by_canonical_name, resolve_bounds

    names = ("sliding_friction", "mass_scale")
    assert by_canonical_name({"friction": 0.2, "alpha": 2.0}, names, "init") == {"sliding_friction": 0.2,
                                                                                 "mass_scale": 2.0}  # fmt: skip
    with pytest.raises(SysidError, match="init names 'rolling_friction', which is not fitted"):
        by_canonical_name({"rolling_friction": 0.1}, names, "init")
    with pytest.raises(SysidError, match="twice"):
        by_canonical_name({"friction": 0.1, "mu": 0.2}, names, "init")
    with pytest.raises(SysidError, match="unknown parameter 'frcition'"):
        by_canonical_name({"frcition": 0.1}, names, "init")
    lo, hi = resolve_bounds(names, {"mu": (0.1, 0.4)})
    assert (lo[0], hi[0]) == (0.1, 0.4)


def test_a_track_stored_one_row_per_coordinate_is_read_as_its_transpose(tmp_path):
    from dano.sysid.data import TrackFileError, read_tracks

    t = np.arange(5) * 0.01
    rows = {"t": t, "x": 0.1 * t, "y": 0 * t, "z": 0 * t + 0.02, "qw": 1 + 0 * t, "qx": 0 * t, "qy": 0 * t, "qz": 0 * t}
    by_frame = tmp_path / "frames.csv"
    by_frame.write_text(",".join(rows) + "\n" + "".join(",".join(f"{v[k]:g}" for v in rows.values()) + "\n"
                                                       for k in range(5)))  # fmt: skip
    by_coordinate = tmp_path / "coordinates.csv"
    by_coordinate.write_text("".join(f"{name}," + ",".join(f"{x:g}" for x in v) + "\n" for name, v in rows.items()))
    a, b = read_tracks(by_frame)[""], read_tracks(by_coordinate)[""]
    np.testing.assert_array_equal(a.pos, b.pos)
    np.testing.assert_array_equal(a.t, b.t)
    numbers_only = tmp_path / "numbers.csv"
    numbers_only.write_text("".join(",".join(f"{x:g}" for x in v) + "\n" for v in rows.values()))
    with pytest.raises(TrackFileError, match="line 1: numbers, not column names"):
        read_tracks(numbers_only)


def test_render_views_into_an_existing_folder_names_the_command_line_option(tmp_path, capsys):
    import trimesh

    trimesh.creation.box(extents=(0.1, 0.1, 0.1)).export(tmp_path / "box.ply")
    (tmp_path / "views").mkdir()
    (tmp_path / "views" / "keep.txt").write_text("earlier output")
    err = _one_line_exit_2(capsys, ["render-views", str(tmp_path / "box.ply"), "-o", str(tmp_path / "views"),
                                    "--views", "2"])  # fmt: skip
    assert "already exists (--overwrite" in err
    assert (tmp_path / "views" / "keep.txt").read_text() == "earlier output"
