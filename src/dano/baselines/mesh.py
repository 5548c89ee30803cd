"""Mesh baseline: convex decomposition (CoACD, cached on disk) and a MuJoCo C model of the pieces."""

import hashlib
import json
from pathlib import Path

import mujoco
import numpy as np
import trimesh

from dano.io import atomic_savez, load_npz

CACHE = Path.home() / ".cache" / "dano" / "coacd"


def convex_decomposition(
    mesh: trimesh.Trimesh, threshold: float = 0.05, max_hulls: int = -1, cache_dir: Path | None = CACHE
) -> list[trimesh.Trimesh]:
    """CoACD convex pieces of a watertight mesh, cached by mesh hash and parameters.

    Args:
        threshold: CoACD's concavity threshold (smaller: more, tighter pieces; slower).
        max_hulls: cap on the number of pieces (-1: none).
        cache_dir: where decompositions are kept (None: no cache).
    """
    key = hashlib.sha256(
        np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes()
        + np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes()
        + json.dumps({"threshold": threshold, "max_hulls": max_hulls}).encode()
    ).hexdigest()[:24]
    path = None if cache_dir is None else Path(cache_dir) / f"{key}.npz"
    if path is not None and path.is_file():
        data = load_npz(path)
        n = int(data["count"])
        return [trimesh.Trimesh(data[f"v{i}"], data[f"f{i}"]) for i in range(n)]
    import coacd

    coacd.set_log_level("error")
    parts = coacd.run_coacd(coacd.Mesh(mesh.vertices, mesh.faces), threshold=threshold, max_convex_hull=max_hulls)
    pieces = [trimesh.Trimesh(v, f) for v, f in parts]
    if path is not None:
        arrays = {f"v{i}": p.vertices for i, p in enumerate(pieces)} | {f"f{i}": p.faces for i, p in enumerate(pieces)}
        atomic_savez(path, count=np.int64(len(pieces)), **arrays)
    return pieces


def mujoco_mesh_model(
    pieces: list[trimesh.Trimesh],
    mass: float,
    pos=(0.0, 0.0, 0.1),
    quat=(1.0, 0.0, 0.0, 0.0),
    friction: float = 0.5,
    timestep: float = 0.002,
    ground: bool = True,
) -> mujoco.MjModel:
    """A MuJoCo (C engine) model: one free body made of convex mesh geoms, on a ground plane.

    Mass is `mass`, spread over the pieces by volume; MuJoCo computes the inertia from the meshes.
    """
    return mujoco_mesh_spec(pieces, mass, pos, quat, friction, timestep, ground).compile()


def mujoco_mesh_spec(
    pieces: list[trimesh.Trimesh],
    mass: float,
    pos=(0.0, 0.0, 0.1),
    quat=(1.0, 0.0, 0.0, 0.0),
    friction: float = 0.5,
    timestep: float = 0.002,
    ground: bool = True,
) -> mujoco.MjSpec:
    """The uncompiled `mujoco_mesh_model`, for adding more to the scene (the body is "object")."""
    spec = mujoco.MjSpec()
    spec.option.timestep = timestep
    if ground:
        spec.worldbody.add_geom(type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0, 0, 1], friction=[friction, 0.005, 0.0001])
    body = spec.worldbody.add_body(name="object", pos=list(pos), quat=list(quat))
    body.add_freejoint()
    density = mass / sum(p.volume for p in pieces)
    for i, p in enumerate(pieces):
        spec.add_mesh(name=f"piece{i}", uservert=p.vertices.ravel().tolist(), userface=p.faces.ravel().tolist())
        body.add_geom(type=mujoco.mjtGeom.mjGEOM_MESH, meshname=f"piece{i}", density=density,
                      friction=[friction, 0.005, 0.0001])  # fmt: skip
    return spec
