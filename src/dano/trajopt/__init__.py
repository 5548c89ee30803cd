"""Trajectory optimisation: constrained iLQR and the push task (paper Sec. V-B)."""

from dano.trajopt.ilqr import OptimalControlProblem, Options, Solution, TrajoptError, rollout, solve
from dano.trajopt.push import PushProblem, PushResult, PushTask, push_problem, solve_push

__all__ = [
    "OptimalControlProblem", "Options", "PushProblem", "PushResult", "PushTask", "Solution", "TrajoptError",
    "push_problem", "rollout", "solve", "solve_push",
]  # fmt: skip
