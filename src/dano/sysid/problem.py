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
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from dano import lanes
from dano import validate as V
from dano._mjx import mjx
from dano.math import quat_conj, quat_exp, quat_log, quat_mul
from dano.sim.compile import compile_scene
from dano.sim.run import at_interval, jitted
from dano.sim.scene import DanoBody, Primitive, Scene
from dano.sim.step import rollout
from dano.sim.world import Params, World
from dano.sysid.configs import Initial, SysidError
from dano.sysid.params import canonical, current_values, with_values
from dano.sysid.windows import Observed, Recording, Windows, build_windows


class AbstractObservation(eqx.Module):
    """What simulated states are compared with when it is not poses: e.g. object masks
    (`dano.vision.observation.PixelObservation`). A problem with an observation fits its residuals
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


class Problem(eqx.Module):
    """A compiled identification problem: the scene at the data's frame rate, the windows, and what
    is fitted. Build with `make_problem`; evaluate with `residuals`.

    A pytree: its arrays (the world's, the MJX model and data, the parameters, the windows) are
    traced and the rest is static, so the compiled functions of `dano.sysid.objective` take it as
    an argument (`traced`) and problems of one structure share them (JAX's own cache).

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
    observed: tuple[Observed, ...] = eqx.field(static=True)
    names: tuple[str, ...] = eqx.field(static=True)
    n_frames: int = eqx.field(static=True)
    initial: Initial = eqx.field(static=True)
    sigma: float = eqx.field(static=True)
    recordings: int = eqx.field(static=True)
    adjustments: dict = eqx.field(default_factory=dict)
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
    initial: Initial | str = Initial.none,
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
    initial = V.option(initial, "initial", SysidError, Initial)
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
    windows, settled = build_windows(
        scene, world, params, model, recordings, observed, qpos0, qvel0, W, settle, initial
    )
    if settled:
        adjustments["settle"] = settled
    current_values(params, names)  # raises if a name has nothing to act on
    return Problem(
        scene=scene, world=world, model=m, data=d, params=params, windows=windows, observed=tuple(observed),
        names=names, n_frames=W, initial=initial, sigma=float(sigma), recordings=len(recordings),
        adjustments=adjustments,
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
    """fn mapped over the leading axis of `batched` (pytrees of windows): `dano.lanes.mapped` (on
    the CPU backend one window after another, on an accelerator `vmap`), and for a single window
    fn itself. Under `vmap` the step's branches (`lax.cond`: contact or none, the broad phase)
    become selects that run both sides, and every loop runs as long as the longest window's: the
    4-window push fit of `tests/test_sysid.py` (400-point bunny, 21 frames) identified in 23.0 s
    cold and 12.1 s warm one window after another, 50.8 s and 34.5 s vmapped (a script, alone),
    to the same digits."""
    if jax.tree_util.tree_leaves(batched)[0].shape[0] != 1:
        return lanes.mapped(fn, *batched)
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
    return jitted(_simulate_windows)(traced(problem), jnp.asarray(theta), jnp.asarray(delta))


def _simulate_windows(problem: Problem, theta, delta) -> Float[Array, "n f nq"]:
    return over_windows(lambda dl, w: simulate_window(problem, theta, dl, w), delta, problem.windows)


class _Untraced:
    """Stands, in `traced`, for what no compiled function reads; fails on use."""

    def __getattr__(self, name: str):
        raise AttributeError(f"a traced Problem has no scene or adjustments (asked for {name!r}): read them outside")


_UNTRACED = _Untraced()


def traced(problem: Problem) -> Problem:
    """`problem` as the compiled functions take it (`dano.sim.run.jitted`: its arrays traced, the
    rest static and part of the compiled program's key). Its scene and its adjustments say where it
    came from and no computation reads them (the world and model were compiled from the scene): they
    are replaced by a marker that fails on use, so that problems of one structure share one program
    whatever their scene's arrays or their record of adjustments."""
    return eqx.tree_at(lambda p: (p.scene, p.adjustments), problem, replace=(_UNTRACED, _UNTRACED))
