"""Tracking an object's pose through a video by matching rendered opacity to object masks (Sec. V-A).

For a pose p = (position, orientation) of the object's field frame, the opacity image T(p) is the
accumulated opacity of the field seen by the camera (`dano.vision.render`). Per frame, the tracker
minimises

    mean (T(p) - M)^2  +  barycentre_weight * |B(T(p)) - B(M)|^2

(M the object mask, B the barycentre of an image in image-size units) with Adam, starting from the
previous frame's pose moved on at the previous velocity. The barycentre term keeps the gradient
pointing the right way when the rendered object and the mask do not overlap yet.

Beyond the paper, `refine` optimises all poses together: the same loss summed over frames plus a
penalty on the poses' second differences (accelerations), which removes frame-to-frame jitter.

The field is queried through a baked grid (`as_grid`) so a render costs a few gathers per sample.
The field is read as an occupancy o = phi / peak, its surface at o = 1/2, and rendered in the
hard-surface limit of accumulated opacity: a pixel's opacity is smoothstep((m - 1/4) / (1/2)) of the
largest occupancy m along its ray (`render_peak`). A ray that grazes the surface has m = 1/2 and
opacity 1/2, so the silhouette's edge is the surface itself, blurred over the field's own soft
boundary for a gradient. (Integrating an optical density instead, as volume rendering does, lets
grazing rays gather opacity in the soft boundary outside the surface: the silhouette grows by about a
voxel and the tracker pushes the object away from the camera to shrink it, 1 cm at 0.6 m in our
measurements.) A mesh's occupancy field, a solidified fitted field (`dano.vision.fit.solidify`) or
any field whose inside is at its peak works; its units do not matter.
"""

import dataclasses
import functools
import time
from typing import cast

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, Float
from tqdm.auto import tqdm

from dano.fields import AbstractField
from dano.fields.grid import as_grid
from dano.math import quat_conj, quat_exp, quat_log, quat_mul, quat_to_mat
from dano.results import AbstractSolution, Result, finish
from dano.surface import field_peak
from dano.vision.camera import Camera, camera_rays
from dano.vision.configs import TrackConfig, TrackError
from dano.vision.fit import cosine_rate
from dano.vision.media import box_downscale
from dano.vision.render import render_peak


@dataclasses.dataclass(frozen=True)
class Silhouette:
    """What rendering a pose needs: camera rays (world), the field as an opacity source, its sphere."""

    origins: Float[Array, "r 3"]
    directions: Float[Array, "r 3"]
    uv: Float[Array, "r 2"]
    field: AbstractField
    peak: float
    centre: Float[Array, " 3"]
    radius: float
    n_samples: int


def silhouette(field: AbstractField, camera: Camera, config: TrackConfig) -> Silhouette:
    """Prepares rendering of `field` by `camera` (rays of the downsampled image, a baked grid)."""
    lo, hi = (np.asarray(b) for b in field.bounds)
    grid = as_grid(field, (config.grid, config.grid, config.grid))
    radius = 0.5 * float(np.linalg.norm(hi - lo))
    peak = field_peak(grid)
    origins, directions = camera_rays(camera)
    uv = np.stack(np.meshgrid(np.arange(camera.width) + 0.5, np.arange(camera.height) + 0.5), -1).reshape(-1, 2)
    return Silhouette(
        jnp.asarray(origins), jnp.asarray(directions), jnp.asarray(uv / [camera.width, camera.height]),
        grid, peak, jnp.asarray(0.5 * (lo + hi)), radius, config.n_samples,
    )  # fmt: skip


def render_silhouette(s: Silhouette, position: Float[Array, " 3"], quat: Float[Array, " 4"]) -> Float[Array, " r"]:
    """Opacity (r,) of the field at pose (position, quat) of its frame (world): its silhouette."""
    rot = quat_to_mat(quat)
    centre = position + rot @ s.centre
    # The rays' path through the object's bounding sphere.
    along = s.directions @ centre - jnp.sum(s.directions * s.origins, axis=-1)
    closest = s.origins + along[:, None] * s.directions - centre[None, :]
    h2 = s.radius**2 - jnp.sum(closest**2, axis=-1)
    half = jnp.where(h2 > 0, jnp.sqrt(jnp.where(h2 > 0, h2, 1.0)), 0.0)  # 0 for a miss, and a finite gradient
    near, far = jnp.maximum(along - half, 0.0), jnp.maximum(along + half, 0.0)

    def occupancy(x):
        return s.field((x - position[None, :]) @ rot) / s.peak

    t = jnp.clip(2.0 * render_peak(occupancy, s.origins, s.directions, near, far, s.n_samples) - 0.5, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def mask_loss(s: Silhouette, opacity: Float[Array, " r"], mask: Float[Array, " r"], weight: float) -> Float[Array, ""]:
    """mean (T - M)^2 + weight |B(T) - B(M)|^2, barycentres in image-size units."""

    def barycentre(image):
        return jnp.sum(image[:, None] * s.uv, axis=0) / (jnp.sum(image) + 1e-6)

    return jnp.mean((opacity - mask) ** 2) + weight * jnp.sum((barycentre(opacity) - barycentre(mask)) ** 2)


def _pose(s: Silhouette, base_pos, base_quat, delta):
    """Pose after an increment `delta` (6,): position in radius units, rotation vector (world) in rad."""
    return base_pos + s.radius * delta[:3], quat_mul(quat_exp(delta[3:]), base_quat)


@dataclasses.dataclass(frozen=True)
class TrackResult(AbstractSolution):
    """Poses of the field frame per frame (world), the final loss per frame, and the wall time
    (`dano.results.AbstractSolution`; `value` is (positions, quats)).

    Attributes:
        positions, quats: (n, 3), (n, 4) per frame tracked.
        losses: (n,) each frame's loss at its pose.
        seconds: wall time, compilation included.
        result: `completed`, or `nonfinite` (stopped at the first frame whose loss is not finite;
            the frames before it are returned).
        message: in words.
        iterations: Adam steps in all (per frame and in the refinement).
    """

    positions: np.ndarray
    quats: np.ndarray
    losses: np.ndarray
    seconds: float
    result: Result = Result.completed
    message: str = ""
    iterations: int = 0

    @property
    def value(self) -> tuple[np.ndarray, np.ndarray]:
        return self.positions, self.quats


def downsample(masks: np.ndarray, camera: Camera, factor: int) -> tuple[np.ndarray, Camera]:
    """Box-averages masks (n, h, w) by an integer `factor` and scales the camera's intrinsics to match."""
    small = box_downscale(np.moveaxis(masks, 0, -1), factor)  # pixels first, frames as channels
    return np.moveaxis(small, -1, 0), camera.downscaled(factor)


def windows(masks: np.ndarray, margin: float = 0.3) -> tuple[tuple[int, int], np.ndarray]:
    """One window size for every frame and each frame's window: the largest bounding box of the masks
    (n, h, w), grown on every side by `margin` times its longest side and clipped to the image; each
    frame's window is centred on its mask's box and kept inside the image.

    Returns:
        (height, width) of the windows, and their top-left corners (n, 2) as (row, column).
    """
    n, h, w = masks.shape
    rows, cols = masks.max(axis=2) > 0, masks.max(axis=1) > 0
    r0, r1 = rows.argmax(axis=1), h - rows[:, ::-1].argmax(axis=1)
    c0, c1 = cols.argmax(axis=1), w - cols[:, ::-1].argmax(axis=1)
    pad = int(np.ceil(margin * max((r1 - r0).max(), (c1 - c0).max())))
    height, width = min(h, int((r1 - r0).max()) + 2 * pad), min(w, int((c1 - c0).max()) + 2 * pad)
    top = np.clip((r0 + r1 - height) // 2, 0, h - height)
    left = np.clip((c0 + c1 - width) // 2, 0, w - width)
    return (height, width), np.stack([top, left], axis=1)


def largest_parts(masks: np.ndarray, visible: np.ndarray | None = None) -> np.ndarray:
    """Each mask's largest connected part (where the windows go, so a few false pixels far from the
    object do not move or grow them); a frame not `visible` (default: all are) takes the last
    visible frame's."""
    from scipy import ndimage

    out = np.zeros_like(masks)
    last = None
    visible = np.ones(len(masks), dtype=bool) if visible is None else visible
    for k, m in enumerate(masks):
        if visible[k]:
            labels, n = ndimage.label(m > 0.5)  # pyright: ignore[reportGeneralTypeIssues]
            if n > 1:
                sizes = ndimage.sum_labels(np.ones_like(m), labels, index=np.arange(1, n + 1))
                last = (labels == 1 + int(np.argmax(sizes))).astype(float)
            else:
                last = (m > 0.5).astype(float)
        assert last is not None  # the first frame is visible
        out[k] = last
    return out


def crop(s: Silhouette, masks: np.ndarray, size: tuple[int, int], corners: np.ndarray):
    """Per frame: the window's rays (origins, directions, uv stacked over frames) and its mask pixels;
    `s` renders the whole image of the masks (n, h, w), `size` and `corners` are from `windows`."""
    width = masks.shape[2]
    rows = corners[:, :1, None] + np.arange(size[0])[None, :, None]
    cols = corners[:, 1:, None] + np.arange(size[1])[None, None, :]
    index = (rows * width + cols).reshape(len(corners), -1)  # (n, window pixels) into the image
    targets = np.take_along_axis(masks.reshape(len(masks), -1), index, axis=1)
    rays = (s.origins[index], s.directions[index], s.uv[index])
    return rays, jnp.asarray(targets)


def _window_loss(s: Silhouette, rays, position, quat, target, weight: float):
    """`mask_loss` of the pose seen through one frame's window (its rays, as from `crop`)."""
    origins, directions, uv = rays
    s = dataclasses.replace(s, origins=origins, directions=directions, uv=uv)
    return mask_loss(s, render_silhouette(s, position, quat), target, weight)


def initial_pose(s: Silhouette, mask: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """A first guess from one mask: the field unrotated, on the ray through the mask's barycentre, at
    the depth where its rendered area matches the mask's."""
    flat = mask.reshape(-1)
    uv = np.asarray(s.uv)
    b = (flat[:, None] * uv).sum(0) / flat.sum()
    pixel = np.clip((b * [camera.width, camera.height]).astype(int), 0, [camera.width - 1, camera.height - 1])
    index = pixel[1] * camera.width + pixel[0]
    origin, direction = np.asarray(s.origins[index]), np.asarray(s.directions[index])
    quat = np.array([1.0, 0.0, 0.0, 0.0])
    depth = 4.0 * s.radius
    for _ in range(3):  # area scales as 1/depth^2
        position = origin + depth * direction - np.asarray(s.centre)
        area = float(jnp.sum(render_silhouette(s, jnp.asarray(position), jnp.asarray(quat))))
        if area <= 0:
            break
        depth *= np.sqrt(area / flat.sum())
    return origin + depth * direction - np.asarray(s.centre), quat


def track(
    field: AbstractField,
    camera: Camera,
    masks: np.ndarray,
    config: TrackConfig = TrackConfig(),
    init: tuple[np.ndarray, np.ndarray] | None = None,
    progress: bool = True,
    throw: bool = True,
) -> TrackResult:
    """Poses of `field`'s frame in each frame of a video, from its object masks.

    Args:
        masks: (n, h, w) in [0, 1], 1 on the object, `camera`'s size.
        init: (position (3,), quat (4,)) of the field frame in the first frame; default: a guess from
            the first mask (see `initial_pose`), which assumes the object starts unrotated.
        throw: raise `SolverError` where a frame's loss is not finite (else the frames before it
            are returned, `result` `nonfinite`).

    Raises:
        TrackError: masks of another size than the camera's, or an empty mask.
        SolverError: `throw` and a frame's loss was not finite.
    """
    masks = np.asarray(masks, dtype=float)
    if masks.ndim != 3 or masks.shape[1:] != (camera.height, camera.width):
        raise TrackError(f"masks are {masks.shape[1:]} pixels but the camera is ({camera.height}, {camera.width})")
    empty = np.flatnonzero(masks.reshape(len(masks), -1).max(axis=1) <= 0)
    if len(empty):
        raise TrackError(f"mask of frame {int(empty[0])} is empty: the object must be visible in every frame")
    held = largest_parts(masks)  # the windows follow the object, not stray pixels
    (height, width), _ = windows(held)
    factor = max(1, -(-max(height, width) // config.max_size))
    small, cam = downsample(masks, camera, factor)
    s = silhouette(field, cam, config)
    held_small, _ = downsample(held, camera, factor)
    size, corners = windows(held_small)
    rays, targets = crop(s, small, size, corners)
    optimiser = optax.scale_by_adam()

    @jax.jit
    def solve(base_pos, base_quat, rays_k, target, n):
        def loss(delta):
            pos, quat = _pose(s, base_pos, base_quat, delta)
            return _window_loss(s, rays_k, pos, quat, target, config.barycentre_weight)

        def body(i, carry):  # Adam with the rate decaying along a cosine to 5 %, so the pose settles
            delta, state = carry
            with jax.numpy_dtype_promotion("standard"):  # optax raises floats to int powers
                direction, state = optimiser.update(jax.grad(loss)(delta), state)
            rate = cosine_rate(config.learning_rate, i / n)
            return delta - rate * cast(Array, direction), state  # `delta`'s structure: an array

        delta = jnp.zeros(6, dtype=base_pos.dtype)
        delta, _ = jax.lax.fori_loop(0, n, body, (delta, optimiser.init(delta)))
        pos, quat = _pose(s, base_pos, base_quat, delta)
        return pos, quat / jnp.linalg.norm(quat), loss(delta)

    start = time.perf_counter()
    pos, quat = initial_pose(s, held_small[0], cam) if init is None else (np.asarray(init[0]), np.asarray(init[1]))
    positions, quats, losses = [], [], []
    result, message, steps = Result.completed, f"{len(small)} frames", 0
    for k in tqdm(range(len(small)), desc="track", unit="frame", disable=not progress):
        guess_pos, guess_quat = jnp.asarray(pos, dtype=float), jnp.asarray(quat, dtype=float)
        if k >= 2:  # constant velocity: move on as between the last two frames
            guess_pos = 2 * positions[-1] - positions[-2]
            guess_quat = quat_mul(quat_mul(quats[-1], quat_conj(quats[-2])), quats[-1])
        n = config.first_iterations if k == 0 else config.iterations
        rays_k = tuple(r[k] for r in rays)
        p, q, value = solve(guess_pos, guess_quat, rays_k, targets[k], n)
        steps += n
        if not np.isfinite(float(value)):
            result, message = Result.nonfinite, f"stopped at frame {k} of {len(small)}"
            break
        positions.append(p)
        quats.append(q)
        losses.append(float(value))
        pos, quat = p, q
    message = f"{result.value}: {message}"
    finish(result, f"track {message}", throw)
    if not positions:
        return TrackResult(np.zeros((0, 3)), np.zeros((0, 4)), np.zeros(0), time.perf_counter() - start, result,
                           message, steps)  # fmt: skip
    positions_a, quats_a = jnp.stack(positions), jnp.stack(quats)
    if config.refine_iterations > 0 and result.ok:
        positions_a, quats_a = refine(s, rays, positions_a, quats_a, targets, config)
        losses = [float(v) for v in _frame_losses(s, rays, positions_a, quats_a, targets, config.barycentre_weight)]
        steps += config.refine_iterations
    return TrackResult(np.asarray(positions_a), np.asarray(quats_a), np.asarray(losses), time.perf_counter() - start,
                       result, message, steps)  # fmt: skip


def _frame_losses(s: Silhouette, rays, positions, quats, targets, weight):
    """Each frame's loss, its window's rays stacked over frames in `rays`."""
    return jax.vmap(lambda r, p, q, m: _window_loss(s, r, p, q, m, weight))(rays, positions, quats, targets)


def refine(s: Silhouette, rays, positions, quats, targets, config: TrackConfig):
    """All poses together: the frames' losses plus `smoothness` times the mean squared second
    difference of the poses (positions in radius units, frame-to-frame rotation vectors in rad)."""
    optimiser = optax.adam(0.25 * config.learning_rate)
    moved = jax.vmap(functools.partial(_pose, s))  # every frame's pose after its increment

    def loss(delta):
        pos, quat = moved(positions, quats, delta)
        fit = jnp.mean(_frame_losses(s, rays, pos, quat, targets, config.barycentre_weight))
        velocity = (pos[1:] - pos[:-1]) / s.radius
        spin = quat_log(quat_mul(quat[1:], quat_conj(quat[:-1])))  # rotation from frame to frame, rad
        accel = jnp.concatenate([velocity[1:] - velocity[:-1], spin[1:] - spin[:-1]], axis=1)
        return fit + config.smoothness * jnp.mean(jnp.sum(accel**2, axis=1))

    @jax.jit
    def run(delta):
        def body(_, carry):
            delta, state = carry
            with jax.numpy_dtype_promotion("standard"):  # optax raises floats to int powers
                updates, state = optimiser.update(jax.grad(loss)(delta), state, delta)
            return optax.apply_updates(delta, updates), state

        delta, _ = jax.lax.fori_loop(0, config.refine_iterations, body, (delta, optimiser.init(delta)))
        return moved(positions, quats, delta)

    pos, quat = run(jnp.zeros((len(positions), 6), dtype=positions.dtype))
    return pos, quat / jnp.linalg.norm(quat, axis=-1, keepdims=True)
