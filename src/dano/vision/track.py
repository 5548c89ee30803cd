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
The field is read as an occupancy, its surface at half its peak: the optical density is
`sharpness * smoothstep(2 phi / peak - 1/2)` (0 below a quarter of the peak, full above three
quarters), so the silhouette's edge is the surface (a soft edge
rendered as is would grow the silhouette, and the tracker would push the object away from the
camera to shrink it). A mesh's occupancy field, a solidified fitted field (`dano.vision.fit.solidify`)
or any field whose inside is at its peak works; its units do not matter.
"""

import dataclasses
import functools
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, Float
from tqdm.auto import tqdm

from dano.errors import DanoError
from dano.fields import AbstractField
from dano.fields.grid import as_grid
from dano.math import quat_conj, quat_exp, quat_log, quat_mul, quat_to_mat
from dano.surface import field_peak
from dano.vision.data import Camera, camera_rays
from dano.vision.fit import cosine_rate
from dano.vision.render import render_opacity


class TrackError(DanoError):
    """Tracking cannot run: masks and camera disagree, an empty mask, bad settings."""


@dataclasses.dataclass(frozen=True)
class TrackConfig:
    """Tracker settings.

    Attributes:
        iterations: Adam steps per frame (`first_iterations` for the first frame).
        learning_rate: Adam's rate on the pose increment; positions are in units of the object's
            radius and rotations in radians, so one rate suits both.
        n_samples: samples per ray through the object's bounding sphere.
        barycentre_weight: weight of the barycentre term.
        max_size: masks are box-averaged down until their longest side is at most this (pixels).
        grid: nodes along each side of the baked field grid.
        sharpness: optical density inside the object, in 1/radius.
        refine_iterations: Adam steps of the joint refinement over all frames (0: none).
        smoothness: weight of the acceleration penalty in the refinement (per frame, in radius units).
    """

    iterations: int = 60
    first_iterations: int = 300
    learning_rate: float = 0.02
    n_samples: int = 48
    barycentre_weight: float = 1.0
    max_size: int = 128
    grid: int = 64
    sharpness: float = 200.0
    refine_iterations: int = 0
    smoothness: float = 1.0


@dataclasses.dataclass(frozen=True)
class Silhouette:
    """What rendering a pose needs: camera rays (world), the field as an opacity source, its sphere."""

    origins: Float[Array, "r 3"]
    directions: Float[Array, "r 3"]
    uv: Float[Array, "r 2"]
    field: AbstractField
    peak: float
    sharpness: float
    centre: Float[Array, " 3"]
    radius: float
    n_samples: int


def silhouette(field: AbstractField, camera: Camera, config: TrackConfig) -> Silhouette:
    """Prepares rendering of `field` by `camera` (rays of the downsampled image, a baked grid)."""
    lo, hi = (np.asarray(b) for b in field.bounds)
    grid = as_grid(field, (config.grid,) * 3)
    radius = 0.5 * float(np.linalg.norm(hi - lo))
    peak = field_peak(grid)
    origins, directions = camera_rays(camera)
    uv = np.stack(np.meshgrid(np.arange(camera.width) + 0.5, np.arange(camera.height) + 0.5), -1).reshape(-1, 2)
    return Silhouette(
        jnp.asarray(origins), jnp.asarray(directions), jnp.asarray(uv / [camera.width, camera.height]),
        grid, peak, config.sharpness / radius, jnp.asarray(0.5 * (lo + hi)), radius, config.n_samples,
    )  # fmt: skip


def render_silhouette(s: Silhouette, position: Float[Array, " 3"], quat: Float[Array, " 4"]) -> Float[Array, " r"]:
    """Accumulated opacity (r,) of the field at pose (position, quat) of its frame, world."""
    rot = quat_to_mat(quat)
    centre = position + rot @ s.centre
    # The rays' path through the object's bounding sphere.
    along = s.directions @ centre - jnp.sum(s.directions * s.origins, axis=-1)
    closest = s.origins + along[:, None] * s.directions - centre[None, :]
    h2 = s.radius**2 - jnp.sum(closest**2, axis=-1)
    half = jnp.where(h2 > 0, jnp.sqrt(jnp.where(h2 > 0, h2, 1.0)), 0.0)  # 0 for a miss, and a finite gradient
    near, far = jnp.maximum(along - half, 0.0), jnp.maximum(along + half, 0.0)

    def sigma(x):
        occupancy = s.field((x - position[None, :]) @ rot) / s.peak
        t = jnp.clip(2.0 * occupancy - 0.5, 0.0, 1.0)
        return s.sharpness * t * t * (3.0 - 2.0 * t)

    return render_opacity(sigma, s.origins, s.directions, near, far, s.n_samples)


def mask_loss(s: Silhouette, opacity: Float[Array, " r"], mask: Float[Array, " r"], weight: float) -> Float[Array, ""]:
    """mean (T - M)^2 + weight |B(T) - B(M)|^2, barycentres in image-size units."""

    def barycentre(image):
        return jnp.sum(image[:, None] * s.uv, axis=0) / (jnp.sum(image) + 1e-6)

    return jnp.mean((opacity - mask) ** 2) + weight * jnp.sum((barycentre(opacity) - barycentre(mask)) ** 2)


def _pose(s: Silhouette, base_pos, base_quat, delta):
    """Pose after an increment `delta` (6,): position in radius units, rotation vector (world) in rad."""
    return base_pos + s.radius * delta[:3], quat_mul(quat_exp(delta[3:]), base_quat)


@dataclasses.dataclass(frozen=True)
class TrackResult:
    """Poses of the field frame per frame (world), the final loss per frame, and the wall time."""

    positions: np.ndarray
    quats: np.ndarray
    losses: np.ndarray
    seconds: float


def downsample(masks: np.ndarray, camera: Camera, max_size: int) -> tuple[np.ndarray, Camera]:
    """Box-averages masks (n, h, w) by the smallest integer factor that brings their longest side to at
    most `max_size`, and scales the camera's intrinsics to match."""
    factor = max(1, -(-max(camera.width, camera.height) // max_size))
    if factor == 1:
        return masks, camera
    n, h, w = masks.shape
    h2, w2 = h // factor, w // factor
    small = masks[:, : h2 * factor, : w2 * factor].reshape(n, h2, factor, w2, factor).mean(axis=(2, 4))
    scaled = dataclasses.replace(
        camera, width=w2, height=h2, fx=camera.fx / factor, fy=camera.fy / factor,
        cx=camera.cx / factor, cy=camera.cy / factor,
    )  # fmt: skip
    return small, scaled


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
) -> TrackResult:
    """Poses of `field`'s frame in each frame of a video, from its object masks.

    Args:
        masks: (n, h, w) in [0, 1], 1 on the object, `camera`'s size.
        init: (position (3,), quat (4,)) of the field frame in the first frame; default: a guess from
            the first mask (see `initial_pose`), which assumes the object starts unrotated.

    Raises:
        TrackError: masks of another size than the camera's, or an empty mask.
    """
    masks = np.asarray(masks, dtype=float)
    if masks.ndim != 3 or masks.shape[1:] != (camera.height, camera.width):
        raise TrackError(f"masks are {masks.shape[1:]} pixels but the camera is ({camera.height}, {camera.width})")
    empty = np.flatnonzero(masks.reshape(len(masks), -1).max(axis=1) <= 0)
    if len(empty):
        raise TrackError(f"mask of frame {int(empty[0])} is empty: the object must be visible in every frame")
    small, cam = downsample(masks, camera, config.max_size)
    s = silhouette(field, cam, config)
    targets = jnp.asarray(small.reshape(len(small), -1))
    optimiser = optax.scale_by_adam()

    @jax.jit
    def solve(base_pos, base_quat, target, n):
        def loss(delta):
            pos, quat = _pose(s, base_pos, base_quat, delta)
            return mask_loss(s, render_silhouette(s, pos, quat), target, config.barycentre_weight)

        def body(i, carry):  # Adam with the rate decaying along a cosine to 5 %, so the pose settles
            delta, state = carry
            with jax.numpy_dtype_promotion("standard"):  # optax raises floats to int powers
                direction, state = optimiser.update(jax.grad(loss)(delta), state)
            rate = cosine_rate(config.learning_rate, i / n)
            return delta - rate * direction, state

        delta = jnp.zeros(6, dtype=base_pos.dtype)
        delta, _ = jax.lax.fori_loop(0, n, body, (delta, optimiser.init(delta)))
        pos, quat = _pose(s, base_pos, base_quat, delta)
        return pos, quat / jnp.linalg.norm(quat), loss(delta)

    start = time.perf_counter()
    pos, quat = initial_pose(s, small[0], cam) if init is None else (np.asarray(init[0]), np.asarray(init[1]))
    positions, quats, losses = [], [], []
    for k in tqdm(range(len(small)), desc="track", unit="frame", disable=not progress):
        guess_pos, guess_quat = jnp.asarray(pos, dtype=float), jnp.asarray(quat, dtype=float)
        if k >= 2:  # constant velocity: move on as between the last two frames
            guess_pos = 2 * positions[-1] - positions[-2]
            guess_quat = quat_mul(quat_mul(quats[-1], quat_conj(quats[-2])), quats[-1])
        n = config.first_iterations if k == 0 else config.iterations
        p, q, value = solve(guess_pos, guess_quat, targets[k], n)
        positions.append(p)
        quats.append(q)
        losses.append(float(value))
        pos, quat = p, q
    positions_a, quats_a = jnp.stack(positions), jnp.stack(quats)
    if config.refine_iterations > 0:
        positions_a, quats_a = refine(s, positions_a, quats_a, targets, config)
        losses = [float(v) for v in _frame_losses(s, positions_a, quats_a, targets, config.barycentre_weight)]
    return TrackResult(np.asarray(positions_a), np.asarray(quats_a), np.asarray(losses), time.perf_counter() - start)


def _frame_losses(s: Silhouette, positions, quats, targets, weight):
    render = jax.vmap(lambda p, q: render_silhouette(s, p, q))
    return jax.vmap(lambda o, m: mask_loss(s, o, m, weight))(render(positions, quats), targets)


def refine(s: Silhouette, positions, quats, targets, config: TrackConfig):
    """All poses together: the frames' losses plus `smoothness` times the mean squared second
    difference of the poses (positions in radius units, frame-to-frame rotation vectors in rad)."""
    optimiser = optax.adam(0.25 * config.learning_rate)
    moved = jax.vmap(functools.partial(_pose, s))  # every frame's pose after its increment

    def loss(delta):
        pos, quat = moved(positions, quats, delta)
        fit = jnp.mean(_frame_losses(s, pos, quat, targets, config.barycentre_weight))
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
