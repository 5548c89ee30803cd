"""Mass, centre of mass and inertia of alpha * phi by randomised quasi-Monte Carlo (eqs. 1-4).

The box of the field is filled with `replicates` independently scrambled Sobol sets. The estimate
pools all of them; the spread between replicates gives an honest standard error (each replicate is
an unbiased estimate, which plain Sobol points are not). Moments are taken about the box centre and
the inertia is the true tensor about the centre of mass, sum m (|r|^2 I - r r^T), r = x - com;
the reference implementation stored the second moment sum m r r^T instead (see README).
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from dano.errors import EmptyFieldError, FieldError, InvalidMassError, NonFiniteFieldError
from dano.fields.base import AbstractField
from dano.sampling import sobol_unit, to_box


class MassProperties(eqx.Module):
    """Monte Carlo mass properties and their standard errors, object frame, SI units."""

    mass: Float[Array, ""]
    com: Float[Array, " 3"]
    inertia: Float[Array, "3 3"]
    alpha: Float[Array, ""]
    mass_stderr: Float[Array, ""]
    com_stderr: Float[Array, " 3"]
    inertia_stderr: Float[Array, "3 3"]


def sample_points(field: AbstractField, log2_samples: int = 15, replicates: int = 8, seed: int = 0) -> np.ndarray:
    """`(replicates, 2**log2_samples, 3)` scrambled Sobol points filling the field's box."""
    return np.stack([to_box(sobol_unit(log2_samples, seed, r), field.bounds) for r in range(replicates)])


def _moments(field: AbstractField, x: Float[Array, "m 3"], centre: Array, volume: float):
    """Raw moments of phi over one replicate: int phi, int phi r, int phi r r^T, r = x - centre[None, :]."""
    phi = field(x)
    r = x - centre[None, :]
    m0 = volume * jnp.mean(phi)
    m1 = volume * jnp.mean(phi[:, None] * r, axis=0)
    m2 = volume * jnp.einsum("n,ni,nj->ij", phi, r, r) / x.shape[0]
    # NaN/Inf become -inf before the min: XLA's CPU min reduction can drop a NaN (a field NaN in part
    # of its box then read as "zero everywhere"), while -inf always survives it.
    return m0, m1, m2, jnp.min(jnp.where(jnp.isfinite(phi), phi, -jnp.inf))


def _properties(m0, m1, m2, centre, alpha):
    c = m1 / m0
    cov = m2 / m0 - jnp.outer(c, c)
    mass = alpha * m0
    inertia = mass * (jnp.trace(cov) * jnp.eye(3) - cov)
    return mass, c + centre, inertia


def mass_properties_from_points(
    field: AbstractField,
    points: Float[Array | np.ndarray, "r m 3"],
    alpha: float | Array | None = 1.0,
    mass: float | Array | None = None,
) -> tuple[MassProperties, Array]:
    """Pure, jit- and grad-able core of `mass_properties` for given sample points.

    Args:
        field: the density field phi.
        points: replicate sets of points filling `field.bounds` uniformly.
        alpha: mass scale (eq. 1). Ignored when `mass` is given.
        mass: total mass in kg; fixes alpha = mass / int phi.

    Returns:
        The properties, and the smallest density seen (for validation).
    """
    points = jnp.asarray(points)
    lo, hi = (jnp.asarray(b, dtype=points.dtype) for b in field.bounds)
    centre = (lo + hi) / 2
    volume = float(np.prod(np.asarray(field.bounds[1]) - np.asarray(field.bounds[0])))
    m0, m1, m2, low = jax.lax.map(lambda x: _moments(field, x, centre, volume), points)

    def scale_for(m0_):
        return mass / m0_ if mass is not None else jnp.asarray(alpha, dtype=points.dtype)

    pooled_m0 = jnp.mean(m0)
    m, com, inertia = _properties(pooled_m0, jnp.mean(m1, 0), jnp.mean(m2, 0), centre, scale_for(pooled_m0))
    each = jax.vmap(lambda a, b, c: _properties(a, b, c, centre, scale_for(a)))(m0, m1, m2)
    n = points.shape[0]
    stderr = [jnp.std(e, axis=0, ddof=1) / np.sqrt(n) for e in each]
    props = MassProperties(m, com, inertia, scale_for(pooled_m0), *stderr)
    return props, jnp.min(low)


def mass_properties(
    field: AbstractField,
    *,
    alpha: float | None = 1.0,
    mass: float | None = None,
    log2_samples: int = 15,
    replicates: int = 8,
    seed: int = 0,
) -> MassProperties:
    """Monte Carlo mass properties of alpha * phi over the field's box (paper eqs. 1-4).

    Args:
        field: the density field.
        alpha: mass scale, kg per (density unit * m^3). Ignored when `mass` is given.
        mass: total mass in kg, which fixes alpha.
        log2_samples: each replicate has 2**log2_samples Sobol points.
        replicates: independently scrambled replicates (>= 2, for the standard error).
        seed: the scrambling seed; the same seed gives the same numbers.

    Raises:
        InvalidMassError: alpha or mass not positive and finite.
        EmptyFieldError: the field is zero everywhere in its box.
        NonFiniteFieldError: the field returned NaN or Inf.

    Example:
        >>> props = mass_properties(SphereField(radius=0.05), mass=1.0)
        >>> props.inertia  # ~ 2/5 m r^2 I
    """
    for name, value in (("alpha", alpha), ("mass", mass)):
        if value is not None and not (np.isfinite(value) and value > 0):
            raise InvalidMassError(f"{name} must be positive and finite, got {value}")
    if replicates < 2:
        raise ValueError(f"replicates must be >= 2 to estimate a standard error, got {replicates}")
    points = sample_points(field, log2_samples, replicates, seed)
    props, low = eqx.filter_jit(mass_properties_from_points)(field, points, alpha, mass)
    return _checked(props, low)


def _checked(props: MassProperties, low: Array) -> MassProperties:
    """Host-side validation of a concrete result (the low density rules out NaN and negatives first)."""
    if not np.isfinite(low):
        raise NonFiniteFieldError("the field returned NaN or Inf inside its box")
    if float(low) < 0:
        raise FieldError(f"the field returned a negative density ({float(low):.3g}); densities must be >= 0")
    if not (np.all(np.isfinite(props.com)) and float(props.mass) > 0):
        raise EmptyFieldError(
            "the field is zero everywhere in its box: no mass, no surface (check its bounds and scale)"
        )
    return props
