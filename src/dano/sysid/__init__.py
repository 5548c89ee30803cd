"""Real-to-sim: physical parameters of DANOs from observed pose trajectories (paper Problem (17))."""

from dano.sysid.data import (
    Track,
    TrackFileError,
    estimate_velocity,
    motion_plane_normal,
    read_tracks,
    to_metric,
    write_track,
)
from dano.sysid.params import DEFAULT_BOUNDS, SysidError, canonical
from dano.sysid.problem import Problem, make_problem, residuals, simulate_windows
from dano.sysid.solve import Identification, identify
from dano.sysid.windows import Recording

__all__ = [
    "DEFAULT_BOUNDS", "Identification", "Problem", "Recording", "SysidError", "Track", "TrackFileError", "canonical",
    "estimate_velocity", "identify", "make_problem", "motion_plane_normal", "read_tracks", "residuals",
    "simulate_windows", "to_metric", "write_track",
]  # fmt: skip
