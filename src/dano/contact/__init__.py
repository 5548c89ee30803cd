"""The probabilistic contact model (paper eqs. 5-16): overlap psi, centroid chi, normal, wrench."""

from dano.contact.overlap import (
    Box,
    Capsule,
    Cylinder,
    HalfSpace,
    HeightField,
    Overlap,
    Polytope,
    Sphere,
    expected_overlap,
    signed_distance,
)
from dano.contact.wrench import ContactParams, Wrench, contact_wrench, coulomb_direction, sliding_force, spin_torque

__all__ = [
    "Box", "Capsule", "ContactParams", "Cylinder", "HalfSpace", "HeightField", "Overlap", "Polytope", "Sphere",
    "Wrench", "contact_wrench",
    "coulomb_direction", "expected_overlap", "signed_distance", "sliding_force", "spin_torque",
]  # fmt: skip
