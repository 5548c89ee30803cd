"""Scenes, host side: declare DANOs, primitives and a ground, compile once to MuJoCo/MJX.

A DANO becomes a MuJoCo body with a free joint whose frame is the object frame moved to the centre
of mass (so `qpos` holds the centre of mass and the object-to-world quaternion), with the DANO's
mass and full inertia tensor (MuJoCo diagonalises it into `body_inertia`/`body_iquat`). It has no
collision geoms: its contacts are computed by `dano.contact` and enter through `xfrc_applied`.
Primitives are ordinary MuJoCo geoms (static, free, or mocap-driven) and collide with each other in
MuJoCo; with DANOs they collide through the DANO contact model.
"""

import dataclasses
from collections.abc import Callable
from typing import Any, Literal, cast

import equinox as eqx
import jax.numpy as jnp
import mujoco
import numpy as np
from jaxtyping import Array, Float

from dano import validate as V
from dano.contact import ContactParams, active
from dano.errors import InvalidValueError
from dano.types import DANO

Number = float | int
Vec3 = tuple[Number, Number, Number]
Quat = tuple[Number, Number, Number, Number]
_MOVING = ("free", "actuated")
PrimitiveKind = Literal["sphere", "capsule", "box"]
Mode = Literal["static", "free", "mocap", "actuated"]


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
    field: object = None

    def __post_init__(self):
        V.text(self.name, "body name", SceneError)
        where = f"body {self.name!r}"
        if not isinstance(self.dano, DANO):
            raise SceneError(f"{where}: dano must be a DANO (dano.build_dano, dano.load_dano), got {type(self.dano)}")
        _check_pose(self, where)
        if not V.is_traced(self.dano.inertia):
            V.inertia_tensor(self.dano.inertia, f"{where}: inertia", SceneError)


def _contact_field(body: DanoBody) -> Callable[[Array], Array] | None:
    """The field a DANO's partners query: the online field if given, else its baked grid."""
    from dano.fields import GridField

    if body.field is not None:
        return cast(Callable[[Array], Array], body.field)
    if body.dano.grid is None:
        return None
    return GridField(jnp.asarray(body.dano.grid), body.dano.grid_bounds)


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
            step's compiled program for the push of `dano.sysid.experiments.push_scene`).
    """

    name: str
    kind: PrimitiveKind
    size: tuple[Number, ...]
    pos: Vec3 = (0.0, 0.0, 0.0)
    quat: Quat = (1.0, 0.0, 0.0, 0.0)
    mode: Mode = "static"
    mass: Number = 1.0
    vel: Vec3 = (0.0, 0.0, 0.0)
    angvel: Vec3 = (0.0, 0.0, 0.0)
    collide: bool = True

    def __post_init__(self):
        V.text(self.name, "primitive name", SceneError)
        V.boolean(self.collide, f"primitive {self.name!r}: collide", SceneError)
        where = f"primitive {self.name!r}"
        V.choice(self.kind, f"{where}: type", SceneError, SIZES)
        V.choice(self.mode, f"{where}: mode", SceneError, ("static", "free", "mocap", "actuated"))
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


def panda(base_pos: Vec3 = (0.0, 0.0, 0.0), qpos: tuple[Number, ...] = (), **kwargs) -> Robot:
    """The Franka Panda of `example-robot-data` (URDF, STL collision meshes), with the 0.1 kg m²
    armature per joint of MuJoCo Menagerie's Panda (the URDF has none; without it the hand's joint,
    M_jj = 0.0067 kg m², is unstable under the default servo at 0.5 ms steps)."""
    kwargs.setdefault("armature", 0.1)
    from importlib.metadata import PackageNotFoundError, distribution
    from pathlib import Path

    from dano.extras import MissingExtraError

    try:
        root = Path(str(distribution("example-robot-data").locate_file("cmeel.prefix/share/example-robot-data")))
    except PackageNotFoundError:
        raise MissingExtraError('the Panda comes from example-robot-data: pip install "dano[robots]"') from None
    path = root / "robots" / "panda_description" / "urdf" / "panda.urdf"
    if not path.is_file():
        raise MissingExtraError(f'the Panda URDF is not at {path}: pip install "dano[robots]"')
    return Robot(str(path), base_pos=base_pos, qpos=qpos, package_dirs=(("example-robot-data", str(root)),), **kwargs)


def _robot_spec(robot: Robot) -> mujoco.MjSpec:
    """Loads the robot with MuJoCo's own compiler: URDF paths resolved, visuals dropped."""
    import re
    from pathlib import Path

    path = Path(robot.path)
    if not path.is_file():
        raise SceneError(f"robot file {path} not found")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise SceneError(f"robot file {path} cannot be read: {e}") from None
    if path.suffix.lower() == ".urdf":
        for name, folder in robot.package_dirs:
            text = text.replace(f"package://{name}/", f"{Path(folder).resolve()}/")
        unresolved = sorted(set(re.findall(r"package://([^/\"]+)", text)))
        if unresolved:
            raise SceneError(
                f"robot file {path} uses package(s) {unresolved} that package_dirs does not give: pass "
                f"package_dirs=(({unresolved[0]!r}, FOLDER),)"
            )
        text = re.sub(r'filename="(?!/)([^"]+)"', lambda m: f'filename="{(path.parent / m.group(1)).resolve()}"', text)
        missing = [f for f in re.findall(r'filename="([^"]+)"', text) if not Path(f).is_file()]
        if missing:
            raise SceneError(f"robot file {path}: mesh file {missing[0]} not found ({len(missing)} missing)")
        compiler = '<mujoco><compiler discardvisual="true" balanceinertia="true" fusestatic="false"/></mujoco>'
        text = re.sub(r"(<robot[^>]*>)", r"\1" + compiler, text, count=1)
        return _parse_robot(path, lambda: mujoco.MjSpec.from_string(text))
    return _parse_robot(path, lambda: mujoco.MjSpec.from_file(str(path)))


def _parse_robot(path, parse) -> mujoco.MjSpec:
    try:
        return parse()
    except ValueError as e:  # MuJoCo's parser: bad XML, a missing mesh of an MJCF, ...
        raise SceneError(f"robot file {path}: MuJoCo cannot load it: {' '.join(str(e).split())}") from None


DEFAULT_SUBSTEPS = {"implicit": 1, "explicit": 4}
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
    force_mode: Literal["points", "centroid"] = "points"
    robot: Robot | None = None
    integrator: Literal["implicit", "explicit"] = "implicit"
    contact_budget: int | None = None

    def __post_init__(self):
        V.choice(self.integrator, "integrator", SceneError, DEFAULT_SUBSTEPS)
        V.choice(self.force_mode, "force_mode", SceneError, ("points", "centroid"))
        if self.substeps is None:
            _set(self, "substeps", DEFAULT_SUBSTEPS[self.integrator])
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
            raise SceneError(f"robot must be a Robot (dano.sim.Robot, dano.sim.panda()), got {type(self.robot)}")
        if self.contact_budget is not None:
            _set(self, "contact_budget", V.integer(self.contact_budget, "contact_budget", SceneError, low=1))

    @property
    def step_size(self) -> float:
        """s, one step of the integrator: `timestep / substeps`."""
        assert self.substeps is not None  # `__post_init__` sets it for each integrator
        return self.timestep / self.substeps

    @property
    def n_steps(self) -> int:
        return int(round(self.duration / self.timestep))


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


class LinkGeom(eqx.Module):
    """A robot collision geom seen by DANOs: MuJoCo geom and body ids, its kind ("box", "sphere",
    "capsule" or "mesh"), size, and for a mesh its convex hull as planes (normals (k, 3), offsets (k,),
    geom frame). `radius` bounds the geom around its centre (broad phase)."""

    geom: int = eqx.field(static=True)
    body: int = eqx.field(static=True)
    root: int = eqx.field(static=True)
    kind: str = eqx.field(static=True)
    size: tuple[float, ...] = eqx.field(static=True)
    radius: float = eqx.field(static=True)
    normals: Float[Array, "k 3"] | None = None
    offsets: Float[Array, " k"] | None = None


class World(eqx.Module):
    """The compiled scene: static indices and constant arrays that the jitted step reads."""

    danos: tuple[DanoState, ...]
    links: tuple[LinkGeom, ...]
    dano_body: tuple[int, ...] = eqx.field(static=True)
    dano_qpos: tuple[int, ...] = eqx.field(static=True)
    dano_qvel: tuple[int, ...] = eqx.field(static=True)
    names: tuple[str, ...] = eqx.field(static=True)
    prim_kind: tuple[str, ...] = eqx.field(static=True)
    prim_body: tuple[int, ...] = eqx.field(static=True)
    prim_mode: tuple[str, ...] = eqx.field(static=True)
    prim_names: tuple[str, ...] = eqx.field(static=True)
    prim_size: tuple[tuple[float, ...], ...] = eqx.field(static=True)
    prim_pos: tuple[tuple[float, ...], ...] = eqx.field(static=True)
    prim_quat: tuple[tuple[float, ...], ...] = eqx.field(static=True)
    prim_qpos: tuple[int, ...] = eqx.field(static=True)
    prim_qvel: tuple[int, ...] = eqx.field(static=True)
    prim_mocap: tuple[int, ...] = eqx.field(static=True)
    prim_actuator: tuple[int, ...] = eqx.field(static=True)
    """An actuated primitive's first force actuator (x; then y, z), or -1."""
    ground_height: float | None = eqx.field(static=True)
    ground_normal: tuple[float, float, float] = eqx.field(static=True)
    link_names: tuple[str, ...] = eqx.field(static=True)
    prim_mass: tuple[float, ...] = eqx.field(static=True)
    substeps: int = eqx.field(static=True)
    dt: float = eqx.field(static=True)
    force_mode: Literal["points", "centroid"] = eqx.field(static=True)
    integrator: str = eqx.field(static=True, default="implicit")
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
        out.extend((i, "primitive", k) for k in range(len(world.prim_kind)))
        out.extend((i, "link", k) for k in range(len(world.links)))
        out.extend((i, "dano", j) for j in range(i + 1, len(world.danos)))
    return tuple(out)


def pair_name(world: World, pair: tuple[int, str, int]) -> tuple[str, str]:
    """The names (DANO, partner) of a pair from `pairs` ("ground" for the ground)."""
    i, kind, k = pair
    other = {
        "ground": lambda: "ground",
        "primitive": lambda: world.prim_names[k],
        "dano": lambda: world.names[k],
        "link": lambda: world.link_names[k],
    }
    return world.names[i], other[kind]()


def principal_frame(inertia) -> tuple[np.ndarray, np.ndarray]:
    """Principal moments (3,) and the quaternion (w, x, y, z) of the principal axes (a proper
    rotation) of an inertia tensor (3, 3) given in the body frame."""
    moments, axes = np.linalg.eigh(np.asarray(inertia, dtype=np.float64))
    if np.linalg.det(axes) < 0:
        axes[:, 0] = -axes[:, 0]
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, axes.ravel())
    return moments, quat


def _add_dano(spec: mujoco.MjSpec, body: DanoBody) -> None:
    """A free body whose inertial frame is the DANO's principal frame.

    The principal frame must be given to the compiler: MuJoCo decides from `ipos`/`iquat` whether
    the inertial frame is the body frame (`body_sameframe`, `body_simple`) and then ignores
    `body_iquat`, so writing the frame into the compiled model afterwards turns the tensor about
    the wrong axes. The moments are written after compiling (`_set_moments`): the compiler rejects
    moments that break the triangle inequality, which the reference DANOs need (`dano.reference`).
    """
    d = body.dano
    _, quat = principal_frame(d.inertia)
    b = spec.worldbody.add_body(name=body.name, pos=list(body.pos), quat=list(body.quat))
    b.add_freejoint(name=f"{body.name}_free")
    b.mass = float(d.mass)
    b.ipos = [0.0, 0.0, 0.0]
    b.iquat = quat.tolist()
    b.inertia = [1.0, 1.0, 1.0]  # replaced after compiling by `_set_moments`
    b.explicitinertial = True


def _set_moments(model: mujoco.MjModel, body: int, inertia: np.ndarray) -> None:
    """Writes the principal moments of a full inertia tensor (body frame) into the compiled model,
    whose inertial frame `_add_dano` already set to the tensor's principal axes."""
    moments, quat = principal_frame(inertia)
    if not np.allclose(np.abs(quat @ model.body_iquat[body]), 1.0, atol=1e-9):
        raise AssertionError("the compiled inertial frame is not the principal frame")  # an invariant
    model.body_inertia[body] = moments


_GEOM = {
    "sphere": mujoco.mjtGeom.mjGEOM_SPHERE,
    "capsule": mujoco.mjtGeom.mjGEOM_CAPSULE,
    "box": mujoco.mjtGeom.mjGEOM_BOX,
}


def _add_primitive(spec: mujoco.MjSpec, p: Primitive) -> None:
    if p.mode == "static":
        spec.worldbody.add_geom(name=p.name, type=_GEOM[p.kind], size=_mj_size(p), pos=list(p.pos), quat=list(p.quat))
        return
    b = spec.worldbody.add_body(name=p.name, pos=list(p.pos), quat=list(p.quat), mocap=p.mode == "mocap")
    if p.mode == "free":
        b.add_freejoint(name=f"{p.name}_free")
    if p.mode == "actuated":
        b.gravcomp = 1.0
        R = np.zeros(9)
        mujoco.mju_quat2Mat(R, np.asarray(p.quat, dtype=float) / np.linalg.norm(p.quat))
        for k, axis in enumerate("xyz"):
            local = R.reshape(3, 3).T[:, k]  # world axis k in the body frame
            b.add_joint(name=f"{p.name}_slide{axis}", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=local.tolist())
            spec.add_actuator(name=f"{p.name}_force{axis}", target=f"{p.name}_slide{axis}",
                              trntype=mujoco.mjtTrn.mjTRN_JOINT).set_to_motor()  # fmt: skip
    geom = b.add_geom(type=_GEOM[p.kind], size=_mj_size(p), mass=p.mass if p.mode in ("free", "actuated") else 0.0)
    if not p.collide:
        geom.contype = geom.conaffinity = 0


def _add_visuals(spec: mujoco.MjSpec) -> None:
    """A checker floor material and a light (rendering only)."""
    spec.add_texture(
        name="grid", type=mujoco.mjtTexture.mjTEXTURE_2D, builtin=mujoco.mjtBuiltin.mjBUILTIN_CHECKER,
        rgb1=[0.25, 0.28, 0.32], rgb2=[0.18, 0.2, 0.23], width=256, height=256,
    )  # fmt: skip
    material = spec.add_material(name="grid", texrepeat=[10, 10], reflectance=0.1)
    material.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = "grid"
    spec.worldbody.add_light(pos=[0, 0, 3], dir=[0, 0, -1], diffuse=[0.7, 0.7, 0.7])


def _mj_size(p: Primitive) -> list[float]:
    return list(p.size) + [0.0] * (3 - len(p.size))


def _budget(scene: Scene, body: DanoBody) -> int:
    n = body.dano.n_points
    k = scene.contact_budget
    if k is None:
        k = active.budget(np.asarray(body.dano.body_points).T, np.asarray(body.dano.normals).T)
    return min(int(k), n)


def _mujoco_moves(scene: Scene, model: mujoco.MjModel) -> bool:
    """`World.mujoco_moves`: anything but the DANOs' free joints and non-colliding actuated
    primitives' slides and motors (a robot, a free primitive, a colliding one, a constraint)."""
    held = sum(p.mode == "actuated" and not p.collide for p in scene.primitives)
    extra_dof = model.nv - 6 * len(scene.bodies) - 3 * held  # a robot's, a free or colliding primitive's
    return extra_dof > 0 or model.nu > 3 * held or model.neq > 0 or model.ntendon > 0


def compile_scene(scene: Scene, check_start: bool = False):
    """Builds the MuJoCo model and the `World`, `Params` and initial `qpos`/`qvel` of a scene.

    `check_start` refuses initial states the contact cannot resolve (`_check_start`: a DANO inside
    the ground, or crossing its own size in one step); `Simulation.from_scene` turns it on, while
    identification leaves it off: its initial states come from the data, not from the scene.

    Returns:
        (mj_model, world, params, qpos0, qvel0): the `mujoco.MjModel` (use `mjx.put_model`), the
        static world, default parameters, and the initial state arrays.
    """
    if len(scene.bodies) > 1:
        blind = [b.name for b in scene.bodies if b.field is None and b.dano.grid is None]
        if blind:
            raise SceneError(
                f"DANOs {blind} carry no density grid, so they cannot touch other DANOs: rebuild them with "
                "`dano build` from a field (reference colliders have none), or pass field= to DanoBody"
            )
    spec = mujoco.MjSpec() if scene.robot is None else _robot_spec(scene.robot)
    robot_bodies = _prepare_robot(spec, scene.robot) if scene.robot is not None else []
    spec.option.timestep = scene.step_size
    spec.option.gravity = list(scene.gravity)
    if scene.integrator == "implicit":
        # MuJoCo's own velocity-dependent forces (servo damping kv) implicit too, as the contact:
        # at one 2 ms step per frame Euler's explicit damping rings up on a light joint.
        spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    _add_visuals(spec)
    spec.nuserdata += 1  # the last slot counts the steps whose contact active sets overflowed
    if scene.ground_height is not None:
        n = np.asarray(_unit(scene.ground_normal))
        quat = np.zeros(4)
        mujoco.mju_quatZ2Vec(quat, n)
        spec.worldbody.add_geom(
            name="ground", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0, 0, 1], pos=(scene.ground_height * n).tolist(),
            quat=quat.tolist(), material="grid",
        )  # fmt: skip
    for body in scene.bodies:
        _add_dano(spec, body)
    for p in scene.primitives:
        _add_primitive(spec, p)
    try:
        model = spec.compile()
    except ValueError as e:  # e.g. a robot link named like a DANO
        raise SceneError(f"MuJoCo cannot compile the scene: {' '.join(str(e).split())}") from None
    for body in scene.bodies:
        _set_moments(model, model.body(body.name).id, np.asarray(body.dano.inertia))

    joints = {model.joint(j).name: j for j in range(model.njnt)}

    def jnt(name):  # the free joint of a body, or the first slide of an actuated primitive
        return joints.get(f"{name}_slidex", joints.get(f"{name}_free"))

    if scene.robot is not None and scene.robot.contact_bodies:
        unknown = sorted(set(scene.robot.contact_bodies) - set(robot_bodies))
        if unknown:
            raise SceneError(f"contact_bodies {unknown} are not bodies of the robot (it has {robot_bodies})")
    links = tuple(_link_geom(model, g) for g in _robot_geoms(model, robot_bodies, scene.robot))
    danos = tuple(
        DanoState(
            points=jnp.asarray(b.dano.body_points.T),
            shares=b.dano.densities / jnp.sum(b.dano.densities),
            mass=jnp.asarray(b.dano.mass),
            inertia=jnp.asarray(b.dano.inertia),
            com=jnp.asarray(b.dano.com),
            field=_contact_field(b),
            peak=jnp.asarray(b.dano.peak if b.dano.peak is not None else jnp.max(b.dano.densities)),
            normals=jnp.asarray(b.dano.normals.T),
            budget=_budget(scene, b),
            reach=float(np.max(np.linalg.norm(np.asarray(b.dano.body_points), axis=1))),
        )
        for b in scene.bodies
    )
    world = World(
        danos=danos,
        links=links,
        link_names=tuple(model.body(link.body).name for link in links),
        dano_body=tuple(model.body(b.name).id for b in scene.bodies),
        dano_qpos=tuple(int(model.jnt_qposadr[jnt(b.name)]) for b in scene.bodies),
        dano_qvel=tuple(int(model.jnt_dofadr[jnt(b.name)]) for b in scene.bodies),
        names=tuple(b.name for b in scene.bodies),
        prim_kind=tuple(p.kind for p in scene.primitives),
        prim_body=tuple(model.body(p.name).id if p.mode != "static" else 0 for p in scene.primitives),
        prim_mode=tuple(p.mode for p in scene.primitives),
        prim_names=tuple(p.name for p in scene.primitives),
        prim_size=tuple(tuple(float(s) for s in p.size) for p in scene.primitives),
        prim_pos=tuple(tuple(float(s) for s in p.pos) for p in scene.primitives),
        prim_quat=tuple(tuple(float(s) for s in p.quat) for p in scene.primitives),
        prim_qpos=tuple(int(model.jnt_qposadr[jnt(p.name)]) if p.mode in _MOVING else -1 for p in scene.primitives),
        prim_qvel=tuple(int(model.jnt_dofadr[jnt(p.name)]) if p.mode in _MOVING else -1 for p in scene.primitives),
        prim_mocap=tuple(
            int(model.body_mocapid[model.body(p.name).id]) if p.mode == "mocap" else -1 for p in scene.primitives
        ),
        prim_actuator=tuple(
            int(model.actuator(f"{p.name}_forcex").id) if p.mode == "actuated" else -1 for p in scene.primitives
        ),
        ground_height=scene.ground_height,
        ground_normal=_unit(scene.ground_normal),
        prim_mass=tuple(float(p.mass) if p.mode in _MOVING else float("inf") for p in scene.primitives),
        substeps=int(scene.substeps),  # pyright: ignore[reportArgumentType]  (`__post_init__` sets it)
        dt=scene.step_size,
        force_mode=scene.force_mode,
        integrator=scene.integrator,
        fallback_slot=model.nuserdata - 1,
        mujoco_moves=_mujoco_moves(scene, model),
    )
    overrides = _pair_overrides(scene, world)
    if check_start:
        _check_start(scene, world, overrides)
    params = Params(
        contact=tuple(overrides.get(pair_name(world, pr), scene.contact) for pr in pairs(world)),
        mass_scale=jnp.ones(len(danos)),
        inertia_scale=jnp.ones(len(danos)),
    )
    qpos, qvel = np.array(model.qpos0), np.zeros(model.nv)
    for b, a, v in zip(scene.bodies, world.dano_qpos, world.dano_qvel, strict=True):
        _set_free(model, qpos, qvel, a, v, b.pos, b.quat, b.vel, b.angvel)
    for p, a, v in zip(scene.primitives, world.prim_qpos, world.prim_qvel, strict=True):
        if p.mode == "free":
            _set_free(model, qpos, qvel, a, v, p.pos, p.quat, p.vel, p.angvel)
        elif p.mode == "actuated":
            qvel[v : v + 3] = p.vel
    if scene.robot is not None:
        ids = {model.body(name).id for name in robot_bodies}
        robot_joints = [j for j in range(model.njnt) if model.jnt_bodyid[j] in ids]
        for j, value in zip(robot_joints, scene.robot.qpos, strict=False):
            qpos[model.jnt_qposadr[j]] = value
        _check_servo_damping(model, qpos)
    return model, world, params, qpos, qvel


def _pair_overrides(scene: Scene, world: World) -> dict[tuple[str, str], ContactParams]:
    """`scene.pair_contact` keyed as `pair_name` names the pairs; a pair given in the other order is
    the same pair. A pair that names no contact pair of the scene is an error, not ignored."""
    known = {pair_name(world, pr) for pr in pairs(world)}
    out: dict[tuple[str, str], ContactParams] = {}
    for (a, b), params in scene.pair_contact:
        key = (a, b) if (a, b) in known else (b, a)
        if key not in known:
            hint = ", ".join(f"{x}/{y}" for x, y in sorted(known)) or "none (contact is off)"
            raise SceneError(f"pair {a}/{b} is not a contact pair of this scene (its pairs: {hint})")
        if key in out:
            raise SceneError(f"pair {a}/{b} is given more than once")
        out[key] = params
    return out


START_DEPTH = 0.003
"""m: how deep below the ground a DANO's deepest surface point may start, beyond the spring's own
rest depth (5 g / k). Deeper, the contact spring throws it out (1 cm deep: 4.5 m/s)."""


def _check_start(scene: Scene, world: World, overrides: dict) -> None:
    """Refuses initial states the contact cannot resolve: a DANO started inside the ground, or moving
    so fast that it crosses its own size in one step (it would tunnel through what it should hit)."""
    dt = scene.step_size
    for body, state in zip(scene.bodies, world.danos, strict=True):
        reach = state.reach
        speed = float(np.linalg.norm(body.vel))
        if speed * dt > reach:
            raise SceneError(
                f"body {body.name!r} starts at {speed:g} m/s, moving {speed * dt:.3g} m per step of {dt:g} s, more "
                f"than its own radius {reach:.3g} m: lower its speed or the time step"
            )
        spin = float(np.linalg.norm(body.angvel))
        if spin * dt > 1.0:
            raise SceneError(f"body {body.name!r} starts spinning at {spin:g} rad/s, over 1 rad per step of {dt:g} s")
        if scene.ground_height is None:
            continue
        n = np.asarray(world.ground_normal)
        R = np.zeros(9)
        mujoco.mju_quat2Mat(R, np.asarray(body.quat) / np.linalg.norm(body.quat))
        points = np.asarray(state.points).T @ R.reshape(3, 3).T + np.asarray(body.pos)
        depth = float(scene.ground_height - np.min(points @ n))
        spring = float(overrides.get((body.name, "ground"), scene.contact).impact_spring)
        allowed = START_DEPTH + 5 * float(np.linalg.norm(scene.gravity)) / max(spring, 1e-12)
        if depth > allowed:
            lift = depth + float(np.asarray(body.pos) @ n) - scene.ground_height
            raise SceneError(
                f"body {body.name!r} starts {depth * 1e3:.3g} mm inside the ground (at most {allowed * 1e3:.2g} mm "
                f"allowed): start its centre at least {lift:.4g} m above the ground (along its normal)"
            )


def _prepare_robot(spec: mujoco.MjSpec, robot: Robot) -> list[str]:
    """Places the robot and adds a position servo per joint; returns the robot's body names."""
    root = spec.worldbody.first_body()
    root.pos, root.quat = list(robot.base_pos), list(robot.base_quat)
    bodies = [body.name for body in spec.bodies if body.name != "world"]
    for body in spec.bodies:
        if robot.gravity_compensation and body.name != "world":
            body.gravcomp = 1.0
    for joint in spec.joints:
        if joint.type in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE):
            act = spec.add_actuator(name=f"{joint.name}_servo", target=joint.name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
            act.set_to_position(kp=float(robot.kp), kv=float(robot.kv))
            if robot.armature is not None:
                joint.armature = float(robot.armature)
    return bodies


def _check_servo_damping(model: mujoco.MjModel, qpos: np.ndarray) -> None:
    """Raises `SceneError` where a joint servo's damping (kv = -biasprm[2]) is explicitly unstable
    at `qpos`: kv h / M_jj >= 2 under Euler (`implicitfast` integrates it implicitly)."""
    if model.opt.integrator == mujoco.mjtIntegrator.mjINT_IMPLICITFAST:
        return
    data = mujoco.MjData(model)
    data.qpos[:] = qpos
    mujoco.mj_forward(model, data)
    M = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, data, M)
    for a in range(model.nu):
        if model.actuator_trntype[a] != mujoco.mjtTrn.mjTRN_JOINT:
            continue
        joint = int(model.actuator_trnid[a, 0])
        dof = int(model.jnt_dofadr[joint])
        kv = -float(model.actuator_biasprm[a, 2])
        ratio = kv * model.opt.timestep / M[dof, dof]
        if ratio >= 2.0:
            raise SceneError(
                f"the servo of joint {model.joint(joint).name!r} is unstable: kv h / M = {kv:g} x "
                f"{model.opt.timestep:g} s / {M[dof, dof]:.3g} = {ratio:.2f} >= 2 (MuJoCo integrates its "
                "damping explicitly); give the robot an armature, a smaller kv, a smaller time step, or use "
                'integrator = "implicit"'
            )


def _robot_geoms(model: mujoco.MjModel, bodies: list[str], robot: Robot | None) -> list[int]:
    """The robot's geoms that touch DANOs (`robot.contact_bodies`, else all), with MuJoCo's own
    collisions switched off for every robot geom: DANOs see them instead."""
    ids = {model.body(name).id for name in bodies}
    geoms = [g for g in range(model.ngeom) if model.geom_bodyid[g] in ids]
    for g in geoms:
        model.geom_contype[g] = model.geom_conaffinity[g] = 0
    if robot is not None and robot.contact_bodies:
        touching = {model.body(name).id for name in robot.contact_bodies}
        geoms = [g for g in geoms if model.geom_bodyid[g] in touching]
    return geoms


_LINK_KINDS = {
    mujoco.mjtGeom.mjGEOM_BOX: "box",
    mujoco.mjtGeom.mjGEOM_SPHERE: "sphere",
    mujoco.mjtGeom.mjGEOM_CAPSULE: "capsule",
    mujoco.mjtGeom.mjGEOM_MESH: "mesh",
}


def _link_geom(model: mujoco.MjModel, g: int) -> LinkGeom:
    """The DANO-side view of a robot collision geom (convex meshes as half-space intersections)."""
    from scipy.spatial import ConvexHull

    body = int(model.geom_bodyid[g])
    kind = _LINK_KINDS.get(mujoco.mjtGeom(model.geom_type[g]))
    if kind is None:
        raise SceneError(f"robot geom {g} of type {mujoco.mjtGeom(model.geom_type[g]).name} is not supported")
    size = tuple(float(v) for v in model.geom_size[g])
    normals = offsets = None
    if kind == "mesh":
        m = model.geom_dataid[g]
        vert = model.mesh_vert[model.mesh_vertadr[m] : model.mesh_vertadr[m] + model.mesh_vertnum[m]]
        planes = np.unique(np.round(ConvexHull(vert).equations, 6), axis=0)  # n . x + c <= 0 inside
        normals, offsets = jnp.asarray(planes[:, :3]), jnp.asarray(-planes[:, 3])
        radius = float(np.max(np.linalg.norm(vert, axis=1)))
    else:
        radius = float(np.linalg.norm(model.geom_size[g])) + (size[1] if kind == "capsule" else 0.0)
    return LinkGeom(g, body, int(model.body_rootid[body]), kind, size, radius, normals, offsets)


def _unit(v) -> tuple[float, float, float]:
    n = np.asarray(v, dtype=float)
    if n.shape != (3,) or not np.linalg.norm(n) > 0:
        raise SceneError(f"ground normal must be a non-zero 3-vector, got {v}")
    return tuple(float(x) for x in n / np.linalg.norm(n))  # type: ignore[return-value]


def _set_free(model, qpos, qvel, a, v, pos, quat, vel, angvel) -> None:
    q = np.asarray(quat, dtype=float)
    q = q / np.linalg.norm(q)
    qpos[a : a + 3], qpos[a + 3 : a + 7] = pos, q
    R = np.zeros(9)
    mujoco.mju_quat2Mat(R, q)
    qvel[v : v + 3] = vel
    qvel[v + 3 : v + 6] = R.reshape(3, 3).T @ np.asarray(angvel, dtype=float)  # MuJoCo: body frame


def _vec(n: int | None = None, nonzero: bool = False):
    def check(value, name):
        count = len(value) if n is None and isinstance(value, list) else (n or 1)
        return V.vector(value, name, SceneError, count, nonzero=nonzero)

    return check


def _num(**kw):
    return lambda value, name: V.number(value, name, SceneError, **kw)


def _choice(options):
    return lambda value, name: V.choice(value, name, SceneError, options)


_name = lambda value, name: V.text(value, name, SceneError)  # noqa: E731
_positive = _num(low=0.0, strict=True)
_POSE = {"pos": _vec(3), "quat": _vec(4, nonzero=True), "vel": _vec(3), "angvel": _vec(3)}
_SCHEMA = {
    "sim": {
        "timestep": _positive, "duration": _positive, "gravity": _vec(3),
        "substeps": lambda v, n: V.integer(v, n, SceneError, low=1),
        "force_mode": _choice(("points", "centroid")), "integrator": _choice(DEFAULT_SUBSTEPS),
        "contact_budget": lambda v, n: V.integer(v, n, SceneError, low=1),
    },
    "ground": {"height": _num(), "normal": _vec(3, nonzero=True)},
    "body": {"name": _name, "dano": _name, "mass": _positive, **_POSE},
    "primitive": {
        "name": _name, "type": _choice(SIZES), "size": _vec(), "mode": _choice(("static", "free", "mocap", "actuated")),
        "mass": _positive, "collide": lambda v, n: V.boolean(v, n, SceneError), **_POSE,
    },
    "contact": {f.name: _num() for f in dataclasses.fields(ContactParams)},
}  # fmt: skip
"""Each TOML table's keys and their checks (the same `dano.validate` checks the classes run)."""
_SCHEMA["pair"] = {"a": _name, "b": _name, **_SCHEMA["contact"]}


def _read(table, kind: str, where: str, path, required: tuple[str, ...] = ()) -> dict:
    """A TOML table checked against `_SCHEMA[kind]`: no unknown or missing keys, every value of
    the right type and range, normalised (floats, tuples); errors name the file and the table."""
    if not isinstance(table, dict):
        raise SceneError(f"{path}: {where} must be a table, got {table!r}")
    schema = _SCHEMA[kind]
    unknown = sorted(set(table) - set(schema))
    if unknown:
        raise SceneError(f"{path}: unknown key(s) {unknown} in {where}; allowed: {sorted(schema)}")
    missing = [k for k in required if k not in table]
    if missing:
        raise SceneError(f"{path}: {where} needs {' and '.join(repr(k) for k in missing)}")
    return {key: _located(path, where, lambda k=key: schema[k](table[k], k)) for key in table}


def load_scene(path) -> Scene:
    """Reads a scene TOML file (format in README); `dano` paths are relative to the file.

    Every value is checked here, before any work, with the checks the Python classes run (`Scene`,
    `DanoBody`, `Primitive`, `ContactParams`); errors name the file, the table and the key.

    Raises:
        SceneError: unknown or missing keys, bad types or values, no bodies, a missing DANO file.
    """
    import tomllib
    from pathlib import Path

    from dano.errors import DanoError
    from dano.io import load_dano

    path = Path(path)
    try:
        doc = tomllib.loads(path.read_text())
    except (FileNotFoundError, IsADirectoryError, NotADirectoryError):
        raise SceneError(f"{path}: no such file") from None
    except UnicodeDecodeError:
        raise SceneError(f"{path}: not a text file") from None
    except tomllib.TOMLDecodeError as e:
        raise SceneError(f"{path}: not valid TOML ({e})") from None
    unknown = sorted(set(doc) - {"sim", "ground", "body", "primitive", "contact", "pair"})
    if unknown:
        raise SceneError(f"{path}: unknown table(s) {unknown}; allowed: body, contact, ground, pair, primitive, sim")
    sim = _read(doc.get("sim", {}), "sim", "[sim]", path)
    values = _read(doc.get("contact", {}), "contact", "[contact]", path)
    contact = _located(path, "[contact]", lambda: dataclasses.replace(ContactParams(), **values))
    bodies = []
    for i, table in enumerate(_tables(doc, "body", path)):
        where = f"[[body]] #{i + 1}"
        b = _read(table, "body", where, path, required=("name", "dano"))
        try:
            obj = load_dano(path.parent / b.pop("dano"))
            obj = obj.with_mass(b.pop("mass")) if "mass" in b else obj
            bodies.append(DanoBody(b.pop("name"), obj, **b))
        except DanoError as e:
            raise SceneError(f"{path}: {where}: {e}") from None
    prims = []
    for i, table in enumerate(_tables(doc, "primitive", path)):
        where = f"[[primitive]] #{i + 1}"
        p = _read(table, "primitive", where, path, required=("name", "type", "size"))
        prims.append(_located(path, where, lambda p=p: Primitive(p.pop("name"), p.pop("type"), p.pop("size"), **p)))
    pair_contact = []
    for i, table in enumerate(_tables(doc, "pair", path)):
        where = f"[[pair]] #{i + 1}"
        p = _read(table, "pair", where, path, required=("a", "b"))
        key = (p.pop("a"), p.pop("b"))
        pair_contact.append((key, _located(path, where, lambda p=p: dataclasses.replace(contact, **p))))
    if not bodies:
        raise SceneError(f"{path}: no [[body]]: a scene needs at least one DANO")
    kw: dict[str, Any] = {**sim, "bodies": tuple(bodies), "primitives": tuple(prims), "contact": contact,
                          "pair_contact": tuple(pair_contact)}  # fmt: skip
    if "ground" in doc:
        ground = _read(doc["ground"], "ground", "[ground]", path)
        kw.update(ground_height=ground.get("height", 0.0), ground_normal=ground.get("normal", (0.0, 0.0, 1.0)))
    else:
        kw["ground_height"] = None
    return _located(path, None, lambda: Scene(**kw))


def _tables(doc: dict, key: str, path) -> list:
    value = doc.get(key, [])
    if not isinstance(value, list):
        raise SceneError(f"{path}: {key} must be written as [[{key}]] tables")
    return value


def _located(path, where: str | None, make):
    """`make()`, with a `SceneError` from the classes' own checks prefixed by file and table."""
    try:
        return make()
    except InvalidValueError as e:
        raise SceneError(f"{path}: {where}: {e}" if where else f"{path}: {e}") from None
