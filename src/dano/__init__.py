"""dano: Dynamics-Augmented Neural Objects in JAX.

Turn a density field (a NeRF, a voxel grid, a mesh's occupancy, an analytic shape) into a rigid
object with mass, centre of mass, inertia and contact samples.

Example:
    >>> import dano
    >>> obj = dano.build_dano(dano.fields.SphereField(radius=0.05), mass=0.5)
    >>> dano.save_dano("ball.dano.npz", obj)

Importing dano changes nothing in the process (no environment variable, no JAX or MuJoCo setting)
and loads JAX only when a name that needs it is first used (PEP 562), so `dano --help` is instant.
"""

import importlib
from typing import TYPE_CHECKING

from dano import errors
from dano.errors import (
    DanoError,
    DanoFileError,
    EmptyFieldError,
    EmptyWindowError,
    FieldError,
    InvalidMassError,
    MeshError,
    MeshNotWatertightError,
    NonFiniteFieldError,
    SpecError,
)

__version__ = "0.1.0"

_LAZY = {
    "DANO": "dano.types",
    "MassProperties": "dano.mass",
    "SurfaceSamples": "dano.surface",
    "build_dano": "dano.build",
    "default_window": "dano.surface",
    "field_from_source": "dano.build",
    "load_dano": "dano.io",
    "load_reference": "dano.reference",
    "mass_properties": "dano.mass",
    "mass_properties_from_points": "dano.mass",
    "outward_normals": "dano.surface",
    "sample_surface": "dano.surface",
    "save_dano": "dano.io",
    "scale_lengths": "dano.build",
}
_SUBMODULES = {"errors", "fields", "contact", "sim", "sysid", "trajopt", "vision", "baselines", "io", "mass", "surface"}

if TYPE_CHECKING:
    from dano import baselines, contact, fields, io, mass, sim, surface, sysid, trajopt, vision
    from dano.build import build_dano, field_from_source, scale_lengths
    from dano.io import load_dano, save_dano
    from dano.mass import MassProperties, mass_properties, mass_properties_from_points
    from dano.reference import load_reference
    from dano.surface import SurfaceSamples, default_window, outward_normals, sample_surface
    from dano.types import DANO


def __getattr__(name: str):
    if name in _LAZY:
        value = getattr(importlib.import_module(_LAZY[name]), name)
    elif name in _SUBMODULES:
        value = importlib.import_module(f"dano.{name}")
    else:
        raise AttributeError(f"module 'dano' has no attribute {name!r}")
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY) | _SUBMODULES)


__all__ = [
    "DANO", "DanoError", "DanoFileError", "EmptyFieldError", "EmptyWindowError", "FieldError",
    "InvalidMassError", "MassProperties", "MeshError", "MeshNotWatertightError", "NonFiniteFieldError",
    "SpecError", "SurfaceSamples", "build_dano", "default_window", "errors", "field_from_source", "fields",
    "load_dano", "load_reference", "mass_properties", "mass_properties_from_points", "outward_normals",
    "sample_surface", "save_dano", "scale_lengths", "baselines", "contact", "io", "mass", "sim", "surface", "sysid",
    "trajopt", "vision",
]  # fmt: skip
