"""Checks at the boundary: every user input (a scene, its TOML, a command-line number, a file's
arrays) is checked before any work, and a bad one raises a named `DanoError` whose one-line message
says what is wrong and what was given.

Each function takes the value, its name as the user wrote it, and the error class to raise, and
returns the value normalised (Python floats, tuples). Values traced under `jax.jit`/`vmap`/`grad`
cannot be checked on the host and pass through unchanged (`is_traced`).
"""

import enum
import math
from collections.abc import Iterable
from typing import Any, TypeVar

import numpy as np

from dano.errors import DanoError

Error = type[DanoError]
E = TypeVar("E", bound=enum.StrEnum)


def is_traced(value: Any) -> bool:
    """Whether `value` is (or holds) a JAX tracer: abstract, so not checkable here."""
    import sys

    if "jax" not in sys.modules:  # nothing can be traced before JAX is imported
        return False
    import jax
    from jax.core import Tracer

    return any(isinstance(leaf, Tracer) for leaf in jax.tree.leaves(value))


def _named(name: str) -> str:
    """The start of a message: "timestep must ..." (or "must ..." for an unnamed command-line value)."""
    return f"{name} " if name else ""


def _show(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def number(
    value: Any,
    name: str,
    error: Error,
    *,
    low: float | None = None,
    strict: bool = False,
) -> float:
    """A finite real number >= low (> low when `strict`), as a float."""
    if value is None or isinstance(value, bool | str | bytes) or np.ndim(value) != 0:
        raise error(_named(name) + f"must be a number, got {_show(value)}")
    try:
        x = float(value)
    except (TypeError, ValueError):
        raise error(_named(name) + f"must be a number, got {_show(value)}") from None
    if not math.isfinite(x):
        raise error(_named(name) + f"must be finite, got {x}")
    if low is not None and (x < low or (strict and x == low)):
        raise error(_named(name) + f"must be {'>' if strict else '>='} {low:g}, got {x:g}")
    return x


def positive(value: Any, name: str, error: Error) -> float:
    """A finite number > 0."""
    return number(value, name, error, low=0.0, strict=True)


def integer(value: Any, name: str, error: Error, *, low: int | None = None) -> int:
    """A whole number >= low (a float such as 4.0 is refused: it is likely a misplaced value)."""
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise error(_named(name) + f"must be a whole number, got {_show(value)}")
    if low is not None and value < low:
        raise error(_named(name) + f"must be a whole number >= {low}, got {value}")
    return int(value)


def vector(value: Any, name: str, error: Error, n: int, *, nonzero: bool = False) -> tuple[float, ...]:
    """`n` finite numbers (a list, tuple or array), as a tuple of floats; `nonzero`: not all zero."""
    if isinstance(value, str | bytes | dict) or not isinstance(value, Iterable | np.ndarray):
        raise error(_named(name) + f"must be {n} numbers, got {_show(value)}")
    items = list(np.asarray(value, dtype=object).reshape(-1)) if isinstance(value, np.ndarray) else list(value)
    if len(items) != n:
        raise error(_named(name) + f"must be {n} numbers, got {len(items)}: {_show(value)}")
    out = tuple(number(v, f"{name}[{i}]", error) for i, v in enumerate(items))
    if nonzero and not any(out):
        raise error(_named(name) + f"must not be all zeros, got {_show(value)}")
    return out


def choice(value: Any, name: str, error: Error, options: Iterable[str]) -> str:
    """One of `options` (strings)."""
    options = tuple(str(o) for o in options)  # a string enumeration's members as their values
    if not isinstance(value, str) or value not in options:
        raise error(_named(name) + f"must be one of {', '.join(repr(o) for o in options)}; got {_show(value)}")
    return value


def option(value: Any, name: str, error: Error, kind: type[E]) -> E:
    """A member of the string enumeration `kind`, given as the member or its value ("points")."""
    try:
        return kind(value)
    except (ValueError, TypeError):
        choices = ", ".join(repr(m.value) for m in kind)
        raise error(_named(name) + f"must be one of {choices}; got {_show(value)}") from None


def settings(
    obj: Any, error: Error, *, whole: dict[str, int] | None = None, positive: Iterable[str] = (),
    nonnegative: Iterable[str] = (),
) -> None:  # fmt: skip
    """Checks a frozen settings dataclass's numeric fields in place (in its `__post_init__`): `whole`
    maps a count's field name to its least value; `positive` and `nonnegative` name real fields."""
    checked = {name: integer(getattr(obj, name), name, error, low=low) for name, low in (whole or {}).items()}
    checked |= {name: number(getattr(obj, name), name, error, low=0.0, strict=True) for name in positive}
    checked |= {name: number(getattr(obj, name), name, error, low=0.0) for name in nonnegative}
    for name, value in checked.items():
        object.__setattr__(obj, name, value)  # a frozen field, normalised


def boolean(value: Any, name: str, error: Error) -> bool:
    """`value` if it is True or False (not 0, 1 or a string), else `error`."""
    if not isinstance(value, bool | np.bool_):
        raise error(f"{_named(name)}must be true or false, got {_show(value)}")
    return bool(value)


def text(value: Any, name: str, error: Error) -> str:
    """A non-empty string without surrounding spaces."""
    if not isinstance(value, str) or not value.strip() or value != value.strip():
        raise error(_named(name) + f"must be a non-empty name without surrounding spaces, got {_show(value)}")
    return value


def inertia_tensor(inertia: Any, name: str, error: Error) -> np.ndarray:
    """A finite, symmetric, positive definite 3x3 inertia tensor. (The triangle inequality of the
    principal moments is not required: the paper authors' reference DANOs break it slightly.)"""
    given = np.asarray(inertia)
    eps = float(np.finfo(given.dtype).eps) if given.dtype.kind == "f" else float(np.finfo(float).eps)
    tensor = given.astype(float)
    if tensor.shape != (3, 3) or not np.all(np.isfinite(tensor)):
        raise error(_named(name) + "must be a finite 3x3 matrix")
    scale = float(np.max(np.abs(tensor)))
    if not scale > 0 or not np.allclose(tensor, tensor.T, rtol=0, atol=1e3 * eps * scale):
        raise error(_named(name) + "must be symmetric and non-zero")
    moments = np.linalg.eigvalsh(tensor)
    if moments[0] <= 0:
        raise error(_named(name) + f"is not positive definite (principal moments {[float(m) for m in moments]})")
    return tensor
