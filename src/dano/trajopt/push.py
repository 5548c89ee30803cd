"""The paper's push-and-slide task (Sec. V-B, Fig. 7) as an optimal control problem.

An end effector pushes a DANO resting on the table so that it slides to a goal, then returns to
its own goal, by any robot behind `dano.trajopt.pushers.AbstractPusher` (a sphere, the Panda).

State x = (qpos, qvel) of the MuJoCo model; one step of the dynamics is one frame of `dt` seconds
(`dano.sim.step.step`: substeps with fresh contact wrenches). Costs: the DANO's final position
and velocity, the end effector's final position and speed, effort. Constraints (augmented
Lagrangian): the DANO's final xy on the goal (`goal_as_constraint`, else a cost), input limits,
the end effector above the ground.
"""

import dataclasses
import functools
from collections.abc import Callable
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from dano import lanes
from dano import validate as V
from dano.scenarios import WorldError, in_world, push_scene
from dano.sim.run import Simulation, at_interval, compiler_options
from dano.sim.scene import Integrator, Scene
from dano.sim.step import Trajectory, scaled_model, step
from dano.trajopt.ilqr import Options, Solution, open_loop, solve
from dano.trajopt.pieces import (
    Flow,
    OptimalControlProblem,
    TrajoptError,
    compile_ahead,
    open_loop_states,
)
from dano.trajopt.pushers import AbstractPusher, dof, pusher
from dano.trajopt.task import PushTask
from dano.types import DANO


@dataclasses.dataclass(frozen=True)
class PushProblem:
    """A push ready to solve: the problem, x0, a first guess of the controls, and what they mean."""

    pusher: AbstractPusher
    task: PushTask
    sim: Simulation
    problem: OptimalControlProblem
    x0: np.ndarray
    initial_controls: np.ndarray
    goal_world: np.ndarray
    ee_goal: np.ndarray
    effector: Callable
    """x -> (end effector position (3,), its velocity terms)."""
    ctrl: Callable
    """u (..., m) -> MuJoCo's `ctrl` (..., nu): a world's own actuators held, then the robot's."""

    @property
    def robot(self) -> str:
        return self.pusher.name

    def object_position(self, x) -> jax.Array:
        a = self.sim.world.dano_qpos[0]
        return jnp.asarray(x)[..., a : a + 3]

    def full_ctrl(self, u) -> jax.Array:
        return self.ctrl(u)


def push_problem(
    dano: DANO,
    robot: "str | AbstractPusher" = "sphere",
    task: PushTask | None = None,
    friction: float = 0.3,
    world: str | Path | None = None,
    at: tuple[float, float] = (0.0, 0.0),
) -> PushProblem:
    """The push of `dano` by `robot` ("sphere", "panda" or any `AbstractPusher`) as an
    `OptimalControlProblem`: on the plane z = 0, or in the MJCF `world` on whatever it has under
    the point `at` (x, y: a table's top; `dano.scenarios.in_world`), the world's own actuators held
    at their initial `ctrl` (its keyframe's) and its bodies moving as MuJoCo moves them.

    Raises:
        TrajoptError: an unknown robot, a goal too close to push to, a bad horizon or integrator,
            a world with nothing under `at`.
    """
    task = PushTask() if task is None else task
    robot = pusher(robot)
    if task.horizon < 2:
        raise TrajoptError(f"horizon must be at least 2 frames, got {task.horizon}")
    goal = np.asarray(task.goal, dtype=float)
    if not np.all(np.isfinite(goal)) or goal.shape != (2,):
        raise TrajoptError(f"goal must be two finite numbers (x, y in m), got {task.goal}")
    distance = float(np.linalg.norm(goal))
    if distance < 1e-3:
        raise TrajoptError("the goal is where the object already is: nothing to push")
    integrator = V.option(task.integrator or robot.integrator, "integrator", TrajoptError, Integrator)
    substep = task.substep or (robot.substep if integrator == robot.integrator else 5e-4)
    if not substep > 0:
        raise TrajoptError(f"substep must be > 0, got {substep}")
    scene = _scene(dano, robot, goal / distance, friction, task.dt, substep, integrator)
    floor = 0.0
    if world is not None:
        try:
            scene, floor = in_world(scene, world, at)
        except WorldError as e:
            raise TrajoptError(str(e)) from None
    sim = Simulation.from_scene(scene)
    # The world's actuators come first in `ctrl`, held where the world starts them.
    held = jnp.asarray(sim.data.ctrl[: sim.model.nu - robot.full_ctrl(robot.hold()).shape[-1]])
    full = functools.partial(_full_ctrl, robot, held)
    dynamics = _dynamics(sim, full)
    sim = _settled(sim, dynamics, task.horizon, robot.hold(), default_options(robot))
    return _assemble(robot, task, sim, dynamics, goal, full, floor)


def _full_ctrl(robot: AbstractPusher, held: jax.Array, u: jax.Array) -> jax.Array:
    """MuJoCo's `ctrl`: the world's actuators `held` (none in dano's own scenes), then the robot's."""
    ctrl = robot.full_ctrl(u)
    return jnp.concatenate([jnp.broadcast_to(held, (*ctrl.shape[:-1], held.shape[0])), ctrl], axis=-1)


SETTLE_S = 0.5
"""How long the object is simulated, the robot holding still, before the push starts from where
it rests (placed just above the table, it comes to rest in that time)."""


def _settled(sim: Simulation, dynamics: Callable, horizon: int, hold: jax.Array, options: Options) -> Simulation:
    """`sim` with its DANOs where they rest after `SETTLE_S` seconds, the robot held still.

    Rolled out `horizon` frames at a time by the solver's own forward pass (`open_loop_states` on
    the push's `dynamics`: `Flow` shares its compiled program with the push's warm start and
    solve), so the settling compiles nothing of its own."""
    scene, world = sim.scene, sim.world
    flow = Flow.of(dynamics, horizon, compiler_options(world))
    controls = jnp.broadcast_to(hold, (horizon, hold.shape[0]))
    x = jnp.concatenate([sim.data.qpos, sim.data.qvel])
    # the solve's dynamics Jacobians (its largest program) compile while this and the warm start run
    compile_ahead(flow, x.shape[0], hold.shape[0], options.jacobian_batch, options.lanes)
    for _ in range(int(np.ceil(SETTLE_S / (horizon * scene.timestep) - 1e-9))):
        x = open_loop_states(flow, x, controls)[-1]
    if not np.all(np.isfinite(np.asarray(x))):
        raise TrajoptError("the object did not come to rest before the push: its settling diverged")
    qpos, rest = np.asarray(sim.data.qpos).copy(), np.asarray(x[: sim.model.nq])
    bodies = []
    for b, a in zip(scene.bodies, world.dano_qpos, strict=True):  # the DANOs moved, at rest; the rest as placed
        qpos[a : a + 7] = rest[a : a + 7]
        bodies.append(dataclasses.replace(b, pos=tuple(float(v) for v in rest[a : a + 3]),
                                          quat=tuple(float(v) for v in rest[a + 3 : a + 7])))  # fmt: skip
    data = sim.data.replace(qpos=jnp.asarray(qpos))  # velocities as placed (at rest)
    return dataclasses.replace(sim, scene=dataclasses.replace(scene, bodies=tuple(bodies)), data=data)


def _dynamics(sim: Simulation, full: Callable) -> Callable:
    """x' = f(x, u, t): one frame of `sim` from the state x = (qpos, qvel) under the controls u
    (`full` maps them to MuJoCo's `ctrl`). The rest of MuJoCo's data (mocap poses, the world's
    activations) is `sim`'s as placed, which settling the DANOs does not change."""
    world, params, d0, nq = sim.world, sim.params, sim.data, sim.model.nq
    m = scaled_model(world, params, sim.mjx_model)

    def dynamics(x, u, t):
        d = d0.replace(qpos=x[:nq], qvel=x[nq:], ctrl=full(u))
        d = step(world, params, m, d)
        return jnp.concatenate([d.qpos, d.qvel])

    return dynamics


def _scene(
    dano: DANO,
    robot: AbstractPusher,
    direction: np.ndarray,
    friction: float,
    dt: float,
    substep: float,
    integrator: Integrator,
) -> Scene:
    scene = robot.place(push_scene(dano, friction, direction=tuple(direction)), dano, direction)
    scene = dataclasses.replace(scene, timestep=substep, substeps=1, duration=dt, integrator=integrator)
    return at_interval(scene, dt)


def _assemble(
    robot: AbstractPusher,
    task: PushTask,
    sim: Simulation,
    dynamics: Callable,
    goal: np.ndarray,
    full: Callable,
    floor: float,
) -> PushProblem:
    """The problem from the settled `sim`; `dynamics` as `_dynamics` made them, `full` maps the
    controls to MuJoCo's `ctrl`, `floor` is the height the clearance is measured from (m)."""
    world, d0, nq = sim.world, sim.data, sim.model.nq
    x0 = np.concatenate([np.asarray(d0.qpos), np.asarray(d0.qvel)])
    a = world.dano_qpos[0]
    goal_world = np.asarray(d0.qpos)[a : a + 2] + goal
    pm = robot.model(sim, task, goal)

    ee_start = np.asarray(pm.effector(jnp.asarray(x0))[0])
    ee_goal = ee_start if task.ee_goal is None else np.asarray(task.ee_goal, dtype=float)
    goal_j, ee_goal_j = jnp.asarray(goal_world), jnp.asarray(ee_goal)
    va = dof(sim, a)
    reference_u = robot.hold()
    goal_is_constraint = robot.goal_as_constraint if task.goal_as_constraint is None else task.goal_as_constraint

    def cost(x, u, t):
        return task.effort_weight * jnp.sum((u - reference_u) ** 2)

    def terminal_cost(x):
        ee, ee_vel = pm.effector(x)
        v = x[nq + va : nq + va + 6]
        c = task.ee_weight * jnp.sum((ee - ee_goal_j) ** 2) + task.velocity_weight * (v @ v + ee_vel @ ee_vel)
        if not goal_is_constraint:
            c = c + task.goal_weight * jnp.sum((x[a : a + 2] - goal_j) ** 2)
        return c

    def constraints(x, u, t):
        return jnp.concatenate([pm.input_limits(x, u), task.clearance + floor - pm.lowest(x)])

    terminal = (lambda x: x[a : a + 2] - goal_j) if goal_is_constraint else None
    options = compiler_options(world)
    problem = OptimalControlProblem(dynamics, cost, terminal_cost, task.horizon, constraints, terminal, options)
    guesses = [pm.guess(s) for s in pm.scales]
    first = _warm_start(problem, x0, guesses, lambda x: x[a : a + 2] - goal_j, default_options(robot).lanes)
    return PushProblem(robot, task, sim, problem, x0, first, goal_world, ee_goal, pm.effector, full)


def _warm_start(
    problem: OptimalControlProblem, x0: np.ndarray, guesses: list[np.ndarray], miss, n_lanes: int | None
) -> np.ndarray:
    """The guess whose open-loop rollout ends nearest the goal (rolled out `dano.lanes.count(n_lanes)`
    at a time, each from a thread of its own: `dano.lanes.in_lanes`).

    iLQR needs a start in contact: from zero controls the pusher never touches the object and the
    goal has no gradient in the controls."""
    start = jnp.asarray(x0)
    # not vmapped: on a CPU a vmapped rollout runs no faster and compiles its own program
    ends = lanes.in_lanes([lambda u=u: open_loop(problem, start, jnp.asarray(u))[-1] for u in guesses], n_lanes)
    misses = np.array([float(jnp.linalg.norm(miss(end))) for end in ends])
    misses = np.where(np.isfinite(misses), misses, np.inf)
    return guesses[int(np.argmin(misses))]


@dataclasses.dataclass(frozen=True)
class PushResult:
    """A solved push and its open-loop replay in the forward simulator.

    Attributes:
        solution: the optimiser's `Solution`.
        final_error_m: distance of the DANO's final xy from the goal, by the optimiser's states.
        ee_error_m: the end effector's final distance from its goal.
        replay_gap_m: the DANO's final position in the replay minus the optimiser's, m (the same
            dynamics: round-off only).
        replay: the replayed `Trajectory` (for `render_video`).
    """

    solution: Solution
    final_error_m: float
    ee_error_m: float
    replay_gap_m: float
    replay: Trajectory

    def summary(self, params: dict | None = None, adjustments: dict | None = None) -> dict:
        """The `dano trajopt --json` object (`dano.results`): `params` as the user gave them, `rms`
        the object's final distance from its goal, then the push's own figures."""
        from dano.results import result_json

        s = self.solution
        return result_json(
            params=params or {}, iterations=s.iterations, converged=s.converged, message=s.message,
            seconds=s.seconds, rms_position=self.final_error_m, adjustments=adjustments,
            final_error_m=self.final_error_m, max_violation=s.max_violation, cost=s.cost,
            outer_iterations=s.outer, ee_error_m=self.ee_error_m, replay_gap_m=self.replay_gap_m,
        )  # fmt: skip


DEFAULT_OPTIONS = Options(max_iterations=150, penalty=100.0, jacobian_batch=1)
"""iLQR settings for the push: ρ starts high enough that the goal matters from the first iteration;
the dynamics Jacobians one frame at a time (vmapped over the horizon, the contact's branches become
selects and its solver loops run as long as the longest: for the sphere's 200-point bunny push,
compile 30.5 s and 0.67 s per expansion vmapped, 21.9 s and 0.20 s one frame at a time)."""


def default_options(robot: "str | AbstractPusher") -> Options:
    """The push's iLQR settings for `robot` (the same for every pusher today: `DEFAULT_OPTIONS`)."""
    pusher(robot)  # an unknown name is refused
    return DEFAULT_OPTIONS


REPLAY_FRAMES = 4
"""Frames per control step of the open-loop replay (`solve_push`, `render_push`)."""


def solve_push(push: PushProblem, options: Options | None = None, progress: bool = False) -> PushResult:
    """Solves the push from its warm start (`default_options(robot)` unless given) and replays the
    controls open loop."""
    options = default_options(push.robot) if options is None else options
    sol = solve(push.problem, jnp.asarray(push.x0), jnp.asarray(push.initial_controls), options, progress=progress)
    final = np.asarray(push.object_position(sol.states[-1]))
    ee = np.asarray(push.effector(jnp.asarray(sol.states[-1]))[0])
    # replayed at the frames `render_push` draws (the same substeps, regrouped), so that a video of
    # the push runs the program compiled here; every k-th frame is the replay at the push's frames
    _, fine, _, k = _replayed(push, jnp.asarray(sol.controls), REPLAY_FRAMES)
    replay = jax.tree_util.tree_map(lambda x: x[::k], fine)
    gap = float(np.linalg.norm(np.asarray(push.object_position(replay.qpos[-1])) - final))
    return PushResult(
        solution=sol, final_error_m=float(np.linalg.norm(final[:2] - push.goal_world)),
        ee_error_m=float(np.linalg.norm(ee - push.ee_goal)), replay_gap_m=gap, replay=replay,
    )  # fmt: skip


def render_push(
    push: PushProblem,
    result: PushResult,
    path,
    frames_per_step: int = REPLAY_FRAMES,
    progress: bool = True,
    style: str = "surface",
    contacts: bool = False,
):
    """Renders the open-loop replay (`replay_frames`) at the real-time frame rate; `style` as in
    `dano.sim.render.render_video`; `contacts`: the contact forces drawn as arrows."""
    from dano.sim.render import render_video

    sim, traj, ctrl = replay_frames(push, result, frames_per_step)
    forces = None
    if contacts:
        from dano.sim.contacts import contact_forces

        forces = contact_forces(sim, traj, ctrl=ctrl)
    fps = 1.0 / sim.scene.timestep  # real time: a frame per frame of the replay
    return render_video(sim, traj, path, fps=fps, progress=progress, style=style, contacts=forces)


def replay_frames(push: PushProblem, result: PushResult, frames_per_step: int = REPLAY_FRAMES):
    """The open-loop replay with `frames_per_step` frames per control step (the same substeps,
    regrouped: a control is held over its step): its simulation, trajectory and per-frame ctrl."""
    return _replayed(push, jnp.asarray(result.solution.controls), frames_per_step)[:3]


def _replayed(push: PushProblem, controls, frames_per_step: int):
    """`replay_frames` of the optimiser's controls, and the frames per step it took: the largest
    count up to `frames_per_step` that divides the scene's substeps."""
    scene = push.sim.scene
    assert scene.substeps is not None  # `Scene.__post_init__` sets it for each integrator
    while scene.substeps % frames_per_step:
        frames_per_step -= 1
    fine = dataclasses.replace(
        scene, timestep=scene.timestep / frames_per_step, substeps=scene.substeps // frames_per_step
    )
    sim = Simulation.from_scene(fine)
    ctrl = jnp.repeat(push.full_ctrl(controls), frames_per_step, axis=0)
    return sim, sim.run(push.task.horizon * frames_per_step, ctrl=ctrl), ctrl, frames_per_step
