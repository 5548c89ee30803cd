"""Torques to pixels: identification from object masks through simulation and rendering.

The paper tracks poses frame by frame with a mask loss and then identifies parameters from the
poses (Sec. V, its limitations iii-iv). Here the two are one problem: the parameters θ and the
initial state are simulated forward (`dano.sysid`'s rollout), the DANO's silhouette is rendered at
every simulated pose with the tracker's renderer (`dano.vision.track.render_silhouette`, same
camera model), and the residuals per frame are

    (T(p_k) − M_k) / σ                             one per pixel of the frame's window
    √(R · w) (B(T(p_k)) − B(M_k)) / σ              the barycentres (image-size units), 2 per frame

with T the rendered opacity, M the mask box-averaged to the window's pixels, R the window's pixel
count, w the barycentre weight and σ the opacity noise: ½Σr² is the tracker's loss summed over
frames (in units of σ²). The physics ties every frame to every other, so the orientation a single
mask cannot resolve (a box seen from above, turned by 180°) and a frame whose mask is wrong cost
the fit little. The same projected Levenberg-Marquardt solver, bounds, intervals and JSON as
pose-based identification (`dano.sysid.identify`) run on it; the Jacobian is forward mode (one
tangent per unknown), so memory does not grow with the pixels' count times the frames'.

Each frame is rendered in a window around its mask (`dano.vision.track.windows`, placed on the
mask's largest connected part so a few false pixels far away do not move it), box-averaged so its
longest side is at most `max_size` pixels. A frame whose mask is empty (a dropped or failed
segmentation) carries no residuals and is reported in the problem's adjustments.

The initial state comes from the poses of a few first frames (`dano.vision.track` run on them, or
a pose track given) and is then fitted with θ (`initial="state"`): the first frames' poses only
need to be good enough to start from.

The standard errors and intervals treat the pixels' errors as independent; neighbouring pixels of
a silhouette's edge are not, so they are optimistic (narrower than the truth).
"""

import dataclasses
from collections.abc import Sequence
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float
from tqdm.auto import tqdm

from dano.errors import DanoError
from dano.fields import AbstractField
from dano.fields.base import Bounds, CallableField, as_bounds
from dano.fields.grid import GridField
from dano.math import quat_conj, quat_exp, quat_mul, quat_to_mat, smootherstep
from dano.sim.scene import DanoBody, Scene
from dano.sysid.data import Track
from dano.sysid.frames import scene_dano
from dano.sysid.pipeline import SysidConfig, canonical_fit
from dano.sysid.problem import (
    AbstractObservation,
    Problem,
    Recording,
    SysidError,
    Windows,
    make_problem,
    own_unknowns,
)
from dano.sysid.solve import Identification, identify
from dano.vision.camera import Camera, camera_rays
from dano.vision.track import Silhouette, TrackConfig, downsample, largest_parts, render_silhouette, track, windows

REFINED = ("camera", "object")
"""What `MaskConfig.refine` may name: the camera's extrinsics, the field's pose in the DANO's frame."""


class MaskError(DanoError):
    """Masks that cannot be fitted: another size than the camera's, too few frames, none visible."""


class MaskTargets(eqx.Module):
    """A window's per-frame view of the masks: the rays of each frame's pixel window and the mask
    there (frames 1..W of the window; a leading window axis in `Windows.observed`)."""

    origins: Float[Array, "*n w r k 3"]
    """The k = supersample² rays through each pixel (world)."""
    directions: Float[Array, "*n w r k 3"]
    uv: Float[Array, "*n w r 2"]
    """Pixel centres in image-size units (0..1), for the barycentres."""
    mask: Float[Array, "*n w r"]
    blur_rows: Float[Array, "*n a a"]
    """The residual image's blur down its columns, then along its rows (`blurred`; identities: none)."""
    blur_cols: Float[Array, "*n b b"]
    correction: Float[Array, "*n 12"]
    """The camera's and the object frame's corrections fitted so far (`PixelObservation.moved`):
    camera rotation vector (about its centre, world) and translation, then the field's rotation
    vector (about the centre of mass, body frame) and translation (body frame); zeros: none."""


def gaussian_blur(n: int, width: float) -> Float[np.ndarray, "n n"]:
    """(n, n) rows of a Gaussian of standard deviation `width` pixels, each summing to 1 over the
    window (0: the identity)."""
    if width <= 0:
        return np.eye(n)
    k = np.arange(n)
    g = np.exp(-0.5 * ((k[:, None] - k[None, :]) / width) ** 2)
    return g / g.sum(axis=1, keepdims=True)


def blurred(problem: Problem, width: float) -> Problem:
    """The problem with its pixel residuals blurred by a Gaussian of `width` window pixels (0: none).

    The residual of a hard-edged silhouette has a Jacobian only within its edge's ramp (a pixel),
    so a Gauss-Newton step moves a misplaced silhouette by about a pixel per iteration; blurred by
    a few pixels, the residual's Jacobian reaches as far, and steps as long. Same shapes: the
    problem's compiled functions are reused."""
    observation, observed = problem.observation, problem.windows.observed
    if not (isinstance(observation, PixelObservation) and isinstance(observed, MaskTargets)):
        raise SysidError("blurred needs a problem fitted to masks (mask_problem)")
    if not (np.isfinite(width) and width >= 0):
        raise MaskError(f"the blur width must be a non-negative number of pixels, got {width}")
    rows, cols = observation.shape
    targets = dataclasses.replace(
        observed,
        blur_rows=jnp.asarray(gaussian_blur(rows, width))[None],
        blur_cols=jnp.asarray(gaussian_blur(cols, width))[None],
    )
    return dataclasses.replace(problem, windows=dataclasses.replace(problem.windows, observed=targets))


class PixelObservation(AbstractObservation):
    """Object masks as the observation of one DANO: residuals of its rendered silhouette (module
    docstring).

    Attributes:
        field: the object's density in its own frame (the DANO's frame), read as occupancy φ / peak.
        peak: the field's fully-inside density.
        centre, radius: the field's bounding sphere in its frame (m): the rays' sampled interval.
        n_samples: samples per ray through the sphere.
        qpos: where the observed DANO's free joint starts in qpos.
        com: (3,) its centre of mass in its frame (qpos holds the centre of mass's position).
        sigma: opacity noise: residuals are in units of it.
        barycentre_weight: w, as the tracker's.
        n_rays: R, pixels per frame's window.
        shape: (rows, columns) of every frame's window (rows · columns = R).
        eye: (3,) the camera's centre, world (what a camera correction turns about).
        refine: what is fitted with θ besides the initial state, in this order: "camera" (its
            extrinsics: rotation vector about its centre and translation, world, 6) and "object" (the
            field's pose in the DANO's frame: rotation vector about the centre of mass and
            translation, 6); small corrections within `limits`.
        limits: (rotation, rad; translation, m) bounds on every component of those corrections.
    """

    field: AbstractField
    peak: float = eqx.field(static=True)
    centre: Float[Array, " 3"]
    radius: float = eqx.field(static=True)
    n_samples: int = eqx.field(static=True)
    qpos: int = eqx.field(static=True)
    com: Float[Array, " 3"]
    sigma: float = eqx.field(static=True)
    barycentre_weight: float = eqx.field(static=True)
    n_rays: int = eqx.field(static=True)
    shape: tuple[int, int] = eqx.field(static=True)
    eye: Float[Array, " 3"]
    refine: tuple[str, ...] = eqx.field(static=True, default=())
    limits: tuple[float, float] = eqx.field(static=True, default=(0.05, 0.02))

    @property
    def per_frame(self) -> int:
        return self.n_rays + 2

    @property
    def n_params(self) -> int:
        return 6 * len(self.refine)

    def param_bounds(self, observed: MaskTargets) -> tuple[np.ndarray, np.ndarray]:
        """Each correction's total (what `observed` holds plus the unknowns) within `limits`."""
        limit = np.tile(np.repeat(np.asarray(self.limits, dtype=float), 3), 2)
        total = np.asarray(observed.correction)
        return (-limit - total)[:, self._columns], (limit - total)[:, self._columns]

    @property
    def _columns(self) -> np.ndarray:
        """Where the unknowns sit in the 12 corrections (`MaskTargets.correction`)."""
        return np.array([6 * REFINED.index(r) + k for r in self.refine for k in range(6)], dtype=int)

    def moved(self, observed: MaskTargets, params: Float[Array, " m"]) -> MaskTargets:
        """`observed` with the unknowns `params` added to its corrections (one window)."""
        full = jnp.zeros(12, params.dtype).at[self._columns].set(params)
        return dataclasses.replace(observed, correction=observed.correction + full)

    def field_poses(self, qpos: Float[Array, "w nq"], correction: Float[Array, " 12"]):
        """The field frame's origin (w, 3) and orientation (w, 4) as the given camera would see it.

        The field sits in the DANO's frame at the object correction (rotation R_o about the centre
        of mass, translation t_o): x_dano = com + R_o (x_field − com) + t_o. A camera moved by
        (R_c about its centre c, then t_c) sees what the given camera sees of the world moved by the
        inverse, x ↦ c + R_cᵀ (x − c − t_c): that is applied to the field's pose.
        """
        pos, quat = qpos[:, self.qpos : self.qpos + 3], qpos[:, self.qpos + 3 : self.qpos + 7]
        camera_rot, camera_shift = quat_exp(correction[0:3]), correction[3:6]
        object_rot, object_shift = quat_exp(correction[6:9]), correction[9:12]
        local = object_shift - quat_to_mat(object_rot) @ self.com  # the field's origin, DANO frame about the com
        origin = pos + jnp.einsum("wij,j->wi", quat_to_mat(quat), local)
        quat = quat_mul(quat, object_rot[None])
        inverse = quat_to_mat(camera_rot).T
        eye = self.eye[None, :]
        origin = eye + (origin - eye - camera_shift[None, :]) @ inverse.T
        return origin, quat_mul(quat_conj(camera_rot)[None], quat)

    def silhouettes(
        self, qpos: Float[Array, "w nq"], observed: MaskTargets, params: Float[Array, " m"] | None = None
    ) -> Float[Array, "w r"]:
        """The rendered opacity of the DANO at each frame's pose, over the frame's window."""
        if params is not None:
            observed = self.moved(observed, params)
        origin, quat = self.field_poses(qpos, observed.correction)

        def frame(p, q, origins, directions, uv):  # each pixel's opacity: the mean over its rays
            r, k = directions.shape[:2]
            rays = (origins.reshape(r * k, 3), directions.reshape(r * k, 3), jnp.repeat(uv, k, axis=0))
            s = Silhouette(*rays, self.field, self.peak, self.centre, self.radius, self.n_samples)
            return jnp.mean(render_silhouette(s, p, q).reshape(r, k), axis=1)

        return jax.vmap(jax.checkpoint(frame))(origin, quat, observed.origins, observed.directions, observed.uv)

    def residuals(
        self, qpos: Float[Array, "w nq"], observed: MaskTargets, params: Float[Array, " m"]
    ) -> Float[Array, "w k"]:
        opacity = self.silhouettes(qpos, observed, params)
        shift = jax.vmap(_barycentre)(opacity, observed.uv) - jax.vmap(_barycentre)(observed.mask, observed.uv)
        scale = float(np.sqrt(self.n_rays * self.barycentre_weight))
        image = (opacity - observed.mask).reshape(-1, *self.shape)
        image = jnp.einsum("ij,wjk,lk->wil", observed.blur_rows, image, observed.blur_cols)
        difference = image.reshape(opacity.shape)
        return jnp.concatenate([difference, scale * shift], axis=1) / self.sigma

    def rms(self, r: np.ndarray, windows: Windows) -> float:
        """Root mean square opacity error over the frames that have a mask."""
        frames = np.asarray(windows.mask) > 0
        return float(np.sqrt(np.mean((r[..., : self.n_rays][frames] * self.sigma) ** 2)))


def _barycentre(image: Float[Array, " r"], uv: Float[Array, "r 2"]) -> Float[Array, " 2"]:
    return jnp.sum(image[:, None] * uv, axis=0) / (jnp.sum(image) + 1e-6)


@dataclasses.dataclass(frozen=True)
class MaskConfig:
    """How masks are compared with simulated silhouettes (`mask_problem`).

    Attributes:
        sigma: opacity noise (residual unit; the estimate does not depend on it).
        barycentre_weight: weight of the barycentre residuals (the tracker's).
        max_size: each frame's window is box-averaged until its longest side is at most this (pixels).
        n_samples: samples per ray through the object's bounding sphere.
        margin: the windows grow by this times the largest mask's longest side on every side.
        supersample: each pixel's opacity is the mean of supersample² rays through it, as the masks
            box-averaged to the window's pixels are the object's share of each pixel. With one ray a
            hard edge changes a pixel only when it crosses the pixel's centre, and the loss is a
            staircase in the pose, flat between steps.
        edge: the silhouette's edge is a ramp about this many pixels wide: the density is rendered
            as peak · S(−d / w) with d the signed distance to its half level and w this width at the
            object's distance (`soft_edged`). The ramp keeps the surface where it is (blurring the
            density would pull it in where two faces meet), and makes the loss smooth at the scale
            of a pixel: measured on a box sliding at 1.6 m/s, a 0.75 mm edge (a third of a pixel)
            took 4 horizons of ~50 Levenberg-Marquardt iterations each, a 3 mm one 20-30.
        first_seconds: the fit is continued over growing horizons: the frames of the first this many
            seconds, then twice as many, ..., then all (`identify_masks`); a horizon over which the
            simulation drifts out of the masks gives no gradient, and one too short for friction to
            act leaves μ free to trade against the initial velocity: counted in frames (8), the
            first horizon at 120 fps was 0.07 s, over which a friction error of 0.15 moves the box
            ½·0.15·g·t² = 3 mm, a pixel; the fit went to μ 0.8 there and never came back
            (bench/pixels.py, box 120 fps noisy: μ 0.75 for 0.4).
        init_seconds: the first frames of this many seconds (at least 3) are tracked for the initial
            state when no start track is given; a body starting within `settle` of the ground is
            put on it along the camera's rays (`_along_rays`).
        pose_sigma: how far the first frames' poses may be off, m: the initial pose is fitted within
            5 of it.
        settle: a body whose lowest point starts within this distance (m) of the ground is started
            on it, sliding (`make_problem`'s `settle`: height, rocking and lifting velocities set by
            contact, the rest fitted). A depth read from a few dozen pixels' silhouette is off by a
            centimetre or more; started that far above the table, the fit found a box tumbling in
            the air that matched the noisy masks' sizes better than the sliding truth (bench/pixels.py,
            box 30 fps noisy: μ 0.32 for 0.4).
        blur: each horizon is fitted with the residual images blurred by these Gaussian widths
            (window pixels) in turn, the last 0 (`blurred`): the sharp residual's Jacobian reaches only
            the edge's ramp, and Levenberg-Marquardt crawled there a pixel per step (the same case:
            every stage at the 50-iteration limit, μ off by 6 %; blurred first, every stage converged,
            1.4 %).
        refine: fitted with θ and the initial state (`PixelObservation.refine`): "camera" (its
            extrinsics) and/or "object" (the field's pose in the DANO's frame), small corrections.
        refine_limits: (rad, m): every component of those corrections within these.
    """

    sigma: float = 0.1
    barycentre_weight: float = 1.0
    max_size: int = 64
    n_samples: int = 48
    margin: float = 0.3
    supersample: int = 2
    edge: float = 1.0
    first_seconds: float = 0.25
    init_seconds: float = 0.2
    pose_sigma: float = 2e-3
    settle: float = 0.02
    blur: tuple[float, ...] = (2.0, 0.0)
    refine: tuple[str, ...] = ()
    refine_limits: tuple[float, float] = (0.05, 0.02)


def dano_field(body: DanoBody) -> tuple[AbstractField, float]:
    """The DANO's density field (its baked grid) and peak, for rendering its silhouette.

    Raises:
        MaskError: the DANO file carries no grid (build it with `dano build`, or give the field).
    """
    dano = body.dano
    if dano.grid is None or dano.grid_bounds is None or dano.peak is None:
        raise MaskError(
            f"DANO {body.name!r} has no baked density grid to render its silhouette: rebuild it with `dano build` "
            "or give its field"
        )
    return GridField(jnp.asarray(dano.grid), dano.grid_bounds), float(dano.peak)


def mask_problem(
    scene: Scene,
    masks: np.ndarray,
    camera: Camera,
    fps: float,
    fit: Sequence[str],
    body: str | None = None,
    start: Track | None = None,
    start_pose: tuple[np.ndarray, np.ndarray] | None = None,
    field: AbstractField | None = None,
    config: MaskConfig = MaskConfig(),
    initial: str = "state",
    progress: bool = True,
) -> Problem:
    """Identification of `fit` from the masks of one DANO of `scene` filmed by a fixed `camera`.

    Args:
        masks: (n, h, w) in [0, 1], 1 on the object, the camera's size; frame k at time k / fps. A frame
            with an empty mask carries no residuals.
        body: the observed DANO (default: the scene's only one).
        start: the body's poses (centre of mass, world) over at least the first 3 frames, for the
            initial state (e.g. from `dano track`); default: `dano.vision.track` on the first
            `config.init_seconds` of masks.
        start_pose: (position (3,), quat (4,)) of the DANO's own frame in the first frame, where the
            tracker starts (default: its guess from the first mask, unrotated).
        field: the density the silhouette is rendered from, in the DANO's frame (default: the grid
            baked into the DANO).
        initial: "state" (default: the initial pose and velocity fitted), "velocity" or "none".

    Raises:
        MaskError: masks of another size than the camera's, fewer than 3 frames, an empty first mask.
        SysidError: as `make_problem`.
    """
    masks = np.asarray(masks, dtype=float)
    if masks.ndim != 3 or masks.shape[1:] != (camera.height, camera.width):
        raise MaskError(f"masks are {masks.shape[1:]} pixels but the camera is ({camera.height}, {camera.width})")
    if len(masks) < 3:
        raise MaskError(f"need at least 3 frames of masks, got {len(masks)}")
    if not (np.isfinite(fps) and fps > 0):
        raise MaskError(f"fps must be positive, got {fps}")
    unknown = [r for r in config.refine if r not in REFINED]
    if unknown or len(set(config.refine)) != len(config.refine):
        raise MaskError(f"refine names each of {REFINED} at most once, got {tuple(config.refine)}")
    limits = np.asarray(config.refine_limits, dtype=float)
    if limits.shape != (2,) or not np.all(np.isfinite(limits) & (limits > 0)):
        raise MaskError(f"refine_limits must be two positive numbers (rad, m), got {config.refine_limits}")
    if not np.all(np.isfinite(masks)) or masks.min() < 0 or masks.max() > 1:
        raise MaskError("masks must be finite and in [0, 1]")
    visible = masks.reshape(len(masks), -1).max(axis=1) > 0.5
    if not visible[0]:
        raise MaskError("the first mask is empty: the object must be visible where the fit starts")
    target = scene_dano(scene, body, "the masks show")
    own, peak = dano_field(target) if field is None else (field, None)
    if peak is None:
        from dano.surface import field_peak

        peak = field_peak(own)
    com = np.asarray(target.dano.com)
    grounded = None
    if start is None:
        start, grounded = _first_frames(own, camera, masks, visible, fps, target, scene, start_pose, config, progress)
    if start.n_frames < 3:
        raise MaskError(f"the start track has {start.n_frames} frames; the initial velocity needs at least 3")
    recording = Recording({target.name: _padded(start, len(masks), 1.0 / fps)})
    problem = make_problem(
        scene, [recording], fit, initial=initial, sigma=config.pose_sigma, rotation_weight=0.0, settle=config.settle,
    )  # fmt: skip
    observation, targets = _observation(problem, target.name, own, peak, com, camera, masks, visible, config)
    mask = problem.windows.mask * jnp.asarray(visible[1:], dtype=problem.windows.mask.dtype)[None, :]
    windows = dataclasses.replace(problem.windows, observed=targets, mask=mask)
    adjustments = dict(problem.adjustments)
    if grounded is not None:
        adjustments["start_along_rays"] = grounded
    if not visible.all():
        adjustments["frames_without_mask"] = [int(k) for k in np.flatnonzero(~visible)]
    return dataclasses.replace(problem, windows=windows, observation=observation, adjustments=adjustments)


def _first_frames(field, camera, masks, visible, fps, target, scene, start_pose, config: MaskConfig, progress):
    """The centre of mass's track over the first visible frames (`config.init_seconds`), by the
    per-frame tracker, put on the ground along the camera's rays where it starts near it
    (`_along_rays`); with what that moved (None: nothing)."""
    want = max(3, int(np.ceil(config.init_seconds * fps - 1e-6)))
    k = 0
    while k < min(want, len(masks)) and visible[k]:
        k += 1
    if k < 3:
        raise MaskError(f"the first 3 masks must show the object to start from (frame {k} is empty)")
    com = np.asarray(target.dano.com)
    result = track(field, camera, masks[:k], TrackConfig(), init=start_pose, progress=progress)
    quats = unflipped(result.quats)
    rot = np.asarray(quat_to_mat(jnp.asarray(quats)))
    pos, moved = _along_rays(
        result.positions + np.einsum("tij,j->ti", rot, com), rot, target.dano, scene, camera, config
    )
    return Track(t=np.arange(k) / fps, pos=_quadratic(pos), quat=quats, source="masks (first frames tracked)"), moved


def _along_rays(pos, rot, dano, scene: Scene, camera: Camera, config: MaskConfig):
    """Tracked centres of mass (k, 3) moved along the camera's rays to the height at which the
    first frame's orientation rests on the ground, when its lowest point is within `config.settle`
    of it (a body sliding on the ground keeps its centre's height; the tracked tilts of later frames
    are no better than their depths); with a report.

    A silhouette fixes where the object is across the view far better than along it: an edge eroded
    or dilated by a pixel reads as the object farther or nearer, by centimetres at a few dozen pixels
    (bench/pixels.py, box 120 fps noisy: the first six frames tracked 1.5-3.8 cm above the table and
    as much off across it, an initial velocity off by 2 m/s). Settling straight down (`make_problem`)
    keeps the error across; along the ray it goes: there, within 5 mm.
    """
    if scene.ground_height is None:
        return pos, None
    n = np.asarray(scene.ground_normal, dtype=float)
    n = n / np.linalg.norm(n)
    offsets = np.asarray(dano.points, dtype=float) - np.asarray(dano.com, dtype=float)
    lowest = np.min(np.einsum("ij,pj,i->p", rot[0], offsets, n))  # the first frame's lowest point, from the centre
    gap = float(pos[0] @ n + lowest - float(scene.ground_height))
    if not gap <= config.settle:
        return pos, None
    eye = np.asarray(camera.position, dtype=float)
    along = (pos - eye) @ n
    if np.any(np.abs(along) < 1e-9):  # a ray parallel to the ground: nothing to intersect
        return pos, None
    scale = (float(scene.ground_height) - lowest - eye @ n) / along
    if np.any(scale <= 0):  # the ground behind the camera along a ray
        return pos, None
    moved = eye + scale[:, None] * (pos - eye)
    shift = np.linalg.norm(moved - pos, axis=1)
    return moved, {"frames": len(pos), "max_moved_m": float(shift.max()), "first_gap_m": gap}


def _quadratic(pos: Float[np.ndarray, "k 3"]) -> Float[np.ndarray, "k 3"]:
    """The least-squares quadratic in time through the positions: the initial velocity is read from
    the first three frames, and one noisy mask (an eroded or dilated edge moves the tracked depth by
    millimetres) would otherwise set it."""
    t = np.arange(len(pos), dtype=float)
    basis = np.stack([np.ones_like(t), t, t * t], axis=1)
    coef, *_ = np.linalg.lstsq(basis, pos, rcond=None)
    return basis @ coef


_HALF_TURNS = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
"""The identity and the half turns about the object frame's x, y and z axes (w, x, y, z)."""


def unflipped(quats: Float[np.ndarray, "n 4"]) -> Float[np.ndarray, "n 4"]:
    """Tracked orientations with half-turn flips undone: a frame more than 90° from where the frames
    before put it (at constant angular velocity) becomes whichever of q, q·Rx(π), q·Ry(π), q·Rz(π)
    is nearest that prediction. A mask cannot tell these apart for an object symmetric about its
    frame's axes (a box: the tracker may report it upside down from one frame to the next), and a
    turn of more than 90° between two frames is no slide's; the initial angular velocity read
    from a flipped frame would be absurd.
    """
    quats = np.asarray(quats, dtype=float)
    out = [quats[0]]
    for k in range(1, len(quats)):
        guess = out[-1] if k < 2 else np.asarray(quat_mul(quat_mul(out[-1], quat_conj(out[-2])), out[-1]))
        if _angle(quats[k], guess) > 0.5 * np.pi:
            candidates = np.asarray(quat_mul(jnp.asarray(quats[k])[None], jnp.asarray(_HALF_TURNS)))
            out.append(min(candidates, key=lambda c: _angle(c, guess)))
        else:
            out.append(quats[k])
    return np.stack(out)


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    return float(2.0 * np.arccos(np.clip(abs(float(np.dot(a, b))), 0.0, 1.0)))


def _padded(start: Track, n: int, dt: float) -> Track:
    """The start track extended to n frames by its last pose (poses after the start are not used:
    the masks are the data), on the masks' clock."""
    if abs(start.dt - dt) > 1e-6 * dt:
        raise MaskError(f"the start track's frame rate {1 / start.dt:.6g} fps is not the masks' {1 / dt:.6g}")
    k = min(start.n_frames, n)
    index = np.minimum(np.arange(n), k - 1)
    return Track(t=np.arange(n) * dt, pos=start.pos[index], quat=start.quat[index], source=start.source)


def _observation(problem: Problem, name, field, peak, com, camera, masks, visible, config: MaskConfig):
    """The `PixelObservation` and each window's `MaskTargets` (one window: frames 1..n-1)."""
    if problem.n_windows != 1:  # make_problem was asked for one window
        raise SysidError("identification from masks simulates the video as one window")
    held = largest_parts(masks, visible)
    (height, width), _ = windows(held, config.margin)
    factor = max(1, -(-max(height, width) // config.max_size))
    small, cam = downsample(masks, camera, factor)
    held_small, _ = downsample(held, camera, factor)
    size, corners = windows(held_small, config.margin)
    ss = int(config.supersample)
    if ss < 1:
        raise MaskError(f"supersample must be at least 1, got {ss}")
    origins, directions = (a.reshape(cam.height, ss, cam.width, ss, 3) for a in camera_rays(_finer(cam, ss)))
    origins, directions = (a.transpose(0, 2, 1, 3, 4).reshape(cam.height * cam.width, ss * ss, 3)
                           for a in (origins, directions))  # fmt: skip
    uv = np.stack(np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5), -1).reshape(-1, 2)
    uv = uv / [cam.width, cam.height]
    rows = corners[:, :1, None] + np.arange(size[0])[None, :, None]
    cols = corners[:, 1:, None] + np.arange(size[1])[None, None, :]
    index = (rows * cam.width + cols).reshape(len(corners), -1)[1:]  # frames 1..n-1, (n - 1, r)
    flat = small.reshape(len(small), -1)[1:]
    targets = MaskTargets(
        jnp.asarray(origins[index])[None], jnp.asarray(directions[index])[None], jnp.asarray(uv[index])[None],
        jnp.asarray(np.take_along_axis(flat, index, axis=1))[None],
        jnp.eye(int(size[0]))[None], jnp.eye(int(size[1]))[None], jnp.zeros((1, 12)),
    )  # fmt: skip
    observed = next(o for o in problem.observed if o.name == name)
    depth = float(np.linalg.norm(np.asarray(problem.windows.qpos[0, observed.qpos : observed.qpos + 3]) - cam.position))
    field = soft_edged(field, peak, config.edge * depth / min(cam.fx, cam.fy))
    peak = 1.0
    lo, hi = (np.asarray(b, dtype=float) for b in field.bounds)
    observation = PixelObservation(
        field=field, peak=float(peak), centre=jnp.asarray(0.5 * (lo + hi)), radius=0.5 * float(np.linalg.norm(hi - lo)),
        n_samples=config.n_samples, qpos=observed.qpos, com=jnp.asarray(com), sigma=float(config.sigma),
        barycentre_weight=float(config.barycentre_weight), n_rays=int(index.shape[1]),
        shape=(int(size[0]), int(size[1])), eye=jnp.asarray(cam.position), refine=tuple(config.refine),
        limits=(float(config.refine_limits[0]), float(config.refine_limits[1])),
    )  # fmt: skip
    return observation, targets


def _finer(camera: Camera, k: int) -> Camera:
    """The camera with k × k pixels for each of its own (row-major rays through their centres)."""
    return dataclasses.replace(
        camera, width=camera.width * k, height=camera.height * k, fx=camera.fx * k, fy=camera.fy * k,
        cx=camera.cx * k, cy=camera.cy * k,
    )  # fmt: skip


class SoftEdged(AbstractField):
    """Occupancy S(−d(x) / width) of an analytic field's signed distance d (its half level exact)."""

    field: AbstractField
    width: float = eqx.field(static=True)
    bounds: Bounds = eqx.field(static=True)

    def __call__(self, x: Float[Array, "n 3"]) -> Float[Array, " n"]:
        return smootherstep(-self.field.signed_distance(x) / self.width)  # pyright: ignore[reportAttributeAccessIssue]


def soft_edged(field: AbstractField, peak: float, width: float, max_nodes: int = 160) -> AbstractField:
    """Occupancy (0..1) whose half level is `field`'s half-peak level and which ramps over ±`width`
    (m) across it: S(−d / width) with d the signed distance to that level (`smootherstep`).

    An analytic field gives d exactly. Any other is baked on a grid of spacing ≤ width / 3 (at most
    `max_nodes` along its longest side), and d is the Euclidean distance transform of its inside
    (≥ half peak) and outside, each side measured to the midpoint between neighbouring nodes of
    opposite sides (exact to half a spacing, then smoothed over the width by the ramp).
    """
    from scipy.ndimage import distance_transform_edt

    from dano.fields.grid import as_grid

    grow = 1.5 * width
    lo, hi = (np.asarray(b, dtype=float) for b in field.bounds)
    bounds = as_bounds(np.stack([lo - grow, hi + grow]))
    if hasattr(field, "signed_distance"):
        return SoftEdged(field, float(width), bounds)
    extent = float(np.max(hi - lo)) + 2 * grow
    spacing = max(width / 3.0, extent / (max_nodes - 1))
    shape = tuple(int(np.ceil((b - a) / spacing)) + 1 for a, b in zip(bounds[0], bounds[1], strict=True))
    upper = np.asarray(bounds[0]) + spacing * (np.asarray(shape) - 1)
    grid = as_grid(CallableField(field, bounds), shape)  # pyright: ignore[reportArgumentType]
    inside = np.asarray(grid.density) >= 0.5 * peak
    outside_to = np.asarray(distance_transform_edt(inside, sampling=spacing))
    inside_to = np.asarray(distance_transform_edt(~inside, sampling=spacing))
    d = outside_to - inside_to
    d = -np.asarray(d) - np.where(inside, -0.5 * spacing, 0.5 * spacing)  # negative inside, to the midpoints
    occupancy = np.asarray(smootherstep(jnp.asarray(-d / width)))
    return GridField(jnp.asarray(occupancy), (tuple(bounds[0]), tuple(upper)))


def simulated_silhouettes(problem: Problem, theta, delta) -> tuple[np.ndarray, np.ndarray]:
    """(rendered opacity, mask) per frame 1..n-1 over the frames' windows, (n - 1, r) each, at (θ, δ)."""
    from dano.sysid.problem import simulate_windows

    observation = problem.observation
    if not isinstance(observation, PixelObservation):
        raise SysidError("the problem is not fitted to masks")
    q = simulate_windows(problem, theta, delta)[0, 1:]
    w0 = jax.tree_util.tree_map(lambda x: x[0], problem.windows)
    params = own_unknowns(w0, jnp.asarray(delta)[0])
    return np.asarray(observation.silhouettes(q, w0.observed, params)), np.asarray(w0.observed.mask)


def identify_masks(
    problem: Problem,
    init: dict[str, float] | None = None,
    bounds: dict[str, tuple[float, float]] | None = None,
    labels: tuple[str, ...] | None = None,
    first_seconds: float = MaskConfig.first_seconds,
    blur: Sequence[float] = MaskConfig.blur,
    max_steps: int = 50,
    interval: str = "gauss-newton",
    level: float = 0.95,
    rtol: float = 1e-6,
    progress: bool = True,
) -> tuple[Problem, Identification]:
    """`dano.sysid.identify` on a problem from `mask_problem`, continued over growing horizons;
    the problem the result's unknowns (`delta`) refer to, started where the earlier horizons put it
    (for `simulated_silhouettes`, `plot_masks`), and the result.

    The frames of the first `first_seconds` are fitted, then twice as many from that estimate (θ and the
    initial state), and so on to the whole video; each horizon is fitted with the residuals blurred
    by each width of `blur` in turn (`blurred`, coarse to fine), the last horizon also sharp (the
    last width, 0; on a horizon before it the sharp stage crawled to its step limit at 120 fps, 4-5
    minutes, to be undone by the next horizon's blurred one); the intervals are computed on the
    last fit (sharp, all frames). Each stage reuses the problem's compiled
    functions (only the frames' weights and the blur matrices change). A horizon
    over which the simulation from a poor guess drifts out of the masks would give no gradient:
    a friction 0.3 too low moves a box sliding for 0.27 s by 10 cm, more than its length.

    Args:
        rtol: stop a horizon when an accepted step lowers the loss by less than this fraction of
            it (the pixels' loss is large and not a χ², so the pose fit's absolute `ftol` is no test).
        (others): as `identify`.
    """
    observation = problem.observation
    if not isinstance(observation, PixelObservation):
        raise SysidError("identify_masks needs a problem fitted to masks (mask_problem)")
    if not (np.isfinite(first_seconds) and first_seconds > 0):
        raise SysidError(f"first_seconds must be a positive duration, got {first_seconds}")
    full = problem.windows.mask
    n = int(full.shape[1])
    horizons = []
    h = max(2, int(np.ceil(first_seconds / problem.scene.timestep - 1e-6)))
    while h < n:
        horizons.append(h)
        h *= 2
    theta = dict(init or {})
    current = problem
    blurs = [float(b) for b in blur]
    if not blurs or any(not (np.isfinite(b) and b >= 0) for b in blurs) or blurs[-1] != 0:
        raise SysidError(f"blur must be non-negative widths ending with 0 (the sharp masks), got {tuple(blur)}")
    coarse = blurs[:-1] or blurs  # a horizon before the last is fitted blurred only: the next one starts blurred again
    stages = [(h, b) for h in horizons for b in coarse] + [(n, b) for b in blurs]
    bar = tqdm(total=len(stages), desc="horizons", unit="stage", disable=None if progress else True, leave=False)
    seconds = 0.0
    stage = problem
    for h in [*horizons, n]:
        prefix = full * (jnp.arange(n) < h).astype(full.dtype)[None, :]
        for b in coarse if h < n else blurs:
            stage = blurred(dataclasses.replace(current, windows=dataclasses.replace(current.windows, mask=prefix)), b)
            if h == n and b == blurs[-1]:
                break  # the last: fitted below, with its intervals
            result = identify(stage, init=theta, bounds=bounds, max_steps=max_steps, rtol=rtol, progress=False)
            seconds += result.seconds
            theta = dict(zip(problem.names, (float(v) for v in result.theta), strict=True))
            current = _restarted(current, result.delta[0])
            bar.update()
    result = identify(
        stage, init=theta, bounds=bounds, labels=labels, max_steps=max_steps, rtol=rtol, interval=interval,
        level=level, progress=False,
    )  # fmt: skip
    bar.update()
    bar.close()
    adjustments = {**result.adjustments, "horizons": [*horizons, n], "blur_px": blurs}
    if observation.refine:
        w0 = jax.tree_util.tree_map(lambda x: x[0], stage.windows)
        total = np.asarray(observation.moved(w0.observed, own_unknowns(w0, jnp.asarray(result.delta[0]))).correction)
        for k, name in enumerate(REFINED):
            if name in observation.refine:
                adjustments[f"{name}_correction"] = {
                    "rotation_rad": [float(v) for v in total[6 * k : 6 * k + 3]],
                    "translation_m": [float(v) for v in total[6 * k + 3 : 6 * k + 6]],
                }
    return stage, dataclasses.replace(result, seconds=result.seconds + seconds, adjustments=adjustments)


def _restarted(problem: Problem, delta: np.ndarray) -> Problem:
    """The problem started where `delta` (one window's unknowns) put it: the initial state moved
    (`start_state`) and the observation's corrections added to its targets; the unknowns then 0."""
    from dano.sysid.problem import start_state

    w0 = jax.tree_util.tree_map(lambda x: x[0], problem.windows)
    qpos, qvel = start_state(problem, w0, jnp.asarray(delta))
    observed = problem.windows.observed
    observation = problem.observation
    assert isinstance(observation, PixelObservation) and isinstance(observed, MaskTargets)
    if observation.n_params:
        params = own_unknowns(w0, jnp.asarray(delta))
        observed = jax.tree_util.tree_map(lambda x: x[None], observation.moved(w0.observed, params))
    windows = dataclasses.replace(problem.windows, qpos=qpos[None], qvel=qvel[None], observed=observed)
    return dataclasses.replace(problem, windows=windows)


def identify_mask_files(
    scene_path: str | Path,
    masks_dir: str | Path,
    camera_path: str | Path,
    config: SysidConfig,
    start: str | Path | None = None,
    start_pose: tuple[np.ndarray, np.ndarray] | None = None,
    field: str | None = None,
    mask_config: MaskConfig = MaskConfig(),
    progress: bool = True,
) -> tuple[Problem, Identification]:
    """What `dano sysid --masks` runs: the scene, a folder of masks (one per frame, in name order;
    all-black frames carry no residuals) and the camera in, identified parameters out (with the
    problem they refer to, as `identify_masks`).

    Args:
        config: `fit`, `fps` (required: the masks' frame rate), `body`, `init`, `bounds`, `max_steps`,
            `interval`, `level` and `initial` (default for masks: "state") apply; the options about pose
            files (window, loss, orientation, gravity, scale, size, frames) are refused.
        start: a pose CSV of the body's centre of mass over (at least) the first 3 frames, e.g. from
            `dano track` (default: the first frames tracked here).
        start_pose: the field frame's pose in the first frame for that tracking (default: a guess).
        field: a field source (`dano.build.field_from_source`) to render the silhouette from, in the
            DANO's frame (default: the DANO's baked grid).

    Raises:
        SysidError: an option that does not apply to masks, no fps; MaskError, VisionDataError: as
            `mask_problem`, `load_masks`, `load_camera`.
    """
    from dano.sim.toml import load_scene
    from dano.sysid.data import TrackFileError, read_tracks
    from dano.vision.camera import load_camera
    from dano.vision.media import load_masks

    pose_only = {
        "window": config.window is not None, "loss": config.loss != "l2", "orientation": config.orientation != "track",
        "gravity": config.gravity is not None, "scale": config.scale is not None, "size": config.size is not None,
        "frames": config.frames is not None,
    }  # fmt: skip
    refused = [k for k, given in pose_only.items() if given]
    if refused:
        raise SysidError(f"--{refused[0]} applies to pose files, not to masks (the camera and the scene are metric)")
    if config.fps is None:
        raise SysidError("give the masks' frame rate (--fps)")
    scene = load_scene(scene_path)
    camera = load_camera(camera_path)
    masks = load_masks(masks_dir, None, (camera.height, camera.width), allow_empty=True)
    target = scene_dano(scene, config.body, "the masks show")
    start_track = None
    if start is not None:
        try:  # its own clock if it has a t column, else the masks'
            tracks = read_tracks(start)
        except TrackFileError as e:
            if "no t column" not in str(e):
                raise
            tracks = read_tracks(start, fps=config.fps)
        if len(tracks) == 1:
            start_track = next(iter(tracks.values()))
        elif target.name in tracks:
            start_track = tracks[target.name]
        else:
            raise SysidError(f"{start}: no track of body {target.name!r} (it has {sorted(tracks)})")
    own = None
    if field is not None:
        from dano.build import field_from_source
        from dano.types import DANO

        own = field_from_source(field)
        if isinstance(own, DANO):
            raise MaskError(
                f"{field}: the silhouette is rendered from a field (grid, checkpoint, mesh, spec), not a DANO"
            )
    names, init, bounds = canonical_fit(config)
    problem = mask_problem(
        scene, masks, camera, config.fps, names, body=target.name, start=start_track, start_pose=start_pose,
        field=own, config=mask_config, initial=config.initial, progress=progress,
    )  # fmt: skip
    return identify_masks(
        problem, init=init, bounds=bounds, labels=tuple(config.fit), first_seconds=mask_config.first_seconds,
        blur=mask_config.blur, max_steps=config.max_steps, interval=config.interval, level=config.level,
        progress=progress,
    )  # fmt: skip
