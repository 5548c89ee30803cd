"""The settings of fitting (`FitConfig`, with its back-ends `GridModel` and `MlpModel`) and tracking
(`TrackConfig`), and their errors: plain frozen data, checked when made, that imports no JAX (the
command line builds its options from them, `dano.cli.configs`)."""

import dataclasses
import enum
from typing import TYPE_CHECKING

import numpy as np

from dano import validate as V
from dano.errors import DanoError

if TYPE_CHECKING:
    from jaxtyping import PRNGKeyArray

    from dano.vision.fit import AbstractRadiance


class FitError(DanoError):
    """The views cannot be fitted (no masks and no bounds, a visual hull that is empty, bad settings)."""


@dataclasses.dataclass(frozen=True)
class GridModel:
    """A voxel grid of density and colour, trilinear (seconds per thousand steps on a CPU).

    Attributes:
        resolution: grid nodes along the box's longest side.
        smoothness: weight of the grid's total variation (mean squared difference of neighbouring
            nodes' raw density), which keeps unseen space and the inside free of noise.
    """

    resolution: int = 64
    smoothness: float = 1e-4

    def __post_init__(self):
        V.settings(self, FitError, whole={"resolution": 4}, nonnegative=["smoothness"])

    def init(self, bounds: np.ndarray, scale: float, key: "PRNGKeyArray") -> "AbstractRadiance":
        """Nearly transparent (raw density -4: sigma ~ 2 % of `scale`)."""
        import jax.numpy as jnp

        from dano.vision.fit import VoxelRadiance

        lo, hi = bounds
        shape = tuple(max(2, int(round(self.resolution * e / (hi - lo).max()))) for e in hi - lo)
        return VoxelRadiance(jnp.full(shape, -4.0), jnp.zeros((*shape, 3)), scale, np.stack([lo, hi]))

    @property
    def regularisation(self) -> float:
        return self.smoothness


@dataclasses.dataclass(frozen=True)
class MlpModel:
    """A `NeuralField` and a colour network (smooth, ~10x slower to train than a grid; a learning
    rate ~5e-3 suits it).

    Attributes:
        width, depth, n_frequencies: the density network (`NeuralFieldConfig`); the colour network
            is as wide.
    """

    width: int = 64
    depth: int = 3
    n_frequencies: int = 5

    def __post_init__(self):
        V.settings(self, FitError, whole={"width": 1, "depth": 1, "n_frequencies": 0})

    def init(self, bounds: np.ndarray, scale: float, key: "PRNGKeyArray") -> "AbstractRadiance":
        """Nearly transparent (last bias -4: sigma ~ 2 % of `scale`)."""
        import equinox as eqx
        import jax
        import jax.numpy as jnp

        from dano.fields import NeuralField
        from dano.fields.neural import NeuralFieldConfig
        from dano.vision.fit import RadianceField

        net = NeuralFieldConfig(width=self.width, depth=self.depth, n_frequencies=self.n_frequencies,
                                density_scale=scale)  # fmt: skip
        k1, k2 = jax.random.split(key)
        density = NeuralField(np.asarray(bounds), net, key=k1)
        bias = density.mlp.layers[-1].bias
        assert bias is not None  # the MLP of a `NeuralField` has biases
        density = eqx.tree_at(lambda f: f.mlp.layers[-1].bias, density, jnp.full_like(bias, -4.0))
        colour = eqx.nn.MLP(3 + 6 * self.n_frequencies, 3, self.width, 2, activation=jax.nn.softplus, key=k2)
        return RadianceField(density, colour)

    @property
    def regularisation(self) -> float:
        return 0.0


class Precision(enum.StrEnum):
    """A floating-point type to train in."""

    float32 = "float32"
    float64 = "float64"


MODELS = {"grid": GridModel, "mlp": MlpModel}
"""The fitting back-ends by name (`FitConfig.model` may name one with its defaults)."""


@dataclasses.dataclass(frozen=True)
class FitConfig:
    """Training settings.

    Attributes:
        model: the back-end and its own settings: `GridModel()` (default; or "grid") or `MlpModel()`
            (or "mlp").
        steps: optimiser steps.
        batch_rays: rays per step.
        n_samples: samples per ray, evenly spread over the ray's path through the box.
        learning_rate: Adam's initial rate (cosine decay to 5 % of it); ~0.1 for a grid, ~5e-3 for an MLP.
        mask_weight: weight of the opacity-vs-mask term.
        opaque_samples: the density scale is set so that `opaque_samples` samples of a unit network
            output make a ray 63 % opaque; it only sets the units the model starts in.
        dtype: training precision ("float32" is twice as fast on a CPU as "float64"); the result
            is returned in JAX's default float type.
    """

    model: GridModel | MlpModel | str = GridModel()
    steps: int = 1000
    batch_rays: int = 2048
    n_samples: int = 128
    learning_rate: float = 0.1
    mask_weight: float = 1.0
    opaque_samples: float = 0.5
    dtype: Precision | str = Precision.float32

    def __post_init__(self):
        whole = {"steps": 1, "batch_rays": 1, "n_samples": 2}
        V.settings(
            self, FitError, whole=whole, positive=["learning_rate", "opaque_samples"], nonnegative=["mask_weight"]
        )
        object.__setattr__(self, "dtype", V.option(self.dtype, "dtype", FitError, Precision))
        if isinstance(self.model, str):
            if self.model not in MODELS:
                raise FitError(f"model must be one of {', '.join(map(repr, MODELS))}, got {self.model!r}")
            object.__setattr__(self, "model", MODELS[self.model]())  # a frozen field, normalised
        elif not isinstance(self.model, GridModel | MlpModel):
            raise FitError(f"model must be a GridModel, an MlpModel or its name, got {type(self.model).__name__}")


class TrackError(DanoError):
    """Tracking cannot run: masks and camera disagree, an empty mask, bad settings."""


@dataclasses.dataclass(frozen=True)
class TrackConfig:
    """Tracker settings.

    Attributes:
        iterations: Adam steps per frame after the first.
        first_iterations: Adam steps for the first frame (from the initial guess).
        learning_rate: Adam's rate on the pose increment; positions are in units of the object's
            radius and rotations in radians, so one rate suits both.
        n_samples: samples per ray through the object's bounding sphere.
        barycentre_weight: weight of the barycentre term.
        max_size: the tracker looks at a window around the object (`windows`); the masks are
            box-averaged down until the window's longest side is at most this (pixels).
        grid: nodes along each side of the baked field grid.
        refine_iterations: Adam steps of the joint refinement over all frames (0: none).
        smoothness: weight of the acceleration penalty in the refinement (per frame, in radius units).
    """

    iterations: int = 60
    first_iterations: int = 300
    learning_rate: float = 0.02
    n_samples: int = 48
    barycentre_weight: float = 1.0
    max_size: int = 128
    grid: int = 128
    refine_iterations: int = 0
    smoothness: float = 1.0

    def __post_init__(self):
        whole = {
            "iterations": 1,
            "first_iterations": 1,
            "n_samples": 2,
            "max_size": 8,
            "grid": 4,
            "refine_iterations": 0,
        }
        V.settings(
            self, TrackError, whole=whole, positive=["learning_rate"], nonnegative=["barycentre_weight", "smoothness"]
        )
