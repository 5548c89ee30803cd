"""Real-to-sim: physical parameters of DANOs from observed pose trajectories (paper Problem (17)).

Names load on first use (PEP 562): the settings (`configs`) import no JAX, so the command line
reads them to build its options and `dano --help` stays instant.
"""

from typing import TYPE_CHECKING

from dano._lazy import attach

_LAZY = {
    "Track": "dano.sysid.data",
    "TrackFileError": "dano.sysid.data",
    "estimate_velocity": "dano.sysid.data",
    "motion_plane_normal": "dano.sysid.data",
    "read_tracks": "dano.sysid.data",
    "to_metric": "dano.sysid.data",
    "write_track": "dano.sysid.data",
    "SysidConfig": "dano.sysid.configs",
    "SysidError": "dano.sysid.configs",
    "DEFAULT_BOUNDS": "dano.sysid.params",
    "canonical": "dano.sysid.params",
    "Problem": "dano.sysid.problem",
    "make_problem": "dano.sysid.problem",
    "residuals": "dano.sysid.problem",
    "simulate_windows": "dano.sysid.problem",
    "Identification": "dano.sysid.solve",
    "identify": "dano.sysid.solve",
    "identify_files": "dano.sysid.pipeline",
    "Recording": "dano.sysid.windows",
}

if TYPE_CHECKING:
    from dano.sysid.configs import SysidConfig, SysidError
    from dano.sysid.data import (
        Track,
        TrackFileError,
        estimate_velocity,
        motion_plane_normal,
        read_tracks,
        to_metric,
        write_track,
    )
    from dano.sysid.params import DEFAULT_BOUNDS, canonical
    from dano.sysid.pipeline import identify_files
    from dano.sysid.problem import Problem, make_problem, residuals, simulate_windows
    from dano.sysid.solve import Identification, identify
    from dano.sysid.windows import Recording


__getattr__, __dir__ = attach(__name__, _LAZY)

__all__ = [
    "DEFAULT_BOUNDS", "Identification", "Problem", "Recording", "SysidConfig", "SysidError", "Track",
    "TrackFileError", "canonical", "estimate_velocity", "identify", "identify_files", "make_problem",
    "motion_plane_normal", "read_tracks", "residuals", "simulate_windows", "to_metric", "write_track",
]  # fmt: skip
