"""The `DANO`: a density field's dynamics (mass, centre of mass, inertia) and contact samples."""

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from dano.errors import InvalidMassError, InvalidValueError
from dano.validate import inertia_tensor


class DANO(eqx.Module):
    """A Dynamics-Augmented Neural Object (paper Sec. IV), a frozen pytree.

    All vectors are in the object's own frame (the frame of the density field), SI units. The body
    frame used in simulation is this frame shifted to the centre of mass: `points - com`.

    Attributes:
        mass: () total mass m = alpha * int phi (eq. 2), kg.
        com: (3,) centre of mass (eq. 3), m.
        inertia: (3, 3) inertia tensor about the centre of mass, sum m (|r|^2 I - r r^T)
            with r = x - com (eq. 4 taken about the centre of mass), kg m^2.
        points: (n, 3) candidate surface points whose density lies in `window`, m.
        densities: (n,) phi at `points`, in the field's own units (unscaled by alpha).
        normals: (n, 3) outward unit normals -grad phi / |grad phi| at `points`.
        alpha: () mass scale of eq. 1, kg per (density unit * m^3).
        window: (2,) density window [low, high] the points were drawn from.
        mass_stderr: () standard error of the Monte Carlo mass, kg (0 if exact or unknown).
        com_stderr: (3,) standard error of `com`, m.
        inertia_stderr: (3, 3) standard error of `inertia`, kg m^2.
        source: where the DANO came from (file, spec), for the record.
        peak: () the field's robust peak density (its "fully inside" level), or None.
        grid: (nx, ny, nz) the field baked on a grid over `grid_bounds`, for contact with other
            DANOs without querying the original field (None when the field is unknown).
        grid_bounds: ((3,), (3,)) box of `grid`, object frame, m.
    """

    mass: Float[Array, ""]
    com: Float[Array, " 3"]
    inertia: Float[Array, "3 3"]
    points: Float[Array, "n 3"]
    densities: Float[Array, " n"]
    normals: Float[Array, "n 3"]
    alpha: Float[Array, ""]
    window: Float[Array, " 2"]
    mass_stderr: Float[Array, ""]
    com_stderr: Float[Array, " 3"]
    inertia_stderr: Float[Array, "3 3"]
    source: str = eqx.field(static=True, default="")
    peak: Float[Array, ""] | None = None
    grid: Float[Array, "nx ny nz"] | None = None
    grid_bounds: tuple[tuple[float, float, float], tuple[float, float, float]] | None = eqx.field(
        static=True, default=None
    )

    def __check_init__(self):
        n = self.points.shape[0]
        shapes = {
            "mass": (self.mass.shape, ()),
            "com": (self.com.shape, (3,)),
            "inertia": (self.inertia.shape, (3, 3)),
            "points": (self.points.shape, (n, 3)),
            "densities": (self.densities.shape, (n,)),
            "normals": (self.normals.shape, (n, 3)),
            "alpha": (self.alpha.shape, ()),
            "window": (self.window.shape, (2,)),
        }
        for name, (got, want) in shapes.items():
            if got != want:
                raise ValueError(f"DANO.{name} must have shape {want}, got {got}")
        if not isinstance(self.mass, jax.core.Tracer) and not (np.isfinite(self.mass) and self.mass > 0):
            raise InvalidMassError(f"mass must be positive and finite, got {float(self.mass)}")
        if not isinstance(self.inertia, jax.core.Tracer):
            inertia_tensor(self.inertia, "DANO.inertia", InvalidValueError)

    @property
    def n_points(self) -> int:
        return self.points.shape[0]

    @property
    def weights(self) -> Float[Array, " n"]:
        """Mass carried by each point, w_i = phi_i / sum phi * m (kg); they sum to the mass."""
        return self.densities / jnp.sum(self.densities) * self.mass

    @property
    def body_points(self) -> Float[Array, "n 3"]:
        """Points in the body frame (origin at the centre of mass), m."""
        return self.points - self.com[None, :]

    def principal_moments(self) -> Float[Array, " 3"]:
        """Eigenvalues of the inertia tensor, ascending, kg m^2."""
        return jnp.linalg.eigvalsh(self.inertia)

    def principal_extents(self) -> Float[Array, " 3"]:
        """The object's size along its principal axes (in `principal_moments` order), m: the spread
        of its surface points along each eigenvector of the inertia. Unlike the bounding box of the
        DANO's own frame, it does not grow when the field was built turned off the object's axes."""
        _, axes = jnp.linalg.eigh(self.inertia)
        along = self.body_points @ axes
        return jnp.max(along, axis=0) - jnp.min(along, axis=0)

    def with_mass(self, mass: float) -> "DANO":
        """The same object with its mass scale chosen so that the total mass is `mass` (kg)."""
        if not (np.isfinite(mass) and mass > 0):
            raise InvalidMassError(f"mass must be positive and finite, got {mass}")
        k = mass / self.mass
        return eqx.tree_at(
            lambda d: (d.mass, d.inertia, d.alpha, d.mass_stderr, d.inertia_stderr),
            self,
            (self.mass * k, self.inertia * k, self.alpha * k, self.mass_stderr * k, self.inertia_stderr * k),
        )
