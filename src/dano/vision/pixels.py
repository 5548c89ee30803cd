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

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from dano.fields import AbstractField
from dano.fields.grid import GridField
from dano.sim.scene import DanoBody, Scene
from dano.sysid.configs import SysidConfig, SysidError
from dano.sysid.data import Track
from dano.sysid.frames import scene_dano
from dano.sysid.pipeline import canonical_fit
from dano.sysid.problem import Problem, make_problem, own_unknowns
from dano.sysid.solve import Identification, identify
from dano.sysid.windows import Recording
from dano.vision.camera import Camera, camera_rays
from dano.vision.observation import (
    REFINED,
    MaskConfig,
    MaskError,
    MaskTargets,
    PixelObservation,
    blurred,
    finer_camera,
    soft_edged,
)
from dano.vision.start import first_frames, padded
from dano.vision.track import downsample, largest_parts, windows


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
        start, grounded = first_frames(own, camera, masks, visible, fps, target, scene, start_pose, config, progress)
    if start.n_frames < 3:
        raise MaskError(f"the start track has {start.n_frames} frames; the initial velocity needs at least 3")
    recording = Recording({target.name: padded(start, len(masks), 1.0 / fps)})
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
    origins, directions = (a.reshape(cam.height, ss, cam.width, ss, 3) for a in camera_rays(finer_camera(cam, ss)))
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
