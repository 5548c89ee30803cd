"""Multi-view datasets in the NeRF-synthetic layout (also read from instant-ngp and nerfstudio).

`transforms_{split}.json` or `transforms.json` holds `camera_angle_x` (horizontal field of view,
rad) or `fl_x`, `fl_y`, `cx`, `cy`, `w`, `h` (pixels; per-frame overrides allowed), and `frames[]`
with `file_path` (relative to the folder, with or without extension) and `transform_matrix` (c2w).
RGBA images carry the object's mask in alpha; otherwise a frame's `mask_path`, or
`masks/<image stem>.png`, gives it. `dano.vision.synthetic.render_views` writes this layout.
"""

import dataclasses
import math
from pathlib import Path

import numpy as np
from jaxtyping import Float

from dano.errors import InvalidValueError
from dano.vision.camera import (
    DATASET_ORTHONORMAL_TOLERANCE,
    Camera,
    VectorLike,
    VisionDataError,
    _matrix,
    _number,
    _positive_int,
    _read_json,
)
from dano.vision.media import IMAGE_SUFFIXES, _read_rgba, box_downscale, read_mask


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
            raise InvalidValueError(f"Views: {n} images but {len(self.cameras)} cameras and {len(self.files)} files")

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
        cameras.append(camera.downscaled(downscale))
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
