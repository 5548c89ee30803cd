"""The parameters identification fits: their names (canonical and aliases), bounds, and how a
vector θ of them is written into and read from the simulator's `Params`."""

import dataclasses
from collections.abc import Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from dano.contact.wrench import ContactParams
from dano.sim.world import Params
from dano.sysid.configs import SysidError

CONTACT_KEYS = tuple(f.name for f in dataclasses.fields(ContactParams))
BODY_KEYS = ("mass_scale", "inertia_scale")
ALIASES = {"friction": "sliding_friction", "mu": "sliding_friction", "alpha": "mass_scale"}

DEFAULT_BOUNDS: dict[str, tuple[float, float]] = {
    "sliding_friction": (0.0, 2.0),
    "sliding_drag": (0.0, 1.0),
    "rolling_friction": (0.0, 0.2),
    "rolling_drag": (0.0, 1.0),
    "torsional_friction": (0.0, 0.2),
    "torsional_drag": (0.0, 1.0),
    "impact_spring": (1e3, 1e6),
    "impact_damper": (1e3, 1e7),
    "coulomb_smoothing": (1.0, 1e4),
    "coulomb_regularizer": (1e-6, 1e-1),
    "coulomb_gain": (0.1, 2.0),
    "indicator_width": (1e-5, 1e-2),
    "mass_scale": (1e-3, 1e3),
    "inertia_scale": (0.1, 10.0),
}
"""Bounds used when none are given: Table I's ranges, widened; scales over decades."""


def canonical(name: str) -> str:
    """The parameter a name given by the user means (`friction` is `sliding_friction`)."""
    key = ALIASES.get(name, name)
    if key not in CONTACT_KEYS and key not in BODY_KEYS:
        raise SysidError(f"unknown parameter {name!r}; fit any of {sorted(CONTACT_KEYS + BODY_KEYS + tuple(ALIASES))}")
    return key


def with_values(params: Params, names: Sequence[str], theta: Float[Array, " p"]) -> Params:
    """`params` with each named parameter set to its value in θ: a contact key in every pair, a
    scale for every DANO (the reference identifies one friction for all of a body's contacts)."""
    for k, name in enumerate(names):
        value = theta[k]
        if name in BODY_KEYS:
            params = eqx.tree_at(lambda p, n=name: getattr(p, n), params, jnp.full_like(getattr(params, name), value))
        else:
            contact = tuple(eqx.tree_at(lambda c, n=name: getattr(c, n), c, value) for c in params.contact)
            params = eqx.tree_at(lambda p: p.contact, params, contact)
    return params


def current_values(params: Params, names: Sequence[str]) -> np.ndarray:
    """The values the scene gives the named parameters (first pair, first DANO)."""
    out = []
    for name in names:
        if name in BODY_KEYS:
            out.append(float(getattr(params, name)[0]))
        elif params.contact:
            out.append(float(getattr(params.contact[0], name)))
        else:
            raise SysidError(f"the scene has no contact pair, so {name!r} has nothing to act on")
    return np.asarray(out)
