"""Trajectory optimisation: constrained iLQR and the push task (paper Sec. V-B)."""

from dano.trajopt.ilqr import OptimalControlProblem, Options, Solution, TrajoptError, rollout, solve

__all__ = ["OptimalControlProblem", "Options", "Solution", "TrajoptError", "rollout", "solve"]
