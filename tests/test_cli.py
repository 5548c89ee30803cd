import json
import subprocess
import sys

import numpy as np
import pytest

from dano.cli import main


def test_build_then_info_json(tmp_path, capsys):
    out = tmp_path / "box.dano.npz"
    assert main(["build", "box:size=0.1,0.06,0.03", "-o", str(out), "--points", "800", "--mass", "0.2"]) == 0
    capsys.readouterr()
    assert main(["info", str(out), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert {"mass", "com", "inertia", "n_points"} <= set(info)
    assert info["mass"] == pytest.approx(0.2) and info["n_points"] == 800
    a, b, c = 0.1, 0.06, 0.03  # soft edges are 5 % of the smallest half-size: close to the solid box
    solid = 0.2 / 12 * np.array([b * b + c * c, a * a + c * c, a * a + b * b])
    np.testing.assert_allclose(np.diag(info["inertia"]), solid, rtol=0.02)
    assert main(["info", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "principal moments" in printed and "principal extents" in printed
    np.testing.assert_allclose(sorted(info["principal_extents"]), [0.03, 0.06, 0.1], rtol=0.03)


def test_scale_multiplies_lengths(tmp_path, capsys):
    small, big = tmp_path / "s.dano.npz", tmp_path / "b.dano.npz"
    main(["build", "sphere:r=1", "-o", str(small), "--points", "200", "--mass", "1"])
    main(["build", "sphere:r=1", "-o", str(big), "--points", "200", "--mass", "1", "--scale", "0.1"])
    capsys.readouterr()
    main(["info", str(small), "--json"])
    i_small = json.loads(capsys.readouterr().out)["inertia"][0][0]
    main(["info", str(big), "--json"])
    i_big = json.loads(capsys.readouterr().out)["inertia"][0][0]
    assert i_big == pytest.approx(0.01 * i_small, rel=1e-3)  # same mass, lengths x0.1: inertia x0.01


def test_errors_are_one_line_and_exit_2(tmp_path, capsys):
    import trimesh

    box = trimesh.creation.box()
    trimesh.Trimesh(box.vertices, box.faces[:-2]).export(tmp_path / "open.stl")
    assert main(["build", str(tmp_path / "open.stl"), "-o", str(tmp_path / "x.dano.npz")]) == 2
    err = capsys.readouterr().err.strip()
    assert "MeshNotWatertightError" in err and "--repair" in err and "\n" not in err
    assert main(["build", "sphere:r=0.05", "-o", str(tmp_path / "x.dano.npz"), "--window", "5000,6000"]) == 2
    assert "EmptyWindowError" in capsys.readouterr().err
    assert main(["info", str(tmp_path / "nothing.dano.npz")]) == 2
    assert "no such file" in capsys.readouterr().err
    assert main(["build", "sphere:r=0.05", "-o", str(tmp_path / "x.dano.npz"), "--mass", "-1"]) == 2
    err = capsys.readouterr().err.strip()
    assert "UsageError: argument --mass: must be > 0, got -1" in err and "\n" not in err
    assert not (tmp_path / "x.dano.npz").exists()


def test_repair_builds_a_watertight_dano(tmp_path, capsys):
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.05)
    trimesh.Trimesh(sphere.vertices, sphere.faces[:-3]).export(tmp_path / "holey.ply")
    out = tmp_path / "s.dano.npz"
    assert (
        main(
            ["build", str(tmp_path / "holey.ply"), "-o", str(out), "--repair", "--points", "500", "--resolution", "40"]
        )
        == 0
    )
    capsys.readouterr()
    main(["info", str(out), "--json"])
    info = json.loads(capsys.readouterr().out)
    assert info["mass"] == pytest.approx(1000 * sphere.volume, rel=0.03)


def test_reference_collider_source(dojo, tmp_path, capsys):
    out = tmp_path / "bunny.dano.npz"
    assert main(["build", str(dojo / "colliders" / "bunny_collider.npz"), "-o", str(out)]) == 0
    capsys.readouterr()
    main(["info", str(out), "--json"])
    info = json.loads(capsys.readouterr().out)
    assert info["mass"] == pytest.approx(3.21985, rel=1e-5) and info["n_points"] == 5000


def test_console_script_runs():
    done = subprocess.run([sys.executable, "-m", "dano.cli", "--help"], capture_output=True, text=True, check=True)
    assert "build" in done.stdout and "demo" in done.stdout


def test_warnings_print_as_one_line_and_leave_the_filters_alone(monkeypatch, capsys, tmp_path):
    import warnings

    from dano.sysid.frames import UnitsWarning

    def warns(args):
        warnings.warn("the DANO 'soap' is 90 m long", UnitsWarning, stacklevel=2)

    monkeypatch.setattr("dano.cli.objects._info", warns)
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        before = warnings.showwarning
        assert main(["info", str(tmp_path / "any.dano.npz")]) == 0
        assert warnings.showwarning is before
    assert capsys.readouterr().err == "dano info: UnitsWarning: the DANO 'soap' is 90 m long\n"


def test_build_json_is_what_info_reads_back(tmp_path, capsys):
    out = tmp_path / "ball.dano.npz"
    assert main(["build", "sphere:r=0.05", "-o", str(out), "--points", "300", "--mass", "0.3", "--json"]) == 0
    built = json.loads(capsys.readouterr().out)
    assert main(["info", str(out), "--json"]) == 0
    assert built == {"output": str(out), **json.loads(capsys.readouterr().out)}
    assert built["mass"] == pytest.approx(0.3) and built["n_points"] == 300


@pytest.mark.parametrize(
    ("old", "new", "dest", "value"),
    [
        (["sysid", "--scene", "s.toml"], ["sysid", "s.toml"], "scene", "s.toml"),
        (["sysid", "s.toml", "--max-steps", "7"], ["sysid", "s.toml", "--max-iterations", "7"], "config_max_steps", 7),
        (["sysid", "s.toml", "--window", "5"], ["sysid", "s.toml", "--window-frames", "5"], "config_window", 5),
        (["render-views", "m.ply", "-o", "d", "--resolution", "32"],
         ["render-views", "m.ply", "-o", "d", "--image-size", "32"], "resolution", 32),
        (["track", "v", "--field", "f", "--camera", "c", "--masks", "m", "-o", "t.csv", "--iterations", "9"],
         ["track", "v", "--field", "f", "--camera", "c", "--masks", "m", "-o", "t.csv", "--steps", "9"],
         "config_iterations", 9),
        (["demo", "--out", "x"], ["demo", "-o", "x"], "out", "x"),
        (["trajopt", "push", "--goal", "0.1", "-0.05"], ["trajopt", "push", "--goal", "0.1,-0.05"],
         "goal", (0.1, -0.05)),
    ],
)  # fmt: skip
def test_one_word_per_concept_and_the_old_spellings_still_parse_with_a_note(monkeypatch, capsys, old, new, dest, value):
    """Renamed options (`dano.cli.RENAMED`) parse to the same value as their new names, and the old
    spelling prints a one-line note naming the new one."""
    from dano import cli
    from dano.cli.arguments import _vector

    parsed = []
    real = cli.parser

    def stub():
        p = real()
        sub = next(a for a in p._actions if isinstance(a, cli.argparse._SubParsersAction))
        for action in sub.choices.values():
            action.set_defaults(run=parsed.append)
        return p

    monkeypatch.setattr(cli, "parser", stub)
    fit = ["--fit", "friction"] if old[0] == "sysid" else []
    for argv in (new, old):
        assert main(argv + fit) == 0
    resolve = {
        "scene": lambda a: a.scene or a.scene_option,
        "goal": lambda a: _vector(a.goal, 2, "--goal", "X,Y"),
    }.get(dest, lambda a: getattr(a, dest))
    assert resolve(parsed[0]) == resolve(parsed[1]) == value
    err = capsys.readouterr().err
    if dest == "goal":  # a vector may be written X,Y or X Y: neither is old
        assert err == ""
    else:
        assert err.count("\n") == 1 and f"{old[-2]} is now" in err, err


@pytest.mark.parametrize("command,configs", [("track", ["TrackConfig"]), ("fit-field", ["FitConfig", "GridModel"])])
def test_a_commands_solver_options_are_generated_from_its_config(monkeypatch, capsys, command, configs):
    """Every number, switch and choice of the solver's settings is an option (its help the field's
    docstring, its default the library's); a value given reaches the config, the others keep the
    library's defaults; a value the config refuses is one line naming the field."""
    import dataclasses

    from dano import cli
    from dano.cli.configs import field_help, from_args
    from dano.vision import configs as C

    p = cli.parser()
    sub = next(a for a in p._actions if isinstance(a, cli.argparse._SubParsersAction)).choices[command]
    dests = {a.dest for a in sub._actions}
    for name in configs:
        cls = getattr(C, name)
        helps = field_help(cls)
        for field in dataclasses.fields(cls):
            if field.name == "model":  # the back-end: its own config's options (GridModel)
                continue
            assert "config_" + field.name in dests, (name, field.name)
            assert helps[field.name], (name, field.name)  # every field documented
    positional = {
        "track": ["v", "--field", "f", "--camera", "c", "--masks", "m", "-o", "t.csv"],
        "fit-field": ["d", "-o", "x.npz"],
    }
    args = sub.parse_args([*positional[command], "--learning-rate", "0.5", "--samples", "17"])
    cls = C.TrackConfig if command == "track" else C.FitConfig
    config = from_args(cls, args)
    assert config.learning_rate == 0.5 and config.n_samples == 17
    default = cls()
    for field in dataclasses.fields(cls):
        if field.name not in ("learning_rate", "n_samples"):
            assert getattr(config, field.name) == getattr(default, field.name)
    bad = sub.parse_args([*positional[command], "--learning-rate", "-1"])
    error = C.TrackError if command == "track" else C.FitError
    with pytest.raises(error, match="^learning_rate must be > 0"):
        from_args(cls, bad)


def test_sysid_options_are_generated_from_its_config():
    """`dano sysid`: every field of `SysidConfig` but the three with their own syntax (`--fit`,
    `--init`, `--bounds`) is an option documented by the field; given values reach the config, the
    others keep the library's defaults but the command's own, `interval` (shown in its help); a
    value the config refuses names the field."""
    import dataclasses

    from dano import cli
    from dano.cli.configs import field_help, from_args
    from dano.sysid.configs import Interval, SysidConfig, SysidError

    p = cli.parser()
    sub = next(a for a in p._actions if isinstance(a, cli.argparse._SubParsersAction)).choices["sysid"]
    dests = {a.dest for a in sub._actions}
    helps = field_help(SysidConfig)
    own = {"fit", "init", "bounds"}
    for field in dataclasses.fields(SysidConfig):
        assert helps[field.name], field.name
        assert ("config_" + field.name in dests) is (field.name not in own), field.name
    given = ["--sigma", "0.002", "--loss", "huber", "--gravity", "0,0,-1", "--frames", "3:9", "--max-steps", "7"]
    args = sub.parse_args(["s.toml", "--fit", "friction", *given])
    config = from_args(SysidConfig, args, fit=("friction",))
    assert config.sigma == 0.002 and config.loss == "huber" and config.max_steps == 7
    assert tuple(config.gravity or ()) == (0.0, 0.0, -1.0) and config.frames == (3, 9)
    assert config.interval is Interval.profile and "(default profile)" in " ".join(sub.format_help().split())
    default = SysidConfig(fit=("friction",))
    for field in dataclasses.fields(SysidConfig):
        if field.name not in {"sigma", "loss", "max_steps", "gravity", "frames", "interval"}:
            assert getattr(config, field.name) == getattr(default, field.name), field.name
    with pytest.raises(SysidError, match="^max_steps must be"):
        SysidConfig(fit=("friction",), max_steps=0)
    with pytest.raises(SysidError, match="^level must be between 0 and 1"):
        SysidConfig(fit=("friction",), level=1.5)


def test_string_options_are_enumerations_that_take_their_values():
    """A mode given as its value is stored as the enumeration's member; a wrong one is refused with
    the choices it takes."""
    from dano.contact.pairs import ForceMode
    from dano.sim.scene import Integrator, Mode, Primitive, Scene, SceneError
    from dano.sysid.configs import Interval, SysidConfig, SysidError

    scene = Scene(force_mode="centroid", integrator="explicit")
    assert scene.force_mode is ForceMode.centroid and scene.integrator is Integrator.explicit and scene.substeps == 4
    assert Primitive("p", "sphere", (0.1,), mode="free").mode is Mode.free
    config = SysidConfig(fit=("friction",), interval="profile", initial="state")
    assert config.interval is Interval.profile and config.initial == "state"
    with pytest.raises(SceneError, match="^integrator must be one of 'implicit', 'explicit'; got 'centroid'"):
        Scene(integrator="centroid")
    with pytest.raises(SysidError, match="^loss must be one of 'l2', 'huber', 'cauchy'; got 'L1'"):
        SysidConfig(fit=("friction",), loss="L1")
