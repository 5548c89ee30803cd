"""Analytic density fields: sphere, box and capsule with a soft boundary.

phi(x) = peak * S(-d(x) / width), with d the signed distance (negative inside) and S the C2
smootherstep (`dano.math.smootherstep`), so the density ramps from `peak` at depth `width` to 0 at
distance `width` outside, and its half level is the exact surface.

They are the ground truth of the tests: `exact_mass_properties` is closed form. Because S is odd
about its midpoint, any integral linear in the density is an average over offset surfaces,

    int g(x) S(-d(x)/w) dx = int rho(t) G(t) dt,   G(t) = int_{d(x) <= t} g(x) dx,
    rho(t) = S'(-t/w) / w  (a bump on [-w, w] with unit mass),

and the offset bodies {d <= t} of a sphere, box or capsule have polynomial volume and second
moments in t (Steiner's formula). rho is a polynomial, so Gauss-Legendre on [-w, 0] and [0, w]
evaluates the t-integral exactly.
"""

import abc
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from dano.errors import FieldError, SpecError
from dano.fields.base import AbstractField, Bounds, as_bounds
from dano.math import safe_norm, smootherstep

_PI = np.pi
Scalar = float | Float[Array, ""]
"""A Python number or a 0-d array (possibly traced, for gradients w.r.t. shape parameters)."""


def _concrete(*values) -> bool:
    return not any(isinstance(v, jax.core.Tracer) for v in values)


def _positive(name: str, value) -> jax.Array:
    value = jnp.asarray(value)
    if _concrete(value) and not (np.all(np.isfinite(value)) and np.all(np.asarray(value) > 0)):
        raise FieldError(f"{name} must be positive and finite, got {np.asarray(value).tolist()}")
    return value


class ExactMassProperties(eqx.Module):
    """Closed-form mass (kg), centre of mass (3,) and inertia about it (3, 3), object frame."""

    mass: Float[Array, ""]
    com: Float[Array, " 3"]
    inertia: Float[Array, "3 3"]


class _AnalyticField(AbstractField):
    """Shared soft-boundary law and closed-form integration; concrete shapes add geometry."""

    width: eqx.AbstractVar[Float[Array, ""]]
    peak: eqx.AbstractVar[Float[Array, ""]]

    @abc.abstractmethod
    def signed_distance(self, x: Float[Array, "n 3"]) -> Float[Array, " n"]:
        """Signed distance to the surface, negative inside, m."""

    @abc.abstractmethod
    def offset_moments(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Volume `(k,)` and second moments int x_i^2 `(k, 3)` of the offset bodies {d <= t}."""

    def __call__(self, x: Float[Array, "n 3"]) -> Float[Array, " n"]:
        return self.peak * smootherstep(-self.signed_distance(x) / self.width)

    def exact_mass_properties(self, alpha: float = 1.0) -> ExactMassProperties:
        """Closed-form mass properties of alpha * phi (paper eqs. 2-4, about the centre of mass)."""
        w = float(self.width)
        nodes, weights = np.polynomial.legendre.leggauss(8)
        t = np.concatenate([(nodes - 1) * w / 2, (nodes + 1) * w / 2])
        dt = np.concatenate([weights, weights]) * w / 2
        u = (1 - t / w) / 2  # smootherstep argument for S(-t/w)
        rho = 15 * u**2 * (1 - u) ** 2 / w
        volume, second = self.offset_moments(t)
        scale = alpha * float(self.peak)
        mass = scale * np.sum(dt * rho * volume)
        sx, sy, sz = scale * np.sum((dt * rho)[:, None] * second, axis=0)
        inertia = np.diag([sy + sz, sx + sz, sx + sy])
        return ExactMassProperties(jnp.asarray(mass), jnp.zeros(3), jnp.asarray(inertia))


class SphereField(_AnalyticField):
    """A ball of `radius` (m) centred at the origin."""

    radius: Float[Array, ""]
    width: Float[Array, ""]
    peak: Float[Array, ""]
    bounds: Bounds = eqx.field(static=True)

    def __init__(self, radius: Scalar, width: Scalar | None = None, peak: Scalar = 1000.0, bounds=None):
        self.radius = _positive("radius", radius)
        self.width = _positive("width", 0.05 * radius if width is None else width)
        self.peak = _positive("peak", peak)
        if bounds is None:
            _check_width(self.width, self.radius)
            bounds = np.full((2, 3), float(self.radius + self.width)) * [[-1], [1]]
        self.bounds = as_bounds(bounds)

    def signed_distance(self, x: Float[Array, "n 3"]) -> Float[Array, " n"]:
        return safe_norm(x) - self.radius

    def offset_moments(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r = float(self.radius) + t
        return 4 * _PI / 3 * r**3, np.repeat((4 * _PI / 15 * r**5)[:, None], 3, axis=1)


class BoxField(_AnalyticField):
    """A box of full edge lengths `size` (3,) (m) centred at the origin, edges along the axes."""

    half_size: Float[Array, " 3"]
    width: Float[Array, ""]
    peak: Float[Array, ""]
    bounds: Bounds = eqx.field(static=True)

    def __init__(
        self, size: Sequence[float] | ArrayLike, width: Scalar | None = None, peak: Scalar = 1000.0, bounds=None
    ):
        size = jnp.asarray(size)
        if size.shape != (3,):
            raise FieldError(f"box size must have 3 entries (x, y, z edge lengths), got shape {size.shape}")
        self.half_size = _positive("box size", size) / 2
        self.width = _positive("width", 0.05 * jnp.min(self.half_size) if width is None else width)
        self.peak = _positive("peak", peak)
        if bounds is None:
            _check_width(self.width, jnp.min(self.half_size))
            hi = np.asarray(self.half_size + self.width)
            bounds = np.stack([-hi, hi])
        self.bounds = as_bounds(bounds)

    def signed_distance(self, x: Float[Array, "n 3"]) -> Float[Array, " n"]:
        q = jnp.abs(x) - self.half_size[None, :]
        return safe_norm(jnp.maximum(q, 0.0)) + jnp.minimum(jnp.max(q, axis=-1), 0.0)

    def offset_moments(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        size = 2 * np.asarray(self.half_size, dtype=np.float64)
        volume = np.where(t < 0, np.prod(size + 2 * t[:, None], axis=1), _rounded_box_volume(size, t))
        second = np.stack(
            [
                np.where(
                    t < 0,
                    (size[i] + 2 * t) ** 3 * np.prod(np.delete(size, i) + 2 * t[:, None], axis=1) / 12,
                    _rounded_box_second_moment(size[i], *np.delete(size, i), t=t),
                )
                for i in range(3)
            ],
            axis=1,
        )
        return volume, second


def _rounded_box_volume(size: np.ndarray, t: np.ndarray) -> np.ndarray:
    a, b, c = size
    return a * b * c + 2 * t * (a * b + b * c + c * a) + _PI * t**2 * (a + b + c) + 4 * _PI / 3 * t**3


def _rounded_box_second_moment(a: float, b: float, c: float, t: np.ndarray) -> np.ndarray:
    """int x^2 over the box (a along x; b, c the others) dilated by a ball of radius t >= 0.

    Pieces: the core, 6 face slabs, 12 quarter-cylinder edges, 8 eighth-ball corners.
    """
    core = a**3 * b * c / 12
    faces = 2 * b * c * ((a / 2 + t) ** 3 - (a / 2) ** 3) / 3 + 2 * t * (b + c) * a**3 / 12
    quarter_disk = (a**2 / 4) * (_PI * t**2 / 4) + a * t**3 / 3 + _PI * t**4 / 16
    edges = _PI * t**2 * a**3 / 12 + 4 * (b + c) * quarter_disk
    corners = 8 * ((a**2 / 4) * (_PI * t**3 / 6) + a * _PI * t**4 / 16 + _PI * t**5 / 30)
    return core + faces + edges + corners


class CapsuleField(_AnalyticField):
    """A capsule along z: the points within `radius` of the segment z in [-half_length, half_length]."""

    radius: Float[Array, ""]
    half_length: Float[Array, ""]
    width: Float[Array, ""]
    peak: Float[Array, ""]
    bounds: Bounds = eqx.field(static=True)

    def __init__(
        self, radius: Scalar, half_length: Scalar, width: Scalar | None = None, peak: Scalar = 1000.0, bounds=None
    ):
        self.radius = _positive("radius", radius)
        self.half_length = _positive("half_length", half_length)
        self.width = _positive("width", 0.05 * radius if width is None else width)
        self.peak = _positive("peak", peak)
        if bounds is None:
            _check_width(self.width, self.radius)
            r = float(self.radius + self.width)
            hi = np.array([r, r, r + float(self.half_length)])
            bounds = np.stack([-hi, hi])
        self.bounds = as_bounds(bounds)

    def signed_distance(self, x: Float[Array, "n 3"]) -> Float[Array, " n"]:
        z = jnp.clip(x[:, 2], -self.half_length, self.half_length)
        closest = jnp.stack([jnp.zeros_like(z), jnp.zeros_like(z), z], axis=-1)
        return safe_norm(x - closest) - self.radius

    def offset_moments(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r, h = float(self.radius) + t, float(self.half_length)
        volume = 2 * h * _PI * r**2 + 4 * _PI / 3 * r**3
        sxx = 2 * h * _PI * r**4 / 4 + 4 * _PI / 15 * r**5
        hemisphere_z2 = h**2 * (2 * _PI * r**3 / 3) + 2 * h * (_PI * r**4 / 4) + 2 * _PI / 15 * r**5
        szz = _PI * r**2 * (2 * h) ** 3 / 12 + 2 * hemisphere_z2
        return volume, np.stack([sxx, sxx, szz], axis=1)


def _check_width(width, half_extent) -> None:
    if _concrete(width, half_extent) and float(width) > float(half_extent):
        raise FieldError(
            f"boundary width {float(width):.4g} exceeds the shape's smallest half-extent {float(half_extent):.4g}"
        )


_SHAPES = {"sphere": SphereField, "box": BoxField, "capsule": CapsuleField}

_KEYS = {
    "sphere": {"r": "radius", "radius": "radius"},
    "box": {"size": "size"},
    "capsule": {"r": "radius", "radius": "radius", "half_length": "half_length", "h": "half_length"},
}
_COMMON = {"width": "width", "peak": "peak"}


def is_spec(text: str) -> bool:
    """True if `text` looks like an analytic spec (`sphere:...`, `box:...`, `capsule:...`)."""
    return text.split(":", 1)[0] in _SHAPES and ":" in text


def from_spec(spec: str) -> _AnalyticField:
    """Builds an analytic field from a spec string (lengths in m, peak density in kg/m^3 at alpha=1).

    Examples: `sphere:r=0.05`, `box:size=0.1,0.06,0.03,width=0.002`,
    `capsule:r=0.02,half_length=0.05,peak=800`.

    Raises:
        SpecError: unknown shape or key, a missing or non-numeric value.
    """
    shape, _, body = spec.partition(":")
    if shape not in _SHAPES or not body:
        raise SpecError(
            f"cannot parse field spec {spec!r}: expected one of {sorted(_SHAPES)} followed by ':key=value,...'"
        )
    keys = _KEYS[shape] | _COMMON
    values: dict[str, list[float]] = {}
    current = None
    for token in body.split(","):
        key, eq, value = token.partition("=")
        if eq:
            if key.strip() not in keys:
                raise SpecError(f"unknown key {key.strip()!r} in {spec!r}; {shape} takes {sorted(keys)}")
            current = keys[key.strip()]
            values[current] = []
        elif current is None:
            raise SpecError(f"cannot parse {token!r} in {spec!r}: expected key=value")
        else:
            value = key
        try:
            values[current].append(float(value))  # type: ignore[index]
        except ValueError:
            raise SpecError(f"value {value!r} in {spec!r} is not a number") from None
    kwargs: dict[str, object] = {k: (v if k == "size" else _one(k, v, spec)) for k, v in values.items()}
    try:
        return _SHAPES[shape](**kwargs)  # type: ignore[arg-type]
    except TypeError as e:
        raise SpecError(f"{spec!r}: {e}") from None


def _one(key: str, values: list[float], spec: str) -> float:
    if len(values) != 1:
        raise SpecError(f"{key} in {spec!r} takes one number, got {len(values)}")
    return values[0]
