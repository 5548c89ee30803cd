"""Names of a package loaded on first use (PEP 562), so that importing the package (and its light
modules, such as the settings the command line reads) loads no JAX."""

import importlib
import sys
import warnings
from collections.abc import Callable, Mapping


def attach(
    package: str, names: Mapping[str, str], renamed: Mapping[str, str] | None = None
) -> tuple[Callable[[str], object], Callable[[], list[str]]]:
    """`__getattr__` and `__dir__` for `package`: `names` maps each public name to the module that
    defines it; `renamed` maps an old name to its new one (a `DeprecationWarning` on use)."""

    def __getattr__(name: str):
        if name in (renamed or {}):
            new = (renamed or {})[name]
            warnings.warn(f"{package}.{name} is now {package}.{new}", DeprecationWarning, stacklevel=2)
            return __getattr__(new)
        if name not in names:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(names[name]), name)
        setattr(sys.modules[package], name, value)
        return value

    def __dir__() -> list[str]:
        return sorted(set(vars(sys.modules[package])) | set(names))

    return __getattr__, __dir__
