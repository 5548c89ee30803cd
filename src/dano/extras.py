"""Optional dependencies: features that need a heavy package install it as an extra, and say so.

    pip install "dano[baselines]"   # the mesh path (dano compare): CoACD, V-HACD, decimation
    pip install "dano[robots]"      # the Franka Panda from example-robot-data (440 MB)
    pip install "dano[bench]"       # bench/sysid.py's comparison solver (optimistix)

`pip install -e ".[test]"` installs every extra the tests use.
"""

import importlib
from types import ModuleType

from dano.errors import DanoError

EXTRAS = {
    "coacd": ("coacd", "baselines"),
    "vhacdx": ("vhacdx", "baselines"),
    "fast_simplification": ("fast-simplification", "baselines"),
    "example_robot_data": ("example-robot-data", "robots"),
    "optimistix": ("optimistix", "bench"),
}
"""Importable module -> (its distribution, the dano extra that installs it)."""


class MissingExtraError(DanoError):
    """A feature needs an optional dependency that is not installed (the message names the extra)."""


def require(module: str, feature: str) -> ModuleType:
    """Imports `module`, or raises `MissingExtraError` naming the extra that installs it.

    Example:
        >>> coacd = require("coacd", "convex decomposition")
    """
    try:
        return importlib.import_module(module)
    except ImportError:
        package, extra = EXTRAS[module.split(".")[0]]
        raise MissingExtraError(f'{feature} needs {package}: pip install "dano[{extra}]"') from None


def installed(distribution: str) -> bool:
    """Whether a distribution (e.g. "example-robot-data", which has no importable module) is installed."""
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import distribution as find

    try:
        find(distribution)
    except PackageNotFoundError:
        return False
    return True
