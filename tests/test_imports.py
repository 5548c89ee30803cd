"""Importing dano changes nothing in the process; the command line starts without JAX; MJX's
import chatter never reaches stdout; rendering picks its OpenGL backend explicitly."""

import os
import subprocess
import sys

import pytest

from dano.sim.render import headless_backends


def _python(code: str, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env)


def test_importing_dano_and_its_simulator_leaves_the_environment_and_stdout_unchanged():
    code = (
        "import os, json; before = dict(os.environ)\n"
        "import jax; x64 = jax.config.jax_enable_x64\n"
        "import dano, dano.sim, dano.sim.implicit, dano.sysid, dano.trajopt, dano.vision, dano.cli\n"
        "import sys; sys.stderr.write(json.dumps([dict(os.environ) == before, jax.config.jax_enable_x64 == x64]))"
    )
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "MUJOCO_GL", "PYOPENGL_PLATFORM")}
    out = _python(code, env)
    assert out.stdout == ""  # MJX's "Failed to import warp" would land here
    assert out.stderr.strip().splitlines()[-1] == "[true, true]"


def test_import_dano_loads_no_jax_and_the_help_needs_none():
    code = (
        "import sys, contextlib, io\n"
        "import dano\n"
        "assert 'jax' not in sys.modules, 'import dano loaded jax'\n"
        "from dano.cli import main\n"
        "with contextlib.redirect_stdout(io.StringIO()) as out:\n"
        "    try:\n"
        "        main(['--help'])\n"
        "    except SystemExit:\n"
        "        pass\n"
        "assert 'jax' not in sys.modules, 'dano --help loaded jax'\n"
        "assert 'simulate' in out.getvalue()\n"
        "print(dano.build_dano.__module__)"
    )
    assert _python(code).stdout.strip() == "dano.build"  # and the lazy names still resolve


def test_version():
    out = subprocess.run([sys.executable, "-m", "dano.cli", "--version"], capture_output=True, text=True, check=True)
    import dano

    assert out.stdout.strip() == f"dano {dano.__version__}"


def test_unknown_attribute_is_an_attribute_error():
    import dano

    with pytest.raises(AttributeError, match="no attribute 'nonsense'"):
        dano.nonsense  # noqa: B018


@pytest.mark.parametrize(
    ("env", "system", "expected"),
    [
        ({"MUJOCO_GL": "osmesa"}, "Linux", (None,)),  # the user's choice, through MuJoCo
        ({}, "Linux", ("egl", "osmesa")),  # headless Linux
        ({"DISPLAY": ":0"}, "Linux", (None, "egl", "osmesa")),
        ({}, "Darwin", (None,)),  # MuJoCo's own (CGL, then GLFW); EGL does not exist there
        ({}, "Windows", (None,)),
    ],
)
def test_the_opengl_backend_is_chosen_per_platform(monkeypatch, env, system, expected):
    for name in ("MUJOCO_GL", "DISPLAY", "WAYLAND_DISPLAY"):
        monkeypatch.delenv(name, raising=False)
    for name, value in env.items():
        monkeypatch.setenv(name, value)
    monkeypatch.setattr("platform.system", lambda: system)
    assert headless_backends() == expected


def test_the_package_is_marked_typed():
    """PEP 561: `py.typed` ships with the package (listed in pyproject's package-data), so type
    checkers read dano's annotations."""
    from importlib.resources import files

    assert (files("dano") / "py.typed").is_file()


@pytest.mark.parametrize(
    ("module", "old", "new"),
    [("dano.sim", "panda", "dano.assets.panda"), ("dano.vision", "render_video", "dano.vision.render_mesh_video")],
)
def test_a_moved_name_still_resolves_for_one_release_with_a_deprecation_warning(module, old, new):
    import importlib

    owner, _, name = new.rpartition(".")
    with pytest.warns(DeprecationWarning, match=new):
        alias = getattr(importlib.import_module(module), old)
    assert alias is getattr(importlib.import_module(owner), name)
