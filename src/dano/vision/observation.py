"""Masks as an observation of a simulation: the residuals of the rendered silhouettes against the
masks (`PixelObservation`), their targets, blur and soft edge, and the settings (`MaskConfig`).
The pipeline that builds and fits such a problem is `dano.vision.pixels`."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from dano.errors import DanoError
from dano.fields import AbstractField
from dano.fields.base import Bounds, CallableField, as_bounds
from dano.fields.grid import GridField
from dano.math import quat_conj, quat_exp, quat_mul, quat_to_mat, smootherstep
from dano.sim.run import jitted
from dano.sysid.configs import SysidError
from dano.sysid.problem import AbstractObservation, Problem, own_unknowns
from dano.sysid.windows import Windows
from dano.vision.camera import Camera
from dano.vision.track import Silhouette, render_silhouette

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


def finer_camera(camera: Camera, k: int) -> Camera:
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
    # one compiled program, kept for the next call (unjitted, each operation of the vmapped render
    # compiled alone)
    opacity = jitted(PixelObservation.silhouettes)(observation, q, w0.observed, params)
    return np.asarray(opacity), np.asarray(w0.observed.mask)
