"""Shared test helpers."""

import numpy as np


def central_difference(f, x: float, rel_step: float = 1e-5) -> float:
    """Central finite difference of a scalar function, step scaled to the input."""
    h = rel_step * max(abs(x), 1.0)
    return (f(x + h) - f(x - h)) / (2 * h)


def partial_differences(f, x0: tuple, rel_step: float = 1e-5) -> list[np.ndarray]:
    """Central differences of `f(*x0)` w.r.t. each scalar argument in turn, steps scaled to the inputs."""
    out = []
    for i, xi in enumerate(x0):
        h = rel_step * max(abs(xi), 1.0)
        plus, minus = list(x0), list(x0)
        plus[i], minus[i] = xi + h, xi - h
        out.append((np.asarray(f(*plus)) - np.asarray(f(*minus))) / (2 * h))
    return out


def analytic_fields():
    """The analytic fields the tests share (sphere, box, capsule with soft edges)."""
    from dano.fields import BoxField, CapsuleField, SphereField

    return [
        SphereField(0.05, width=0.005),
        BoxField([0.1, 0.06, 0.03], width=0.003),
        CapsuleField(0.02, 0.05, width=0.004),
    ]


def rel_err(a, b) -> float:
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))
