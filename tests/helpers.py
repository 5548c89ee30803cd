"""Shared test helpers."""

import numpy as np


def central_difference(f, x: float, rel_step: float = 1e-5) -> float:
    """Central finite difference of a scalar function, step scaled to the input."""
    h = rel_step * max(abs(x), 1.0)
    return (f(x + h) - f(x - h)) / (2 * h)


def rel_err(a, b) -> float:
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))
