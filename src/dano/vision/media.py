"""Images, masks and videos read from disk, and masks made by colour keying.

A video for tracking is a video file (anything PyAV reads: .mp4, .mov, .avi, .mkv, .webm) or a
folder of .png/.jpg frames taken in name order.

Masks from any segmenter (SAM 2, XMem, rembg, a green screen, ...): write one single-channel or RGB
PNG per frame into a folder, white (255) = object and black (0) = background (grey = partial),
named so that sorting the names gives the frames' order; the frames' own stems do
(`frame_0001.png` -> `masks/frame_0001.png`), and for a video `000000.png`, `000001.png`, ...
`load_masks(folder, n_frames, (height, width))` reads them back and checks count and size. For
footage against a plain backdrop, `colour_key_masks` makes them directly.
"""

from pathlib import Path

import imageio.v3 as iio
import numpy as np
from jaxtyping import Float

from dano.vision.camera import VectorLike, VisionDataError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
VIDEO_SUFFIXES = (".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v")


def box_downscale(image: Float[np.ndarray, "h w *c"], k: int) -> Float[np.ndarray, "h2 w2 *c"]:
    """Averages k x k blocks of pixels (dropping a remainder of rows or columns)."""
    if k == 1:
        return image
    h, w = image.shape[0] // k, image.shape[1] // k
    blocks = image[: h * k, : w * k].reshape(h, k, w, k, *image.shape[2:])
    return blocks.mean(axis=(1, 3), dtype=np.float64).astype(image.dtype)


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

    For synthetic footage (`dano.vision.synthetic.render_mesh_video`) or lab footage against a uniform backdrop; real
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
