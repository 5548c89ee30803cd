"""The command line's argument types: every value checked when it is parsed, before any work,
with one-line errors (`UsageError`)."""

import argparse
import sys
from pathlib import Path

import numpy as np

from dano import validate
from dano.errors import DanoError


class UsageError(DanoError):
    """A command-line argument that is missing, malformed or out of range (exit status 2)."""


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors: `dano CMD: UsageError: argument --x: ... (see dano CMD --help)`."""

    def error(self, message: str):  # type: ignore[override]
        print(f"{self.prog}: UsageError: {message} (see {self.prog} --help)", file=sys.stderr)
        sys.exit(2)


def _checked(check):
    """An argparse `type=` from a `dano.validate`-style check: its `DanoError` becomes argparse's."""

    def parse(text: str):
        try:
            return check(text)
        except DanoError as e:
            raise argparse.ArgumentTypeError(str(e)) from None

    return parse


def _int(low: int | None = None):
    def check(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise UsageError(f"must be a whole number, got {text!r}") from None
        return validate.integer(value, "", UsageError, low=low)

    return _checked(check)


def _float(low: float | None = None, strict: bool = False):
    def check(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise UsageError(f"must be a number, got {text!r}") from None
        return validate.number(value, "", UsageError, low=low, strict=strict)

    return _checked(check)


_POSITIVE = _float(0.0, strict=True)


def _existing(text: str) -> str:
    """An input file that exists."""
    if not Path(text).is_file():
        raise UsageError(f"no file {text!r}")
    return text


def _output(*suffixes: str):
    """An output file: its folder exists, it is not a folder, and (if given) its suffix is allowed.
    Checked when the command line is parsed, before any work, so nothing is half done."""

    def check(text: str) -> str:
        path = Path(text)
        if suffixes and not text.lower().endswith(suffixes):
            raise UsageError(f"{text!r} must end with {' or '.join(suffixes)}")
        if path.is_dir():
            raise UsageError(f"{text!r} is a folder; give a file name")
        return _in_a_folder(text)

    return _checked(check)


def _in_a_folder(text: str) -> str:
    """A path whose folder exists (an output file, or a folder the command creates)."""
    parent = Path(text).parent
    if not parent.is_dir():
        raise UsageError(f"folder {str(parent)!r} of {text!r} does not exist")
    return text


def _numbers(n: int, form: str, quaternion_at: int | None = None):
    """A check of `n` comma-separated numbers (e.g. `x,y,z,qw,qx,qy,qz`); a quaternion part must be
    non-zero. Wrap it with `_checked` for argparse."""

    def check(text: str) -> tuple[float, ...]:
        try:
            values = tuple(float(v) for v in text.split(","))
        except ValueError:
            values = ()
        if len(values) != n or not all(np.isfinite(values)):
            raise UsageError(f"takes {n} comma-separated numbers {form}, got {text!r}")
        if quaternion_at is not None and not any(values[quaternion_at:]):
            raise UsageError(f"the quaternion of {text!r} is zero")
        return values

    return check


def _vector_part(text: str) -> tuple[float, ...]:
    """One token of a vector written `X,Y` (or, the older way, `X Y`): its comma-separated numbers."""
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise UsageError(f"takes comma-separated numbers, got {text!r}") from None
    if not all(np.isfinite(values)):
        raise UsageError(f"takes finite numbers, got {text!r}")
    return values


def _vector(parts: list[tuple[float, ...]], n: int, option: str, form: str) -> tuple[float, ...]:
    """The vector of `_vector_part` tokens: `n` numbers in all."""
    values = tuple(v for part in parts for v in part)
    if len(values) != n:
        raise UsageError(f"{option} takes {n} numbers {form}, got {' '.join(','.join(map(str, p)) for p in parts)}")
    return values


def _frames(text: str) -> tuple[int, int | None]:
    first, colon, stop = text.partition(":")
    try:
        if not colon:
            raise ValueError
        span = (int(first or 0), int(stop) if stop else None)
    except ValueError:
        raise UsageError(f"takes FIRST:STOP row numbers, e.g. 400:901, got {text!r}") from None
    if span[0] < 0 or (span[1] is not None and span[1] <= span[0]):
        raise UsageError(f"needs 0 <= FIRST < STOP, got {text!r}")
    return span


def _level(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise UsageError(f"must be a number, got {text!r}") from None
    if not 0.0 < value < 1.0:
        raise UsageError(f"a confidence level is between 0 and 1, got {text}")
    return value


def _gravity(text: str):
    return text if text == "fit" else _numbers(3, "gx,gy,gz (or 'fit')")(text)


VIDEO = (".mp4", ".gif")
PLOT = (".png", ".pdf", ".svg", ".jpg")


def _parse_window(text: str | None) -> tuple[float, float] | None:
    if text is None:
        return None
    try:
        low, high = (float(v) for v in text.split(","))
    except ValueError:
        raise DanoError(f"--window takes LOW,HIGH densities, got {text!r}") from None
    return low, high


def _parse_pairs(text: str | None, option: str, n: int) -> dict:
    """`name=value,name=value` (n = 1) or `name=low:high,...` (n = 2)."""
    out: dict = {}
    for item in (text or "").split(","):
        if not item.strip():
            continue
        try:
            name, value = item.split("=")
            values = [float(v) for v in value.split(":")]
        except ValueError:
            values = []
        if len(values) != n:
            form = "name=value" if n == 1 else "name=low:high"
            raise DanoError(f"{option} takes {form}[,...], got {item!r}")
        out[name.strip()] = values[0] if n == 1 else tuple(values)
    return out


def _parse_levels(text: str | None, peak: float) -> list[float]:
    if text is None:
        return [0.03 * peak, 0.5 * peak, 0.95 * peak]
    try:
        return [float(v) for v in text.split(",")]
    except ValueError:
        raise DanoError(f"--levels takes comma-separated densities, got {text!r}") from None
