"""Command-line options generated from a settings dataclass: one option per field, its type from the
annotation, its help from the class's `Attributes:` docstring, its default the field's own (so a
default lives in one place, the library), and the config rebuilt from the parsed values.

    >>> add_config(parser, TrackConfig, names={"iterations": ("--steps", "--iterations")})
    >>> config = from_args(TrackConfig, args)
"""

import argparse
import dataclasses
import enum
import inspect
import re
import types
import typing
from collections.abc import Callable, Mapping, Sequence
from typing import Any

from dano.cli.arguments import _float, _int

_PREFIX = "config_"
SUPPRESS = argparse.SUPPRESS


def field_help(cls: type) -> dict[str, str]:
    """Each field's sentence(s) from the `Attributes:` section of `cls`'s docstring (a line
    `a, b: text` documents both fields)."""
    doc = inspect.cleandoc(cls.__doc__ or "")
    _, _, section = doc.partition("Attributes:\n")
    out: dict[str, str] = {}
    names: list[str] = []
    for line in section.splitlines():
        if line and not line.startswith(" "):
            break  # the next section
        entry = re.match(r"^    (\w[\w, ]*): (.*)$", line)
        if entry:
            names = [n.strip() for n in entry.group(1).split(",")]
            for name in names:
                out[name] = entry.group(2)
        elif line.strip():
            for name in names:
                out[name] += " " + line.strip()
    return out


def _kind(annotation) -> tuple[type | None, bool]:
    """The scalar type an option parses (int, float, str, bool or a string enumeration, also where
    its field takes the enumeration or its value) and whether None is allowed; (None, _) for a field
    the command line cannot give."""
    optional = False
    if isinstance(annotation, types.UnionType) or typing.get_origin(annotation) is typing.Union:
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        optional = len(args) < len(typing.get_args(annotation))
        enums = [a for a in args if isinstance(a, type) and issubclass(a, enum.Enum)]
        annotation = args[0] if len(args) == 1 else enums[0] if len(enums) == 1 and str in args else None
    if annotation in (int, float, str, bool) or (isinstance(annotation, type) and issubclass(annotation, enum.Enum)):
        return annotation, optional
    return None, optional


def add_config(
    parser: argparse.ArgumentParser | argparse._ArgumentGroup,
    cls: type,
    *,
    names: Mapping[str, Sequence[str]] | None = None,
    skip: Sequence[str] = (),
    types: Mapping[str, tuple[Callable[[str], Any], str]] | None = None,
    defaults: Mapping[str, Any] | None = None,
) -> None:
    """Adds `--field-name` (or `names[field]`: the option's spellings, the first shown) for each field
    of the dataclass `cls` the command line can give (numbers, text, switches, enumerations), but
    those in `skip`. Numbers are checked to be numbers here and against their bounds by `cls`;
    `types[field]` = (parser, metavar) reads a field the annotation cannot (a vector, a range) or
    checks one at parse time. `defaults[field]`: the command's own default where it differs from the
    library's (shown in the help, and used when the option is not given)."""
    helps = field_help(cls)
    hints = typing.get_type_hints(cls)
    for field in dataclasses.fields(cls):
        kind, optional = _kind(hints[field.name])
        custom = (types or {}).get(field.name)
        if field.name in skip or (kind is None and custom is None):
            continue
        flags = list((names or {}).get(field.name, ["--" + field.name.replace("_", "-")]))
        default = field.default if field.default is not dataclasses.MISSING else None
        given = SUPPRESS
        if field.name in (defaults or {}):
            default = given = (defaults or {})[field.name]
        text = helps.get(field.name, "").replace("%", "%%")
        shown = default.value if isinstance(default, enum.Enum) else default
        help = f"{text} (default {shown})" if default is not None or optional else text
        dest = _PREFIX + field.name
        if custom is not None:
            parser.add_argument(*flags, type=custom[0], metavar=custom[1], dest=dest, default=given, help=help)
        elif kind is bool:
            parser.add_argument(*flags, action=argparse.BooleanOptionalAction, dest=dest, default=given, help=help)
        elif kind is not None and issubclass(kind, enum.Enum):
            choices = [m.value for m in kind]
            parser.add_argument(*flags, choices=choices, dest=dest, default=given, help=help)
        else:
            parse = {int: _int(), float: _float(), str: str}[kind]
            if optional:
                parse = _none_or(parse)
            metavar = {int: "N", float: "X", str: "TEXT"}[kind]
            parser.add_argument(*flags, type=parse, metavar=metavar, dest=dest, default=given, help=help)


def _none_or(parse):
    def check(text: str):
        return None if text.lower() == "none" else parse(text)

    return check


def from_args(cls: type, args: argparse.Namespace, **given):
    """`cls` with the fields the command line gave (`add_config`), then `given`; every other field
    keeps its default."""
    values = {
        field.name: getattr(args, _PREFIX + field.name)
        for field in dataclasses.fields(cls)
        if hasattr(args, _PREFIX + field.name)
    }
    return cls(**(values | given))
