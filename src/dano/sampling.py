"""Quasi-random points: scrambled Sobol sequences, seeded, for Monte Carlo over a field's box."""

import numpy as np
from scipy.stats import qmc

from dano.fields.base import Bounds


def sobol_unit(log2_n: int, seed: int, stream: int = 0) -> np.ndarray:
    """`2**log2_n` scrambled Sobol points in [0, 1)^3; (seed, stream) picks the scrambling."""
    engine = qmc.Sobol(d=3, scramble=True, rng=np.random.default_rng([seed, stream]))
    return engine.random_base2(log2_n)


def to_box(u: np.ndarray, bounds: Bounds) -> np.ndarray:
    """Maps unit-cube points to the box `bounds`."""
    lo, hi = np.asarray(bounds)
    return lo + u * (hi - lo)
