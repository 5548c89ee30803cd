"""Pinhole cameras: rays, projection, look-at poses and camera files.

Cameras follow the NeRF/OpenGL convention: `c2w` (4, 4) maps camera to world coordinates; the
camera looks along its -z axis with +y up and +x right. Image coordinates are continuous,
(u, v) = (column, row) with v growing downward, and pixel (row i, column j) covers
[j, j + 1) x [i, i + 1), so its centre is (j + 0.5, i + 0.5). MuJoCo cameras use the same axes
(look along -z, +y up), so `c2w`'s rotation is MuJoCo's camera frame as it is.

A camera file is JSON `{"width", "height", "fx", "fy", "cx", "cy", "c2w"}` (pixels; c2w 4 x 4).
Every problem with an input file raises `VisionDataError` naming the file.
"""

import dataclasses
import json
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from jaxtyping import Float

from dano.errors import DanoFileError, InvalidValueError
from dano.io import atomic_write


class VisionDataError(DanoFileError):
    """An image, mask, camera, dataset or video file that cannot be used; the message names it."""


ORTHONORMAL_TOLERANCE = 1e-4
"""Largest allowed |R^T R - I| entry of a camera file's rotation (files hold ~8+ digits)."""
DATASET_ORTHONORMAL_TOLERANCE = 1e-3
"""The same for dataset `transform_matrix`es, which some tools write in single precision."""
VectorLike = np.ndarray | Sequence[float]
"""A small vector (a point, a colour): an array or a sequence of floats."""
MatrixLike = np.ndarray | Sequence[Sequence[float]]


@dataclasses.dataclass(frozen=True, eq=False)
class Camera:
    """A pinhole camera (no distortion) in the NeRF/OpenGL convention (module docstring).

    Attributes:
        width: image width, pixels.
        height: image height, pixels.
        fx: focal length along u, pixels.
        fy: focal length along v, pixels.
        cx: principal point u, pixels (width / 2 for a centred one).
        cy: principal point v, pixels, downward.
        c2w: (4, 4) camera-to-world transform, world units (m); its rotation is orthonormal.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    c2w: Float[np.ndarray, "4 4"]

    def __post_init__(self):
        c2w = np.array(self.c2w, dtype=np.float64)
        problem = _pose_problem(c2w, DATASET_ORTHONORMAL_TOLERANCE)
        if problem is not None:
            raise InvalidValueError(f"Camera: c2w {problem}")
        c2w.setflags(write=False)
        for name in ("width", "height"):
            object.__setattr__(self, name, int(getattr(self, name)))
        for name in ("fx", "fy", "cx", "cy"):
            object.__setattr__(self, name, float(getattr(self, name)))
        object.__setattr__(self, "c2w", c2w)
        if self.width < 1 or self.height < 1 or not (self.fx > 0 and self.fy > 0):
            raise InvalidValueError(f"Camera: need positive sizes and focal lengths, got {self}")
        if not (
            math.isfinite(self.fx) and math.isfinite(self.fy) and math.isfinite(self.cx) and math.isfinite(self.cy)
        ):
            raise InvalidValueError(f"Camera: intrinsics must be finite, got {self}")

    @property
    def rotation(self) -> Float[np.ndarray, "3 3"]:
        """(3, 3) camera-to-world rotation: columns are the camera's x (right), y (up), z (backward)."""
        return self.c2w[:3, :3]

    @property
    def position(self) -> Float[np.ndarray, "3"]:
        """(3,) the camera centre in world coordinates."""
        return self.c2w[:3, 3]

    def downscaled(self, k: int) -> "Camera":
        """The camera of its image box-averaged over k x k pixels (`dano.vision.media.box_downscale`):
        continuous image coordinates divide by k, a remainder of rows or columns is dropped."""
        if k == 1:
            return self
        w, h = self.width // k, self.height // k
        return Camera(w, h, self.fx / k, self.fy / k, self.cx / k, self.cy / k, self.c2w)


def camera_rays(camera: Camera) -> tuple[Float[np.ndarray, "p 3"], Float[np.ndarray, "p 3"]]:
    """Rays through the pixel centres, row-major (pixel index = v * width + u).

    Returns:
        origins: (height * width, 3) the camera centre, repeated, world frame.
        directions: (height * width, 3) unit directions, world frame.
    """
    u = np.arange(camera.width) + 0.5
    v = np.arange(camera.height) + 0.5
    uu, vv = np.meshgrid(u, v, indexing="xy")
    local = np.stack([(uu - camera.cx) / camera.fx, -(vv - camera.cy) / camera.fy, -np.ones_like(uu)], axis=-1)
    directions = local.reshape(-1, 3) @ camera.rotation.T
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    origins = np.broadcast_to(camera.position, directions.shape).copy()
    return origins, directions


def project(
    camera: Camera, points: Float[np.ndarray, "n 3"]
) -> tuple[Float[np.ndarray, "n 2"], Float[np.ndarray, " n"]]:
    """Projects world points into the image (the inverse of `camera_rays`).

    Args:
        camera: the camera.
        points: (n, 3) world frame.

    Returns:
        uv: (n, 2) continuous pixel coordinates (u right, v down; pixel centres at +0.5).
        depth: (n,) distance along the viewing axis (-z of the camera), positive in front; points
            with depth <= 0 are behind the camera and their uv is meaningless.
    """
    local = (np.asarray(points, dtype=np.float64) - camera.position) @ camera.rotation
    depth = -local[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = camera.cx + camera.fx * local[:, 0] / depth
        v = camera.cy - camera.fy * local[:, 1] / depth
    return np.stack([u, v], axis=1), depth


def look_at(eye: VectorLike, target: VectorLike, up: VectorLike = (0.0, 0.0, 1.0)) -> Float[np.ndarray, "4 4"]:
    """The c2w (4, 4) of a camera at `eye` looking at `target`, with `up` pointing up in the image.

    If the view direction is parallel to `up` the world axis least aligned with it serves instead.

    Example:
        >>> camera = camera_from_fov(64, 64, math.radians(40), look_at((0.5, 0, 0.2), (0, 0, 0)))
    """
    eye, target, up = (np.asarray(a, dtype=np.float64) for a in (eye, target, up))
    forward = target - eye
    if not np.linalg.norm(forward) > 0:
        raise InvalidValueError(f"look_at: eye {eye} and target {target} coincide")
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-6 * max(np.linalg.norm(up), 1e-300):
        right = np.cross(forward, np.eye(3)[np.argmin(np.abs(forward))])
    right /= np.linalg.norm(right)
    c2w = np.eye(4)
    c2w[:3, :3] = np.stack([right, np.cross(right, forward), -forward], axis=1)
    c2w[:3, 3] = eye
    return c2w


def camera_from_fov(width: int, height: int, fov_x: float, c2w: MatrixLike) -> Camera:
    """A camera with square pixels and a centred principal point.

    Args:
        width, height: image size, pixels.
        fov_x: horizontal field of view, rad (NeRF's `camera_angle_x`).
        c2w: (4, 4) camera-to-world transform.
    """
    fx = 0.5 * width / math.tan(0.5 * fov_x)
    return Camera(width, height, fx, fx, 0.5 * width, 0.5 * height, np.asarray(c2w, dtype=np.float64))


def save_camera(path: str | Path, camera: Camera) -> None:
    """Writes `camera` as JSON (format in the module docstring), atomically."""
    record = {k: getattr(camera, k) for k in ("width", "height", "fx", "fy", "cx", "cy")}
    record["c2w"] = camera.c2w.tolist()
    with atomic_write(path, suffix=".json") as tmp:
        tmp.write_text(json.dumps(record, indent=2) + "\n")


def load_camera(path: str | Path) -> Camera:
    """Reads a camera written by `save_camera`.

    Raises:
        VisionDataError: naming the file: missing keys, non-positive sizes or focal lengths, a c2w
            that is not 4 x 4, finite, with bottom row (0, 0, 0, 1) and an orthonormal rotation.
    """
    path = Path(path)
    record = _read_json(path)
    missing = [k for k in ("width", "height", "fx", "fy", "cx", "cy", "c2w") if k not in record]
    if missing:
        raise VisionDataError(f"{path}: missing key(s) {missing}")
    width, height = (_positive_int(record[k], f"{path}: {k!r}") for k in ("width", "height"))
    fx, fy = (_number(record[k], f"{path}: {k!r}", positive=True) for k in ("fx", "fy"))
    cx, cy = (_number(record[k], f"{path}: {k!r}") for k in ("cx", "cy"))
    c2w = _matrix(record["c2w"], f"{path}: 'c2w'", ORTHONORMAL_TOLERANCE)
    return Camera(width, height, fx, fy, cx, cy, c2w)


def _pose_problem(c2w: np.ndarray, tolerance: float) -> str | None:
    """What is wrong with a camera-to-world matrix, or None."""
    if c2w.shape != (4, 4):
        return f"must be 4 x 4, got shape {c2w.shape}"
    if not np.all(np.isfinite(c2w)):
        return "has NaN or infinite entries"
    if not np.allclose(c2w[3], (0.0, 0.0, 0.0, 1.0), rtol=0.0, atol=1e-9):
        return f"bottom row must be 0, 0, 0, 1, got {c2w[3].tolist()}"
    R = c2w[:3, :3]
    error = float(np.max(np.abs(R.T @ R - np.eye(3))))
    if error > tolerance or np.linalg.det(R) < 0:
        return f"rotation is not orthonormal and right-handed (|R^T R - I| = {error:.2g}, det {np.linalg.det(R):.4g})"
    return None


def _matrix(value, where: str, tolerance: float) -> np.ndarray:
    try:
        c2w = np.array(value, dtype=np.float64)
    except (ValueError, TypeError):
        raise VisionDataError(f"{where} must be a 4 x 4 list of numbers") from None
    problem = _pose_problem(c2w, tolerance)
    if problem is not None:
        raise VisionDataError(f"{where} {problem}")
    return c2w


def _number(value, where: str, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise VisionDataError(f"{where} must be a finite number, got {value!r}")
    if positive and not value > 0:
        raise VisionDataError(f"{where} must be positive, got {value!r}")
    return float(value)


def _positive_int(value, where: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int | float) or value != int(value) or value < 1:
        raise VisionDataError(f"{where} must be a positive integer, got {value!r}")
    return int(value)


def _read_json(path: Path) -> dict:
    if not path.is_file():
        raise VisionDataError(f"{path}: no such file")
    try:
        record = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise VisionDataError(f"{path}: not readable JSON ({e})") from None
    if not isinstance(record, dict):
        raise VisionDataError(f"{path}: expected a JSON object, got {type(record).__name__}")
    return record
