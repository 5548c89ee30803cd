"""Files: atomic `.npz` writing, pickle-free reading, the `.dano.npz` format, reference colliders.

`.dano.npz` (format "dano", version 1) holds one array per `DANO` attribute plus `format`,
`version` and `source`. Files are written to a temporary name in the target folder and renamed,
so a crash never leaves half a file; they are read with `allow_pickle=False`.
"""

import contextlib
import os
import shutil
import tempfile
import zipfile
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np

from dano.errors import DanoError, DanoFileError
from dano.types import DANO

FORMAT = "dano"
VERSION = 2
READABLE = (1, 2)
"""Version 2 added the optional `peak`, `grid` and `grid_bounds` (for DANO-DANO contact)."""
_ARRAYS = ("mass", "com", "inertia", "points", "densities", "normals", "alpha", "window",
           "mass_stderr", "com_stderr", "inertia_stderr")  # fmt: skip


def _shapes(n: int) -> dict[str, tuple[int, ...]]:
    return {"mass": (), "com": (3,), "inertia": (3, 3), "points": (n, 3), "densities": (n,), "normals": (n, 3),
            "alpha": (), "window": (2,), "mass_stderr": (), "com_stderr": (3,), "inertia_stderr": (3, 3)}  # fmt: skip


def _usual_permissions(path: Path, mode: int) -> None:
    """`mode` less the process's umask (mkstemp and mkdtemp leave files and folders private)."""
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(path, mode & ~umask)


@contextlib.contextmanager
def atomic_write(path: str | Path, suffix: str = ".tmp") -> Iterator[Path]:
    """Yields a temporary path beside `path`; renamed onto `path` if the block succeeds, else removed.

    So a crash or an error never leaves half a file. The file gets the usual permissions (mkstemp
    would leave 0600).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=suffix)
    os.close(fd)
    tmp = Path(name)
    try:
        yield tmp
        _usual_permissions(tmp, 0o666)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


@contextlib.contextmanager
def atomic_folder(path: str | Path) -> Iterator[Path]:
    """Yields a temporary folder beside `path`; renamed onto `path` (replacing what is there) if the
    block succeeds, else removed: a folder of outputs appears complete or not at all."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp"))
    try:
        yield tmp
        _usual_permissions(tmp, 0o777)
        if path.exists():
            old = tmp.with_suffix(".old")
            os.replace(path, old)
            os.replace(tmp, path)
            shutil.rmtree(old) if old.is_dir() else old.unlink()
        else:
            os.replace(tmp, path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def atomic_savez(path: str | Path, **arrays) -> None:
    """`np.savez_compressed` to `path` via a temporary file and an atomic rename."""
    with atomic_write(path) as tmp, open(tmp, "wb") as f:
        data: dict[str, Any] = {k: np.asarray(v) for k, v in arrays.items()}  # Any: no key is `allow_pickle`
        np.savez_compressed(f, **data)
        f.flush()
        os.fsync(f.fileno())


def load_npz(path: str | Path, required: Iterable[str] = ()) -> dict[str, np.ndarray]:
    """Reads every array of an `.npz` without pickle.

    Raises:
        DanoFileError: the file is missing, not an npz, holds object arrays, or lacks a key.
    """
    path = Path(path)
    if not path.is_file():
        raise DanoFileError(f"{path}: no such file")
    try:
        # Open the file ourselves: np.load leaks its handle when the zip is corrupt.
        with open(path, "rb") as fh, np.load(fh, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (ValueError, OSError, zipfile.BadZipFile, EOFError) as e:
        raise DanoFileError(f"{path}: not a readable .npz file ({e})") from None
    missing = [k for k in required if k not in data]
    if missing:
        raise DanoFileError(f"{path}: missing arrays {missing}")
    return data


def save_dano(path: str | Path, dano: DANO) -> None:
    """Writes `dano` to `path` (conventionally `*.dano.npz`) atomically."""
    arrays = {name: np.asarray(getattr(dano, name)) for name in _ARRAYS}
    if dano.peak is not None:
        arrays["peak"] = np.asarray(dano.peak)
    if dano.grid is not None:
        arrays |= {"grid": np.asarray(dano.grid), "grid_bounds": np.asarray(dano.grid_bounds)}
    atomic_savez(path, format=np.str_(FORMAT), version=np.int64(VERSION), source=np.str_(dano.source), **arrays)


def load_dano(path: str | Path) -> DANO:
    """Reads a `.dano.npz` written by `save_dano`.

    Raises:
        DanoFileError: corrupt file, another format or version, bad shapes or non-finite values.
    """
    data = load_npz(path, required=("format", "version"))
    if str(data["format"]) != FORMAT:
        raise DanoFileError(f"{path}: format is {str(data['format'])!r}, expected {FORMAT!r}")
    if data["version"].shape != () or data["version"].dtype.kind not in "iu" or int(data["version"]) not in READABLE:
        raise DanoFileError(f"{path}: format version {data['version']} is not supported (this dano reads {READABLE})")
    missing = [k for k in _ARRAYS if k not in data]
    if missing:
        raise DanoFileError(f"{path}: missing arrays {missing}")
    for name in _ARRAYS:
        if data[name].dtype.kind != "f" or not np.all(np.isfinite(data[name])):
            raise DanoFileError(f"{path}: array {name!r} must be finite floats")
    n = data["points"].shape[0] if data["points"].ndim == 2 else -1
    for name, shape in _shapes(n).items():
        if data[name].shape != shape:
            raise DanoFileError(f"{path}: array {name!r} has shape {data[name].shape}, expected {shape}")
    extra = _optional(path, data)
    try:
        return DANO(**{k: jnp.asarray(data[k]) for k in _ARRAYS}, source=str(data.get("source", "")), **extra)
    except (ValueError, DanoError) as e:  # bad shapes, a non-positive mass
        raise DanoFileError(f"{path}: {e}") from None


def _optional(path, data: dict[str, np.ndarray]) -> dict:
    """The optional version-2 arrays, checked."""
    extra: dict = {}
    for name in ("peak", "grid", "grid_bounds"):
        if name in data and data[name].dtype.kind not in "fiu":
            raise DanoFileError(f"{path}: array {name!r} must be numbers, got {data[name].dtype}")
    if "peak" in data:
        if data["peak"].shape != () or not (np.isfinite(data["peak"]) and data["peak"] > 0):
            raise DanoFileError(f"{path}: 'peak' must be a positive number")
        extra["peak"] = jnp.asarray(data["peak"])
    if "grid" in data:
        grid, gb = data["grid"], data.get("grid_bounds")
        if grid.ndim != 3 or gb is None or gb.shape != (2, 3) or not np.all(gb[1] > gb[0]):
            raise DanoFileError(f"{path}: 'grid' must be 3-D with 'grid_bounds' of shape (2, 3)")
        if not np.all(np.isfinite(grid)) or np.any(grid < 0):
            raise DanoFileError(f"{path}: 'grid' must be finite and non-negative")
        extra["grid"] = jnp.asarray(grid)
        extra["grid_bounds"] = (tuple(map(float, gb[0])), tuple(map(float, gb[1])))
    return extra
