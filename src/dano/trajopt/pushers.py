"""The robots that push, behind one interface (`AbstractPusher`; `PUSHERS` by name): where each
stands, what holds it still, its controls, limits and first guesses.

- "sphere" (`SpherePusher`): the paper's simplification, a fully actuated sphere driven by a force.
- "panda" (`PandaPusher`): the 7-joint Franka Panda of example-robot-data driven by its servos.
"""

import abc
import dataclasses
from collections.abc import Callable
from typing import ClassVar, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from dano.assets import panda
from dano.sim.run import Simulation
from dano.sim.scene import Integrator, Scene
from dano.sim.step import mjx_kinematics
from dano.trajopt.pieces import TrajoptError
from dano.trajopt.task import PushTask
from dano.types import DANO

PANDA_HOME = (0.0, 0.614, 0.0, -2.073, 0.0, 2.686, 0.785, 0.02, 0.02)
"""Panda joints with the hand pointing down 0.58 m in front of the base, fingertips 1.5 cm above the floor."""
PANDA_CONTACT = ("panda_link7", "panda_hand", "panda_leftfinger", "panda_rightfinger")
"""The Panda links that can touch a tabletop object in the push (the rest stay > 14 cm up)."""
PANDA_TORQUE = (87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0)
"""The Panda's joint torque limits, N m (Franka's datasheet)."""


class PusherModel(NamedTuple):
    """A pusher as the optimiser sees it in a compiled simulation (state x = (qpos, qvel)).

    Attributes:
        effector: x -> (end effector position (3,), world, m; its velocity terms).
        lowest: x -> (k,) heights of the end effector's lowest points, m (kept above the clearance).
        input_limits: (x, u) -> (c,) constraints <= 0 on the controls.
        guess: scale -> (T, m) controls of a first guess; `scales` the scales the warm start tries.
    """

    effector: Callable[[jax.Array], tuple[jax.Array, jax.Array]]
    lowest: Callable[[jax.Array], jax.Array]
    input_limits: Callable[[jax.Array, jax.Array], jax.Array]
    guess: Callable[[float], np.ndarray]
    scales: np.ndarray


class AbstractPusher(abc.ABC):
    """What the push needs of a robot: where it stands, what holds it still, its controls and limits.

    Attributes:
        name: "sphere", "panda", ...
        integrator, substep: its default simulator step for the push (s).
        goal_as_constraint: whether the DANO's final xy is a constraint (else a cost) by default.
    """

    name: ClassVar[str]
    integrator: ClassVar[Integrator]
    substep: ClassVar[float]
    goal_as_constraint: ClassVar[bool]

    @abc.abstractmethod
    def place(self, scene: Scene, dano: DANO, direction: np.ndarray) -> Scene:
        """The push scene (`dano.scenarios.push_scene`, its sphere behind the object) with this robot
        in it, placed to push along the unit xy `direction`."""

    @abc.abstractmethod
    def hold(self) -> jax.Array:
        """The controls (m,) that hold the robot still; the effort cost is measured from them."""

    def full_ctrl(self, u: jax.Array) -> jax.Array:
        """MuJoCo's `ctrl` (..., nu) from the optimised controls (..., m)."""
        return u

    @abc.abstractmethod
    def model(self, sim: Simulation, task: PushTask, goal: np.ndarray) -> PusherModel:
        """The robot's effector, limits and first guesses in the compiled `sim` (goal: xy, m)."""


class SpherePusher(AbstractPusher):
    """The paper's simplification: a fully actuated sphere (1 kg, weight compensated) driven by a
    force (N) along x, y, z, bounded by `PushTask.force_limit`; solved jointly with the DANO by the
    implicit step."""

    name = "sphere"
    integrator, substep = Integrator.implicit, 8e-3
    goal_as_constraint = True

    def place(self, scene: Scene, dano: DANO, direction: np.ndarray) -> Scene:
        return scene

    def hold(self) -> jax.Array:
        return jnp.zeros(3)

    def model(self, sim: Simulation, task: PushTask, goal: np.ndarray) -> PusherModel:
        nq = sim.model.nq
        p = sim.world.prims[0].qpos
        home = jnp.asarray(sim.scene.primitives[0].pos)
        radius = float(sim.scene.primitives[0].size[0])
        vp = dof(sim, p)
        direction = goal / np.linalg.norm(goal)

        def effector(x) -> tuple[jax.Array, jax.Array]:  # position and velocity
            return home + x[p : p + 3], x[nq + vp : nq + vp + 3]

        def lowest(x) -> jax.Array:
            return (home[2] + x[p + 2] - radius)[None]

        def input_limits(x, u):
            return jnp.concatenate([u - task.force_limit, -u - task.force_limit])

        def guess(scale) -> np.ndarray:  # push towards the goal for a third, brake for a third
            T, third = task.horizon, task.horizon // 3
            u = np.zeros((T, 3))
            u[:third, :2] = scale * direction
            u[third : 2 * third, :2] = -0.5 * scale * direction
            return u

        return PusherModel(effector, lowest, input_limits, guess, np.linspace(0.5, task.force_limit, 16))


class PandaPusher(AbstractPusher):
    """The 7-joint Franka Panda of example-robot-data, its collision meshes touching the DANO through
    the contact model; controls are the arm's position-servo targets (fingers held), bounded by the
    joint ranges, with the servo torque kp (target − q) − kv q̇ within the Panda's torque limits.
    Like the sphere it runs ten implicit steps of 8 ms per frame: its servo-driven links take the
    contact's reactions explicitly, which the arm's mass and servos hold at that step (the warm
    start's bunny ends 1.4 mm from where 160 explicit substeps of 0.5 ms take it; README). The goal
    is a cost by default: the contact through its hand's faceted hull is too rough near the goal
    for the augmented Lagrangian to drive the miss below 1e-4 m."""

    name = "panda"
    integrator, substep = Integrator.implicit, 8e-3
    goal_as_constraint = False

    def place(self, scene: Scene, dano: DANO, direction: np.ndarray) -> Scene:
        # The hand sweeps sideways (base yaw) about 0.58 m in front of the base: the object sits
        # beside the hand on the side away from the goal direction, base placed accordingly.
        reach = float(np.max(np.linalg.norm(np.asarray(dano.body_points)[:, :2], axis=1)))
        side = np.array([-direction[1], direction[0]])
        base = -0.58 * side - (reach + 0.06) * direction
        yaw = float(np.arctan2(side[1], side[0]))
        quat = (float(np.cos(yaw / 2)), 0.0, 0.0, float(np.sin(yaw / 2)))
        arm = panda(base_pos=(*base, 0.0), qpos=PANDA_HOME, base_quat=quat, contact_bodies=PANDA_CONTACT)
        return dataclasses.replace(scene, primitives=(), robot=arm)

    def hold(self) -> jax.Array:
        return jnp.asarray(PANDA_HOME[:7])

    def full_ctrl(self, u: jax.Array) -> jax.Array:
        fingers = jnp.asarray(PANDA_HOME[7:], dtype=u.dtype)
        return jnp.concatenate([u, jnp.broadcast_to(fingers, (*u.shape[:-1], 2))], axis=-1)

    def model(self, sim: Simulation, task: PushTask, goal: np.ndarray) -> PusherModel:
        model, nq, d0 = sim.model, sim.model.nq, sim.data
        boxes = [link for link in sim.world.links if link.kind == "box"]  # the fingers
        box_geoms, box_sizes = jnp.asarray([b.geom for b in boxes]), jnp.asarray([b.size for b in boxes])
        hand = model.body("panda_hand").id
        assert sim.scene.robot is not None  # the panda's scene
        kp, kv = sim.scene.robot.kp, sim.scene.robot.kv
        lo, hi = (jnp.asarray(model.jnt_range[:7, i]) for i in (0, 1))
        tau = jnp.asarray(PANDA_TORQUE)

        def kinematics(x):
            return mjx_kinematics(sim.mjx_model, d0.replace(qpos=x[:nq]))

        # the hand's position; its speed enters through the joint velocities
        def effector(x) -> tuple[jax.Array, jax.Array]:
            return kinematics(x).xpos[hand], x[nq : nq + 7]

        def lowest(x) -> jax.Array:  # each finger box's lowest corner (|.| smoothed: the boxes start upright)
            k = kinematics(x)
            up = k.geom_xmat[box_geoms].reshape(-1, 3, 3)[:, 2, :]
            return k.geom_xpos[box_geoms, 2] - jnp.sum(jnp.sqrt(up**2 + 1e-6) * box_sizes, axis=1)

        def input_limits(x, u):
            torque = kp * (u - x[:7]) - kv * x[nq : nq + 7]
            return jnp.concatenate([u - hi, lo - u, torque - tau, -torque - tau])

        def guess(scale) -> np.ndarray:  # sweep the base yaw towards the goal and hold
            u = np.tile(np.asarray(PANDA_HOME[:7]), (task.horizon, 1))
            u[:, 0] = -scale * np.minimum(1.0, np.arange(1, task.horizon + 1) / (0.6 * task.horizon))
            return u

        return PusherModel(effector, lowest, input_limits, guess, np.linspace(0.05, 1.0, 16))


PUSHERS: dict[str, AbstractPusher] = {p.name: p for p in (SpherePusher(), PandaPusher())}
"""The robots `push_problem` knows by name; any other `AbstractPusher` can be passed itself."""
ROBOT_STEP = {name: (p.integrator, p.substep) for name, p in PUSHERS.items()}
"""Each robot's default simulator step for the push: (integrator, step length in s). Both run the
implicit step at ten 8 ms steps per 0.08 s frame instead of the explicit step's 160 substeps of
0.5 ms: the sphere's frame Jacobian costs a seventh (51 vs 376 ms, measured beside another job
when its default changed), the Panda push's iteration a third (4.4 vs 13.1 s on average, the
first one's compile included; README)."""


def pusher(robot: "str | AbstractPusher") -> AbstractPusher:
    """The pusher named `robot` ("sphere", "panda"), or `robot` itself.

    Raises:
        TrajoptError: an unknown name.
    """
    if isinstance(robot, AbstractPusher):
        return robot
    if robot not in PUSHERS:
        raise TrajoptError(f"robot must be one of {', '.join(map(repr, PUSHERS))}, got {robot!r}")
    return PUSHERS[robot]


def dof(sim: Simulation, qpos_address: int) -> int:
    """The qvel address of the joint whose qpos starts at `qpos_address`."""
    model = sim.model
    j = int(np.nonzero(model.jnt_qposadr == qpos_address)[0][0])
    return int(model.jnt_dofadr[j])
