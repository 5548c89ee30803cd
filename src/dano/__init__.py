"""dano: Dynamics-Augmented Neural Objects in JAX.

Turn a density field (a NeRF, a voxel grid, a mesh's occupancy, an analytic shape) into a rigid
object with mass, centre of mass, inertia and contact samples.

Example:
    >>> import dano
    >>> obj = dano.build_dano(dano.fields.SphereField(radius=0.05), mass=0.5)
    >>> dano.save_dano("ball.dano.npz", obj)
"""

from dano import (
    _env,  # noqa: F401  (first: sets XLA_FLAGS and MUJOCO_GL before JAX and MuJoCo start)
    errors,
    fields,
)
from dano.build import build_dano, field_from_source, scale_lengths
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
from dano.io import load_dano, save_dano
from dano.mass import MassProperties, mass_properties, mass_properties_from_points
from dano.reference import load_reference
from dano.surface import SurfaceSamples, default_window, outward_normals, sample_surface
from dano.types import DANO

__version__ = "0.1.0"

__all__ = [
    "DANO", "DanoError", "DanoFileError", "EmptyFieldError", "EmptyWindowError", "FieldError",
    "InvalidMassError", "MassProperties", "MeshError", "MeshNotWatertightError", "NonFiniteFieldError",
    "SpecError", "SurfaceSamples", "build_dano", "default_window", "errors", "field_from_source", "fields",
    "load_dano", "load_reference", "mass_properties", "mass_properties_from_points", "outward_normals",
    "sample_surface", "save_dano", "scale_lengths",
]  # fmt: skip
