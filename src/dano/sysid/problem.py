"""Problem (17) as least squares: simulated minus observed poses, over shooting windows.

Each observed run is cut into windows of `window` frame intervals; every window starts from the
observed state at its first frame (the pose read from the data, the velocity estimated from the
frames around it, or either fitted as extra unknowns) and is simulated with the candidate
parameters θ. With one window per run this is the paper's single shooting from x̂₁; short windows
(multiple shooting) keep an early error in a chaotic contact from swamping the loss.

Residuals per observed body and frame, in units of the tracking noise σ (m):

    position  (x_sim − x_obs) / σ
    rotation  log(q_obs⁻¹ ⊗ q_sim) · L / σ     (rotation vector, rad; |·| is the geodesic angle)

L (m/rad) turns an angle into a length: the body's radius of gyration by default, so a rotation
error weighs like the displacement it causes at the body's typical radius.
"""

import abc
import dataclasses
import warnings
from collections.abc import Mapping, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, PyTree

from dano._mjx import mjx
from dano.contact.wrench import ContactParams
from dano.errors import DanoError
from dano.math import quat_conj, quat_exp, quat_log, quat_mul
from dano.sim.compile import compile_scene
from dano.sim.run import at_interval
from dano.sim.scene import DanoBody, Primitive, Scene
from dano.sim.step import rollout
from dano.sim.world import Params, World, pairs
from dano.sysid.data import Track, estimate_velocity


class SysidError(DanoError):
    """A system identification problem that cannot be set up as asked."""


CONTACT_KEYS = tuple(f.name for f in dataclasses.fields(ContactParams))
BODY_KEYS = ("mass_scale", "inertia_scale")
ALIASES = {"friction": "sliding_friction", "mu": "sliding_friction", "alpha": "mass_scale"}

DEFAULT_BOUNDS: dict[str, tuple[float, float]] = {
    "sliding_friction": (0.0, 2.0),
    "sliding_drag": (0.0, 1.0),
    "rolling_friction": (0.0, 0.2),
    "rolling_drag": (0.0, 1.0),
    "torsional_friction": (0.0, 0.2),
    "torsional_drag": (0.0, 1.0),
    "impact_spring": (1e3, 1e6),
    "impact_damper": (1e3, 1e7),
    "coulomb_smoothing": (1.0, 1e4),
    "coulomb_regularizer": (1e-6, 1e-1),
    "coulomb_gain": (0.1, 2.0),
    "indicator_width": (1e-5, 1e-2),
    "mass_scale": (1e-3, 1e3),
    "inertia_scale": (0.1, 10.0),
}
"""Bounds used when none are given: Table I's ranges, widened; scales over decades."""


def canonical(name: str) -> str:
    """The parameter a name given by the user means (`friction` is `sliding_friction`)."""
    key = ALIASES.get(name, name)
    if key not in CONTACT_KEYS and key not in BODY_KEYS:
        raise SysidError(f"unknown parameter {name!r}; fit any of {sorted(CONTACT_KEYS + BODY_KEYS + tuple(ALIASES))}")
    return key


def with_values(params: Params, names: Sequence[str], theta: Float[Array, " p"]) -> Params:
    """`params` with each named parameter set to its value in θ: a contact key in every pair, a
    scale for every DANO (the reference identifies one friction for all of a body's contacts)."""
    for k, name in enumerate(names):
        value = theta[k]
        if name in BODY_KEYS:
            params = eqx.tree_at(lambda p, n=name: getattr(p, n), params, jnp.full_like(getattr(params, name), value))
        else:
            contact = tuple(eqx.tree_at(lambda c, n=name: getattr(c, n), c, value) for c in params.contact)
            params = eqx.tree_at(lambda p: p.contact, params, contact)
    return params


def current_values(params: Params, names: Sequence[str]) -> np.ndarray:
    """The values the scene gives the named parameters (first pair, first DANO)."""
    out = []
    for name in names:
        if name in BODY_KEYS:
            out.append(float(getattr(params, name)[0]))
        elif params.contact:
            out.append(float(getattr(params.contact[0], name)))
        else:
            raise SysidError(f"the scene has no contact pair, so {name!r} has nothing to act on")
    return np.asarray(out)


@dataclasses.dataclass(frozen=True)
class Recording:
    """One observed run.

    Attributes:
        tracks: observed poses by scene body name: DANOs and free or actuated primitives are
            observations; a mocap primitive's track is its prescribed path (a known input). All
            tracks share the same times.
        ctrl: (T - 1, nu) known actuator controls from each frame to the next (robot servo targets,
            then actuated primitives' forces), or None for zeros.
    """

    tracks: Mapping[str, Track]
    ctrl: np.ndarray | None = None

    @property
    def n_frames(self) -> int:
        return next(iter(self.tracks.values())).n_frames

    @property
    def dt(self) -> float:
        return next(iter(self.tracks.values())).dt


class Windows(eqx.Module):
    """All shooting windows of all recordings, stacked on a leading axis n (padded to W frames)."""

    qpos: Float[Array, "n nq"]
    """Initial qpos of each window (observed bodies from the data, the others from the scene)."""
    qvel: Float[Array, "n nv"]
    mocap0: Float[Array, "n k 3"]
    """Mocap body positions at the window's first frame."""
    mocap: Float[Array, "n w k 3"]
    """Mocap positions at the end of each frame of the window."""
    ctrl: Float[Array, "n w nu"]
    external: Float[Array, "n w nbody 6"]
    target_pos: Float[Array, "n w b 3"]
    """Observed positions at the window's frames 1..W, per observed body."""
    target_quat: Float[Array, "n w b 4"]
    mask: Float[Array, "n w"]
    """1 where the frame exists, 0 in the padding of a short last window."""
    basis: Float[Array, "n S s"]
    """Maps the s fitted initial-state unknowns to the S corrections of qpos/qvel (see `start_state`)."""
    observed: PyTree | None = None
    """What an `AbstractObservation` compares each window with (a pytree, leading axis n), or None."""


class AbstractObservation(eqx.Module):
    """What simulated states are compared with when it is not poses: e.g. object masks
    (`dano.vision.pixels.PixelObservation`). A problem with an observation fits its residuals
    instead of the pose residuals; the windows' `observed` holds its per-window data."""

    @abc.abstractmethod
    def residuals(self, qpos: Float[Array, "w nq"], observed, params: Float[Array, " m"]) -> Float[Array, "w k"]:
        """Residuals (w, k) of a window's simulated qpos at its frames 1..W against `observed`
        (the window's slice of `Windows.observed`), with the observation's own unknowns `params`
        (`n_params` of them, fitted per window after its initial state's: a camera correction, ...)."""

    @property
    def n_params(self) -> int:
        """m: the observation's own unknowns per window (none by default)."""
        return 0

    def param_bounds(self, observed) -> tuple[np.ndarray, np.ndarray]:
        """(n, m) bounds on the observation's unknowns of each window (`Windows.observed`)."""
        n = int(jax.tree_util.tree_leaves(observed)[0].shape[0])
        return np.zeros((n, self.n_params)), np.zeros((n, self.n_params))

    @property
    @abc.abstractmethod
    def per_frame(self) -> int:
        """k: residuals per frame."""

    @abc.abstractmethod
    def rms(self, r: np.ndarray, windows: Windows) -> float:
        """The root mean square error, in the observation's own units, of residuals (n, W, k)."""


@dataclasses.dataclass(frozen=True)
class Observed:
    """An observed body: where its state lives in qpos/qvel and how it moves."""

    name: str
    qpos: int
    qvel: int
    kind: str  # "free" (7 qpos, 6 qvel) or "slide" (3 + 3: an actuated primitive, no rotation)
    offset: tuple[float, ...]  # (3,) world position at qpos = 0 (slides)
    length: float  # m/rad, turns a rotation error into a length
    weight: float = 1.0  # multiplies the rotation residuals (0: positions only)

    @property
    def n_velocity(self) -> int:
        return 6 if self.kind == "free" else 3


@dataclasses.dataclass(frozen=True)
class Problem:
    """A compiled identification problem: the scene at the data's frame rate, the windows, and what
    is fitted. Build with `make_problem`; evaluate with `residuals`.

    Attributes:
        names: the fitted parameters (canonical names), θ in this order.
        initial: which parts of each window's initial state are unknowns: "none", "velocity" or
            "state" (pose and velocity).
        sigma: the tracking noise, m: residuals are in units of it.
    """

    scene: Scene
    world: World
    model: mjx.Model
    data: mjx.Data
    params: Params
    windows: Windows
    observed: tuple[Observed, ...]
    names: tuple[str, ...]
    n_frames: int
    initial: str
    sigma: float
    recordings: int
    compiler_options: dict | None = None
    cache: dict = dataclasses.field(default_factory=dict, repr=False, compare=False)
    """Compiled functions of this problem's structure (reused for new data of the same shapes)."""
    adjustments: dict = dataclasses.field(default_factory=dict, compare=False)
    """What was changed between the data and the simulation, by kind (reported in the result):
    `timestep` (the scene's step replaced by the frame interval), `settle` (bodies put on the ground
    at a window's start), and what the caller adds (`scale`, `gravity`, ...)."""
    observation: AbstractObservation | None = None
    """Compared with instead of the observed poses (masks, ...), or None: the poses' residuals."""

    @property
    def n_windows(self) -> int:
        return int(self.windows.qpos.shape[0])

    @property
    def n_state(self) -> int:
        """Unknowns per window: its initial state's (`start_state`), then the observation's own."""
        return int(self.windows.basis.shape[2]) + (self.observation.n_params if self.observation is not None else 0)

    def state_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(n, s) bounds on each window's unknowns: a pose correction within 5σ of the observed
        pose (5σ/L for a rotation), velocities free; then the observation's (`param_bounds`)."""
        per = []
        for o in self.observed:
            if self.initial == "state":
                per += [5 * self.sigma] * 3 + ([5 * self.sigma / o.length] * 3 if o.kind == "free" else [])
            per += [np.inf] * o.n_velocity
        full = np.asarray(per)
        basis = np.asarray(self.windows.basis)
        # every column of the basis is one unit direction of one block, so it inherits that block's bound
        limit = np.array([[full[np.argmax(np.abs(col))] for col in b.T] for b in basis]).reshape(self.n_windows, -1)
        if self.observation is None or self.observation.n_params == 0:
            return -limit, limit
        lo, hi = self.observation.param_bounds(self.windows.observed)
        return np.concatenate([-limit, lo], axis=1), np.concatenate([limit, hi], axis=1)

    @property
    def n_residuals(self) -> int:
        """Residuals that carry data (rotation of sliding bodies and padding excluded)."""
        if self.observation is not None:
            return int(np.sum(np.asarray(self.windows.mask))) * self.observation.per_frame
        per_frame = sum(6 if o.kind == "free" else 3 for o in self.observed)
        return int(np.sum(np.asarray(self.windows.mask))) * per_frame


def make_problem(
    scene: Scene,
    recordings: Sequence[Recording],
    fit: Sequence[str],
    window: int | None = None,
    initial: str = "none",
    sigma: float = 1e-3,
    rotation_length: float | None = None,
    settle: float | None = None,
    rotation_weight: float | int = 1.0,
) -> Problem:
    """Sets up Problem (17) for `scene` and observed `recordings`.

    The scene gives the bodies, contact parameters and anything not observed; its time step is
    replaced by the data's frame interval, split into substeps no longer than the scene's own
    (`scene.timestep / scene.substeps`), so the simulator's frames are the camera's frames.

    Args:
        fit: parameter names (see `canonical`).
        window: frame intervals per shooting window; None for one window per recording.
        initial: "none" (initial states from the data), "velocity" or "state" (fitted too).
        sigma: tracking noise, m (residual unit; does not change the estimate, only the loss scale).
        rotation_length: m/rad for rotation residuals; default each body's radius of gyration.
        rotation_weight: multiplies the rotation residuals (0: positions only, for a tracker that
            could not resolve the orientation; `ConstantOrientationWarning` says when it looks so).
        settle: a DANO whose lowest surface point is within this distance (m) of the ground at a
            window's start is put on the ground there and its velocity along the normal dropped
            (default 3σ; 0 to keep the data as they are). The penalty contact is stiff: a body read
            1 mm into the table from noisy data would be thrown off it (k ψ ≫ m g).

    Raises:
        SysidError: unknown names, no observed body, mismatched frame rates, or windows that would
            start from a state the data does not give.
    """
    if not jax.config.jax_enable_x64:  # pyright: ignore[reportAttributeAccessIssue]  (a dynamic option)
        raise SysidError(
            "system identification needs float64 (the Jacobians of stiff contact overflow float32): call "
            "jax.config.update('jax_enable_x64', True) first (the dano command does)"
        )
    names = tuple(canonical(n) for n in fit)
    if len(set(names)) != len(names):
        raise SysidError(f"a parameter is named twice in {list(fit)}")
    if not recordings:
        raise SysidError("no trajectories to fit")
    if initial not in ("none", "velocity", "state"):
        raise SysidError(f"initial must be 'none', 'velocity' or 'state', got {initial!r}")
    dt = recordings[0].dt
    for r in recordings:
        if abs(r.dt - dt) > 1e-6 * dt:
            raise SysidError(f"all trajectories must share one frame rate: {1 / r.dt:.6g} vs {1 / dt:.6g} fps")
    given_step = scene.step_size
    scene = at_interval(scene, dt)
    adjustments: dict = {}
    if abs(scene.step_size - given_step) > 1e-12 * given_step:
        adjustments["timestep"] = {"frame_s": scene.timestep, "substeps": scene.substeps, "scene_step_s": given_step}
    model, world, params, qpos0, qvel0 = compile_scene(scene, check_start=False)  # the data give the states
    m = mjx.put_model(model)
    d = mjx.make_data(m)

    longest = max(r.n_frames - 1 for r in recordings)
    W = longest if window is None else int(window)
    if W < 1:
        raise SysidError(f"window must be at least 1 frame interval, got {window}")
    recordings = [named_after_scene(scene, r) for r in recordings]
    if not (np.isfinite(rotation_weight) and rotation_weight >= 0):
        raise SysidError(f"rotation_weight must be a finite number >= 0, got {rotation_weight}")
    observed = _observed(scene, world, recordings, rotation_length, float(rotation_weight))
    if rotation_weight > 0:
        warn_constant_orientations(recordings, sigma, {o.name for o in observed if o.kind == "free"})
    settle = 3.0 * sigma if settle is None else float(settle)
    windows, settled = _windows(scene, world, params, model, recordings, observed, qpos0, qvel0, W, settle, initial)
    if settled:
        adjustments["settle"] = settled
    current_values(params, names)  # raises if a name has nothing to act on
    from dano.sim.run import compiler_options

    return Problem(
        scene=scene, world=world, model=m, data=d, params=params, windows=windows, observed=observed,
        names=names, n_frames=W, initial=initial, sigma=float(sigma), recordings=len(recordings),
        compiler_options=compiler_options(world), adjustments=adjustments,
    )  # fmt: skip


def _resolve(scene: Scene, name: str) -> tuple[str, DanoBody | Primitive]:
    danos = {b.name: b for b in scene.bodies}
    prims = {p.name: p for p in scene.primitives}
    if name == "":
        if len(scene.bodies) != 1:
            raise SysidError(
                f"the trajectory file has no body column, and the scene has {len(scene.bodies)} DANOs: "
                "name the body (a `body` column, or --body)"
            )
        return "dano", scene.bodies[0]
    if name in danos:
        return "dano", danos[name]
    if name in prims:
        return prims[name].mode, prims[name]
    raise SysidError(f"the trajectory names body {name!r}, which the scene does not have ({sorted(danos | prims)})")


class ConstantOrientationWarning(UserWarning):
    """An orientation track that does not change while its body moves: likely a tracker that could
    not resolve rotation, whose constant quaternion the fit would take as the truth."""


def warn_constant_orientations(recordings: Sequence[Recording], sigma: float, names: set[str]) -> None:
    """Warns for each track whose orientation is constant (within 1e-6 rad) while its position
    travels more than 10 sigma (measured: a real soap track's constant quaternion moved the fitted
    friction from 0.57 to 0.44)."""
    for r in recordings:
        for name, track in r.tracks.items():
            if name not in names:  # a slide-jointed pusher does not turn: its constant orientation is right
                continue
            q = np.asarray(track.quat)
            turn = 2.0 * np.arccos(np.clip(np.abs(q @ q[0]), 0.0, 1.0))
            travel = float(np.max(np.linalg.norm(np.asarray(track.pos) - np.asarray(track.pos)[0], axis=1)))
            if float(np.max(turn)) < 1e-6 and travel > 10.0 * sigma:
                warnings.warn(
                    f"the orientation of {name or 'the body'!r} is constant over {len(q)} frames while it travels "
                    f"{travel:.3g} m: if the tracker could not resolve rotation, fit positions only "
                    "(--rotation-weight 0, or make_problem(rotation_weight=0))",
                    ConstantOrientationWarning,
                    stacklevel=3,
                )


def _observed(scene: Scene, world: World, recordings, rotation_length, weight: float = 1.0) -> tuple[Observed, ...]:
    names = sorted({n for r in recordings for n in r.tracks})
    out = []
    for name in names:
        kind, body = _resolve(scene, name)
        if kind == "dano":
            assert isinstance(body, DanoBody)
            i = world.names.index(body.name)
            dano = body.dano
            gyration = float(np.sqrt(np.trace(np.asarray(dano.inertia)) / (2.0 * float(dano.mass))))
            length = gyration if rotation_length is None else float(rotation_length)
            out.append(Observed(name, world.dano_qpos[i], world.dano_qvel[i], "free", (0.0, 0.0, 0.0), length, weight))
        elif kind in ("free", "actuated"):
            assert isinstance(body, Primitive)
            g = next(p for p in world.prims if p.name == body.name)
            length = max(body.size) if rotation_length is None else float(rotation_length)
            moving = "free" if kind == "free" else "slide"
            out.append(Observed(name, g.qpos, g.qvel, moving, g.pos, length, weight))
        elif kind == "static":
            raise SysidError(f"body {name!r} is static in the scene; it cannot be observed moving")
    if not out:
        raise SysidError("no trajectory observes a DANO or a moving primitive")
    for r in recordings:
        for o in out:
            if o.name not in r.tracks:
                raise SysidError(f"body {o.name!r} is observed in some trajectories but not all")
    return tuple(out)


def named_after_scene(scene: Scene, r: Recording) -> Recording:
    """The recording with a body-less track ("" key) named after the scene's only DANO."""
    if "" not in r.tracks:
        return r
    _, body = _resolve(scene, "")
    tracks = {(body.name if k == "" else k): v for k, v in r.tracks.items()}
    return dataclasses.replace(r, tracks=tracks)


def _windows(scene, world, params, model, recordings, observed, qpos0, qvel0, W, settle, initial):
    """Cuts every recording into windows of W frame intervals and stacks them; also returns what
    settling changed ({"window", "body", "moved_m", "normal_speed_dropped_m_s"} per settled body)."""
    mocap_names = [p.name for p in scene.primitives if p.mode == "mocap"]
    mocap_home = np.array([p.pos for p in scene.primitives if p.mode == "mocap"], dtype=float).reshape(-1, 3)
    moving = len(world.dano_qpos) + sum(p.moving for p in world.prims)
    rows, report = [], []
    for r in recordings:
        T = r.n_frames
        starts = list(range(0, T - 1, W))
        unobserved = moving - len([o for o in observed if o.name in r.tracks])
        if len(starts) > 1 and (unobserved > 0 or world.links):
            raise SysidError(
                "multiple shooting restarts every moving body from the data: observe all of them (DANOs, free "
                "and actuated primitives), and no robot, or use one window"
            )
        mocap = np.broadcast_to(mocap_home, (T, *mocap_home.shape)).copy()
        for j, name in enumerate(mocap_names):
            if name in r.tracks:
                mocap[:, j] = r.tracks[name].pos
        ctrl = np.zeros((T - 1, model.nu)) if r.ctrl is None else np.asarray(r.ctrl, dtype=float)
        if ctrl.shape != (T - 1, model.nu):
            raise SysidError(f"ctrl must be (frames - 1, nu) = {(T - 1, model.nu)}, got {ctrl.shape}")
        external = np.zeros((T, model.nbody, 6))
        for o in observed:
            track = r.tracks.get(o.name)
            if track is not None and track.wrench is not None:
                external[:, model.body(o.name).id] = track.wrench
        for s in starts:
            row = _window(r, observed, qpos0, qvel0, mocap, ctrl, external, s, W)
            settled = {}
            if settle > 0 and world.ground_height is not None:
                settled = _settle(world, params, scene.gravity, observed, row, settle)
            report += [{"window": len(rows), "body": name, **change} for name, change in settled.items()]
            row["basis"] = _basis(observed, row, set(settled), initial, np.asarray(world.ground_normal))
            rows.append(row)
    stacked = {k: jnp.asarray(np.stack([row[k] for row in rows])) for k in rows[0] if k != "basis"}
    return Windows(**stacked, basis=jnp.asarray(_compact([row["basis"] for row in rows]))), report


def _window(r: Recording, observed, qpos0, qvel0, mocap, ctrl, external, s: int, W: int) -> dict:
    T = r.n_frames
    n = min(W, T - 1 - s)
    frames = np.minimum(np.arange(s + 1, s + W + 1), T - 1)  # pad by repeating the last frame
    steps = np.minimum(np.arange(s, s + W), T - 2)
    qpos, qvel = qpos0.copy(), qvel0.copy()
    target_pos, target_quat = [], []
    for o in observed:
        tr = r.tracks[o.name]
        lin, ang = estimate_velocity(tr, s)
        if o.kind == "free":
            qpos[o.qpos : o.qpos + 3], qpos[o.qpos + 3 : o.qpos + 7] = tr.pos[s], tr.quat[s]
            qvel[o.qvel : o.qvel + 3], qvel[o.qvel + 3 : o.qvel + 6] = lin, ang
        else:
            qpos[o.qpos : o.qpos + 3] = tr.pos[s] - np.asarray(o.offset)
            qvel[o.qvel : o.qvel + 3] = lin
        target_pos.append(tr.pos[frames])
        target_quat.append(tr.quat[frames])
    return {
        "qpos": qpos,
        "qvel": qvel,
        "mocap0": mocap[s],
        "mocap": mocap[frames],
        "ctrl": ctrl[steps],
        "external": external[steps],
        "target_pos": np.stack(target_pos, axis=1),
        "target_quat": np.stack(target_quat, axis=1),
        "mask": (np.arange(W) < n).astype(float),
    }


def _settle(world: World, params: Params, gravity, observed, row: dict, margin: float) -> dict[str, dict]:
    """Puts DANOs that start within `margin` of the ground at their resting height (in place);
    returns what changed per body name: `moved_m` along the normal, `normal_speed_dropped_m_s`,
    `tilt_rate_dropped_rad_s`.

    The height is where the contact spring carries the weight, k ψ = m |g·n| (ψ from the smooth
    inside indicator), found by bisection along the ground normal n with the orientation kept; the
    velocity along n and the spin about axes in the ground plane (rocking, which the contact damps
    within a substep; read from noisy poses it is mostly noise) are dropped. The penalty contact
    is stiff: 0.3 mm too deep and a flat face pushes with hundreds of times its weight, so a height
    read from noisy data cannot be used as is.
    """
    from scipy.spatial.transform import Rotation

    from dano.contact.overlap import indicator

    n = np.asarray(world.ground_normal)
    g_n = abs(float(np.dot(gravity, n)))
    settled = {}
    for p, (i, kind, _) in zip(params.contact, pairs(world), strict=True):
        o = next((o for o in observed if o.name == world.names[i]), None)
        if kind != "ground" or o is None or g_n == 0:
            continue
        state = world.danos[i]
        points, shares = np.asarray(state.points), np.asarray(state.shares)
        x, q = row["qpos"][o.qpos : o.qpos + 3], row["qpos"][o.qpos + 3 : o.qpos + 7]
        height = n @ (Rotation.from_quat(q[[1, 2, 3, 0]]).as_matrix() @ points + x[:, None]) - world.ground_height
        width = float(p.indicator_width)
        target = g_n / float(p.impact_spring)  # ψ / m at rest

        def load(shift, height=height, shares=shares, width=p.indicator_width):
            return float(np.sum(shares * np.asarray(indicator(jnp.asarray(height + shift), width))))

        lowest = float(np.min(height))
        if abs(lowest) > margin:
            continue
        deep, free = -lowest - margin - width, -lowest + width + 1e-9  # shifts: load(deep) > target, load(free) = 0
        for _ in range(60):
            mid = 0.5 * (deep + free)
            deep, free = (mid, free) if load(mid) > target else (deep, mid)
        shift = 0.5 * (deep + free)
        row["qpos"][o.qpos : o.qpos + 3] = x + shift * n
        v = row["qvel"][o.qvel : o.qvel + 3]
        row["qvel"][o.qvel : o.qvel + 3] = v - (v @ n) * n
        n_body = _in_body(q, n)  # the free joint's spin is in its frame
        w = row["qvel"][o.qvel + 3 : o.qvel + 6]
        tilt = w - (w @ n_body) * n_body
        row["qvel"][o.qvel + 3 : o.qvel + 6] = w - tilt
        settled[o.name] = {
            "moved_m": float(shift), "normal_speed_dropped_m_s": float(v @ n),
            "tilt_rate_dropped_rad_s": float(np.linalg.norm(tilt)),
        }  # fmt: skip
    return settled


def _in_body(quat: np.ndarray, v: np.ndarray) -> np.ndarray:
    """World vector `v` in the frame of a body at orientation `quat` (w, x, y, z)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_quat(quat[[1, 2, 3, 0]]).as_matrix().T @ v


def _basis(observed, row: dict, settled: set[str], initial: str, n: np.ndarray) -> np.ndarray:
    """Columns spanning the initial-state corrections δ of a window (S, S), zero columns for the
    directions held fixed.

    A body resting on the ground (settled) keeps contact: its corrections are planar (position
    and velocity along the ground, rotation and spin about its normal). Free rocking or lifting
    velocities are nearly unobservable there (the contact damps them within a substep) and only
    let the fit wander; everywhere else all 6 (or 12) directions are free.
    """
    blocks = []
    for o in observed:
        k = {"none": 0, "velocity": 1, "state": 2}[initial]
        if o.kind != "free" or o.name not in settled:
            blocks += [np.eye(o.n_velocity)] * k
            continue
        q = row["qpos"][o.qpos + 3 : o.qpos + 7]
        n_body = _in_body(q, n)
        t1 = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
        t1 /= np.linalg.norm(t1)
        t2 = np.cross(n, t1)
        planar = np.zeros((6, 6))
        planar[:3, 0], planar[:3, 1], planar[3:, 2] = t1, t2, n_body  # along the ground; about its normal
        blocks += [planar] * k
    size = sum(b.shape[0] for b in blocks)
    out = np.zeros((size, size))
    i = 0
    for b in blocks:
        out[i : i + b.shape[0], i : i + b.shape[0]] = b
        i += b.shape[0]
    return out


def _compact(bases: list[np.ndarray]) -> np.ndarray:
    """Drops the columns that are zero in every window: (n, S, s) with s the unknowns actually fitted."""
    stacked = np.stack(bases)
    used = np.any(stacked != 0, axis=(0, 1))
    return stacked[:, :, used]


def start_state(problem: Problem, w: Windows, delta: Float[Array, " s"]) -> tuple[Array, Array]:
    """A window's (unbatched `w`) initial qpos, qvel with its fitted corrections δ applied.

    Per observed body, `basis @ δ` holds (position 3, rotation vector 3 in the body frame) when the
    pose is fitted, then the velocity correction (6, or 3 for a slide), in `qvel`'s frames.
    """
    qpos, qvel = w.qpos, w.qvel
    if problem.initial == "none":
        return qpos, qvel
    delta = w.basis @ delta[: w.basis.shape[-1]]  # the observation's own unknowns follow (`own_unknowns`)
    i = 0
    for o in problem.observed:
        if problem.initial == "state":
            qpos = qpos.at[o.qpos : o.qpos + 3].add(delta[i : i + 3])
            i += 3
            if o.kind == "free":
                q = quat_mul(qpos[o.qpos + 3 : o.qpos + 7], quat_exp(delta[i : i + 3]))
                qpos = qpos.at[o.qpos + 3 : o.qpos + 7].set(q)
                i += 3
        qvel = qvel.at[o.qvel : o.qvel + o.n_velocity].add(delta[i : i + o.n_velocity])
        i += o.n_velocity
    return qpos, qvel


def own_unknowns(w: Windows, delta: Float[Array, " s"]) -> Float[Array, " m"]:
    """The observation's own unknowns among a window's (`w` unbatched): those after its initial state's."""
    return delta[w.basis.shape[-1] :]


def window_residuals(
    problem: Problem, theta: Float[Array, " p"], delta: Float[Array, " s"], w: Windows
) -> Float[Array, "w b 6"] | Float[Array, "w k"]:
    """Residuals of one window (`w` unbatched): per frame and observed body, position then rotation;
    or per frame the problem's `observation` residuals (w, k).

    Padding frames (and frames without an observation) give zeros (a `where`, so a blow-up there
    cannot leak NaN into the loss).
    """
    q = simulate_window(problem, theta, delta, w, checkpoint=False)[1:]
    if problem.observation is not None:
        r = problem.observation.residuals(q, w.observed, own_unknowns(w, delta))
        return jnp.where(w.mask[:, None] > 0, r, 0.0)
    out = []
    for b, o in enumerate(problem.observed):
        if o.kind == "free":
            pos, rot = q[:, o.qpos : o.qpos + 3], q[:, o.qpos + 3 : o.qpos + 7]
            angle = quat_log(quat_mul(quat_conj(w.target_quat[:, b]), rot)) * (o.length * o.weight)
        else:
            pos = q[:, o.qpos : o.qpos + 3] + jnp.asarray(o.offset)[None, :]
            angle = jnp.zeros_like(pos)
        out.append(jnp.concatenate([pos - w.target_pos[:, b], angle], axis=-1) / problem.sigma)
    r = jnp.stack(out, axis=1)
    return jnp.where(w.mask[:, None, None] > 0, r, 0.0)


def residuals(
    problem: Problem, theta: Float[Array, " p"], delta: Float[Array, "n s"], windows: Windows | None = None
) -> Float[Array, "n w b 6"] | Float[Array, "n w k"]:
    """Residuals of all windows (vmapped; `problem.windows` unless given): the objective is ½ Σ r²."""
    windows = problem.windows if windows is None else windows
    return over_windows(lambda dl, w: window_residuals(problem, theta, dl, w), delta, windows)


def over_windows(fn, *batched):
    """fn mapped over the leading axis of `batched` (pytrees of windows): `vmap`, or for a single
    window fn itself: under `vmap` the step's branches (`lax.cond`: contact or none, the broad
    phase) become selects that run both sides, and tracing batches every loop of the step."""
    if jax.tree_util.tree_leaves(batched)[0].shape[0] != 1:
        return jax.vmap(fn)(*batched)
    out = fn(*jax.tree_util.tree_map(lambda x: x[0], batched))
    return jax.tree_util.tree_map(lambda x: x[None], out)


def simulate_window(
    problem: Problem, theta: Float[Array, " p"], delta: Float[Array, " s"], w: Windows, checkpoint: bool = True
) -> Float[Array, "f nq"]:
    """qpos (W + 1, nq) of one window's simulation (`w` unbatched), its initial state first."""
    params = with_values(problem.params, problem.names, theta)
    qpos, qvel = start_state(problem, w, delta)
    d = problem.data.replace(qpos=qpos, qvel=qvel, mocap_pos=w.mocap0)
    return rollout(
        problem.world, params, problem.model, d, problem.n_frames, ctrl=w.ctrl, mocap_pos=w.mocap,
        external=w.external, checkpoint=checkpoint,
    ).qpos  # fmt: skip


def simulate_windows(problem: Problem, theta, delta) -> Float[Array, "n f nq"]:
    """qpos (n, W + 1, nq) of every window's simulation (its initial state first), for plots and reports."""
    if "simulate" not in problem.cache:

        def batched(th, dl, w):
            return over_windows(lambda dl, w: simulate_window(problem, th, dl, w), dl, w)

        problem.cache["simulate"] = jax.jit(batched, compiler_options=problem.compiler_options)
    return problem.cache["simulate"](jnp.asarray(theta), jnp.asarray(delta), problem.windows)
