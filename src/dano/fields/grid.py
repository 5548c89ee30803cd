"""Voxel-grid density field with trilinear interpolation.

Samples sit on the nodes of a regular grid spanning `bounds` with both ends included, so node
(i, j, k) is at lo + (i, j, k) * (hi - lo) / (shape - 1). Outside the box the field is 0.
The `.npz` layout is `density` (nx, ny, nz) float and `bounds` (2, 3) float.
"""

from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from dano.errors import DanoFileError, FieldError
from dano.fields.base import AbstractField, Bounds, as_bounds, evaluate
from dano.io import atomic_savez, load_npz


class GridField(AbstractField):
    """Trilinear interpolation of node densities `density` (nx, ny, nz) over `bounds`."""

    density: Float[Array, "nx ny nz"]
    bounds: Bounds = eqx.field(static=True, converter=as_bounds)

    def __check_init__(self):
        if self.density.ndim != 3 or min(self.density.shape) < 2:
            raise FieldError(
                f"a grid needs a 3-D density array with >= 2 nodes per axis, got shape {self.density.shape}"
            )

    def __call__(self, x: Float[Array, "n 3"]) -> Float[Array, " n"]:
        return trilinear(self.density, self.bounds, x)

    @property
    def spacing(self) -> np.ndarray:
        """Node spacing per axis, m."""
        lo, hi = np.asarray(self.bounds)
        return (hi - lo) / (np.asarray(self.density.shape) - 1)


def trilinear(values: Float[Array, "nx ny nz ..."], bounds: Bounds, x: Float[Array, "n 3"]) -> Float[Array, "n ..."]:
    """Trilinear interpolation of node values (with optional trailing channels) at points `x`; 0 outside."""
    lo, hi = jnp.asarray(bounds, dtype=x.dtype)
    cells = jnp.asarray(values.shape[:3], dtype=x.dtype) - 1
    u = (x - lo[None, :]) / (hi - lo)[None, :] * cells[None, :]
    inside = jnp.all((u >= 0) & (u <= cells[None, :]), axis=-1)
    i0 = jnp.clip(jnp.floor(u), 0, cells[None, :] - 1)
    f = u - i0
    i0 = i0.astype(jnp.int32)
    channels = (1,) * (values.ndim - 3)
    value = jnp.zeros((x.shape[0], *values.shape[3:]), dtype=values.dtype)
    for corner in range(8):
        bits = jnp.asarray([[(corner >> 2) & 1, (corner >> 1) & 1, corner & 1]], dtype=jnp.int32)
        idx = i0 + bits
        weight = jnp.prod(jnp.where(bits == 1, f, 1 - f), axis=-1)
        value = value + weight.reshape(-1, *channels) * values[idx[:, 0], idx[:, 1], idx[:, 2]]
    return jnp.where(inside.reshape(-1, *channels), value, 0.0)


def grid_nodes(bounds: Bounds, shape: tuple[int, int, int]) -> np.ndarray:
    """Node coordinates `(*shape, 3)` of a grid over `bounds`, both ends included."""
    lo, hi = np.asarray(bounds)
    axes = [np.linspace(lo[i], hi[i], shape[i]) for i in range(3)]
    return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)


def save_grid(path: str | Path, field: GridField) -> None:
    """Writes a grid field to `.npz` atomically."""
    atomic_savez(path, density=np.asarray(field.density), bounds=np.asarray(field.bounds))


def load_grid(path: str | Path) -> GridField:
    """Reads a grid `.npz` with keys `density` (nx, ny, nz) and `bounds` (2, 3).

    Raises:
        DanoFileError: missing keys, wrong shapes, non-finite or negative values.
    """
    data = load_npz(path, required=("density", "bounds"))
    density = data["density"]
    if density.ndim != 3 or density.dtype.kind not in "fiu":
        raise DanoFileError(f"{path}: 'density' must be a 3-D numeric array, got {density.dtype} {density.shape}")
    if not np.all(np.isfinite(density)) or np.any(density < 0):
        raise DanoFileError(f"{path}: 'density' must be finite and non-negative")
    try:
        return GridField(jnp.asarray(density, dtype=jnp.result_type(float)), data["bounds"])
    except FieldError as e:
        raise DanoFileError(f"{path}: {e}") from None


def as_grid(field: AbstractField, shape: tuple[int, int, int]) -> GridField:
    """Bakes any field into a grid over its own box (the fast path for repeated queries)."""
    nodes = grid_nodes(field.bounds, shape).reshape(-1, 3)
    values = evaluate(field, nodes)
    return GridField(jnp.asarray(values.reshape(shape)), field.bounds)
