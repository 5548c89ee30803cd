"""Pixels in and out: pinhole cameras, NeRF-style datasets, rendered ground truth, videos and masks.

Cameras follow the NeRF/OpenGL convention: `c2w` (4, 4) maps camera to world coordinates; the
camera looks along its -z axis with +y up and +x right. Image coordinates are continuous,
(u, v) = (column, row) with v growing downward, and pixel (row i, column j) covers
[j, j + 1) x [i, i + 1), so its centre is (j + 0.5, i + 0.5). MuJoCo cameras use the same axes
(look along -z, +y up), so `c2w`'s rotation is MuJoCo's camera frame as it is.

Files:
- Multi-view datasets use the NeRF-synthetic layout (also read from instant-ngp and nerfstudio):
  `transforms_{split}.json` or `transforms.json` holding `camera_angle_x` (horizontal field of
  view, rad) or `fl_x`, `fl_y`, `cx`, `cy`, `w`, `h` (pixels; per-frame overrides allowed), and
  `frames[]` with `file_path` (relative to the folder, with or without extension) and
  `transform_matrix` (c2w). RGBA images carry the object's mask in alpha; otherwise a frame's
  `mask_path`, or `masks/<image stem>.png`, gives it. `render_views` writes this layout.
- A camera is JSON `{"width", "height", "fx", "fy", "cx", "cy", "c2w"}` (pixels; c2w 4 x 4).
- A video for tracking is a video file (anything PyAV reads: .mp4, .mov, .avi, .mkv, .webm) or a
  folder of .png/.jpg frames taken in name order; `render_video` writes `frames/000000.png`, ...,
  `masks/`, `camera.json` and the true poses `poses.csv` (`t,x,y,z,qw,qx,qy,qz`, read by
  `dano.sysid.read_tracks`).

Masks from any segmenter (SAM 2, XMem, rembg, a green screen, ...): write one single-channel or RGB
PNG per frame into a folder, white (255) = object and black (0) = background (grey = partial),
named so that sorting the names gives the frames' order; the frames' own stems do
(`frame_0001.png` -> `masks/frame_0001.png`), and for a video `000000.png`, `000001.png`, ...
`load_masks(folder, n_frames, (height, width))` reads them back and checks count and size. For
footage against a plain backdrop, `colour_key_masks` makes them directly.

Every problem with an input file raises `VisionDataError` naming the file.
"""

import contextlib
import dataclasses
import json
import math
import os
import shutil
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path

import imageio.v3 as iio
import mujoco
import numpy as np
import trimesh
from jaxtyping import Float
from tqdm.auto import tqdm

from dano.errors import DanoFileError, MeshError
from dano.io import atomic_write
from dano.sim.render import make_renderer
from dano.sysid.data import Track, write_track


class VisionDataError(DanoFileError):
    """An image, mask, camera, dataset or video file that cannot be used; the message names it."""


ORTHONORMAL_TOLERANCE = 1e-4
"""Largest allowed |R^T R - I| entry of a camera file's rotation (files hold ~8+ digits)."""
DATASET_ORTHONORMAL_TOLERANCE = 1e-3
"""The same for dataset `transform_matrix`es, which some tools write in single precision."""
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v")
VectorLike = np.ndarray | Sequence[float]
"""A small vector (a point, a colour): an array or a sequence of floats."""
MatrixLike = np.ndarray | Sequence[Sequence[float]]


# ---------------------------------------------------------------------------------------------
# Cameras


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
            raise ValueError(f"Camera: c2w {problem}")
        c2w.setflags(write=False)
        for name in ("width", "height"):
            object.__setattr__(self, name, int(getattr(self, name)))
        for name in ("fx", "fy", "cx", "cy"):
            object.__setattr__(self, name, float(getattr(self, name)))
        object.__setattr__(self, "c2w", c2w)
        if self.width < 1 or self.height < 1 or not (self.fx > 0 and self.fy > 0):
            raise ValueError(f"Camera: need positive sizes and focal lengths, got {self}")
        if not (
            math.isfinite(self.fx) and math.isfinite(self.fy) and math.isfinite(self.cx) and math.isfinite(self.cy)
        ):
            raise ValueError(f"Camera: intrinsics must be finite, got {self}")

    @property
    def rotation(self) -> Float[np.ndarray, "3 3"]:
        """(3, 3) camera-to-world rotation: columns are the camera's x (right), y (up), z (backward)."""
        return self.c2w[:3, :3]

    @property
    def position(self) -> Float[np.ndarray, "3"]:
        """(3,) the camera centre in world coordinates."""
        return self.c2w[:3, 3]


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
        raise ValueError(f"look_at: eye {eye} and target {target} coincide")
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


# ---------------------------------------------------------------------------------------------
# Multi-view datasets


@dataclasses.dataclass(frozen=True, eq=False)
class Views:
    """Posed images of one object.

    Attributes:
        images: (n, h, w, 3) float32 RGB in [0, 1], composited onto the background where masked out.
        masks: (n, h, w) float32 in [0, 1], 1 = object (fractional after downscaling), or None.
        cameras: n cameras, one per image, all of size (w, h).
        files: n image paths, for messages.
    """

    images: Float[np.ndarray, "n h w 3"]
    masks: Float[np.ndarray, "n h w"] | None
    cameras: tuple[Camera, ...]
    files: tuple[str, ...]

    def __post_init__(self):
        n = len(self.images)
        if len(self.cameras) != n or len(self.files) != n or (self.masks is not None and len(self.masks) != n):
            raise ValueError(f"Views: {n} images but {len(self.cameras)} cameras and {len(self.files)} files")

    @property
    def n_views(self) -> int:
        return len(self.images)


def load_nerf_synthetic(
    root: str | Path, split: str = "train", downscale: int = 1, background: VectorLike = (1.0, 1.0, 1.0)
) -> Views:
    """Reads a NeRF-synthetic / instant-ngp style dataset (format in the module docstring).

    Args:
        root: the dataset folder.
        split: reads `transforms_{split}.json` if present, else `transforms.json`.
        downscale: integer factor; images and masks are box-averaged over downscale^2 pixels (a
            remainder of rows or columns is cropped) and the intrinsics divided by it.
        background: (3,) RGB in [0, 1] that RGBA images are composited onto.

    Raises:
        VisionDataError: naming the file: no transforms file, a missing or unreadable image or
            mask, images of different sizes, a bad transform_matrix, a mask of another size than
            its image, an empty mask, or frames with and without masks mixed.

    Example:
        >>> views = load_nerf_synthetic("data/nerf_synthetic/lego", "train", downscale=4)
        >>> views.images.shape, views.cameras[0].fx
    """
    root = Path(root)
    if isinstance(downscale, bool) or not isinstance(downscale, int) or downscale < 1:
        raise VisionDataError(f"{root}: downscale must be a positive integer, got {downscale!r}")
    path = _transforms_file(root, split)
    meta = _read_json(path)
    frames = meta.get("frames")
    if not isinstance(frames, list) or not frames:
        raise VisionDataError(f"{path}: no 'frames' list")
    bg = np.asarray(background, dtype=np.float32).reshape(3)
    images, masks, cameras, files = [], [], [], []
    for k, frame in enumerate(frames):
        where = f"{path}, frame {k}"
        if not isinstance(frame, dict) or "file_path" not in frame or "transform_matrix" not in frame:
            raise VisionDataError(f"{where}: needs 'file_path' and 'transform_matrix'")
        image_file = _image_file(root, frame["file_path"], where)
        rgb, alpha = _read_rgba(image_file, bg)
        if images and rgb.shape != images[0].shape:
            raise VisionDataError(f"{image_file}: size {rgb.shape[1]}x{rgb.shape[0]} differs from {files[0]}'s "
                                  f"{images[0].shape[1]}x{images[0].shape[0]}")  # fmt: skip
        mask = _frame_mask(root, frame, image_file, rgb.shape[:2], where)
        mask = alpha if mask is None else mask
        c2w = _matrix(frame["transform_matrix"], f"{where}: 'transform_matrix'", DATASET_ORTHONORMAL_TOLERANCE)
        camera = _nerf_camera({**meta, **frame}, rgb.shape[1], rgb.shape[0], c2w, where)
        images.append(rgb)
        masks.append(mask)
        cameras.append(_downscaled_camera(camera, downscale))
        files.append(str(image_file))
    return Views(
        images=np.stack([box_downscale(im, downscale) for im in images]),
        masks=_stack_masks(masks, files, downscale),
        cameras=tuple(cameras),
        files=tuple(files),
    )


def _transforms_file(root: Path, split: str) -> Path:
    for name in (f"transforms_{split}.json", "transforms.json"):
        if (root / name).is_file():
            return root / name
    raise VisionDataError(f"{root / f'transforms_{split}.json'}: no such file (nor {root / 'transforms.json'})")


def _image_file(root: Path, file_path, where: str) -> Path:
    """The image a frame's `file_path` names: as written, or with an image extension added."""
    if not isinstance(file_path, str) or not file_path:
        raise VisionDataError(f"{where}: 'file_path' must be a non-empty string")
    base = root / file_path
    candidates = [base] + [
        base.with_name(base.name + s) for s in IMAGE_SUFFIXES + tuple(s.upper() for s in IMAGE_SUFFIXES)
    ]
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    raise VisionDataError(f"{base}: image not found (named by {where})")


def _nerf_camera(keys: dict, width: int, height: int, c2w: np.ndarray, where: str) -> Camera:
    """Intrinsics from `fl_x`/`fl_y`/`cx`/`cy` (instant-ngp) or `camera_angle_x` (NeRF-synthetic)."""
    for key, actual in (("w", width), ("h", height)):
        if key in keys and _positive_int(keys[key], f"{where}: {key!r}") != actual:
            raise VisionDataError(f"{where}: {key!r} is {keys[key]} but the image is {width}x{height}")
    if "fl_x" in keys:
        fx = _number(keys["fl_x"], f"{where}: 'fl_x'", positive=True)
        fy = _number(keys.get("fl_y", fx), f"{where}: 'fl_y'", positive=True)
    elif "camera_angle_x" in keys:
        angle = _number(keys["camera_angle_x"], f"{where}: 'camera_angle_x'", positive=True)
        if not angle < math.pi:
            raise VisionDataError(f"{where}: 'camera_angle_x' must be below pi rad, got {angle}")
        fx = fy = 0.5 * width / math.tan(0.5 * angle)
    else:
        raise VisionDataError(f"{where}: no intrinsics: need 'camera_angle_x' or 'fl_x'")
    cx = _number(keys.get("cx", 0.5 * width), f"{where}: 'cx'")
    cy = _number(keys.get("cy", 0.5 * height), f"{where}: 'cy'")
    return Camera(width, height, fx, fy, cx, cy, c2w)


def _downscaled_camera(camera: Camera, k: int) -> Camera:
    """The camera of an image box-averaged over k x k pixels: continuous coordinates divide by k."""
    return Camera(camera.width // k, camera.height // k, camera.fx / k, camera.fy / k, camera.cx / k, camera.cy / k,
                  camera.c2w)  # fmt: skip


def _frame_mask(root: Path, frame: dict, image_file: Path, size: tuple[int, int], where: str) -> np.ndarray | None:
    """The frame's `mask_path`, else `root/masks/<image stem>.*`, else None."""
    if "mask_path" in frame:
        mask_file = _image_file(root, frame["mask_path"], where)
    else:
        found = [root / "masks" / (image_file.stem + s) for s in IMAGE_SUFFIXES]
        mask_file = next((f for f in found if f.is_file()), None)
        if mask_file is None:
            return None
    return read_mask(mask_file, size)


def _stack_masks(masks: list[np.ndarray | None], files: list[str], k: int) -> np.ndarray | None:
    missing = [f for f, m in zip(files, masks, strict=True) if m is None]
    if len(missing) == len(masks):
        return None
    if missing:
        raise VisionDataError(f"{missing[0]}: has no mask (no alpha, no mask_path, no masks/ file) but other frames do")
    return np.stack([box_downscale(m, k) for m in masks])  # type: ignore[arg-type]


def box_downscale(image: Float[np.ndarray, "h w *c"], k: int) -> Float[np.ndarray, "h2 w2 *c"]:
    """Averages k x k blocks of pixels (dropping a remainder of rows or columns)."""
    if k == 1:
        return image
    h, w = image.shape[0] // k, image.shape[1] // k
    blocks = image[: h * k, : w * k].reshape(h, k, w, k, *image.shape[2:])
    return blocks.mean(axis=(1, 3), dtype=np.float64).astype(image.dtype)


# ---------------------------------------------------------------------------------------------
# Images and masks


def read_image(path: str | Path) -> Float[np.ndarray, "h w c"]:
    """Reads an image as float32 in [0, 1], (h, w, c) with c = 1 (grey), 2 (grey, alpha), 3 or 4."""
    path = Path(path)
    try:
        raw = iio.imread(path)
    except (OSError, ValueError, SyntaxError) as e:
        raise VisionDataError(f"{path}: not a readable image ({e})") from None
    return _to_float(raw, path)


def _to_float(raw: np.ndarray, path: Path) -> np.ndarray:
    if raw.ndim == 2:
        raw = raw[:, :, None]
    if raw.ndim != 3 or raw.shape[2] not in (1, 2, 3, 4):
        raise VisionDataError(f"{path}: expected a grey, RGB or RGBA image, got an array of shape {raw.shape}")
    if raw.dtype == np.uint8 or raw.dtype == np.uint16:
        return raw.astype(np.float32) / np.float32(np.iinfo(raw.dtype).max)
    if raw.dtype == np.bool_:
        return raw.astype(np.float32)
    if raw.dtype.kind == "f" and np.all(np.isfinite(raw)):
        return np.clip(raw, 0.0, 1.0).astype(np.float32)
    raise VisionDataError(f"{path}: unsupported pixel type {raw.dtype}")


def _read_rgba(path: Path, background: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """(h, w, 3) RGB composited onto `background` and (h, w) alpha, or None without alpha."""
    image = read_image(path)
    colour = image[:, :, :3] if image.shape[2] >= 3 else np.repeat(image[:, :, :1], 3, axis=2)
    if image.shape[2] in (2, 4):
        alpha = image[:, :, -1]
        return colour * alpha[:, :, None] + background * (1.0 - alpha[:, :, None]), alpha
    return colour, None


def read_mask(
    path: str | Path, size: tuple[int, int] | None = None, allow_empty: bool = False
) -> Float[np.ndarray, "h w"]:
    """Reads a mask image as (h, w) float32 in [0, 1], white = object.

    Colour masks are averaged over R, G, B; an alpha channel multiplies the result, so white
    on black and white on transparent both work.

    Args:
        path: the image.
        size: (height, width) it must have, or None.
        allow_empty: accept an all-black mask (a frame where segmentation found nothing).

    Raises:
        VisionDataError: unreadable, of another size, or empty (all black) unless allowed.
    """
    path = Path(path)
    image = read_image(path)
    mask = image[:, :, :3].mean(axis=2) if image.shape[2] >= 3 else image[:, :, 0]
    if image.shape[2] in (2, 4):
        mask = mask * image[:, :, -1]
    if size is not None and mask.shape != tuple(size):
        raise VisionDataError(f"{path}: mask is {mask.shape[1]}x{mask.shape[0]}, its image {size[1]}x{size[0]}")
    if not allow_empty and not np.any(mask > 0):
        raise VisionDataError(f"{path}: empty mask (all black): the object is not in the frame")
    return mask


# ---------------------------------------------------------------------------------------------
# Rendering ground truth with MuJoCo

_LIGHTS = (  # (direction the light travels, diffuse): a key light from above and three fills
    ((-0.3, -0.5, -1.0), 0.4),
    ((0.8, 0.4, 0.3), 0.2),
    ((-0.5, 0.8, 0.2), 0.2),
    ((0.2, -0.6, 0.8), 0.2),
)
_AMBIENT = 0.5
"""Every surface gets 0.6-0.9 of its colour whatever its normal; no specular, so no view dependence."""


def sphere_cameras(
    centre: VectorLike, distance: float, n_views: int, resolution: int, fov_x: float, seed: int = 0
) -> tuple[Camera, ...]:
    """Square cameras on a sphere around `centre`, looking at it, z up.

    Directions are a golden-spiral (Fibonacci) set covering the sphere evenly, rotated by a
    rotation drawn from `seed`, so different seeds give different but equally even views.

    Args:
        centre: (3,) world frame, m.
        distance: from `centre`, m.
        resolution: image width and height, pixels.
        fov_x: horizontal (= vertical) field of view, rad.
    """
    i = np.arange(n_views) + 0.5
    z = 1.0 - 2.0 * i / n_views
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i
    r = np.sqrt(1.0 - z * z)
    directions = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
    q = np.random.default_rng(seed).normal(size=4)
    R = np.zeros(9)
    mujoco.mju_quat2Mat(R, q / np.linalg.norm(q))
    centre = np.asarray(centre, dtype=np.float64)
    eyes = centre + distance * directions @ R.reshape(3, 3).T
    return tuple(camera_from_fov(resolution, resolution, fov_x, look_at(eye, centre)) for eye in eyes)


def framing_distance(radius: float, fov: float, margin: float = 0.1) -> float:
    """The distance, m, at which a sphere of `radius` (m) fills a field of view `fov` (rad) but a margin.

    The sphere's angular radius asin(radius / distance) is then asin(sin(fov / 2) / (1 + margin)).
    """
    return (1.0 + margin) * radius / math.sin(0.5 * fov)


def bounding_sphere(mesh: trimesh.Trimesh) -> tuple[Float[np.ndarray, "3"], float]:
    """The centre of the mesh's axis-aligned bounding box and the largest vertex distance from it, m."""
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    centre = 0.5 * (vertices.min(axis=0) + vertices.max(axis=0))
    return centre, float(np.max(np.linalg.norm(vertices - centre, axis=1)))


def render_views(
    mesh: trimesh.Trimesh,
    out_dir: str | Path,
    n_views: int = 50,
    resolution: int = 64,
    fov_x_deg: float = 40.0,
    distance: float | None = None,
    seed: int = 0,
    rgba: VectorLike = (0.8, 0.6, 0.4, 1.0),
    overwrite: bool = False,
    progress: bool = True,
) -> Path:
    """Renders a mesh from around it into a NeRF-synthetic dataset folder (read by `load_nerf_synthetic`).

    Writes `transforms.json` (`camera_angle_x`, frames with `file_path` "images/r_000.png" and
    `transform_matrix`), RGBA PNGs `images/r_000.png` whose alpha is the object's exact mask
    (MuJoCo's segmentation render), and the same masks as `masks/r_000.png` (0 or 255). Cameras
    come from `sphere_cameras` around the mesh's bounding-box centre. Lighting is fixed directional
    light without specular highlights, so a surface point looks the same from every view. The
    folder appears complete or not at all (written beside it, then renamed).

    Args:
        mesh: in world coordinates, m.
        out_dir: the dataset folder to create.
        n_views: number of images.
        resolution: image width and height, pixels.
        fov_x_deg: field of view, degrees.
        distance: camera distance from the centre, m; default `framing_distance` of the bounding sphere.
        seed: rotates the camera directions.
        rgba: the object's colour, each in [0, 1].
        overwrite: replace `out_dir` if it exists (else raise `VisionDataError`).
        progress: show a progress bar.

    Example:
        >>> render_views(trimesh.creation.icosphere(radius=0.05), "ball_views", n_views=20)
        >>> views = load_nerf_synthetic("ball_views")
    """
    if n_views < 1 or resolution < 1 or not 0.0 < fov_x_deg < 180.0:
        raise ValueError(f"render_views: need n_views, resolution >= 1 and 0 < fov_x_deg < 180, got "
                         f"{n_views}, {resolution}, {fov_x_deg}")  # fmt: skip
    fov = math.radians(fov_x_deg)
    centre, radius = bounding_sphere(mesh)
    distance = framing_distance(radius, fov) if distance is None else float(distance)
    cameras = sphere_cameras(centre, distance, n_views, resolution, fov, seed)
    digits = max(3, len(str(n_views - 1)))
    names = [f"r_{k:0{digits}d}.png" for k in range(n_views)]
    with _atomic_folder(out_dir, overwrite) as tmp, _MeshRenderer(mesh, rgba, cameras[0], None) as renderer:
        (tmp / "images").mkdir()
        (tmp / "masks").mkdir()
        renderer.set_depth_range(cameras, centre[None], radius)
        for camera, name in zip(tqdm(cameras, desc="views", disable=not progress, unit="view"), names, strict=True):
            colour, mask, _ = renderer.render(camera, np.eye(4))
            iio.imwrite(
                tmp / "images" / name, np.concatenate([colour, 255 * mask[:, :, None].astype(np.uint8)], axis=2)
            )
            iio.imwrite(tmp / "masks" / name, 255 * mask.astype(np.uint8))
        frames = [
            {"file_path": f"images/{n}", "transform_matrix": c.c2w.tolist()}
            for n, c in zip(names, cameras, strict=True)
        ]
        (tmp / "transforms.json").write_text(json.dumps({"camera_angle_x": fov, "frames": frames}, indent=2) + "\n")
    return Path(out_dir)


def render_video(
    mesh: trimesh.Trimesh,
    poses: MatrixLike,
    camera: Camera,
    out_dir: str | Path,
    rgba: VectorLike = (0.8, 0.6, 0.4, 1.0),
    background: VectorLike = (0.5, 0.5, 0.5),
    fps: float = 30.0,
    floor: bool = False,
    floor_height: float = 0.0,
    overwrite: bool = False,
    progress: bool = True,
) -> Path:
    """Renders a mesh moving in front of a fixed camera: ground truth for pose tracking.

    Writes `frames/000000.png` (RGB on a plain `background`), `masks/000000.png` (0 or 255, the
    object only, never the floor), `camera.json` (`save_camera`) and `poses.csv` (`t,x,y,z,qw,qx,qy,qz`
    with t = i / fps: the mesh frame's pose). The folder appears complete or not at all.

    Args:
        mesh: in its own frame, m.
        poses: (n, 7) x, y, z, qw, qx, qy, qz of the mesh frame in the world (mesh -> world), m.
        camera: the fixed camera; MuJoCo renders square pixels (fx = fy) with a centred principal point only.
        out_dir: the folder to create.
        rgba: the object's colour.
        background: RGB of everything that is neither object nor floor.
        fps: frames per second, for the t column.
        floor: add a checkered floor plane z = `floor_height` (m, world frame).
        overwrite: replace `out_dir` if it exists (else raise `VisionDataError`).
        progress: show a progress bar.
    """
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 2 or poses.shape[1] != 7 or len(poses) == 0 or not np.all(np.isfinite(poses)):
        raise VisionDataError(f"{out_dir}: poses must be a finite (n, 7) array, got shape {poses.shape}")
    if np.any(np.linalg.norm(poses[:, 3:], axis=1) < 1e-9):
        raise VisionDataError(f"{out_dir}: poses have a zero quaternion")
    if not fps > 0:
        raise ValueError(f"render_video: fps must be positive, got {fps}")
    track = Track.from_poses(poses, 1.0 / fps, source=str(out_dir))
    transforms = [_transform(p, q) for p, q in zip(track.pos, track.quat, strict=True)]
    centre, radius = bounding_sphere(mesh)
    centres = np.stack([T[:3, :3] @ centre + T[:3, 3] for T in transforms])
    bg = np.round(255 * np.clip(np.asarray(background, dtype=np.float64).reshape(3), 0, 1)).astype(np.uint8)
    with (
        _atomic_folder(out_dir, overwrite) as tmp,
        _MeshRenderer(mesh, rgba, camera, floor_height if floor else None) as renderer,
    ):
        (tmp / "frames").mkdir()
        (tmp / "masks").mkdir()
        renderer.set_depth_range([camera], centres, radius)
        for k, T in enumerate(tqdm(transforms, desc="frames", disable=not progress, unit="frame")):
            colour, mask, scene = renderer.render(camera, T)
            iio.imwrite(tmp / "frames" / f"{k:06d}.png", np.where(scene[:, :, None], colour, bg))
            iio.imwrite(tmp / "masks" / f"{k:06d}.png", 255 * mask.astype(np.uint8))
        save_camera(tmp / "camera.json", camera)
        write_track(tmp / "poses.csv", track)
    return Path(out_dir)


def _transform(pos: np.ndarray, quat: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    R = np.zeros(9)
    mujoco.mju_quat2Mat(R, quat)
    T[:3, :3], T[:3, 3] = R.reshape(3, 3), pos
    return T


class _MeshRenderer:
    """MuJoCo's offscreen renderer for one mesh on a mocap body, a camera, lights and maybe a floor.

    A context manager: the GL context is released on exit.
    """

    def __init__(self, mesh: trimesh.Trimesh, rgba: VectorLike, camera: Camera, floor_height: float | None):
        try:
            self.model = _scene_spec(mesh, rgba, camera.width, camera.height, floor_height).compile()
        except ValueError as e:  # MuJoCo's compiler rejects empty or degenerate meshes
            raise MeshError(f"MuJoCo cannot render this mesh: {' '.join(str(e).split())}") from None
        self.data = mujoco.MjData(self.model)
        self.object_id = self.model.geom("object").id
        self.floor_id = self.model.geom("floor").id if floor_height is not None else -2
        self.renderer = make_renderer(self.model, camera.height, camera.width)

    def __enter__(self) -> "_MeshRenderer":
        return self

    def __exit__(self, *exc) -> None:
        self.renderer.close()

    def set_depth_range(self, cameras: Sequence[Camera], centres: np.ndarray, radius: float) -> None:
        """Near and far clipping planes that keep every object position in view (MuJoCo scales them by extent)."""
        distances = np.linalg.norm(np.stack([c.position for c in cameras])[:, None] - centres[None], axis=2)
        near = max(1e-3 * float(distances.max() + radius), 0.5 * float(distances.min() - radius))
        far = 100.0 * float(distances.max() + radius)
        extent = float(self.model.stat.extent)
        self.model.vis.map.znear, self.model.vis.map.zfar = near / extent, far / extent

    def render(self, camera: Camera, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Colour (h, w, 3) uint8, object mask (h, w) bool and object-or-floor mask (h, w) bool.

        Args:
            camera: must have this renderer's size.
            pose: (4, 4) mesh frame -> world.
        """
        _set_camera(self.model, camera)
        self.data.mocap_pos[0] = pose[:3, 3]
        mujoco.mju_mat2Quat(self.data.mocap_quat[0], pose[:3, :3].ravel())
        mujoco.mj_kinematics(self.model, self.data)
        mujoco.mj_camlight(self.model, self.data)
        self.renderer.update_scene(self.data, camera="view")
        self.renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
        colour = self.renderer.render().copy()
        self.renderer.enable_segmentation_rendering()
        try:
            segment = self.renderer.render()
        finally:
            self.renderer.disable_segmentation_rendering()
        is_geom = segment[:, :, 1] == mujoco.mjtObj.mjOBJ_GEOM
        mask = is_geom & (segment[:, :, 0] == self.object_id)
        return colour, mask, mask | (is_geom & (segment[:, :, 0] == self.floor_id))


def _set_camera(model: mujoco.MjModel, camera: Camera) -> None:
    """Points the model's camera "view" like `camera`.

    MuJoCo's camera frame is ours (looks along -z, +y up), so its orientation is c2w's rotation.
    Its intrinsics are only a vertical field of view over the whole image height with the
    principal point at the centre, which is fy = height / (2 tan(fovy / 2)).
    """
    if (
        abs(camera.fx - camera.fy) > 1e-6 * camera.fy
        or max(abs(camera.cx - 0.5 * camera.width), abs(camera.cy - 0.5 * camera.height)) > 1e-6 * camera.width
    ):
        raise VisionDataError(f"MuJoCo renders square pixels about a centred principal point only; got {camera}")
    if (camera.width, camera.height) != (model.vis.global_.offwidth, model.vis.global_.offheight):
        raise ValueError(f"camera size {camera.width}x{camera.height} differs from the renderer's")
    model.cam_pos[0] = camera.position
    mujoco.mju_mat2Quat(model.cam_quat[0], np.ascontiguousarray(camera.rotation).ravel())
    model.cam_fovy[0] = math.degrees(2.0 * math.atan(0.5 * camera.height / camera.fy))


def _scene_spec(
    mesh: trimesh.Trimesh, rgba: VectorLike, width: int, height: int, floor_height: float | None
) -> mujoco.MjSpec:
    """The MuJoCo scene: the mesh on a mocap body, a camera "view", directional lights, maybe a floor."""
    spec = mujoco.MjSpec()
    spec.visual.global_.offwidth, spec.visual.global_.offheight = width, height
    spec.visual.quality.offsamples = 0  # no multisampling: colour edges agree with the segmentation exactly
    spec.visual.headlight.active = 0
    spec.add_material(name="object", rgba=list(np.asarray(rgba, dtype=np.float64).reshape(4)), specular=0.0,
                      shininess=0.0, reflectance=0.0)  # fmt: skip
    spec.add_mesh(name="object", uservert=np.asarray(mesh.vertices, dtype=np.float64).ravel().tolist(),
                  userface=np.asarray(mesh.faces, dtype=np.int64).ravel().tolist(),
                  inertia=mujoco.mjtMeshInertia.mjMESH_INERTIA_SHELL)  # fmt: skip
    body = spec.worldbody.add_body(name="object", mocap=True)
    body.add_geom(name="object", type=mujoco.mjtGeom.mjGEOM_MESH, meshname="object", material="object",
                  contype=0, conaffinity=0)  # fmt: skip
    spec.worldbody.add_camera(name="view")
    for k, (direction, diffuse) in enumerate(_LIGHTS):
        spec.worldbody.add_light(type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL, dir=list(direction),
                                 diffuse=[diffuse] * 3, ambient=[_AMBIENT if k == 0 else 0.0] * 3,
                                 specular=[0.0] * 3, castshadow=False)  # fmt: skip
    if floor_height is not None:
        _add_floor(spec, floor_height, bounding_sphere(mesh)[1])
    return spec


def _add_floor(spec: mujoco.MjSpec, height: float, radius: float) -> None:
    """A checkered plane z = height, tiles about the object's radius, large enough to reach the horizon."""
    spec.add_texture(name="floor", type=mujoco.mjtTexture.mjTEXTURE_2D, builtin=mujoco.mjtBuiltin.mjBUILTIN_CHECKER,
                     rgb1=[0.25, 0.3, 0.35], rgb2=[0.4, 0.45, 0.5], width=64, height=64)  # fmt: skip
    spec.add_material(name="floor", textures=["", "floor"], texrepeat=[0.5 / radius, 0.5 / radius], texuniform=True,
                      specular=0.0, shininess=0.0, reflectance=0.0)  # fmt: skip
    size = [1000.0 * radius, 1000.0 * radius, 1.0]
    spec.worldbody.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, pos=[0.0, 0.0, height], size=size,
                            material="floor", contype=0, conaffinity=0)  # fmt: skip


@contextlib.contextmanager
def _atomic_folder(out_dir: str | Path, overwrite: bool) -> Iterator[Path]:
    """Yields a temporary folder beside `out_dir`, renamed onto it if the block succeeds, else removed."""
    out_dir = Path(out_dir)
    if out_dir.exists() and not overwrite:
        raise VisionDataError(f"{out_dir}: already exists (--overwrite, or overwrite=True, replaces it)")
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=out_dir.parent, prefix=f".{out_dir.name}.", suffix=".tmp"))
    try:
        yield tmp
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o777 & ~umask)  # mkdtemp makes it private
        if out_dir.exists():
            old = tmp.with_suffix(".old")
            os.replace(out_dir, old)
            os.replace(tmp, out_dir)
            shutil.rmtree(old) if old.is_dir() else old.unlink()
        else:
            os.replace(tmp, out_dir)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


# ---------------------------------------------------------------------------------------------
# Videos and masks for tracking


def load_frames(path: str | Path) -> tuple[Float[np.ndarray, "n h w 3"], list[str]]:
    """Reads a video file or a folder of images (sorted by name) as RGB frames.

    Args:
        path: a video (`VIDEO_SUFFIXES`, read with PyAV) or a folder of .png/.jpg images.

    Returns:
        frames: (n, h, w, 3) float32 RGB in [0, 1] (alpha dropped, grey repeated).
        files: the n image paths, or "video.mp4#000000", ... for a video.

    Raises:
        VisionDataError: naming the file: missing, unreadable, no frames, frames of different sizes.
    """
    path = Path(path)
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not files:
            raise VisionDataError(f"{path}: no .png or .jpg images")
        frames = [_rgb(read_image(f)) for f in files]
        for f, frame in zip(files, frames, strict=True):
            if frame.shape != frames[0].shape:
                raise VisionDataError(f"{f}: size {frame.shape[1]}x{frame.shape[0]} differs from {files[0]}'s "
                                      f"{frames[0].shape[1]}x{frames[0].shape[0]}")  # fmt: skip
        return np.stack(frames), [str(f) for f in files]
    if not path.is_file():
        raise VisionDataError(f"{path}: no such file or folder")
    if path.suffix.lower() not in VIDEO_SUFFIXES:
        raise VisionDataError(f"{path}: expected a video ({', '.join(VIDEO_SUFFIXES)}) or a folder of images")
    frames = _read_video(path)
    return frames, [f"{path}#{k:06d}" for k in range(len(frames))]


def _read_video(path: Path) -> np.ndarray:
    from av.error import FFmpegError  # PyAV, imageio's video plugin

    try:
        raw = iio.imread(path, plugin="pyav")
    except (OSError, ValueError, FFmpegError) as e:
        raise VisionDataError(f"{path}: not a readable video ({e})") from None
    if raw.ndim != 4 or len(raw) == 0:
        raise VisionDataError(f"{path}: no frames")
    return np.stack([_rgb(_to_float(frame, path)) for frame in raw])


def _rgb(image: np.ndarray) -> np.ndarray:
    return image[:, :, :3] if image.shape[2] >= 3 else np.repeat(image[:, :, :1], 3, axis=2)


def load_masks(
    folder: str | Path, n_expected: int | None, size: tuple[int, int], allow_empty: bool = False
) -> Float[np.ndarray, "n h w"]:
    """Reads one mask per frame from a folder of images, in name order (module docstring).

    Args:
        folder: holding .png/.jpg masks, white = object.
        n_expected: the number of frames (None: as many as there are masks).
        size: (height, width) of the frames.
        allow_empty: accept all-black masks (frames where segmentation found nothing).

    Returns:
        (n_expected, height, width) float32 in [0, 1].

    Raises:
        VisionDataError: naming the file or folder: a frame without a mask (the first missing
            index), an extra mask, a mask of another size, an empty mask (unless allowed), no masks.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise VisionDataError(f"{folder}: no such folder of masks")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise VisionDataError(f"{folder}: no mask images (.png, .jpg) in it")
    n_expected = len(files) if n_expected is None else n_expected
    if len(files) < n_expected:
        raise VisionDataError(f"{folder}: {len(files)} masks for {n_expected} frames: no mask for frame {len(files)}"
                              + (" and after" if n_expected - len(files) > 1 else ""))  # fmt: skip
    if len(files) > n_expected:
        raise VisionDataError(f"{files[n_expected]}: {len(files)} masks for {n_expected} frames; this one is extra")
    return np.stack([read_mask(f, size, allow_empty) for f in files])


def colour_key_masks(
    frames: Float[np.ndarray, "n h w 3"], background_rgb: VectorLike, tolerance: float = 0.1
) -> Float[np.ndarray, "n h w"]:
    """Masks by background subtraction: 1 where a pixel differs from a plain backdrop colour.

    For synthetic footage (`render_video`) or lab footage against a uniform backdrop; real
    footage usually wants a segmenter (module docstring).

    Args:
        frames: (n, h, w, 3) RGB in [0, 1].
        background_rgb: (3,) the backdrop's RGB in [0, 1].
        tolerance: a pixel is background if every channel is within this of the backdrop.

    Returns:
        (n, h, w) float32, 1 = object, 0 = background.
    """
    background = np.asarray(background_rgb, dtype=np.float32).reshape(3)
    return (np.max(np.abs(frames - background), axis=-1) > tolerance).astype(np.float32)
