"""The density-field interface.

A field maps points `(n, 3)` in the object's own frame (m) to non-negative densities `(n,)` and knows
an axis-aligned box, `bounds`, outside of which it is zero. Fields are `eqx.Module`s: frozen pytrees
whose array leaves are the parameters (so `jax.grad` reaches them) and whose box is static.
"""

import abc
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from dano.errors import FieldError, NonFiniteFieldError

Bounds = tuple[tuple[float, float, float], tuple[float, float, float]]
"""((x_lo, y_lo, z_lo), (x_hi, y_hi, z_hi)) in the field's frame, m."""


def as_bounds(bounds: ArrayLike | Bounds | Sequence[Sequence[float]]) -> Bounds:
    """Checks and converts a `(2, 3)` array-like box to the hashable `Bounds` tuple."""
    b = np.asarray(bounds, dtype=np.float64)
    if b.shape != (2, 3):
        raise FieldError(f"bounds must have shape (2, 3) (low corner, high corner), got {b.shape}")
    if not np.all(np.isfinite(b)) or not np.all(b[1] > b[0]):
        raise FieldError(f"bounds need finite corners with high > low on every axis, got {b.tolist()}")
    lo, hi = b
    return (tuple(float(v) for v in lo), tuple(float(v) for v in hi))  # type: ignore[return-value]


class AbstractField(eqx.Module):
    """A density field phi: R^3 -> R_+ (paper eq. 1 before the mass scale alpha)."""

    if TYPE_CHECKING:
        # At run time an `AbstractVar` makes no dataclass field: a subclass's own `bounds` field
        # keeps its place in `__init__` (`CallableField(fn, bounds)`). Type checkers read it as a
        # field of this class, first in every subclass's `__init__`; a read-only property promises
        # the attribute without making a field.
        @property
        def bounds(self) -> Bounds: ...
    else:
        bounds: eqx.AbstractVar[Bounds]

    @abc.abstractmethod
    def __call__(self, x: Float[Array, "n 3"]) -> Float[Array, " n"]:
        """Densities at points `x` (object frame, m)."""

    @property
    def box_volume(self) -> float:
        """Volume of the bounding box, m^3."""
        lo, hi = np.asarray(self.bounds)
        return float(np.prod(hi - lo))


class CallableField(AbstractField):
    """Any user function `fn(x: (n, 3)) -> (n,)` with the box that contains its object.

    `fn` may be a plain function or an `eqx.Module` (its arrays are then parameters that
    `eqx.filter_grad` reaches).

    Example:
        >>> field = CallableField(lambda x: 1e3 * (jnp.sum(x**2, -1) < 0.01), ((-.1,) * 3, (.1,) * 3))
    """

    fn: Callable[[Array], Array]
    bounds: Bounds = eqx.field(static=True, converter=as_bounds)

    def __call__(self, x: Float[Array, "n 3"]) -> Float[Array, " n"]:
        return self.fn(x)


class TransformedField(AbstractField):
    """`field` rigidly moved and uniformly scaled: phi'(x) = phi(R^T (x - t) / s).

    Lengths are multiplied by `scale`; densities keep their value, so the mass at a fixed mass
    scale grows as scale^3.
    """

    field: AbstractField
    rotation: Float[Array, "3 3"]
    translation: Float[Array, " 3"]
    scale: Float[Array, ""]
    bounds: Bounds = eqx.field(static=True)

    def __init__(
        self,
        field: AbstractField,
        rotation: Float[ArrayLike, "3 3"] | None = None,
        translation: Float[ArrayLike, " 3"] | None = None,
        scale: float = 1.0,
    ):
        if not scale > 0:
            raise FieldError(f"scale must be positive, got {scale}")
        self.field = field
        self.rotation = jnp.eye(3) if rotation is None else jnp.asarray(rotation)
        self.translation = jnp.zeros(3) if translation is None else jnp.asarray(translation)
        self.scale = jnp.asarray(scale, dtype=self.translation.dtype)
        lo, hi = np.asarray(field.bounds)
        corners = np.stack(np.meshgrid(*zip(lo, hi, strict=True), indexing="ij"), -1).reshape(-1, 3)
        moved = scale * corners @ np.asarray(self.rotation).T + np.asarray(self.translation)
        self.bounds = as_bounds(np.stack([moved.min(0), moved.max(0)]))

    def __call__(self, x: Float[Array, "n 3"]) -> Float[Array, " n"]:
        return self.field(((x - self.translation[None, :]) @ self.rotation) / self.scale)


def as_field(obj: AbstractField | Callable[[Array], Array], bounds: ArrayLike | Bounds | None = None):
    """Returns `obj` if it is a field, else wraps a callable with the given box."""
    if isinstance(obj, AbstractField):
        return obj
    if callable(obj):
        if bounds is None:
            raise FieldError("a plain callable needs bounds=(low corner, high corner) of its object")
        return CallableField(obj, bounds)
    raise FieldError(f"expected a density field or a callable, got {type(obj).__name__}")


@eqx.filter_jit
def _evaluate_chunk(field: AbstractField, x: Array) -> Array:
    return field(x)


def evaluate(field: AbstractField, x: ArrayLike, chunk: int = 65536) -> np.ndarray:
    """Host helper: densities at many points, in fixed-size jitted chunks, checked.

    Raises:
        NonFiniteFieldError: the field returned NaN or Inf.
        FieldError: the field returned a negative density or the wrong shape.
    """
    x = np.asarray(x)
    n = x.shape[0]
    out = []
    for start in range(0, n, chunk):
        part = x[start : start + chunk]
        pad = chunk - part.shape[0] if n > chunk else 0
        if pad:
            part = np.concatenate([part, np.repeat(part[-1:], pad, axis=0)])
        values = np.asarray(_evaluate_chunk(field, jnp.asarray(part)))
        out.append(values[: values.shape[0] - pad])
    values = np.concatenate(out) if out else np.zeros(0)
    check_densities(values, n)
    return values


def check_densities(values: np.ndarray, n: int) -> None:
    """Raises a named error if field output is not `(n,)`, finite and non-negative."""
    if values.shape != (n,):
        raise FieldError(f"a field must map (n, 3) points to (n,) densities, got shape {values.shape}")
    if not np.all(np.isfinite(values)):
        bad = int(np.sum(~np.isfinite(values)))
        raise NonFiniteFieldError(f"the field returned NaN or Inf at {bad} of {n} points")
    if np.any(values < 0):
        raise FieldError(f"the field returned negative densities (min {values.min():.3g}); densities must be >= 0")
