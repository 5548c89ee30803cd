"""Density field of a watertight triangle mesh: its occupancy, baked to a grid with a soft edge.

Host work, done once: the grid nodes' inside/outside test (trimesh with Embree), the exact distance
to the surface for the nodes within `width` of it, and phi = peak * S(-d / width) at every node
(the same soft-boundary law as the analytic fields). The result is a `GridField`, so queries are a
trilinear interpolation, and the normals -grad phi / |grad phi| follow the true surface instead of
the voxel staircase a 0/1 occupancy would give.
"""

from pathlib import Path

import jax.numpy as jnp
import numpy as np
import trimesh
from scipy import ndimage
from tqdm.auto import tqdm

from dano.errors import MeshError, MeshNotWatertightError
from dano.fields.grid import GridField, grid_nodes
from dano.math import smootherstep

MESH_SUFFIXES = (".ply", ".obj", ".stl", ".off", ".glb", ".gltf")


def load_mesh(path: str | Path, repair: bool = False, scale: float = 1.0) -> trimesh.Trimesh:
    """Loads a triangle mesh as one watertight `Trimesh`, lengths multiplied by `scale`.

    Args:
        path: a `.ply`, `.obj`, `.stl`, `.off`, `.glb` or `.gltf` file.
        repair: fill holes and drop stray pieces with pymeshfix when the mesh is not watertight.
        scale: metres per mesh unit.

    Raises:
        MeshError: unreadable file or no triangles.
        MeshNotWatertightError: the mesh has holes and `repair` is False.
    """
    path = Path(path)
    if not path.is_file():
        raise MeshError(f"{path}: no such file")
    try:
        mesh = trimesh.load(path, force="mesh", process=True)
    except Exception as e:  # trimesh raises many kinds on a malformed file
        raise MeshError(f"{path}: cannot read mesh ({type(e).__name__}: {e})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise MeshError(f"{path}: no triangles found")
    if not mesh.is_watertight:
        if not repair:
            raise MeshNotWatertightError(
                f"{path} is not watertight ({len(mesh.split(only_watertight=False))} pieces, open edges): "
                "repair it with pymeshfix (pass repair=True, or --repair on the command line)"
            )
        mesh = repair_mesh(mesh)
    if mesh.volume < 0:
        mesh.invert()
    if scale != 1.0:
        mesh.apply_scale(scale)
    return mesh


def repair_mesh(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """Makes a mesh watertight with pymeshfix (keeps the largest piece, fills holes)."""
    import pymeshfix

    vertices, faces = pymeshfix.clean_from_arrays(
        np.ascontiguousarray(mesh.vertices, dtype=np.float64), np.ascontiguousarray(mesh.faces, dtype=np.int32)
    )
    repaired = trimesh.Trimesh(vertices, faces, process=True)
    if not repaired.is_watertight:
        raise MeshNotWatertightError("pymeshfix could not make the mesh watertight")
    return repaired


def mesh_field(
    mesh: trimesh.Trimesh,
    resolution: int = 96,
    width_voxels: float = 2.0,
    peak: float = 1000.0,
    progress: bool = True,
) -> GridField:
    """Bakes a watertight mesh into a soft-occupancy grid field.

    Args:
        mesh: watertight mesh, lengths in m (see `load_mesh`).
        resolution: nodes along the longest side of the mesh's box; voxels are cubes.
        width_voxels: half-width of the soft boundary in voxels (phi falls from peak to 0 over
            2 * width_voxels voxels centred on the surface).
        peak: density inside, kg/m^3 at mass scale 1 (default: water).
        progress: show a progress bar.

    Returns:
        A `GridField` whose 1/2 level set is the mesh surface.
    """
    if not mesh.is_watertight:
        raise MeshNotWatertightError("the mesh is not watertight: repair it with pymeshfix first")
    if resolution < 8:
        raise MeshError(f"resolution must be >= 8, got {resolution}")
    h = float(np.max(mesh.extents)) / (resolution - 1)
    width = width_voxels * h
    pad = width + 2 * h
    lo, hi = mesh.bounds[0] - pad, mesh.bounds[1] + pad
    shape = tuple(int(np.ceil((hi[i] - lo[i]) / h)) + 1 for i in range(3))
    hi = lo + h * (np.asarray(shape) - 1)
    bounds = (tuple(lo), tuple(hi))
    nodes = grid_nodes(bounds, shape).reshape(-1, 3)  # type: ignore[arg-type]

    chunk = 1 << 16
    inside = np.empty(len(nodes), dtype=bool)
    for start in tqdm(range(0, len(nodes), chunk), desc="mesh occupancy", disable=not progress, unit="chunk"):
        inside[start : start + chunk] = mesh.contains(nodes[start : start + chunk])
    inside = inside.reshape(shape)

    # Only nodes near a change of occupancy can lie within `width` of the surface.
    reach = int(np.ceil(width / h)) + 1
    core = np.asarray(ndimage.binary_erosion(inside, iterations=reach), dtype=bool)
    near = ndimage.binary_dilation(inside, iterations=reach) & ~core
    band = np.flatnonzero(near.ravel())
    distance = np.full(len(nodes), np.inf)
    for start in tqdm(range(0, len(band), 8192), desc="surface distance", disable=not progress, unit="chunk"):
        idx = band[start : start + 8192]
        distance[idx] = trimesh.proximity.closest_point(mesh, nodes[idx])[1]
    signed = np.where(inside.ravel(), -distance, distance)
    density = peak * np.asarray(smootherstep(jnp.asarray(-signed / width)))
    return GridField(jnp.asarray(density.reshape(shape)), bounds)
