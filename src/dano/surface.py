"""Candidate surface points (paper Sec. IV, "Neural Object Sampling Procedure") and their normals.

Candidates are drawn from one scrambled Sobol sequence over the field's box, in order, and the
first `n` whose density lies in the window [low, high] are kept. A prefix of a Sobol sequence is
evenly spread over the box, so the kept points are evenly spread over the band of the surface the
window selects, with no clumps and no duplicates (the reference strided a jittered grid instead).
Outward normals are -grad phi / |grad phi|, by autodiff or by central differences.

The surface as a triangle mesh (`level_set_mesh`, `surface_mesh`: marching cubes at a density level)
is for pictures and for the mesh path; the contact model uses the points.
"""

from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import trimesh
from jaxtyping import Array, Float
from scipy.stats import qmc

from dano.errors import EmptyFieldError, EmptyWindowError, MeshError
from dano.fields.base import AbstractField, check_densities, evaluate
from dano.fields.grid import GridField, grid_nodes
from dano.math import normalize
from dano.sampling import sobol_unit, to_box
from dano.types import DANO

WINDOW_FRACTIONS = (0.1, 0.9)
"""Default window as fractions of the field's peak: symmetric about the half level, the surface."""


class SurfaceSamples(eqx.Module):
    """Points (n, 3) m, their densities (n,), outward unit normals (n, 3), and the window (2,)."""

    points: Float[Array, "n 3"]
    densities: Float[Array, " n"]
    normals: Float[Array, "n 3"]
    window: Float[Array, " 2"]


def field_peak(field: AbstractField, seed: int = 0, log2_n: int = 16) -> float:
    """Robust peak density: the 99th percentile of the positive densities over the box.

    A percentile rather than the maximum, so that a few spikes (common in fields fitted to images)
    do not set the scale.
    """
    values = np.asarray(_densities(field, jnp.asarray(to_box(sobol_unit(log2_n, seed, 1000), field.bounds))))
    check_densities(values, values.shape[0])
    positive = values[values > 0]
    if positive.size == 0:
        raise EmptyFieldError(
            "the field is zero everywhere in its box: no mass, no surface (check its bounds and scale)"
        )
    return float(np.percentile(positive, 99))


def default_window(field: AbstractField, seed: int = 0) -> tuple[float, float]:
    """[0.1, 0.9] x the field's robust peak (see `field_peak`)."""
    peak = field_peak(field, seed)
    return WINDOW_FRACTIONS[0] * peak, WINDOW_FRACTIONS[1] * peak


@eqx.filter_jit
def _densities(field: AbstractField, x: Array) -> Array:
    return field(x)


def density_gradient(field: AbstractField, x: Float[Array, "n 3"]) -> Float[Array, "n 3"]:
    """grad phi at each point, by autodiff (each density depends on its own point only)."""
    return jax.grad(lambda p: jnp.sum(field(p)))(x)


def density_gradient_fd(field: AbstractField, x: Float[Array, "n 3"], step: float) -> Float[Array, "n 3"]:
    """grad phi by central differences with the given step (m), as in the paper."""
    offsets = step * jnp.eye(3, dtype=x.dtype)
    plus = jnp.stack([field(x + e[None, :]) for e in offsets], axis=-1)
    minus = jnp.stack([field(x - e[None, :]) for e in offsets], axis=-1)
    return (plus - minus) / (2 * step)


def outward_normals(
    field: AbstractField,
    x: Float[Array, "n 3"],
    method: Literal["autodiff", "fd"] = "autodiff",
    step: float | None = None,
) -> Float[Array, "n 3"]:
    """Outward unit normals -grad phi / |grad phi| (0 where the gradient vanishes)."""
    if method == "autodiff":
        g = density_gradient(field, x)
    else:
        g = density_gradient_fd(field, x, _default_step(field) if step is None else step)
    return normalize(-g)


def _default_step(field: AbstractField) -> float:
    lo, hi = np.asarray(field.bounds)
    return 1e-3 * float(np.linalg.norm(hi - lo))


def sample_surface(
    field: AbstractField,
    n: int = 5000,
    window: tuple[float, float] | None = None,
    *,
    seed: int = 0,
    normals: Literal["autodiff", "fd"] = "autodiff",
    fd_step: float | None = None,
    max_candidates: int = 1 << 24,
) -> SurfaceSamples:
    """Samples `n` candidate surface points whose density lies in `window`.

    Args:
        field: the density field.
        n: number of points (the paper uses 5000).
        window: [low, high] densities; default `default_window(field)`.
        seed: Sobol scrambling seed; the same seed gives the same points.
        normals: "autodiff" (exact gradient) or "fd" (central differences, step `fd_step`).
        fd_step: finite-difference step, m (default 1e-3 of the box diagonal).
        max_candidates: give up after this many candidates.

    Raises:
        EmptyWindowError: the window holds no points, or fewer than `n` within `max_candidates`.
    """
    low, high = default_window(field, seed) if window is None else (float(window[0]), float(window[1]))
    if not (np.isfinite(low) and np.isfinite(high) and 0 <= low <= high):
        raise EmptyWindowError(f"density window [{low}, {high}] must satisfy 0 <= low <= high")
    engine = qmc.Sobol(d=3, scramble=True, rng=np.random.default_rng([seed, 2000]))
    chunk, seen = 1 << 16, 0
    kept: list[np.ndarray] = []
    count = 0
    while count < n and seen < max_candidates:
        x = to_box(engine.random(chunk), field.bounds)
        values = np.asarray(_densities(field, jnp.asarray(x)))
        check_densities(values, chunk)
        inside = x[(values >= low) & (values <= high)]
        kept.append(inside)
        count += len(inside)
        seen += chunk
    if count == 0:
        raise EmptyWindowError(f"no point of {seen} candidates has a density in [{low:.4g}, {high:.4g}]")
    if count < n:
        raise EmptyWindowError(
            f"only {count} of {seen} candidates have a density in [{low:.4g}, {high:.4g}], {n} wanted: "
            "widen the window or ask for fewer points"
        )
    points = jnp.asarray(np.concatenate(kept)[:n])
    densities = _densities(field, points)
    unit = _normals_jit(field, points, normals, fd_step)
    return SurfaceSamples(points, densities, unit, jnp.asarray([low, high], dtype=points.dtype))


@eqx.filter_jit
def _normals_jit(field, points, method, step):
    return outward_normals(field, points, method, step)


def level_set_mesh(field: AbstractField, level: float, resolution: int = 100) -> trimesh.Trimesh:
    """The surface {phi = level} by marching cubes (scikit-image) on a grid over the field's box.

    The grid is padded with one layer of zeros, so a surface that reaches the box (a floater at
    the domain's edge) still closes. Faces are wound outward (positive volume).

    Args:
        level: the density level, in the field's own units.
        resolution: grid nodes along the box's longest side (voxels are cubes).

    Raises:
        MeshError: no surface at that level (it is above the field's maximum or not positive).
    """
    from skimage.measure import marching_cubes

    if not level > 0:
        raise MeshError(f"the level must be a positive density, got {level}")
    if resolution < 8:
        raise MeshError(f"resolution must be >= 8, got {resolution}")
    lo, hi = (np.asarray(b, dtype=float) for b in field.bounds)
    h = float(np.max(hi - lo)) / (resolution - 1)
    shape = tuple(int(np.ceil((hi[i] - lo[i]) / h)) + 1 for i in range(3))
    nodes = grid_nodes((tuple(lo), tuple(lo + h * (np.asarray(shape) - 1))), shape)  # type: ignore[arg-type]
    values = np.pad(evaluate(field, nodes.reshape(-1, 3)).reshape(shape), 1)
    if not values.max() > level:
        raise MeshError(f"no surface at level {level:g}: the field's densities are at most {values.max():g}")
    verts, faces, _, _ = marching_cubes(values, level=level, spacing=(h, h, h))
    return outward(trimesh.Trimesh(verts + lo - h, faces, process=True))


def outward(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """The mesh with its faces wound outward (positive volume), inverted in place if they were not."""
    if mesh.volume < 0:
        mesh.invert()
    return mesh


def surface_mesh(dano: DANO, resolution: int = 64) -> trimesh.Trimesh:
    """The DANO's surface as a triangle mesh in its body frame (the object frame shifted to the
    centre of mass): marching cubes of its baked density grid at the middle of its density window,
    the band its surface points were drawn from. For pictures and for plain MuJoCo's visual geoms;
    the contact model never uses it.

    Raises:
        MeshError: the DANO carries no baked grid (a reference collider: rebuild it with `dano build`).
    """
    if dano.grid is None or dano.grid_bounds is None:
        raise MeshError("the DANO carries no density grid to mesh: rebuild it with `dano build`")
    level = 0.5 * float(dano.window[0] + dano.window[1])
    mesh = level_set_mesh(GridField(dano.grid, dano.grid_bounds), level, resolution)
    mesh.apply_translation(-np.asarray(dano.com, dtype=float))
    return mesh
