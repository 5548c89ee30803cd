"""Scenes, declared: DANOs, primitives, a robot and a ground, checked when made.

A `Scene` is plain frozen data; `dano.sim.compile.compile_scene` turns it into a MuJoCo model and
the `dano.sim.world.World` the step reads, `dano.sim.toml.load_scene` reads one from a TOML file.
A DANO becomes a MuJoCo body with a free joint whose frame is the object frame moved to the centre
of mass (so `qpos` holds the centre of mass and the object-to-world quaternion), with the DANO's
mass and full inertia tensor. It has no collision geoms: its contacts are computed by
`dano.contact` and enter through `xfrc_applied`. Primitives are ordinary MuJoCo geoms (static,
free, mocap-driven or actuated) and collide with each other in MuJoCo; with DANOs they collide
through the DANO contact model.
"""

import dataclasses
import enum
from collections.abc import Callable
from typing import Literal

from jaxtyping import Array

from dano import validate as V
from dano.contact import ContactParams
from dano.contact.pairs import ForceMode
from dano.errors import InvalidValueError
from dano.types import DANO

Number = float | int
Vec3 = tuple[Number, Number, Number]
Quat = tuple[Number, Number, Number, Number]
PrimitiveKind = Literal["sphere", "capsule", "box"]


class Mode(enum.StrEnum):
    """How a primitive moves: `static` never; `free` on a free joint, as physics says; `mocap` along a
    path it is given; `actuated` on three slide joints driven by motors (`ctrl`)."""

    static = "static"
    free = "free"
    mocap = "mocap"
    actuated = "actuated"


MODES: tuple[Mode, ...] = tuple(Mode)


class SceneError(InvalidValueError):
    """A scene that cannot be simulated as given (unknown key, wrong type or range, missing file,
    unknown pair, a body started inside the ground), raised before any simulation."""


def _set(obj, name: str, value) -> None:
    object.__setattr__(obj, name, value)  # normalising a frozen dataclass's field in __post_init__


def _check_pose(obj, where: str, keys=("pos", "vel", "angvel"), quat: str = "quat") -> None:
    """The pose and velocity fields of a body: 3-vectors and a non-zero quaternion, as floats."""
    for key in keys:
        _set(obj, key, V.vector(getattr(obj, key), f"{where}: {key}", SceneError, 3))
    _set(obj, quat, V.vector(getattr(obj, quat), f"{where}: {quat}", SceneError, 4, nonzero=True))


@dataclasses.dataclass(frozen=True)
class DanoBody:
    """A DANO placed in the world.

    Attributes:
        name: unique body name.
        dano: the object.
        pos: (3,) initial centre of mass, world, m.
        quat: (4,) initial orientation w, x, y, z, object frame -> world.
        vel: (3,) initial velocity of the centre of mass, world, m/s.
        angvel: (3,) initial angular velocity, world, rad/s.
        field: the density field to query online in contacts with other DANOs (e.g. the neural
            network itself); None uses the grid baked into the DANO (the fast path).
    """

    name: str
    dano: DANO
    pos: Vec3 = (0.0, 0.0, 0.0)
    quat: Quat = (1.0, 0.0, 0.0, 0.0)
    vel: Vec3 = (0.0, 0.0, 0.0)
    angvel: Vec3 = (0.0, 0.0, 0.0)
    field: Callable[[Array], Array] | None = None

    def __post_init__(self):
        V.text(self.name, "body name", SceneError)
        where = f"body {self.name!r}"
        if not isinstance(self.dano, DANO):
            raise SceneError(f"{where}: dano must be a DANO (dano.build_dano, dano.load_dano), got {type(self.dano)}")
        _check_pose(self, where)
        if not V.is_traced(self.dano.inertia):
            V.inertia_tensor(self.dano.inertia, f"{where}: inertia", SceneError)


@dataclasses.dataclass(frozen=True)
class Primitive:
    """A sphere, capsule (along its local z) or box: static, free, mocap-driven, or actuated.

    "actuated" is a fully actuated end effector: the body slides along world x, y and z (no
    rotation) under three force actuators (N), after any robot's actuators in `ctrl`, with its
    weight compensated (as an arm holding it would).

    Attributes:
        size: sphere (radius,); capsule (radius, half_length); box (hx, hy, hz) half extents; m.
        mass: kg, for free primitives (inertia of a solid of that shape).
        collide: whether MuJoCo's own contacts apply to it (with the ground and other primitives);
            DANO contacts always do. An actuated end effector kept clear of them some other way
            (a constraint, a horizontal push) can turn them off: with nothing else for MuJoCo to
            move, the implicit step then integrates it itself and skips `mjx.step` (half of a
            step's compiled program for the push of `dano.scenarios.push_scene`).
    """

    name: str
    kind: PrimitiveKind
    size: tuple[Number, ...]
    pos: Vec3 = (0.0, 0.0, 0.0)
    quat: Quat = (1.0, 0.0, 0.0, 0.0)
    mode: Mode | str = Mode.static
    mass: Number = 1.0
    vel: Vec3 = (0.0, 0.0, 0.0)
    angvel: Vec3 = (0.0, 0.0, 0.0)
    collide: bool = True

    def __post_init__(self):
        V.text(self.name, "primitive name", SceneError)
        V.boolean(self.collide, f"primitive {self.name!r}: collide", SceneError)
        where = f"primitive {self.name!r}"
        V.choice(self.kind, f"{where}: type", SceneError, SIZES)
        _set(self, "mode", V.option(self.mode, f"{where}: mode", SceneError, Mode))
        n = len(SIZES[self.kind])
        size = V.vector(self.size, f"{where}: size ({', '.join(SIZES[self.kind])})", SceneError, n)
        for name, value in zip(SIZES[self.kind], size, strict=True):
            V.positive(value, f"{where}: size {name}", SceneError)
        _set(self, "size", size)
        _set(self, "mass", V.positive(self.mass, f"{where}: mass", SceneError))
        _check_pose(self, where)


SIZES = {"sphere": ("radius",), "capsule": ("radius", "half_length"), "box": ("hx", "hy", "hz")}
"""The size entries of each primitive type, m (half extents for a box)."""


@dataclasses.dataclass(frozen=True)
class Robot:
    """A fixed-base robot from a URDF or MJCF file, its joints driven by position servos.

    Its collision geometry (primitives, and convex meshes as intersections of half-spaces) touches
    DANOs through the DANO contact model; MuJoCo's own collisions of the robot are switched off
    (MJX mesh collisions are far too slow on CPU).

    Attributes:
        path: a `.urdf` or MJCF `.xml` file (URDF `package://` paths are resolved via `package_dirs`).
        base_pos, base_quat: pose of the robot's root body in the world.
        qpos: initial joint positions (in joint order; missing ones are 0).
        kp, kv: position servo gains per joint (N m/rad, N m s/rad).
        armature: rotor inertia added to each servoed joint (kg m², or kg for a slide), or None to
            keep the file's. MuJoCo integrates the servo's damping kv explicitly, which is stable
            only while kv h / M_jj < 2 (h the step, M_jj the joint's inertia); a light wrist joint
            breaks that, and `compile_scene` refuses such a robot.
        gravity_compensation: cancel gravity on the robot's links (as a torque-controlled arm would).
        package_dirs: {package name: folder} for `package://name/...` paths.
        contact_bodies: names of the links whose geoms touch DANOs (empty: all). Each contact pair
            is code in the compiled step, so leaving out links that cannot reach the objects keeps
            compile times down (most of all for `jax.jacfwd` of long rollouts).
    """

    path: str
    base_pos: Vec3 = (0.0, 0.0, 0.0)
    base_quat: Quat = (1.0, 0.0, 0.0, 0.0)
    qpos: tuple[Number, ...] = ()
    kp: Number = 300.0
    kv: Number = 30.0
    armature: Number | None = None
    gravity_compensation: bool = True
    package_dirs: tuple[tuple[str, str], ...] = ()
    contact_bodies: tuple[str, ...] = ()

    def __post_init__(self):
        V.text(str(self.path), "robot path", SceneError)
        _set(self, "path", str(self.path))
        _check_pose(self, "robot", keys=("base_pos",), quat="base_quat")
        qpos = self.qpos if isinstance(self.qpos, str) else tuple(self.qpos)  # a string is refused below
        _set(self, "qpos", V.vector(qpos, "robot: qpos", SceneError, len(qpos)))
        for key in ("kp", "kv"):
            _set(self, key, V.number(getattr(self, key), f"robot: {key}", SceneError, low=0.0))
        if self.armature is not None:
            _set(self, "armature", V.number(self.armature, "robot: armature", SceneError, low=0.0))
        try:
            dirs = dict(self.package_dirs)  # (name, folder) pairs, or a {name: folder} dict
        except (TypeError, ValueError):
            raise SceneError(f"robot: package_dirs must be (name, folder) pairs, got {self.package_dirs!r}") from None
        for name, folder in dirs.items():
            V.text(name, "robot: package name", SceneError)
            V.text(str(folder), f"robot: folder of package {name!r}", SceneError)
        _set(self, "package_dirs", tuple((name, str(folder)) for name, folder in dirs.items()))
        _set(self, "contact_bodies", tuple(V.text(b, "robot: contact_bodies entry", SceneError)
                                           for b in self.contact_bodies))  # fmt: skip


class Integrator(enum.StrEnum):
    """How a step applies contact: `implicit` solves it in the DANOs' velocities (`dano.sim.implicit`);
    `explicit` applies the wrench at the current state (the paper's scheme, `dano.sim.step`)."""

    implicit = "implicit"
    explicit = "explicit"


DEFAULT_SUBSTEPS: dict[Integrator | str, int] = {Integrator.implicit: 1, Integrator.explicit: 4}
"""Steps per frame each integrator needs at the default 2 ms frame: the implicit step is stable at
one, the explicit one's stiff springs need ~0.5 ms."""


@dataclasses.dataclass(frozen=True)
class Scene:
    """Everything a simulation needs (see README for the TOML form).

    Attributes:
        timestep: s, one recorded frame.
        substeps: steps per frame; None (default) for the integrator's own (`DEFAULT_SUBSTEPS`: 1
            for the implicit step, stable at one 2 ms step per frame, more only for accuracy; 4 for
            the explicit one, whose stiff springs need ~0.5 ms; `dano.sim.step`).
        duration: s.
        gravity: (3,) m/s^2.
        ground_height: the ground is the half-space {x : normal . x <= height}, or None for none.
        ground_normal: (3,) its unit outward normal (default +z: the plane z = height).
        bodies: DANOs.
        primitives: MuJoCo primitives.
        contact: default contact parameters of every pair.
        pair_contact: overrides per pair, keyed by (dano name, other name); the ground is "ground".
        force_mode: "points" applies each sampled point's own force at the point; "centroid" applies
            the total at the overlap centroid chi, as in the paper.
        robot: an optional robot (see `Robot`, `panda`).
        integrator: "implicit" (default) solves the contact implicitly in the DANOs' velocities
            (stable at one 2 ms step per frame at every Table I corner, no energy gain, friction
            that sticks; `dano.sim.implicit`); "explicit" applies the wrench at the current state
            (the paper's scheme: needs ~0.5 ms steps, `substeps=4`; free flight reproduces the
            paper authors' stored trajectories, `dano.reference`).
        contact_budget: points of each DANO per contact pair that the implicit step solves over
            (`dano.contact.active`): None (default) from each DANO's geometry (the most points
            near a supporting plane, `dano.contact.active.budget`); a step whose pairs need more
            is solved over all points, exactly, and counted (`Trajectory.fallbacks`).
        mjcf: an MJCF world to put the DANOs in (a file): its bodies, joints, actuators (driven by
            `ctrl`, before the actuated primitives' motors), keyframes and options are kept, and
            MuJoCo's own contacts among its geoms; every colliding geom of it (box, sphere,
            capsule, convex mesh, plane) touches the DANOs through the DANO contact model. The
            scene's own ground is added beside it unless `ground_height` is None. A robot goes
            into the world's file (`robot` and `mjcf` together are refused).
    """

    timestep: Number = 0.002
    substeps: int | None = None
    duration: Number = 1.0
    gravity: Vec3 = (0.0, 0.0, -9.81)
    ground_height: Number | None = 0.0
    ground_normal: Vec3 = (0.0, 0.0, 1.0)
    bodies: tuple[DanoBody, ...] = ()
    primitives: tuple[Primitive, ...] = ()
    contact: ContactParams = dataclasses.field(default_factory=ContactParams)
    pair_contact: tuple[tuple[tuple[str, str], ContactParams], ...] = ()
    force_mode: ForceMode | str = ForceMode.points
    robot: Robot | None = None
    integrator: Integrator | str = Integrator.implicit
    contact_budget: int | None = None
    mjcf: str | None = None

    def __post_init__(self):
        _set(self, "integrator", V.option(self.integrator, "integrator", SceneError, Integrator))
        _set(self, "force_mode", V.option(self.force_mode, "force_mode", SceneError, ForceMode))
        if self.substeps is None:
            _set(self, "substeps", DEFAULT_SUBSTEPS[Integrator(self.integrator)])
        _set(self, "substeps", V.integer(self.substeps, "substeps", SceneError, low=1))
        _set(self, "timestep", V.positive(self.timestep, "timestep", SceneError))
        _set(self, "duration", V.positive(self.duration, "duration", SceneError))
        _set(self, "gravity", V.vector(self.gravity, "gravity", SceneError, 3))
        if self.ground_height is not None:
            _set(self, "ground_height", V.number(self.ground_height, "ground height", SceneError))
        _set(self, "ground_normal", V.vector(self.ground_normal, "ground normal", SceneError, 3, nonzero=True))
        for key, kind in (("bodies", DanoBody), ("primitives", Primitive)):
            items = tuple(getattr(self, key))
            wrong = [type(x).__name__ for x in items if not isinstance(x, kind)]
            if wrong:
                raise SceneError(f"{key} must hold {kind.__name__}s, got {wrong[0]}")
            _set(self, key, items)
        names = [b.name for b in self.bodies] + [p.name for p in self.primitives]
        duplicates = sorted({n for n in names if names.count(n) > 1})
        if duplicates or "ground" in names:
            which = f"{duplicates} appear more than once" if duplicates else "'ground' names the ground"
            raise SceneError(f"body and primitive names must be unique and not 'ground': {which}")
        if not isinstance(self.contact, ContactParams):
            raise SceneError(f"contact must be a ContactParams, got {type(self.contact).__name__}")
        pair_contact = tuple(self.pair_contact)
        for key, value in pair_contact:
            if not (isinstance(key, tuple) and len(key) == 2 and all(isinstance(k, str) for k in key)):
                raise SceneError(f"pair_contact keys are (dano name, other name), got {key!r}")
            if not isinstance(value, ContactParams):
                raise SceneError(f"pair_contact {key}: must be a ContactParams, got {type(value).__name__}")
        _set(self, "pair_contact", pair_contact)
        if self.robot is not None and not isinstance(self.robot, Robot):
            raise SceneError(f"robot must be a Robot (dano.sim.Robot, dano.assets.panda()), got {type(self.robot)}")
        if self.contact_budget is not None:
            _set(self, "contact_budget", V.integer(self.contact_budget, "contact_budget", SceneError, low=1))
        if self.mjcf is not None:
            _set(self, "mjcf", V.text(str(self.mjcf), "mjcf", SceneError))
            if self.robot is not None:
                raise SceneError("a scene takes a robot or an MJCF world, not both: put the robot in the world's file")

    @property
    def step_size(self) -> float:
        """s, one step of the integrator: `timestep / substeps`."""
        assert self.substeps is not None  # `__post_init__` sets it for each integrator
        return self.timestep / self.substeps

    @property
    def n_steps(self) -> int:
        return int(round(self.duration / self.timestep))
