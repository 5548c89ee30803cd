"""Scenes from TOML files (format in README): every table and key checked against a schema that
runs the classes' own checks (`dano.validate`), every error naming the file, the table and the key."""

import dataclasses
import tomllib
from pathlib import Path
from typing import Any

from dano import validate as V
from dano.contact import ContactParams
from dano.errors import DanoError, InvalidValueError
from dano.io import load_dano
from dano.sim.scene import DEFAULT_SUBSTEPS, MODES, SIZES, DanoBody, Primitive, Scene, SceneError


def _vec(n: int | None = None, nonzero: bool = False):
    def check(value, name):
        count = len(value) if n is None and isinstance(value, list) else (n or 1)
        return V.vector(value, name, SceneError, count, nonzero=nonzero)

    return check


def _num(**kw):
    return lambda value, name: V.number(value, name, SceneError, **kw)


def _choice(options):
    return lambda value, name: V.choice(value, name, SceneError, options)


_name = lambda value, name: V.text(value, name, SceneError)  # noqa: E731
_positive = _num(low=0.0, strict=True)
_POSE = {"pos": _vec(3), "quat": _vec(4, nonzero=True), "vel": _vec(3), "angvel": _vec(3)}
_SCHEMA = {
    "sim": {
        "timestep": _positive, "duration": _positive, "gravity": _vec(3),
        "substeps": lambda v, n: V.integer(v, n, SceneError, low=1),
        "force_mode": _choice(("points", "centroid")), "integrator": _choice(DEFAULT_SUBSTEPS),
        "contact_budget": lambda v, n: V.integer(v, n, SceneError, low=1),
    },
    "ground": {"height": _num(), "normal": _vec(3, nonzero=True)},
    "body": {"name": _name, "dano": _name, "mass": _positive, **_POSE},
    "primitive": {
        "name": _name, "type": _choice(SIZES), "size": _vec(), "mode": _choice(MODES),
        "mass": _positive, "collide": lambda v, n: V.boolean(v, n, SceneError), **_POSE,
    },
    "contact": {f.name: _num() for f in dataclasses.fields(ContactParams)},
    "world": {"mjcf": _name},
}  # fmt: skip
"""Each TOML table's keys and their checks (the same `dano.validate` checks the classes run)."""
_SCHEMA["pair"] = {"a": _name, "b": _name, **_SCHEMA["contact"]}


def _read(table, kind: str, where: str, path, required: tuple[str, ...] = ()) -> dict:
    """A TOML table checked against `_SCHEMA[kind]`: no unknown or missing keys, every value of
    the right type and range, normalised (floats, tuples); errors name the file and the table."""
    if not isinstance(table, dict):
        raise SceneError(f"{path}: {where} must be a table, got {table!r}")
    schema = _SCHEMA[kind]
    unknown = sorted(set(table) - set(schema))
    if unknown:
        raise SceneError(f"{path}: unknown key(s) {unknown} in {where}; allowed: {sorted(schema)}")
    missing = [k for k in required if k not in table]
    if missing:
        raise SceneError(f"{path}: {where} needs {' and '.join(repr(k) for k in missing)}")
    return {key: _located(path, where, lambda k=key: schema[k](table[k], k)) for key in table}


def load_scene(path) -> Scene:
    """Reads a scene TOML file (format in README); `dano` paths are relative to the file.

    Every value is checked here, before any work, with the checks the Python classes run (`Scene`,
    `DanoBody`, `Primitive`, `ContactParams`); errors name the file, the table and the key.

    Raises:
        SceneError: unknown or missing keys, bad types or values, no bodies, a missing DANO file.
    """
    path = Path(path)
    try:
        doc = tomllib.loads(path.read_text())
    except (FileNotFoundError, IsADirectoryError, NotADirectoryError):
        raise SceneError(f"{path}: no such file") from None
    except UnicodeDecodeError:
        raise SceneError(f"{path}: not a text file") from None
    except tomllib.TOMLDecodeError as e:
        raise SceneError(f"{path}: not valid TOML ({e})") from None
    unknown = sorted(set(doc) - {"sim", "ground", "body", "primitive", "contact", "pair", "world"})
    if unknown:
        allowed = "body, contact, ground, pair, primitive, sim, world"
        raise SceneError(f"{path}: unknown table(s) {unknown}; allowed: {allowed}")
    sim = _read(doc.get("sim", {}), "sim", "[sim]", path)
    values = _read(doc.get("contact", {}), "contact", "[contact]", path)
    contact = _located(path, "[contact]", lambda: dataclasses.replace(ContactParams(), **values))
    bodies = []
    for i, table in enumerate(_tables(doc, "body", path)):
        where = f"[[body]] #{i + 1}"
        b = _read(table, "body", where, path, required=("name", "dano"))
        try:
            obj = load_dano(path.parent / b.pop("dano"))
            obj = obj.with_mass(b.pop("mass")) if "mass" in b else obj
            bodies.append(DanoBody(b.pop("name"), obj, **b))
        except DanoError as e:
            raise SceneError(f"{path}: {where}: {e}") from None
    prims = []
    for i, table in enumerate(_tables(doc, "primitive", path)):
        where = f"[[primitive]] #{i + 1}"
        p = _read(table, "primitive", where, path, required=("name", "type", "size"))
        prims.append(_located(path, where, lambda p=p: Primitive(p.pop("name"), p.pop("type"), p.pop("size"), **p)))
    pair_contact = []
    for i, table in enumerate(_tables(doc, "pair", path)):
        where = f"[[pair]] #{i + 1}"
        p = _read(table, "pair", where, path, required=("a", "b"))
        key = (p.pop("a"), p.pop("b"))
        pair_contact.append((key, _located(path, where, lambda p=p: dataclasses.replace(contact, **p))))
    if not bodies:
        raise SceneError(f"{path}: no [[body]]: a scene needs at least one DANO")
    kw: dict[str, Any] = {**sim, "bodies": tuple(bodies), "primitives": tuple(prims), "contact": contact,
                          "pair_contact": tuple(pair_contact)}  # fmt: skip
    if "world" in doc:
        world = _read(doc["world"], "world", "[world]", path, required=("mjcf",))
        kw["mjcf"] = str(path.parent / world["mjcf"])  # relative to the scene's file
    if "ground" in doc:
        ground = _read(doc["ground"], "ground", "[ground]", path)
        defaults = {f.name: f.default for f in dataclasses.fields(Scene)}
        kw.update(
            ground_height=ground.get("height", defaults["ground_height"]),
            ground_normal=ground.get("normal", defaults["ground_normal"]),
        )
    else:
        kw["ground_height"] = None
    return _located(path, None, lambda: Scene(**kw))


def _tables(doc: dict, key: str, path) -> list:
    value = doc.get(key, [])
    if not isinstance(value, list):
        raise SceneError(f"{path}: {key} must be written as [[{key}]] tables")
    return value


def _located(path, where: str | None, make):
    """`make()`, with a `SceneError` from the classes' own checks prefixed by file and table."""
    try:
        return make()
    except InvalidValueError as e:
        raise SceneError(f"{path}: {where}: {e}" if where else f"{path}: {e}") from None
