"""Property-based tests of the input boundary (hypothesis): for any mutated scene file, pose CSV,
`.dano.npz` or command line, the result is either success or a `DanoError` with a one-line
message: never a traceback, never a clobbered earlier output.

Examples are bounded (`max_examples`) and derandomised, so CI runs the same cases every time.
"""

import argparse
import copy
import io
import math
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import dano
from dano.cli import main, parser
from dano.errors import DanoError
from dano.fields import SphereField
from dano.sim import load_scene
from dano.sim.compile import compile_scene
from dano.sim.toml import _SCHEMA
from dano.sysid.data import read_tracks

PARSER = parser  # the real one: each command-line example patches `dano.cli.parser` to a stub around it
FUZZ = settings(
    max_examples=120, derandomize=True, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)

BASE = {
    "sim": {"timestep": 0.002, "duration": 0.02, "gravity": [0.0, 0.0, -9.81], "integrator": "implicit"},
    "ground": {"height": 0.0, "normal": [0.0, 0.0, 1.0]},
    "contact": {"sliding_friction": 0.5, "impact_spring": 3e4},
    "body": [{"name": "ball", "dano": "ball.dano.npz", "pos": [0.0, 0.0, 0.05], "quat": [1.0, 0.0, 0.0, 0.0]}],
    "primitive": [{"name": "wall", "type": "box", "size": [0.01, 0.1, 0.1], "pos": [0.3, 0.0, 0.1], "mode": "static"}],
    "pair": [{"a": "ball", "b": "ground", "sliding_friction": 0.2}],
}


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v == math.inf else "-inf" if v == -math.inf else repr(v))
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f'"{k}" = {_toml_value(x)}' for k, x in v.items()) + "}"
    raise TypeError(type(v))


def to_toml(doc: dict) -> str:
    out = io.StringIO()
    for key, value in doc.items():
        if isinstance(value, list) and value and all(isinstance(t, dict) for t in value):
            for table in value:
                out.write(f"[[{key}]]\n" + "".join(f'"{k}" = {_toml_value(v)}\n' for k, v in table.items()) + "\n")
        elif isinstance(value, dict):
            out.write(f"[{key}]\n" + "".join(f'"{k}" = {_toml_value(v)}\n' for k, v in value.items()) + "\n")
        else:
            out.write(f'"{key}" = {_toml_value(value)}\n')
    return out.getvalue()


scalars = st.one_of(
    st.integers(-5, 5),
    st.floats(allow_nan=True, allow_infinity=True, width=64),
    st.sampled_from([0.0, -1.0, 1e-12, 1e12, 0.002, 2.0]),
    st.text(max_size=6),
    st.sampled_from(["ball", "ground", "wall", "box", "sphere", "capsule", "free", "mocap", "explicit", "points"]),
    st.booleans(),
)
values = st.one_of(scalars, st.lists(scalars, max_size=5), st.dictionaries(st.text(max_size=4), scalars, max_size=2))


@st.composite
def mutated_scenes(draw) -> dict:
    doc = copy.deepcopy(BASE)
    for _ in range(draw(st.integers(1, 3))):
        table = draw(st.sampled_from(sorted(doc)))
        items = doc[table]
        target = items[draw(st.integers(0, len(items) - 1))] if isinstance(items, list) and items else items
        action = draw(st.sampled_from(["set", "set", "set", "delete", "drop_table", "whole"]))
        if action == "set" and isinstance(target, dict):
            target[draw(st.sampled_from([*sorted(_SCHEMA[table]), "unknown"]))] = draw(values)
        elif action == "delete" and isinstance(target, dict) and target:
            target.pop(draw(st.sampled_from(sorted(target))))
        elif action == "drop_table":
            doc.pop(table)
        else:
            doc[table] = draw(values)
        if not doc:
            break
    return doc


@pytest.fixture(scope="module")
def ball_file(tmp_path_factory):
    folder = tmp_path_factory.mktemp("fuzz")
    obj = dano.build_dano(SphereField(0.03), n_points=200, mass=0.2, log2_samples=10, replicates=4)
    dano.save_dano(folder / "ball.dano.npz", obj)
    return folder / "ball.dano.npz"


def _one_line(e: DanoError) -> None:
    message = str(e)
    assert message and "\n" not in message and "Traceback" not in message, message


def _load_and_compile(ball_file: Path, content: bytes, strict: bool = False) -> None:
    """Writes `content` as a scene beside the ball's DANO, loads and compiles it: success, or a
    one-line `DanoError` (re-raised when `strict`)."""
    with tempfile.TemporaryDirectory() as folder:
        (Path(folder) / "ball.dano.npz").write_bytes(ball_file.read_bytes())
        path = Path(folder) / "s.toml"
        path.write_bytes(content)
        try:
            compile_scene(load_scene(path))
        except DanoError as e:
            if strict:
                raise
            _one_line(e)


def test_the_unmutated_scene_loads_and_compiles(ball_file):
    _load_and_compile(ball_file, to_toml(BASE).encode(), strict=True)


@FUZZ
@given(doc=mutated_scenes())
def test_any_mutated_scene_loads_and_compiles_or_names_its_error(ball_file, doc):
    _load_and_compile(ball_file, to_toml(doc).encode())


@FUZZ
@given(data=st.data())
def test_any_byte_edit_of_a_scene_file_loads_or_names_its_error(ball_file, data):
    text = bytearray(to_toml(BASE).encode())
    for _ in range(data.draw(st.integers(1, 4))):
        i = data.draw(st.integers(0, len(text) - 1))
        text[i] = data.draw(st.sampled_from(list(b"-0.9e[]{}=\"'#\n ,xnaifT\x00\xff")))
    _load_and_compile(ball_file, bytes(text))


CSV = "t,x,y,z,qw,qx,qy,qz\n" + "".join(f"{k * 0.01:.2f},{k * 0.001:.4f},0,0.02,1,0,0,0\n" for k in range(6))
cells = st.one_of(
    st.sampled_from(["", "nan", "inf", "-1", "0", "1e308", "abc", "1,2", '"', "body", "t", "0.01"]),
    st.floats(allow_nan=True, allow_infinity=True).map(str),
)


@FUZZ
@given(data=st.data())
def test_any_mutated_pose_csv_reads_or_names_its_line(data):
    rows = [line.split(",") for line in CSV.strip().split("\n")]
    for _ in range(data.draw(st.integers(1, 4))):
        r = data.draw(st.integers(0, len(rows) - 1))
        action = data.draw(st.sampled_from(["cell", "cell", "drop_row", "drop_cell", "dup_row"]))
        if action == "cell":
            rows[r][data.draw(st.integers(0, len(rows[r]) - 1))] = data.draw(cells)
        elif action == "drop_row" and len(rows) > 1:
            rows.pop(r)
        elif action == "drop_cell" and len(rows[r]) > 1:
            rows[r].pop()
        else:
            rows.insert(r, list(rows[r]))
    fps = data.draw(st.one_of(st.none(), st.sampled_from([0.0, -30.0, 30.0, math.nan])))
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "track.csv"
        path.write_text("\n".join(",".join(r) for r in rows) + "\n")
        try:
            tracks = read_tracks(path, fps=fps)
        except DanoError as e:
            _one_line(e)
        else:
            for track in tracks.values():
                assert np.all(np.isfinite(track.pos)) and np.allclose(np.linalg.norm(track.quat, axis=1), 1.0)


@settings(max_examples=40, derandomize=True, deadline=None)
@given(data=st.data())
def test_any_corrupted_dano_file_is_read_or_refused(ball_file, data):
    arrays = dict(np.load(ball_file))
    name = data.draw(st.sampled_from(sorted(arrays)))
    kind = data.draw(st.sampled_from(["nan", "negate", "shape", "drop", "string"]))
    if kind == "nan" and arrays[name].dtype.kind == "f":
        arrays[name] = np.full_like(arrays[name], np.nan)
    elif kind == "negate" and arrays[name].dtype.kind == "f":
        arrays[name] = -arrays[name]
    elif kind == "shape":
        arrays[name] = np.zeros((2, 2))
    elif kind == "drop":
        arrays.pop(name)
    else:
        arrays[name] = np.asarray("x")
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "bad.dano.npz"
        np.savez(path, **arrays)
        try:
            dano.load_dano(path)
        except DanoError as e:
            _one_line(e)


OPTIONS = {
    "build": ["--points", "--mass", "--alpha", "--scale", "--seed", "--window", "--resolution", "-o"],
    "simulate": ["--steps", "--video", "-o"],
    "sysid": ["--fps", "--scale", "--size", "--gravity", "--window", "--sigma", "--init", "--bounds", "--max-steps",
              "--fit", "--scene", "--traj", "--plot"],
    "trajopt": ["--horizon", "--dt", "--friction", "--max-iterations", "--goal", "--video", "--robot"],
    "track": ["--fps", "--scale", "--init", "--iterations", "--refine", "-o", "--field", "--camera", "--masks"],
    "render-views": ["--views", "--resolution", "--scale", "--seed", "-o"],
    "fit-field": ["--steps", "--resolution", "--samples", "--downscale", "--seed", "-o", "--raw"],
    "compare": ["--resolution", "--threshold", "--max-hulls", "--max-faces", "--points", "--friction", "--levels"],
}  # fmt: skip
tokens = st.one_of(
    st.sampled_from(["0", "-1", "1", "2.5", "nan", "inf", "-0.3,-0.3,-0.9", "a,b,c", "x.avi", "out.csv", "/",
                     "missing/x.csv", "friction", "friction=0.3", "mu=a:b", "1e999", "", "--", "-"]),
    st.text(max_size=5),
)  # fmt: skip


@FUZZ
@given(data=st.data())
def test_any_command_line_parses_or_is_a_one_line_usage_error(data, tmp_path):
    """Every subcommand's options with random values; the subcommand's work is replaced by a check
    that the parsed values are what the validators promise, so only the boundary is under test."""
    from dano import cli

    command = data.draw(st.sampled_from(sorted(OPTIONS)))
    argv = (
        [command, "SOURCE"]
        if command in ("build", "simulate", "track", "render-views", "fit-field", "compare")
        else [command]
    )  # noqa: E501
    if command == "trajopt":
        argv.append("push")
    for _ in range(data.draw(st.integers(0, 4))):
        argv += [data.draw(st.sampled_from(OPTIONS[command])), data.draw(tokens)]
    ran: list = []

    def stub_parser():
        p = PARSER()
        sub = next(a for a in p._actions if isinstance(a, argparse._SubParsersAction))
        for action in sub.choices.values():  # every subcommand runs the stub
            action.set_defaults(run=ran.append)
        return p

    with pytest.MonkeyPatch.context() as m:
        m.setattr(cli, "parser", stub_parser)
        m.chdir(tmp_path)
        m.setattr("sys.stderr", err := io.StringIO())
        code = main(argv)
    assert code in (0, 2), (argv, code, err.getvalue())
    if code == 2:
        message = err.getvalue().strip()
        assert message.count("\n") == 0 and message.startswith("dano"), message
    else:
        (args,) = ran
        for key, value in vars(args).items():
            if isinstance(value, float):
                assert math.isfinite(value), (key, value)
    assert list(tmp_path.iterdir()) == []
