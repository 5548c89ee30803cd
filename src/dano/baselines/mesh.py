"""The mesh path the paper argues against (Sec. VI): field -> level-set mesh -> convex pieces -> MuJoCo.

Each step is a small function with its knobs exposed:
`dano.surface.level_set_mesh` (marching cubes at a density level) -> `clean_mesh` (largest component, pymeshfix)
-> `convex_decomposition` (CoACD or V-HACD, cached on disk) -> `mujoco_mesh_model` (MuJoCo C).
`dano.baselines.compare` runs the same scenarios on these and on the DANO.
"""

import hashlib
import json
import sys
import threading
import time
from pathlib import Path

import mujoco
import numpy as np
import trimesh
from tqdm.auto import tqdm

from dano.errors import MeshError
from dano.extras import require
from dano.io import atomic_savez, load_npz

CACHE = Path.home() / ".cache" / "dano" / "convex"


def clean_mesh(mesh: trimesh.Trimesh, largest_component: bool = True, repair: bool = True) -> trimesh.Trimesh:
    """The usual clean-up of a level-set mesh: keep the largest connected piece (drops floaters),
    then make it watertight with pymeshfix.

    Raises:
        MeshError: nothing is left, or pymeshfix cannot close the mesh.
    """
    if largest_component:
        parts = mesh.split(only_watertight=False)
        if len(parts):
            mesh = max(parts, key=lambda p: (p.is_watertight, abs(p.volume) if p.is_watertight else p.area))
    if repair:
        from dano.fields.mesh import repair_mesh

        mesh = repair_mesh(mesh)
    if len(mesh.faces) == 0:
        raise MeshError("clean-up left an empty mesh")
    return mesh


def convex_decomposition(
    mesh: trimesh.Trimesh,
    method: str = "coacd",
    threshold: float = 0.05,
    max_hulls: int = -1,
    cache_dir: str | Path | None = CACHE,
    progress: bool = True,
) -> list[trimesh.Trimesh]:
    """Convex pieces of a mesh by CoACD (default) or V-HACD (`vhacdx`), cached by mesh hash and parameters.

    Decompositions are slow (CoACD takes minutes on a detailed mesh), so each result is kept in
    `cache_dir` under a hash of the vertices, faces, method and parameters; a progress bar shows the
    elapsed time while one runs.

    Args:
        method: "coacd" or "vhacd".
        threshold: CoACD's concavity threshold (smaller: more, tighter pieces; slower). For V-HACD,
            the allowed volume error in percent is `100 * threshold`.
        max_hulls: cap on the number of pieces (-1: none for CoACD, 64 for V-HACD).
        cache_dir: where decompositions are kept (None: no cache).

    Raises:
        MeshError: an unknown method, an empty mesh, or a decomposition with no pieces.
    """
    return decompose(mesh, method, threshold, max_hulls, cache_dir, progress)[0]


def decompose(
    mesh: trimesh.Trimesh,
    method: str = "coacd",
    threshold: float = 0.05,
    max_hulls: int = -1,
    cache_dir: str | Path | None = CACHE,
    progress: bool = True,
) -> tuple[list[trimesh.Trimesh], float]:
    """`convex_decomposition` and the seconds the decomposition took (when it ran, also on a cache hit)."""
    if method not in ("coacd", "vhacd"):
        raise MeshError(f"method must be 'coacd' or 'vhacd', got {method!r}")
    if len(mesh.faces) == 0:
        raise MeshError("cannot decompose an empty mesh")
    key = hashlib.sha256(
        np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes()
        + np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes()
        + json.dumps({"method": method, "threshold": threshold, "max_hulls": max_hulls}).encode()
    ).hexdigest()[:24]
    path = None if cache_dir is None else Path(cache_dir) / f"{method}-{key}.npz"
    if path is not None and path.is_file():
        data = load_npz(path)
        n = int(data["count"])
        return [trimesh.Trimesh(data[f"v{i}"], data[f"f{i}"]) for i in range(n)], float(data.get("seconds", np.nan))
    start = time.perf_counter()
    with _elapsed(f"{method} on {len(mesh.faces)} faces", progress):
        parts = _coacd(mesh, threshold, max_hulls) if method == "coacd" else _vhacd(mesh, threshold, max_hulls)
    seconds = time.perf_counter() - start
    pieces = [trimesh.Trimesh(v, f) for v, f in parts if len(f)]
    if not pieces:
        raise MeshError(f"{method} returned no convex pieces")
    if path is not None:
        arrays = {f"v{i}": p.vertices for i, p in enumerate(pieces)} | {f"f{i}": p.faces for i, p in enumerate(pieces)}
        atomic_savez(path, count=np.int64(len(pieces)), seconds=np.float64(seconds), **arrays)
    return pieces, seconds


def _coacd(mesh: trimesh.Trimesh, threshold: float, max_hulls: int):
    coacd = require("coacd", "CoACD convex decomposition")
    coacd.set_log_level("error")
    return coacd.run_coacd(coacd.Mesh(mesh.vertices, mesh.faces), threshold=threshold, max_convex_hull=max_hulls)


def _vhacd(mesh: trimesh.Trimesh, threshold: float, max_hulls: int):
    vhacdx = require("vhacdx", "V-HACD convex decomposition")
    return vhacdx.compute_vhacd(
        np.ascontiguousarray(mesh.vertices, dtype=np.float64), np.ascontiguousarray(mesh.faces, dtype=np.uint32),
        maxConvexHulls=64 if max_hulls < 1 else max_hulls, minimumVolumePercentErrorAllowed=100 * threshold,
    )  # fmt: skip


class _elapsed:
    """A progress bar that shows the elapsed time while a blocking call runs."""

    def __init__(self, what: str, enabled: bool):
        self.what, self.enabled = what, enabled

    def __enter__(self):
        if not self.enabled:
            return self
        self.bar = tqdm(desc=self.what, bar_format="{desc}: {elapsed}", mininterval=1.0)
        self.done = threading.Event()

        def tick():  # on a terminal only: a log gets the start and the end
            while not self.done.wait(1.0):
                if sys.stderr.isatty():
                    self.bar.refresh()

        self.thread = threading.Thread(target=tick, daemon=True)
        self.thread.start()
        return self

    def __exit__(self, *exc):
        if self.enabled:
            self.done.set()
            self.thread.join()
            self.bar.close()
        return False


def mujoco_mesh_model(pieces: list[trimesh.Trimesh], mass: float, **kwargs) -> mujoco.MjModel:
    """`mujoco_mesh_spec(pieces, mass, **kwargs)`, compiled."""
    return mujoco_mesh_spec(pieces, mass, **kwargs).compile()


def mujoco_mesh_spec(
    pieces: list[trimesh.Trimesh],
    mass: float,
    pos=(0.0, 0.0, 0.1),
    quat=(1.0, 0.0, 0.0, 0.0),
    friction: float = 0.5,
    timestep: float = 0.002,
    ground: bool = True,
    inertial: tuple[np.ndarray, np.ndarray] | None = None,
) -> mujoco.MjSpec:
    """A MuJoCo (C engine) model of one free body (named "object") made of convex mesh geoms, on a
    ground plane; uncompiled, so more can be added to the scene (`mujoco_mesh_model` compiles it).

    Mass is `mass`. Without `inertial`, it is spread over the pieces by volume and MuJoCo computes
    the inertia from them; `inertial = (com (3,), inertia about the com (3, 3))`, body frame, sets
    them explicitly (e.g. from the uncut mesh, which the pieces only approximate).
    """
    if not mass > 0:
        raise MeshError(f"mass must be positive, got {mass}")
    spec = mujoco.MjSpec()
    spec.option.timestep = timestep
    if ground:
        spec.worldbody.add_geom(type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0, 0, 1], friction=[friction, 0.005, 0.0001])
    body = spec.worldbody.add_body(name="object", pos=list(pos), quat=list(quat))
    body.add_freejoint()
    density = mass / sum(p.volume for p in pieces)
    if inertial is not None:
        com, inertia = (np.asarray(v, dtype=float) for v in inertial)
        body.explicitinertial = True
        body.mass, body.ipos = mass, com.tolist()
        body.fullinertia = [inertia[0, 0], inertia[1, 1], inertia[2, 2], inertia[0, 1], inertia[0, 2], inertia[1, 2]]
    for i, p in enumerate(pieces):
        spec.add_mesh(name=f"piece{i}", uservert=p.vertices.ravel().tolist(), userface=p.faces.ravel().tolist())
        body.add_geom(type=mujoco.mjtGeom.mjGEOM_MESH, meshname=f"piece{i}", friction=[friction, 0.005, 0.0001],
                      density=0.0 if inertial is not None else density)  # fmt: skip
    return spec
