"""The contact wrench (paper eqs. 11-16) from an overlap and the bodies' velocities.

With u the velocity of the contact point of the DANO relative to the other body, Omega their
relative angular velocity (world), and n the normal from the other body towards the DANO:

    F_imp = psi (k n - c_d u_n)                            spring k (m/s^2), damper c_d (1/s)
    F_t   = -d_s |F_imp| u_t + mu_s |F_imp| C(u_t)          sliding drag d_s (s/m), friction mu_s
    tau_n = -d_t |F_imp| Omega_n + mu_t |F_imp| C(Omega_n)  torsional drag/friction
    tau_t = -d_r |F_imp| Omega_t + mu_r |F_imp| C(Omega_t)  rolling drag/friction
    F = F_imp + F_t,  tau = tau_n + tau_t + (chi - x) x F   (about the centre of mass x, world)

C(a) = -(2/pi) atan(s |a|) a / (eps + |a|) is the smoothed Coulomb direction of the reference:
it tends to -a/|a| for |a| >> 1/s and is smooth at a = 0, so gradients exist at zero slip.
Units follow the reference: psi is the overlapping mass in kg, so k is a force per kg.
"""

import dataclasses

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from dano.errors import InvalidValueError
from dano.math import safe_norm
from dano.validate import is_traced

Scalar = float | Float[Array, ""]


def _as_leaf(value):
    if value is None or isinstance(value, str | bytes | bool):
        raise InvalidValueError(f"contact parameters are numbers, got {value!r}")
    return jnp.asarray(value, dtype=jnp.result_type(float))


def _param(default: float):
    """A scalar parameter leaf: a Python float or an array (traced, for gradients), stored as an array."""
    return eqx.field(default=default, converter=_as_leaf)


_POSITIVE = ("coulomb_regularizer", "stiction_velocity")
"""Parameters that divide: they must be > 0; every other one must be >= 0."""


class ContactParams(eqx.Module):
    """Per-pair contact parameters (paper Table I); every one is a differentiable leaf.

    Defaults are the scene file's documented defaults; Table I gives their useful ranges.
    """

    impact_spring: Scalar = _param(3e4)
    """k, N per kg of overlap (m/s^2); Table I 1e4-1e5."""
    impact_damper: Scalar = _param(3e5)
    """c_d, 1/s; Table I 1e5-1e6."""
    sliding_friction: Scalar = _param(0.5)
    """mu_s, dimensionless; Table I 0-1."""
    sliding_drag: Scalar = _param(0.0)
    """d_s, s/m; Table I 0-0.1."""
    rolling_friction: Scalar = _param(0.01)
    """mu_r, m (torque per newton); Table I 0-0.1."""
    rolling_drag: Scalar = _param(0.0)
    """d_r, m s; Table I 0-0.1."""
    torsional_friction: Scalar = _param(0.01)
    """mu_t, m; Table I 0-0.1."""
    torsional_drag: Scalar = _param(0.0)
    """d_t, m s; Table I 0-0.1."""
    coulomb_smoothing: Scalar = _param(30.0)
    """s of C(a), s/m: slip speeds well above 1/s feel full dry friction."""
    coulomb_regularizer: Scalar = _param(1e-3)
    """eps of C(a), m/s."""
    coulomb_gain: Scalar = _param(2 / 3.141592653589793)
    """g of C(a) = -g atan(s|a|) a / (eps + |a|): 2/pi saturates at 1. The reference's stored
    trajectories were made with g = 1 (dry friction pi/2 times the nominal coefficient)."""
    indicator_width: Scalar = _param(5e-4)
    """delta of the smooth inside test, m; 0 is the paper's hard indicator."""
    stiction_velocity: Scalar = _param(1e-5)
    """v_s of the implicit step's friction law, m/s (and rad/s for spin): below it friction is
    viscous, above it Coulomb's (see `dano.contact.friction`); a body held by friction creeps at
    about v_s. The explicit step uses `coulomb_smoothing` and `coulomb_regularizer` instead."""

    def __check_init__(self):
        """Every concrete value finite and non-negative (`_POSITIVE` ones > 0): a negative friction
        or spring feeds energy in, a NaN poisons every contact. Traced values (inside `jit`, `grad`)
        are not checked here."""
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if is_traced(value):
                continue
            x = np.asarray(value)
            bad = ~np.isfinite(x) | ((x <= 0) if f.name in _POSITIVE else (x < 0))
            if np.any(bad):
                shown = x if x.ndim == 0 else x[bad][:3]
                sign = "> 0" if f.name in _POSITIVE else ">= 0"
                raise InvalidValueError(f"contact parameter {f.name} must be finite and {sign}, got {shown}")


class Wrench(eqx.Module):
    """Force (3,) N and torque about the centre of mass (3,) N m, world frame."""

    force: Float[Array, " 3"]
    torque: Float[Array, " 3"]


def coulomb_direction(
    a: Float[Array, "3 ..."], smoothing, regularizer, gain: float | Array = 2 / jnp.pi
) -> Float[Array, "3 ..."]:
    """C(a) = -g atan(s|a|) a / (eps + |a|), g = 2/pi by default; vectors along axis 0."""
    norm = safe_norm(a, axis=0)[None]
    return -gain * jnp.arctan(smoothing * norm) * a / (regularizer + norm)


def _split(a: Float[Array, "3 ..."], n: Float[Array, "3 ..."]):
    normal = jnp.sum(a * n, axis=0, keepdims=True) * n
    return normal, a - normal


def sliding_force(
    p: ContactParams, psi: Float[Array, "..."], normal: Float[Array, "3 ..."], u: Float[Array, "3 ..."]
) -> tuple[Float[Array, "3 ..."], Float[Array, "..."]]:
    """Normal and sliding force (eqs. 11-12) and |F_imp|; vectors along axis 0 ((3,) or (3, n))."""
    u_n, u_t = _split(u, normal)
    f_imp = psi[None] * (p.impact_spring * normal - p.impact_damper * u_n)
    mag = safe_norm(f_imp, axis=0)
    c = coulomb_direction(u_t, p.coulomb_smoothing, p.coulomb_regularizer, p.coulomb_gain)
    return f_imp + mag[None] * (-p.sliding_drag * u_t + p.sliding_friction * c), mag


def spin_torque(
    p: ContactParams, magnitude: Float[Array, "..."], normal: Float[Array, "3 ..."], omega: Float[Array, "3 ..."]
) -> Float[Array, "3 ..."]:
    """Torsional and rolling friction torques (eqs. 13-14) for normal-force magnitudes `magnitude`."""
    w_n, w_t = _split(omega, normal)
    c = lambda a: coulomb_direction(a, p.coulomb_smoothing, p.coulomb_regularizer, p.coulomb_gain)  # noqa: E731
    return magnitude[None] * (
        -p.torsional_drag * w_n + p.torsional_friction * c(w_n) - p.rolling_drag * w_t + p.rolling_friction * c(w_t)
    )


def contact_wrench(
    p: ContactParams,
    psi: Float[Array, " k"],
    at: Float[Array, "3 k"],
    normal: Float[Array, "3 kn"],
    com: Float[Array, " 3"],
    velocity: Float[Array, " 3"],
    angular_velocity: Float[Array, " 3"],
    other_com: Float[Array, " 3"],
    other_velocity: Float[Array, " 3"],
    other_angular_velocity: Float[Array, " 3"],
) -> Wrench:
    """The wrench of eqs. 11-16 on a DANO from overlaps `psi` (kg) at world points `at`.

    With k = 1 and `at` the overlap centroid chi this is the paper's wrench; with the sampled points
    and their shares of the overlap, the per-point version. `normal` is (3, k), or (3, 1) for one
    normal shared by all points (then the spin torques add up before the Coulomb law).

    Args:
        p: contact parameters.
        psi, at, normal: overlaps (k,), points (3, k) and normals (3, k) or (3, 1), world frame.
        com, velocity, angular_velocity: the DANO's centre of mass (m), velocity (m/s), angular
            velocity (rad/s), world frame.
        other_com, other_velocity, other_angular_velocity: the same for the other body (zeros for
            the static ground).

    Returns:
        The force (N) and the torque about `com` (N m), world frame.
    """
    r = at - com[:, None]
    u = velocity[:, None] + jnp.cross(angular_velocity[:, None], r, axis=0)
    u = u - other_velocity[:, None] - jnp.cross(other_angular_velocity[:, None], at - other_com[:, None], axis=0)
    f, magnitude = sliding_force(p, psi, normal, u)
    if normal.shape[1] == 1:
        magnitude = jnp.sum(magnitude)[None]
    tau = spin_torque(p, magnitude, normal, (angular_velocity - other_angular_velocity)[:, None])
    force = jnp.sum(f, axis=1)
    return Wrench(force, jnp.sum(tau, axis=1) + jnp.sum(jnp.cross(r, f, axis=0), axis=1))
