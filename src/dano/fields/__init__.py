"""Density fields phi: (n, 3) points in the object frame (m) -> (n,) non-negative densities."""

from dano.fields.analytic import BoxField, CapsuleField, ExactMassProperties, SphereField, from_spec, is_spec
from dano.fields.base import AbstractField, Bounds, CallableField, TransformedField, as_field, evaluate
from dano.fields.grid import GridField, as_grid, load_grid, save_grid
from dano.fields.mesh import MESH_SUFFIXES, load_mesh, mesh_field, repair_mesh
from dano.fields.neural import (
    NeuralField,
    NeuralFieldConfig,
    distill,
    load_neural_field,
    save_neural_field,
)

__all__ = [
    "AbstractField", "Bounds", "BoxField", "CallableField", "CapsuleField", "ExactMassProperties",
    "GridField", "MESH_SUFFIXES", "NeuralField", "NeuralFieldConfig", "SphereField", "TransformedField",
    "as_field", "as_grid", "distill", "evaluate", "from_spec", "is_spec", "load_grid", "load_mesh",
    "load_neural_field", "mesh_field", "repair_mesh", "save_grid", "save_neural_field",
]  # fmt: skip
