"""Trajectory optimisation (paper Sec. V-B): constrained iLQR (`pieces`, the problem and iLQR's pure
functions; `ilqr`, the solver) and the push task (`task`, `push`) by robots behind one interface
(`pushers`)."""

from dano.trajopt.ilqr import Options, Solution, solve
from dano.trajopt.pieces import OptimalControlProblem, TrajoptError, rollout
from dano.trajopt.push import PushProblem, PushResult, push_problem, solve_push
from dano.trajopt.pushers import PUSHERS, AbstractPusher, PandaPusher, SpherePusher
from dano.trajopt.task import PushTask

__all__ = [
    "PUSHERS", "AbstractPusher", "OptimalControlProblem", "Options", "PandaPusher", "PushProblem", "PushResult",
    "PushTask", "Solution", "SpherePusher", "TrajoptError", "push_problem", "rollout", "solve", "solve_push",
]  # fmt: skip
