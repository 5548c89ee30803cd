"""Building a DANO from a density field: mass properties (eqs. 1-4) + surface samples."""

from pathlib import Path
from typing import Literal, cast

import jax.numpy as jnp
import numpy as np

from dano.errors import DanoFileError, InvalidMassError, SpecError
from dano.fields import (
    MESH_SUFFIXES,
    AbstractField,
    Bounds,
    TransformedField,
    as_grid,
    from_spec,
    is_spec,
    load_grid,
    load_mesh,
    load_neural_field,
    mesh_field,
)
from dano.fields.neural import is_neural_checkpoint
from dano.io import load_npz
from dano.mass import mass_properties
from dano.reference import is_reference, load_reference
from dano.surface import field_peak, sample_surface
from dano.types import DANO


def build_dano(
    field: AbstractField,
    *,
    n_points: int = 5000,
    alpha: float | None = 1.0,
    mass: float | None = None,
    window: tuple[float, float] | None = None,
    seed: int = 0,
    normals: Literal["autodiff", "fd"] = "autodiff",
    log2_samples: int = 15,
    replicates: int = 8,
    grid_resolution: int = 48,
    source: str = "",
) -> DANO:
    """Builds a DANO from a field.

    Args:
        field: the density field phi (object frame, m).
        n_points: candidate surface points to sample (the paper uses 5000).
        alpha: mass scale of eq. 1; ignored when `mass` is given.
        mass: total mass in kg (fixes alpha).
        window: density window [low, high] of the surface points (default from the field).
        seed: seed of every random choice; the same seed gives the same DANO.
        normals: "autodiff" or "fd" (central differences).
        log2_samples, replicates: Monte Carlo budget of the mass properties (see `mass_properties`).
        grid_resolution: nodes along the longest side of the baked density grid kept for contact
            between DANOs (0: none).
        source: a note of where the field came from, kept in the file.

    Example:
        >>> dano = build_dano(SphereField(radius=0.05), mass=0.5)
        >>> dano.mass, dano.n_points
    """
    props = mass_properties(field, alpha=alpha, mass=mass, log2_samples=log2_samples, replicates=replicates, seed=seed)
    surface = sample_surface(field, n_points, window, seed=seed, normals=normals)
    grid = _bake(field, grid_resolution) if grid_resolution else None
    return DANO(
        mass=props.mass,
        com=props.com,
        inertia=props.inertia,
        points=surface.points,
        densities=surface.densities,
        normals=surface.normals,
        alpha=jnp.asarray(props.alpha),
        window=surface.window,
        mass_stderr=props.mass_stderr,
        com_stderr=props.com_stderr,
        inertia_stderr=props.inertia_stderr,
        source=source,
        peak=jnp.asarray(field_peak(field, seed)),
        grid=None if grid is None else grid.density,
        grid_bounds=None if grid is None else grid.bounds,
    )


def _bake(field: AbstractField, resolution: int):
    """The field on a grid of cubic cells, `resolution` nodes along the longest side of its box."""
    lo, hi = np.asarray(field.bounds)
    h = float(np.max(hi - lo)) / (resolution - 1)
    shape = tuple(int(np.ceil((hi[i] - lo[i]) / h)) + 1 for i in range(3))
    return as_grid(field, shape)  # type: ignore[arg-type]


def scale_lengths(dano: DANO, scale: float) -> DANO:
    """The DANO of the field with lengths multiplied by `scale` at the same mass scale alpha.

    Mass grows as scale^3 and inertia as scale^5, exactly as building from the scaled field would give.
    """
    s = scale
    return DANO(
        mass=dano.mass * s**3,
        com=dano.com * s,
        inertia=dano.inertia * s**5,
        points=dano.points * s,
        densities=dano.densities,
        normals=dano.normals,
        alpha=dano.alpha,
        window=dano.window,
        mass_stderr=dano.mass_stderr * s**3,
        com_stderr=dano.com_stderr * s,
        inertia_stderr=dano.inertia_stderr * s**5,
        source=dano.source,
        peak=dano.peak,
        grid=dano.grid,
        grid_bounds=None
        if dano.grid_bounds is None
        else cast(Bounds, (tuple(v * s for v in dano.grid_bounds[0]), tuple(v * s for v in dano.grid_bounds[1]))),
    )


def field_from_source(
    source: str, *, scale: float = 1.0, resolution: int = 96, repair: bool = False, reference_inertia: str = "tensor"
):
    """Opens a field (or, for a reference collider, a ready DANO) from a command-line SOURCE.

    SOURCE is an analytic spec (`sphere:r=0.05`), a mesh file (`.ply .obj .stl .off .glb .gltf`),
    a grid `.npz` (`density`, `bounds`), a neural checkpoint `.npz`, or a reference collider `.npz`.
    Returns an `AbstractField`, or a `DANO` for a reference collider (`reference_inertia`: its
    inertia as a tensor, or "second_moment" as the reference's own simulator used it, `load_reference`).

    Raises:
        DanoFileError, MeshError, SpecError: unreadable or unrecognised source.
    """
    if not (scale > 0 and scale < float("inf")):
        raise InvalidMassError(f"--scale must be a positive length factor, got {scale}")
    if reference_inertia not in ("tensor", "second_moment"):
        raise SpecError(f"reference_inertia must be 'tensor' or 'second_moment', got {reference_inertia!r}")
    path = Path(source)
    if is_spec(source) and not path.exists():
        field = from_spec(source)
    elif path.suffix.lower() in MESH_SUFFIXES:
        return mesh_field(load_mesh(path, repair=repair, scale=scale), resolution=resolution)
    elif path.suffix.lower() == ".npz":
        data = load_npz(path)
        if reference_inertia != "tensor" and not is_reference(data):
            raise SpecError(f"{path} is not a reference collider: --reference-inertia applies to those only")
        if is_reference(data):
            dano = load_reference(path, inertia=reference_inertia)  # pyright: ignore[reportArgumentType]
            return dano if scale == 1.0 else scale_lengths(dano, scale)
        if is_neural_checkpoint(data):
            field = load_neural_field(path)
        elif "density" in data and "bounds" in data:
            field = load_grid(path)
        elif "format" in data and str(data["format"]) == "dano":
            raise DanoFileError(f"{path} is already a DANO: use `dano info {path}`")
        else:
            raise DanoFileError(f"{path}: not a grid, neural checkpoint or reference collider (keys {sorted(data)})")
    else:
        raise DanoFileError(
            f"cannot open {source!r}: expected a spec like 'sphere:r=0.05', a mesh {MESH_SUFFIXES} or an .npz"
        )
    return field if scale == 1.0 else TransformedField(field, scale=scale)
