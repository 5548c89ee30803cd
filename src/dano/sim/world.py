"""The compiled scene as the jitted step sees it: static indices and constant arrays.

`dano.sim.compile.compile_scene` builds these from a `Scene`; nothing here touches MuJoCo's host
side, so the step, the identification and the optimiser read one small, hashable structure.
"""

import dataclasses
from collections.abc import Callable

import equinox as eqx
from jaxtyping import Array, Float

from dano.contact import ContactParams
from dano.contact.pairs import ForceMode
from dano.sim.scene import Integrator

MOVING = ("free", "actuated")
"""Primitive modes whose body has degrees of freedom of its own."""


class DanoState(eqx.Module):
    """Per-DANO constant data used inside the step.

    Attributes:
        points: (3, n) surface points, body frame (origin at the centre of mass), m.
        normals: (3, n) their outward normals, body frame.
        shares: (n,) normalised densities; the contact weights are these times the current mass.
        mass, inertia: base mass (kg) and inertia about the centre of mass (body frame).
        com: (3,) centre of mass in the object frame (to query `field`), m.
        field: density field in the object frame, for contact with other DANOs (None: unavailable).
        peak: the field's "fully inside" density.
    """

    points: Float[Array, "3 n"]
    normals: Float[Array, "3 n"]
    shares: Float[Array, " n"]
    mass: Float[Array, ""]
    inertia: Float[Array, "3 3"]
    com: Float[Array, " 3"]
    field: Callable[[Array], Array] | None
    peak: Float[Array, ""]
    budget: int = eqx.field(static=True, default=0)
    """points per contact pair that the implicit step solves over (`dano.contact.active`); 0: all."""
    reach: float = eqx.field(static=True, default=float("inf"))
    """m: the largest distance of a point from the centre of mass (the broad phase's bounding
    sphere; inf: no broad phase)."""


@dataclasses.dataclass(frozen=True)
class PrimGeom:
    """A MuJoCo primitive as the step sees it: static data, hashable (`World.prims` is static).

    Attributes:
        name: its `Primitive.name`.
        kind: "sphere", "capsule" or "box"; size: its sizes (`dano.sim.scene.SIZES`), m.
        mode: "static", "free", "mocap" or "actuated".
        body: its MuJoCo body id (0 for a static geom).
        pos, quat: its pose as declared (a static geom's, or an actuated one's origin), world.
        qpos, qvel: the addresses of its free joint or first slide (x; then y, z), or -1.
        mocap: its mocap index, or -1.
        actuator: an actuated primitive's first force actuator (x; then y, z), or -1.
        mass: kg for a free or actuated primitive, inf for one nothing moves.
    """

    name: str
    kind: str
    size: tuple[float, ...]
    mode: str
    body: int
    pos: tuple[float, ...]
    quat: tuple[float, ...]
    qpos: int
    qvel: int
    mocap: int
    actuator: int
    mass: float

    @property
    def moving(self) -> bool:
        """Whether the primitive has degrees of freedom (free or actuated)."""
        return self.mode in MOVING


class LinkGeom(eqx.Module):
    """A robot's or a world's collision geom seen by DANOs: MuJoCo geom and body ids, its kind
    ("box", "sphere", "capsule", "cylinder", "mesh" or "hfield"), size, for a mesh its convex hull as
    planes (normals (k, 3), offsets (k,), geom frame), for a height field its heights (rows, cols;
    m). `radius` bounds the geom around its centre (broad phase)."""

    geom: int = eqx.field(static=True)
    body: int = eqx.field(static=True)
    root: int = eqx.field(static=True)
    kind: str = eqx.field(static=True)
    size: tuple[float, ...] = eqx.field(static=True)
    radius: float = eqx.field(static=True)
    normals: Float[Array, "k 3"] | None = None
    offsets: Float[Array, " k"] | None = None
    heights: Float[Array, "rows cols"] | None = None


class World(eqx.Module):
    """The compiled scene: static indices and constant arrays that the jitted step reads."""

    danos: tuple[DanoState, ...]
    links: tuple[LinkGeom, ...]
    dano_body: tuple[int, ...] = eqx.field(static=True)
    dano_qpos: tuple[int, ...] = eqx.field(static=True)
    dano_qvel: tuple[int, ...] = eqx.field(static=True)
    names: tuple[str, ...] = eqx.field(static=True)
    prims: tuple[PrimGeom, ...] = eqx.field(static=True)
    ground_height: float | None = eqx.field(static=True)
    ground_normal: tuple[float, float, float] = eqx.field(static=True)
    link_names: tuple[str, ...] = eqx.field(static=True)
    substeps: int = eqx.field(static=True)
    dt: float = eqx.field(static=True)
    force_mode: ForceMode = eqx.field(static=True)
    integrator: Integrator = eqx.field(static=True, default=Integrator.implicit)
    fallback_slot: int = eqx.field(static=True, default=-1)
    """`mjx.Data.userdata` slot counting the steps whose active sets overflowed (-1: none)."""
    mujoco_moves: bool = eqx.field(static=True, default=True)
    """Whether `mjx.step` moves anything the implicit step does not integrate itself: False where
    MuJoCo holds only DANOs (free joints, no geoms), static or mocap geometry and actuated
    primitives that do not collide (`Primitive.collide`), whose slides the step integrates."""
    contact: bool = eqx.field(static=True, default=True)
    """False: no DANO contact pair at all (`pairs` is empty; `dano.sim.run.profile` times the engine
    alone with it)."""


class Params(eqx.Module):
    """Differentiable simulation parameters.

    Attributes:
        contact: one `ContactParams` per DANO pair, in `pairs(world)` order.
        mass_scale: (n_dano,) multiplies each DANO's mass, inertia and contact weights.
        inertia_scale: (n_dano,) multiplies each DANO's inertia only.
    """

    contact: tuple[ContactParams, ...]
    mass_scale: Float[Array, " d"]
    inertia_scale: Float[Array, " d"]


def pairs(world: World) -> tuple[tuple[int, str, int], ...]:
    """Contact pairs (dano index, other kind, other index); kinds: ground, primitive, dano (i < j)."""
    out: list[tuple[int, str, int]] = []
    if not world.contact:
        return ()
    for i in range(len(world.danos)):
        if world.ground_height is not None:
            out.append((i, "ground", 0))
        out.extend((i, "primitive", k) for k in range(len(world.prims)))
        out.extend((i, "link", k) for k in range(len(world.links)))
        out.extend((i, "dano", j) for j in range(i + 1, len(world.danos)))
    return tuple(out)


def pair_name(world: World, pair: tuple[int, str, int]) -> tuple[str, str]:
    """The names (DANO, partner) of a pair from `pairs` ("ground" for the ground)."""
    i, kind, k = pair
    other = {
        "ground": lambda: "ground",
        "primitive": lambda: world.prims[k].name,
        "dano": lambda: world.names[k],
        "link": lambda: world.link_names[k],
    }
    return world.names[i], other[kind]()
