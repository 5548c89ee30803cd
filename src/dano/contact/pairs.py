"""One contact pair, one small function: where a DANO overlaps its partner, and how much.

Every pair kind (a half-space, a primitive, a robot link's geom, another DANO) reduces to the same
`PointSet`: world points, each with its overlap (kg) and a unit normal from the partner towards
the DANO. The wrench (eqs. 11-16) and the implicit step read only that, so a new partner kind is
one geometry function here and nothing else.

    "points" mode: every sampled point with its own share of the overlap (paper, limitation i);
    "centroid" mode: one point, the overlap centroid chi with the whole overlap psi (eqs. 7-10).
"""

import enum
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from dano.contact.overlap import HalfSpace, Primitive, expected_overlap, outward_normal
from dano.math import normalize, safe_norm


class ForceMode(enum.StrEnum):
    """Where a pair's contact force acts: `points` each sampled point's own force at the point;
    `centroid` the total at the overlap centroid χ, as in the paper (eq. 12)."""

    points = "points"
    centroid = "centroid"


class Frame(eqx.Module):
    """Pose and velocity of a rigid body, world frame: centre of mass x (3,), rotation R (3, 3),
    velocity v (3,), angular velocity w (3,)."""

    x: Float[Array, " 3"]
    R: Float[Array, "3 3"]
    v: Float[Array, " 3"]
    w: Float[Array, " 3"]


class Body(eqx.Module):
    """A DANO's contact data at the current scales.

    Attributes:
        points: (3, n) surface points, body frame (origin at the centre of mass), m.
        normals: (3, n) their outward normals, body frame.
        weights: (n,) kg, summing to the mass.
        mass: () kg.
        inertia: (3, 3) about the centre of mass, body frame, kg m^2.
        field: density field in the object frame (for other DANOs' points), or None.
        com: (3,) centre of mass in the object frame (to query `field`), m.
        peak: () the field's "fully inside" density.
    """

    points: Float[Array, "3 n"]
    normals: Float[Array, "3 n"]
    weights: Float[Array, " n"]
    mass: Float[Array, ""]
    inertia: Float[Array, "3 3"]
    field: Callable[[Array], Array] | None
    com: Float[Array, " 3"]
    peak: Float[Array, ""]

    def without_field(self) -> "Body":
        """The same body without its field: all that contact with a primitive needs, and what DANOs
        of different fields can be stacked as (`dano.sim.groups.member_lookup`)."""
        return Body(self.points, self.normals, self.weights, self.mass, self.inertia, None, self.com, self.peak)


class PointSet(eqx.Module):
    """Where a DANO touches its partner: world points `at` (3, k), their overlaps `psi` (k,) in kg,
    and unit normals (3, k) from the partner towards the DANO, or (3, 1) shared by all points."""

    at: Float[Array, "3 k"]
    psi: Float[Array, " k"]
    normal: Float[Array, "3 kn"]


def world_points(body: Body, a: Frame) -> Float[Array, "3 n"]:
    return a.R @ body.points + a.x[:, None]


def primitive_points(shape: Primitive, body: Body, a: Frame, delta, mode: ForceMode) -> PointSet:
    """A DANO against a primitive {f <= 0} (eqs. 7-8): each point inside weighs w_i S(-f/delta)."""
    P = world_points(body, a)
    o = expected_overlap(shape, P, body.weights, delta)
    if mode == "centroid":
        return PointSet(o.chi[:, None], o.psi[None], o.normal[:, None])
    if isinstance(shape, HalfSpace):
        return PointSet(P, o.inside, o.normal[:, None])
    return PointSet(P, o.inside, jax.vmap(outward_normal, (None, 1), 1)(shape, P))


def occupancy(body: Body, frame: Frame, points: Float[Array, "3 k"]) -> Float[Array, " k"]:
    """How much each world point is inside a DANO: its field there over its peak, in [0, 1]."""
    assert body.field is not None, "a DANO without a field has no occupancy"  # `compile_scene` refuses those
    local = frame.R.T @ (points - frame.x[:, None]) + body.com[:, None]
    return jnp.clip(body.field(local.T) / body.peak, 0.0, 1.0)


def dano_points(A: Body, B: Body, a: Frame, b: Frame, mode: ForceMode) -> PointSet:
    """DANO A against DANO B (eqs. 9-10 and the normal after them).

    Each body's points count with their weight times the other body's occupancy there: kg, like
    the primitive case, whose occupancy is the indicator. The normal (from B towards A) is the
    overlap-weighted sum of B's outward normals at B's points minus A's at A's points.
    """
    PA, PB = world_points(A, a), world_points(B, b)
    psi_a = A.weights * occupancy(B, b, PA)
    psi_b = B.weights * occupancy(A, a, PB)
    at = jnp.concatenate([PA, PB], axis=1)
    psi = jnp.concatenate([psi_a, psi_b])
    normal = normalize((b.R @ B.normals) @ psi_b - (a.R @ A.normals) @ psi_a)[:, None]
    if mode == "centroid":
        total = jnp.sum(psi)
        chi = at @ psi / jnp.where(total > 0, total, 1.0)
        return PointSet(chi[:, None], total[None], normal)
    return PointSet(at, psi, normal)


def near(body: Body, a: Frame, centre: Float[Array, " 3"], radius: float | Float[Array, ""]) -> Array:
    """Broad phase: the DANO's bounding sphere meets the ball of `radius` around `centre`."""
    reach = jnp.max(safe_norm(body.points, axis=0)) + radius
    return safe_norm(a.x - centre) < reach


def empty_like(points: PointSet) -> PointSet:
    return jax.tree_util.tree_map(jnp.zeros_like, points)


def relative_velocity(points: PointSet, a: Frame, b: Frame) -> Float[Array, "3 k"]:
    """Velocity of the DANO's material at each point relative to the partner's, world, m/s."""
    u = a.v[:, None] + jnp.cross(a.w[:, None], points.at - a.x[:, None], axis=0)
    return u - b.v[:, None] - jnp.cross(b.w[:, None], points.at - b.x[:, None], axis=0)


def wrench_about(points: PointSet, forces: Float[Array, "3 k"], x: Float[Array, " 3"]) -> Float[Array, " 6"]:
    """The total (force, torque about x) of forces at the points, world."""
    torque = jnp.sum(jnp.cross(points.at - x[:, None], forces, axis=0), axis=1)
    return jnp.concatenate([jnp.sum(forces, axis=1), torque])


def reaction(wrench: Float[Array, " 6"], a_x: Float[Array, " 3"], b_x: Float[Array, " 3"]) -> Float[Array, " 6"]:
    """The partner's share of a pair wrench (force, torque about the DANO's centre `a_x`): equal and
    opposite, its torque taken about the partner's centre `b_x`."""
    force, torque = wrench[:3], wrench[3:]
    return -jnp.concatenate([force, torque + jnp.cross(a_x - b_x, force)])
