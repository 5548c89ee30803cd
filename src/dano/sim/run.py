"""Host-side driver: compile a scene, roll it out, check it, and write the trajectory.

Penalty contact is stiff: when the time step is too large for the spring and damper, the state
grows without bound. `check_trajectory` turns that into a `SimulationError` that names the first
bad frame and the likely cause, instead of returning NaNs. Before a blow-up there is an energy
gain: `audit_energy` checks that a scene with nothing driving it (no robot, no actuated or mocap
primitive, no controls or external wrenches) never has more mechanical energy than it started
with, and names the frame, the body, its contacts' penetration and the time step when it does.
"""

import csv
import dataclasses
import functools
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from dano import lanes
from dano._mjx import mjx
from dano.contact.overlap import signed_distance
from dano.contact.pairs import occupancy, world_points
from dano.errors import DanoError
from dano.io import atomic_write
from dano.math import quat_to_mat
from dano.sim.compile import compile_scene
from dano.sim.scene import Scene
from dano.sim.step import Trajectory, dano_bodies, dano_frames, partners, rollout
from dano.sim.world import Params, World, pair_name, pairs


class SimulationError(DanoError):
    """The simulation blew up (non-finite state or runaway speed) or made energy from nowhere."""


MAX_SPEED = 100.0
"""m/s (or rad/s * 0.1 m): beyond this a tabletop scene has certainly blown up."""

ENERGY_TOLERANCE = 0.01
"""`audit_energy`'s allowance above the initial energy, as a fraction of the scene's energy scale:
its initial kinetic energy plus each free body's weight times its size (a 1 kg, 0.15 m box at
rest: 15 mJ, the energy of a 1.5 mm hop)."""


@dataclasses.dataclass(frozen=True)
class Simulation:
    """A compiled scene ready to roll out: the MuJoCo model, the MJX model and data, the world."""

    scene: Scene
    model: mujoco.MjModel
    mjx_model: mjx.Model
    data: mjx.Data
    world: World
    params: Params

    @classmethod
    def from_scene(cls, scene: Scene) -> "Simulation":
        model, world, params, qpos, qvel = compile_scene(scene, check_start=True)
        m = mjx.put_model(model)
        d = mjx.make_data(m).replace(qpos=jnp.asarray(qpos), qvel=jnp.asarray(qvel))
        return cls(scene, model, m, d, world, params)

    def run(self, n_frames: int | None = None, params=None, ctrl=None, mocap_pos=None, external=None) -> Trajectory:
        """Rolls out (jitted) and checks the result; raises `SimulationError` on a blow-up.

        `ctrl` (n_frames, nu), `mocap_pos` (n_frames, nmocap, 3) and `external` (n_frames, nbody, 6)
        are optional per-frame inputs (see `rollout`).
        """
        n = self.scene.n_steps if n_frames is None else n_frames
        params = self.params if params is None else params
        traj = jitted(rollout)(self.world, params, self.mjx_model, self.data, n, ctrl, mocap_pos, external)
        if ctrl is None and mocap_pos is None and external is None:
            audit_energy(traj, self, params)  # first: the energy grows before the state blows up
        check_trajectory(traj, self.scene, self.world)
        _warn_fallbacks(traj, self.world)
        return traj

    def run_batch(
        self, data: mjx.Data, n_frames: int | None = None, params=None, vmap: bool | None = None
    ) -> Trajectory:
        """Rolls out a batch of states (`data` with a leading batch axis on every leaf, e.g. from
        `batch_data`); checks every environment as `run` does (no energy audit). Returns the
        batched `Trajectory`.

        `vmap=True`: vmapped and sharded over all local devices (`shard_batch`), the way for an
        accelerator or several devices. `vmap=False`: one environment after another, the batch
        split over the cores, each share from a thread of its own (`rollout_lanes`): on a CPU a
        vmapped step runs every branch both ways and its loops as long as the longest
        environment's, while one after another each runs as `run` would, on a core of its own
        (`python bench/simulate.py`: 64 bunnies 2.9x the vmapped throughput, 1.3x one alone, on this
        2-core machine, README). None: `False` on a single CPU device, else `True`."""
        n = self.scene.n_steps if n_frames is None else n_frames
        params = self.params if params is None else params
        leaves = jax.tree_util.tree_leaves(data)
        if not leaves or jnp.ndim(leaves[0]) == 0 or jnp.shape(leaves[0])[0] == 0:
            raise SimulationError("run_batch needs a batch of at least one environment (a leading axis on every leaf)")
        if vmap is None:
            vmap = not (jax.default_backend() == "cpu" and jax.local_device_count() == 1)
        if vmap:
            world, params, m = replicated((self.world, params, self.mjx_model))  # beside the batch's shares
            traj = jitted(rollout_batch)(world, params, m, shard_batch(data), n)
        else:
            traj = rollout_lanes(self.world, params, self.mjx_model, data, n)
        for i in range(traj.qpos.shape[0]):
            check_trajectory(jax.tree_util.tree_map(lambda x, i=i: x[i], traj), self.scene, self.world)
        _warn_fallbacks(traj, self.world)
        return traj

    def batch_data(self, size: int) -> mjx.Data:
        """`size` copies of the initial state, with a leading batch axis (set qpos, qvel per env)."""
        return jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (size, *jnp.shape(x))), self.data)


@dataclasses.dataclass(frozen=True)
class Profile:
    """Where a rollout's time goes (`profile`), seconds: tracing and lowering, XLA compilation, one
    run (median), and one run with the DANO contact switched off (the engine alone: MuJoCo's step
    and the DANOs' free motion); `contact` is the difference. Per frame: divide by `frames`."""

    frames: int
    lower: float
    compile: float
    run: float
    engine: float

    @property
    def contact(self) -> float:
        return max(self.run - self.engine, 0.0)

    def lines(self) -> list[str]:
        per = 1e3 / self.frames
        share = lambda x: 100.0 * x / self.run if self.run > 0 else 0.0  # noqa: E731
        return [
            f"compile: {self.lower:.2f} s tracing and lowering + {self.compile:.2f} s XLA",
            f"run:     {self.run:.3f} s for {self.frames} frames ({self.run * per:.3f} ms per frame)",
            f"  contact {self.contact * per:.3f} ms per frame ({share(self.contact):.0f} %), "
            f"engine {self.engine * per:.3f} ms per frame ({share(self.engine):.0f} %)",
        ]


def profile(sim: Simulation, n_frames: int | None = None, repeats: int = 3) -> Profile:
    """Times a rollout of `sim` apart (`Profile`): lowering and compiling (`lower().compile()`), the
    median of `repeats` runs, and the same rollout without any DANO contact pair."""
    n = sim.scene.n_steps if n_frames is None else n_frames

    def timed(world, params):
        fn = jax.jit(
            lambda d: rollout(world, params, sim.mjx_model, d, n).qpos[-1], compiler_options=compiler_options(world)
        )
        t0 = time.perf_counter()
        lowered = fn.lower(sim.data)
        t1 = time.perf_counter()
        compiled = lowered.compile()
        t2 = time.perf_counter()
        runs = []
        for _ in range(max(1, repeats)):
            t = time.perf_counter()
            jax.block_until_ready(compiled(sim.data))
            runs.append(time.perf_counter() - t)
        return t1 - t0, t2 - t1, float(np.median(runs))

    lower, comp, run = timed(sim.world, sim.params)
    free = dataclasses.replace(sim.world, contact=False)
    engine = timed(free, dataclasses.replace(sim.params, contact=()))[2]
    return Profile(n, lower, comp, run, engine)


def shard_batch(tree):
    """Places a batch (the leading axis of every array leaf) across all local devices with
    `jax.sharding`, so that a jitted, vmapped computation on it runs on each device's share; on
    one device, or for a batch of 1, it is returned as is. Raises `SimulationError` when the batch
    does not divide evenly over the devices."""
    devices = jax.local_devices()
    leaves = [x for x in jax.tree_util.tree_leaves(tree) if jnp.ndim(x) > 0]
    size = leaves[0].shape[0] if leaves else 1
    if len(devices) == 1 or size == 1:
        return tree
    if size % len(devices):
        raise SimulationError(f"a batch of {size} does not divide over {len(devices)} devices: use a multiple")
    batched = _over_devices(jax.sharding.PartitionSpec("batch"))
    return jax.tree_util.tree_map(lambda x: jax.device_put(x, batched) if jnp.ndim(x) > 0 else x, tree)


def replicated(tree):
    """Places every array leaf of `tree` whole on all local devices (what a sharded batch's
    computation reads beside its share: the world, the parameters, the model); on one device it is
    returned as is."""
    if len(jax.local_devices()) == 1:
        return tree
    whole = _over_devices(jax.sharding.PartitionSpec())
    return jax.tree_util.tree_map(lambda x: jax.device_put(x, whole) if eqx.is_array(x) else x, tree)


def _over_devices(spec: jax.sharding.PartitionSpec) -> jax.sharding.NamedSharding:
    """`spec` on a one-axis ("batch") mesh of all local devices."""
    return jax.sharding.NamedSharding(jax.sharding.Mesh(np.asarray(jax.local_devices()), ("batch",)), spec)


FALLBACK_SHARE = 0.02
"""`ContactBudgetWarning` is raised when more than this share of a rollout's steps overflowed their
active sets; a rarer overflow (a hard impact's one step) costs little and is only counted."""


def _warn_fallbacks(traj: Trajectory, world) -> None:
    """Says when contact active sets overflowed often (exact, but at the cost of all points): more
    than `FALLBACK_SHARE` of the steps. `Trajectory.fallbacks` counts every one."""
    if traj.fallbacks is None:
        return
    count = int(np.max(np.asarray(traj.fallbacks)[..., -1]))
    steps = (np.shape(traj.fallbacks)[-1] - 1) * world.substeps
    if count > FALLBACK_SHARE * steps:
        budgets = ", ".join(f"{name} {s.budget}" for name, s in zip(world.names, world.danos, strict=True))
        warnings.warn(
            f"{count} of {steps} steps needed more contact points than the active set holds ({budgets} points "
            "per pair) and were solved over all points: exact, but slower; raise Scene(contact_budget=...)",
            ContactBudgetWarning,
            stacklevel=3,
        )


class ContactBudgetWarning(UserWarning):
    """Steps whose contact active sets overflowed were solved over all points (`dano.contact.active`)."""


@functools.cache
def jitted(fn: Callable, options: tuple | None = None) -> Callable:
    """`fn` under `eqx.filter_jit` with this backend's `compiler_options` (or `options`, XLA's as
    sorted (name, value) pairs), made once per function on first use: its arrays traced, everything
    else (the world's static structure, a frame count) static, so one compiled program serves every
    scene of the same structure and its cache is JAX's own, not an attribute of an object."""
    xla = compiler_options(None) if options is None else (dict(options) or None)
    return eqx.filter_jit(fn, compiler_options=xla)  # pyright: ignore[reportCallIssue]  (jax.jit's keyword)


def rollout_batch(world: World, params: Params, m: mjx.Model, d: mjx.Data, n: int) -> Trajectory:
    """`rollout` of every state of a batch `d` (a leading axis on every leaf), vmapped."""
    return jax.vmap(lambda d: rollout(world, params, m, d, n))(d)


def rollout_map(world: World, params: Params, m: mjx.Model, d: mjx.Data, n: int) -> Trajectory:
    """`rollout` of every state of a batch `d` (a leading axis on every leaf), one environment after
    another (`jax.lax.map`): each keeps its own branches and loops, as `rollout` alone runs them."""
    return jax.lax.map(lambda d: rollout(world, params, m, d, n), d)


def rollout_lanes(
    world: World, params: Params, m: mjx.Model, d: mjx.Data, n: int, n_lanes: int | None = None
) -> Trajectory:
    """`rollout` of every state of a batch `d` (a leading axis on every leaf): the batch split into
    `dano.lanes.count(n_lanes)` equal chunks (the last padded with its last environment), each
    rolled out by `rollout_map` from a thread of its own; the trajectories in the batch's order."""
    size = jax.tree_util.tree_leaves(d)[0].shape[0]
    chunks = lanes.shares(size, lanes.count(n_lanes))
    fn = jitted(rollout_map)
    parts = lanes.in_parallel(
        [lambda i=i: fn(world, params, m, jax.tree_util.tree_map(lambda x: x[i], d), n) for i in chunks]
    )
    return jax.tree_util.tree_map(lambda *xs: jnp.concatenate(xs)[:size], *parts)


def compiler_options(world) -> dict | None:
    """XLA options for jitting a rollout of `world` on this backend (dano sets no process-wide flag).

    On CPU, XLA's fusion emitters (jaxlib 0.10) duplicate work inside fusions along a kinematic
    chain once its frames are rotated: `python bench/xla_fusion.py` measured MJX kinematics of a
    9-hinge chain with rotated frames at 7292 ms per call with them and 0.16 ms without, the Panda's
    73 ms and 0.30 ms; one implicit step of the resting bunny DANO 1.08 / 0.90 ms, then 0.71 / 0.68
    and 0.76 / 0.77 ms on repeats (no difference). So every dano jit on CPU turns them off (the
    same as the process-wide `XLA_FLAGS` that earlier versions set on import). Pass the result to
    `jax.jit(..., compiler_options=...)` when jitting `rollout` yourself.
    """
    del world  # the same for every scene today; kept so a per-scene choice needs no API change
    if jax.default_backend() == "cpu":
        return {"xla_cpu_use_fusion_emitters": False}
    return None


def check_trajectory(traj: Trajectory, scene: Scene, world: World) -> None:
    """Raises `SimulationError` at the first frame with a non-finite state or a runaway speed,
    naming the degree of freedom (a DANO by name, or MuJoCo's index) and the likely cause.

    The scene's inputs were checked before simulating (no negative or NaN parameter, no zero
    quaternion, no start inside the ground or faster than a body's size per step, a positive
    definite inertia), so what is left is the step against the contact's stiffness."""
    qpos, qvel = np.asarray(traj.qpos), np.asarray(traj.qvel)
    bad = ~np.all(np.isfinite(qpos), axis=1) | ~np.all(np.isfinite(qvel), axis=1)
    bad |= np.max(np.abs(np.nan_to_num(qvel, nan=np.inf)), axis=1) > MAX_SPEED
    if not bad.any():
        return
    frame = int(np.argmax(bad))
    speeds = np.abs(np.nan_to_num(qvel[frame], nan=np.inf))
    dof = int(np.argmax(speeds))
    owner = f"degree of freedom {dof}"
    for name, start in zip(world.names, world.dano_qvel, strict=True):
        if start <= dof < start + 6:
            owner = f"body {name!r}"
    h = scene.step_size
    advice = (
        "raise substeps or lower impact_spring / impact_damper (the explicit step needs ~0.5 ms at Table I's stiff "
        'corners), or use integrator = "implicit"'
        if scene.integrator == "explicit"
        else "lower the time step (substeps) or the contact stiffness, or check the robot's servo gains and forces"
    )
    raise SimulationError(
        f"the simulation blew up at frame {frame} (t = {frame * scene.timestep:.4g} s): {owner} reached "
        f"{speeds[dof]:.3g} (m/s or rad/s; limit {MAX_SPEED:g}) at a step of {h:.3g} s; {advice}"
    )


def driven(sim: Simulation) -> bool:
    """Whether anything feeds energy into the scene: a robot, actuators, actuated or mocap primitives."""
    return bool(sim.model.nu or sim.model.nmocap or any(p.mode == "actuated" for p in sim.world.prims))


def mechanical_energy(sim: Simulation, params, qpos: np.ndarray, qvel: np.ndarray):
    """Kinetic and gravitational energy (J) of each free body (DANOs at the mass and inertia
    scales of `params`) at each state, from the compiled model's inertias: names, kinetic and
    potential (T, bodies)."""
    model, w = sim.model, sim.world
    factors = zip(w.dano_body, np.asarray(params.mass_scale), np.asarray(params.inertia_scale), strict=True)
    scale = {b: (float(ms), float(ms * s)) for b, ms, s in factors}
    names, kinetic, potential = [], [], []
    g = np.asarray(model.opt.gravity)
    for j in np.flatnonzero(model.jnt_type == mujoco.mjtJoint.mjJNT_FREE):
        b, a, v = int(model.jnt_bodyid[j]), int(model.jnt_qposadr[j]), int(model.jnt_dofadr[j])
        mass_factor, inertia_factor = scale.get(b, (1.0, 1.0))
        mass, moments = model.body_mass[b] * mass_factor, model.body_inertia[b] * inertia_factor
        R = np.asarray(quat_to_mat(qpos[:, a + 3 : a + 7]))  # body -> world
        R_i = np.asarray(quat_to_mat(model.body_iquat[b]))  # inertial -> body
        w_body = qvel[:, v + 3 : v + 6]
        lever = R @ model.body_ipos[b]
        v_com = qvel[:, v : v + 3] + np.cross(np.einsum("tij,tj->ti", R, w_body), lever)
        w_i = w_body @ R_i
        names.append(mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, b) or f"body {b}")
        kinetic.append(0.5 * mass * np.sum(v_com**2, axis=1) + 0.5 * np.sum(moments * w_i**2, axis=1))
        potential.append(-mass * (qpos[:, a : a + 3] + lever) @ g)
    stack = lambda c: np.stack(c, axis=1) if c else np.zeros((len(qpos), 0))  # noqa: E731
    return names, stack(kinetic), stack(potential)


def audit_energy(traj: Trajectory, sim: Simulation, params=None) -> None:
    """Raises `SimulationError` at the first frame whose total mechanical energy is above the
    initial one by more than `ENERGY_TOLERANCE` of the scene's energy scale, in a scene that nothing
    drives (`driven`); the message names the body that gained most, its contacts' deepest
    penetration and the time step."""
    if driven(sim):
        return
    params = sim.params if params is None else params
    qpos, qvel = np.asarray(traj.qpos), np.asarray(traj.qvel)
    names, kinetic, potential = mechanical_energy(sim, params, qpos, qvel)
    if not names:
        return
    E = kinetic + potential
    total = E.sum(axis=1)
    weight = float(np.linalg.norm(sim.model.opt.gravity)) * sim.model.body_mass
    size = 2.0 * np.array([sim.model.geom_rbound[sim.model.geom_bodyid == b].max(initial=0.0)
                           for b in range(sim.model.nbody)])  # fmt: skip
    for i, b in enumerate(sim.world.dano_body):
        size[b] = 2.0 * float(np.max(np.linalg.norm(np.asarray(sim.world.danos[i].points), axis=0)))
        weight[b] *= float(np.asarray(params.mass_scale)[i])
    scale = float(np.sum(weight * size)) + float(kinetic[0].sum())
    gain = total - total[0] > ENERGY_TOLERANCE * scale
    broken = ~np.isfinite(total)  # `check_trajectory`'s to report, unless the energy grew before
    if not gain.any() or (broken.any() and np.argmax(broken) < np.argmax(gain)):
        return
    f = int(np.argmax(gain))
    worst = int(np.argmax(E[f] - E[0]))
    raise SimulationError(
        f"energy from nowhere: at frame {f} (t = {f * sim.scene.timestep:.4g} s) the scene has "
        f"{total[f] - total[0]:+.3g} J more than at the start ({(total[f] - total[0]) / scale:.1%} of its energy "
        f"scale {scale:.3g} J) with nothing driving it; most of it went to {names[worst]!r}"
        f"{penetration(sim, params, qpos[f], qvel[f], names[worst])}; "
        f"time step {sim.scene.step_size:.3g} s "
        f"({sim.scene.integrator}). A body placed inside another releases the contact spring's energy; "
        "otherwise lower impact_spring or raise substeps"
        + ("" if sim.scene.integrator == "implicit" else ', or use integrator = "implicit"')
    )


def penetration(sim: Simulation, params, qpos: np.ndarray, qvel: np.ndarray, name: str) -> str:
    """Where DANO `name` touches at this state, for a message: ", touching ground (3.2 mm deep)",
    with every primitive partner it is inside of and every DANO partner it overlaps; "" if none."""
    w = sim.world
    if name not in w.names:
        return ""
    d = sim.data.replace(qpos=jnp.asarray(qpos), qvel=jnp.asarray(qvel))
    bodies, frames = dano_bodies(w, params), dano_frames(w, d)
    touching = []
    for (i, kind, k), mate in zip(pairs(w), partners(w, d), strict=True):
        other = pair_name(w, (i, kind, k))[1]
        if name not in (w.names[i], other if kind == "dano" else None):
            continue
        if mate.shape is None:
            A, B = bodies[i], bodies[k]
            if A.field is not None and B.field is not None:
                inside = jnp.max(occupancy(B, frames[k], world_points(A, frames[i])))
                if float(jnp.maximum(inside, jnp.max(occupancy(A, frames[i], world_points(B, frames[k]))))) > 0:
                    touching.append(f"{w.names[i]} and {other} overlapping")
            continue
        depth = -float(jnp.min(signed_distance(mate.shape, world_points(bodies[i], frames[i]))))
        if depth > 0:
            touching.append(f"{other} ({1e3 * depth:.3g} mm deep)")
    return f", touching {', '.join(touching)}" if touching else ""


def body_poses(traj: Trajectory, sim: Simulation) -> dict[str, np.ndarray]:
    """Per DANO and free primitive: (T+1, 7) rows x, y, z, qw, qx, qy, qz (centre of mass, world)."""
    qpos = np.asarray(traj.qpos)
    w = sim.world
    out = {name: qpos[:, a : a + 7] for name, a in zip(w.names, w.dano_qpos, strict=True)}
    for p in w.prims:
        if p.mode == "free":
            out[p.name] = qpos[:, p.qpos : p.qpos + 7]
        elif p.mode == "actuated":
            fixed = np.broadcast_to(np.asarray(p.quat, dtype=float), (len(qpos), 4))
            out[p.name] = np.concatenate([np.asarray(p.pos) + qpos[:, p.qpos : p.qpos + 3], fixed], axis=1)
    return out


def write_csv(path: str | Path, traj: Trajectory, sim: Simulation) -> None:
    """Writes `t,body,x,y,z,qw,qx,qy,qz`, one row per frame per body, atomically."""
    poses = body_poses(traj, sim)
    with atomic_write(path) as tmp, open(tmp, "w", newline="") as f:
        out = csv.writer(f)
        out.writerow(["t", "body", "x", "y", "z", "qw", "qx", "qy", "qz"])
        n = next(iter(poses.values())).shape[0] if poses else 0
        for t in range(n):
            for name, rows in poses.items():
                out.writerow([f"{t * sim.scene.timestep:.6f}", name, *(f"{v:.9g}" for v in rows[t])])


def at_rest(scene: Scene, seconds: float = 0.5) -> Scene:
    """The scene with its DANOs moved to where they are after `seconds` of simulation (placed just
    above the table, they come to rest), so pushes start from a true equilibrium."""
    sim = Simulation.from_scene(dataclasses.replace(scene, duration=seconds))
    traj = sim.run()
    check_trajectory(traj, sim.scene, sim.world)
    poses = body_poses(traj, sim)
    bodies = tuple(
        dataclasses.replace(b, pos=tuple(float(v) for v in poses[b.name][-1, :3]),
                            quat=tuple(float(v) for v in poses[b.name][-1, 3:]))
        for b in scene.bodies
    )  # fmt: skip
    return dataclasses.replace(scene, bodies=bodies)


def at_interval(scene: Scene, dt: float) -> Scene:
    """The scene with one frame per `dt` s, split into substeps no longer than the scene's own
    (`scene.timestep / scene.substeps`: the contact's Jacobian needs them short, see README)."""
    substeps = max(1, int(np.ceil(dt / scene.step_size - 1e-9)))
    return dataclasses.replace(scene, timestep=dt, substeps=substeps)
