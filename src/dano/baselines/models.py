"""The collision models of one object the mesh path is measured with: level-set meshes cut into
convex pieces (MuJoCo C's colliders), the DANO, the true mesh, and the paper authors' reference
models; each with its volume, centre of mass and inertia per mass for the comparison."""

import dataclasses
import time
from typing import cast

import numpy as np
import trimesh

from dano.baselines.mesh import CACHE, clean_mesh, decompose
from dano.errors import DanoError
from dano.extras import require
from dano.fields import AbstractField
from dano.surface import level_set_mesh, outward
from dano.types import DANO


class CompareError(DanoError, ValueError):
    """Bad input to the comparison (no levels, a level with no surface, a bad scenario)."""


@dataclasses.dataclass(frozen=True)
class Model:
    """One collision model of the object.

    Attributes:
        label: e.g. "level 3", "DANO", "truth".
        volume: m^3 (for the DANO, mass / (alpha * peak)).
        com: (3,) centre of mass, field frame, m.
        inertia_per_mass: (3, 3) inertia about the centre of mass divided by the mass, m^2.
        mesh: the level-set (or true) mesh, for the figure; None for the DANO.
        pieces: its convex pieces (MuJoCo's colliders); None for the DANO.
        dano: the DANO; None for meshes.
        preprocess_s: seconds to make it from the field (marching cubes, clean-up, decomposition;
            for the DANO, `build_dano`), as measured by the caller or here.
    """

    label: str
    volume: float
    com: np.ndarray
    inertia_per_mass: np.ndarray
    mesh: trimesh.Trimesh | None = None
    pieces: list | None = None
    dano: DANO | None = None
    preprocess_s: float = 0.0


def mesh_model(
    label: str,
    mesh: trimesh.Trimesh,
    decomposition: str = "coacd",
    threshold: float = 0.05,
    max_hulls: int = -1,
    cache_dir=CACHE,
    progress: bool = True,
    preprocess_s: float = 0.0,
    max_faces: int = 10000,
) -> Model:
    """A mesh as a collision model: convex pieces (the mesh itself if convex), and the mass properties
    of the mesh (of the pieces when the mesh is not watertight, e.g. a NeRF level set with holes).

    The decomposition runs on a copy decimated to `max_faces` (quadric decimation; CoACD's time grows
    with the face count), the mass properties come from the mesh as given."""
    if mesh.is_convex:
        pieces, seconds = [mesh], 0.0
    else:
        start = time.perf_counter()
        if len(mesh.faces) > max_faces:
            require("fast_simplification", "decimating a mesh before its decomposition")
        coarse = mesh.simplify_quadric_decimation(face_count=max_faces) if len(mesh.faces) > max_faces else mesh
        decimation = time.perf_counter() - start
        pieces, seconds = decompose(coarse, decomposition, threshold, max_hulls, cache_dir, progress)
        seconds += decimation
    elapsed = preprocess_s + seconds  # the decomposition's own time, also when it came from the cache
    if not mesh.is_watertight:  # no inside to integrate: the pieces' mass properties, as MuJoCo's own
        return _pieces_model(label, mesh, pieces, elapsed)
    volume = float(mesh.volume)
    com = np.asarray(mesh.center_mass, dtype=float)
    inertia = np.asarray(mesh.moment_inertia, dtype=float) / volume  # trimesh: unit density, about the com
    return Model(label, volume, com, inertia, mesh, pieces, None, elapsed)


def dano_model(label: str, dano: DANO, preprocess_s: float = 0.0) -> Model:
    """A DANO as a collision model. Its volume-equivalent is mass / (alpha * peak); unknown (nan,
    reported as None) when the field's peak is (the authors' colliders)."""
    mass = float(dano.mass)
    volume = float("nan") if dano.peak is None else mass / (float(dano.alpha) * float(dano.peak))
    return Model(label, volume, np.asarray(dano.com), np.asarray(dano.inertia) / mass, None, None, dano, preprocess_s)


def level_set_models(
    field: AbstractField,
    levels: list[float],
    resolution: int = 100,
    clean: bool = False,
    decomposition: str = "coacd",
    threshold: float = 0.05,
    max_hulls: int = -1,
    cache_dir=CACHE,
    progress: bool = True,
    max_faces: int = 10000,
) -> list[Model]:
    """One mesh model per density level: marching cubes, optional clean-up, convex decomposition."""
    if not levels:
        raise CompareError("give at least one density level")
    models = []
    for level in levels:
        start = time.perf_counter()
        mesh = level_set_mesh(field, level, resolution)
        if clean:
            mesh = clean_mesh(mesh)
        elapsed = time.perf_counter() - start
        models.append(
            mesh_model(
                f"level {level:g}", mesh, decomposition, threshold, max_hulls, cache_dir, progress, elapsed, max_faces
            )
        )
    return models


def _geometry(model: Model) -> np.ndarray:
    """(n, 3) points of the model's surface in its field frame (mesh vertices, else the DANO's points)."""
    if model.mesh is not None:
        return np.asarray(model.mesh.vertices, dtype=float)
    return np.asarray(model.dano.points)  # type: ignore[union-attr]


REFERENCE_LEVELS = {
    "bluesoap": {3.0: "levelsets/bluesoap_level_3_decomposed.obj", 70.0: "levelsets/bluesoap_level_70.stl",
                 100.0: "levelsets/bluesoap_level_100.obj"},
    "halfsoap": {20.0: "halfsoap_low.obj", 40.0: "halfsoap_high.obj"},
    "bunny": {10.0: "levelsets/bunny_level_10.obj", 100.0: "levelsets/bunny_level_100.obj",
              200.0: "levelsets/bunny_level_200.obj"},
}  # fmt: skip
"""The authors' level-set meshes per reference object (paths under `shared/data/dojo/meshes`, collider
frame; see its README): raw density level -> file. Files named `*_decomposed.obj` are convex pieces
already (one `o` group each)."""


def reference_models(
    name: str,
    data_dir,
    max_faces: int = 10000,
    decomposition: str = "coacd",
    threshold: float = 0.05,
    max_hulls: int = -1,
    cache_dir=CACHE,
    progress: bool = True,
) -> tuple[list[Model], Model]:
    """The authors' level-set meshes of a reference object as mesh models, and its DANO collider.

    Meshes are welded, wound outward, decimated to `max_faces` (quadric decimation) and decomposed;
    the authors' own decomposition is used where they give one.

    Raises:
        CompareError: an unknown name or a missing file.
    """
    from pathlib import Path

    from dano.reference import load_reference

    if name not in REFERENCE_LEVELS:
        raise CompareError(f"no reference level sets for {name!r}; known: {sorted(REFERENCE_LEVELS)}")
    root = Path(data_dir)
    collider = root / "colliders" / f"{name}_collider.npz"
    if not collider.is_file():
        raise CompareError(f"{collider} not found: --data-dir must be the folder with colliders/ and meshes/")
    models = []
    for level, rel in REFERENCE_LEVELS[name].items():
        path = root / "meshes" / rel
        if not path.is_file():
            raise CompareError(f"{path} not found")
        start = time.perf_counter()
        if path.stem.endswith("_decomposed"):
            pieces = _obj_groups(path)
            whole = cast(trimesh.Trimesh, trimesh.util.concatenate(pieces))
            models.append(_pieces_model(f"level {level:g}", whole, pieces, time.perf_counter() - start))
            continue
        mesh = outward(cast(trimesh.Trimesh, trimesh.load(path, force="mesh", process=True)))
        mesh.merge_vertices()
        models.append(mesh_model(f"level {level:g}", mesh, decomposition, threshold, max_hulls, cache_dir, progress,
                                 time.perf_counter() - start, max_faces))  # fmt: skip
    return models, dano_model("DANO (authors')", load_reference(collider))


def _obj_groups(path) -> list[trimesh.Trimesh]:
    """The `o` groups of an OBJ file as separate meshes, each its vertices' convex hull (wound outward)."""
    groups: list[list[list[float]]] = []
    with open(path, encoding="utf-8") as f:
        for line in f:
            if line.startswith("o "):
                groups.append([])
            elif line.startswith("v ") and groups:
                groups[-1].append([float(v) for v in line.split()[1:4]])
    if not groups:
        raise CompareError(f"{path}: no 'o' groups (convex pieces) in the file")
    return [trimesh.convex.convex_hull(np.asarray(g)) for g in groups if len(g) >= 4]


def _pieces_model(label: str, whole: trimesh.Trimesh, pieces: list, preprocess_s: float) -> Model:
    """Mass properties of a set of convex pieces, summed piece by piece (they barely overlap)."""
    volumes = np.array([p.volume for p in pieces])
    com = sum(v * p.center_mass for v, p in zip(volumes, pieces, strict=True)) / volumes.sum()
    inertia = np.zeros((3, 3))
    for v, p in zip(volumes, pieces, strict=True):
        r = p.center_mass - com
        inertia += p.moment_inertia + v * (r @ r * np.eye(3) - np.outer(r, r))
    return Model(label, float(volumes.sum()), com, inertia / volumes.sum(), whole, pieces, None, preprocess_s)
