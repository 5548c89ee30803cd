"""Optional dependencies: a feature whose extra is missing says which extra to install; the
installed versions meet pyproject's floors (the versions the suite runs on)."""

import re
import sys
import tomllib
from importlib.metadata import version
from pathlib import Path

import pytest

from dano.extras import EXTRAS, MissingExtraError, installed, require

PYPROJECT = Path(__file__).resolve().parents[1] / "pyproject.toml"


@pytest.mark.parametrize("module", sorted(EXTRAS))
def test_a_missing_extra_is_named(monkeypatch, module):
    monkeypatch.setitem(sys.modules, module, None)  # makes `import module` raise ImportError
    package, extra = EXTRAS[module]
    with pytest.raises(MissingExtraError, match=rf'the feature needs {package}: pip install "dano\[{extra}\]"'):
        require(module, "the feature")


def test_the_panda_without_its_extra_names_it(monkeypatch):
    from importlib.metadata import PackageNotFoundError

    from dano.assets import panda

    def missing(name):
        raise PackageNotFoundError(name)

    monkeypatch.setattr("dano.assets.distribution", missing)
    with pytest.raises(MissingExtraError, match=r'pip install "dano\[robots\]"'):
        panda()


def _floors() -> dict[str, str]:
    project = tomllib.loads(PYPROJECT.read_text())["project"]
    specs = list(project["dependencies"])
    for extra in ("baselines", "robots", "test"):
        specs += [s for s in project["optional-dependencies"][extra] if not s.startswith("dano[")]
    floors: dict[str, str] = {}
    for spec in specs:
        match = re.fullmatch(r"([A-Za-z0-9_.-]+)>=([0-9.]+)", spec.split(";")[0].strip())
        assert match, f"{spec!r}: every dependency states a floor (name>=version)"
        floors[match.group(1)] = match.group(2)
    return floors


def _tuple(v: str) -> tuple[int, ...]:
    return tuple(int(re.sub(r"\D.*", "", part) or 0) for part in v.split(".")[:3])


def test_every_installed_dependency_meets_its_floor():
    floors = _floors()
    assert {"jax", "scipy", "mujoco-mjx", "coacd", "example-robot-data", "hypothesis"} <= set(floors)
    below = {name: (version(name), floor) for name, floor in floors.items()
             if installed(name) and _tuple(version(name)) < _tuple(floor)}  # fmt: skip
    assert not below, f"installed below pyproject's floor: {below}"
    assert _tuple(floors["scipy"]) >= (1, 15)  # qmc.Sobol(rng=...)
