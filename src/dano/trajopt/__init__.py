"""Trajectory optimisation: constrained iLQR (`ilqr`), the push task (`task`, `push`) by robots behind
one interface (`pushers`), paper Sec. V-B."""

from dano.trajopt.ilqr import OptimalControlProblem, Options, Solution, TrajoptError, rollout, solve
from dano.trajopt.push import PushProblem, PushResult, push_problem, solve_push
from dano.trajopt.pushers import PUSHERS, AbstractPusher, PandaPusher, SpherePusher
from dano.trajopt.task import PushTask

__all__ = [
    "PUSHERS", "AbstractPusher", "OptimalControlProblem", "Options", "PandaPusher", "PushProblem", "PushResult",
    "PushTask", "Solution", "SpherePusher", "TrajoptError", "push_problem", "rollout", "solve", "solve_push",
]  # fmt: skip
