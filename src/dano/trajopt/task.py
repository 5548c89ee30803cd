"""What a push should achieve and how hard (`PushTask`), shared by the pushers and the problem."""

import dataclasses

from dano.sim.scene import Integrator


@dataclasses.dataclass(frozen=True)
class PushTask:
    """What to achieve and how hard.

    Attributes:
        goal: where the DANO's centre of mass should end, xy (m), relative to where it rests.
        horizon: frames; dt: seconds per frame.
        integrator, substep: the simulator's step and its length, s; None: the robot's default
            (`ROBOT_STEP`). The explicit step needs substeps of ≤ 0.5 ms (its contact's Jacobian is
            wrong at longer ones, see README).
        ee_goal: where the end effector should end (world, m); default where it starts.
        goal_as_constraint: the DANO's final xy as an equality constraint (True) or a cost of weight
            `goal_weight` (False). None: the robot's default, a constraint for the sphere and a cost
            for the Panda, whose contact through its hand's faceted hull is too rough near the goal
            for the augmented Lagrangian to drive the miss below 1e-4 m (it stalls at millimetres).
        force_limit: |force| per axis for the sphere, N.
        clearance: lowest height of the end effector's lowest point, m.
        goal_weight, ee_weight, velocity_weight, effort_weight: cost weights (per m², m², (m/s)²,
            N² or rad²).
    """

    goal: tuple[float, float] = (0.1, 0.0)
    horizon: int = 10
    dt: float = 0.08
    integrator: Integrator | str | None = None
    substep: float | None = None
    ee_goal: tuple[float, float, float] | None = None
    goal_as_constraint: bool | None = None
    force_limit: float = 10.0
    clearance: float = 0.005
    goal_weight: float = 1e3
    ee_weight: float = 1.0
    velocity_weight: float = 1.0
    effort_weight: float = 1e-3
