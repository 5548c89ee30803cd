"""The scenes every tool shares: the paper's slide (a DANO thrown onto a table, Sec. V-A) and push (an
end effector of known mass and force pushing a DANO at rest, Sec. V-A/B), and the random pushes of
an identification experiment. Identification (`dano.sysid.experiments`), trajectory optimisation
(`dano.trajopt.push`), the MuJoCo C baselines (`dano.baselines`) and `dano demo` build on these."""

import dataclasses
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from dano.contact import ContactParams
from dano.contact.pairs import ForceMode
from dano.math import quat_to_mat
from dano.reference import load_reference
from dano.sim.run import at_interval, at_rest
from dano.sim.scene import DanoBody, Integrator, Mode, Primitive, Scene
from dano.types import DANO


def at_rate(scene: Scene, fps: float) -> Scene:
    """The scene with one frame per camera frame (see `dano.sim.run.at_interval`)."""
    return at_interval(scene, 1.0 / fps)


def resting_height(dano: DANO) -> float:
    """Height of the centre of mass that puts the DANO's lowest surface point 0.1 mm above z = 0."""
    return float(-np.min(np.asarray(dano.body_points)[:, 2])) + 1e-4


def slide_scene(
    dano: DANO,
    friction: float = 0.5,
    velocity: tuple[float, float] = (1.6, 0.3),
    spin: float = 2.0,
    force_mode: ForceMode | str = ForceMode.points,
) -> Scene:
    """A DANO launched along the table z = 0 with `velocity` (m/s) and `spin` (rad/s about z)."""
    body = DanoBody("object", dano, pos=(0.0, 0.0, resting_height(dano)), vel=(*velocity, 0.0), angvel=(0.0, 0.0, spin))
    return Scene(bodies=(body,), contact=ContactParams(sliding_friction=friction), force_mode=force_mode)


PUSHER = "pusher"


def push_scene(
    dano: DANO, friction: float = 0.3, radius: float = 0.03, mass: float = 1.0, direction: tuple = (1.0, 0.0)
) -> Scene:
    """A DANO at rest on the table and a sphere end effector (actuated along x, y, z, weight
    compensated, known `mass`) at its centre of mass's height, 2 cm clear of it on the side away
    from the unit xy `direction` it would push in (default: behind it along -x). The pusher does not
    collide with the table in MuJoCo (`Primitive.collide`): it pushes horizontally, weight
    compensated, so it never meets it, and the implicit step then integrates it without `mjx.step`."""
    z = resting_height(dano)
    reach = float(np.max(np.linalg.norm(np.asarray(dano.body_points)[:, :2], axis=1)))
    x, y = (-(reach + radius + 0.02) * np.asarray(direction, dtype=float)).tolist()
    pusher = Primitive(PUSHER, "sphere", (radius,), pos=(x, y, z), mode=Mode.actuated, mass=mass, collide=False)
    return Scene(
        bodies=(DanoBody("object", dano, pos=(0.0, 0.0, z)),), primitives=(pusher,),
        contact=ContactParams(sliding_friction=friction),
    )  # fmt: skip


class WorldError(ValueError):
    """A scene that cannot be placed in an MJCF world as asked."""


def in_world(scene: Scene, world: str | Path, at: tuple[float, float] = (0.0, 0.0)) -> tuple[Scene, float]:
    """A scene built on the plane z = 0 (its DANOs, primitives and robot) moved onto whatever the
    MJCF `world` has under the point `at` (x, y; a table's top, its floor), in that world (its own
    floor instead of the scene's ground). Returns the scene and the height of that surface (m).

    Raises:
        WorldError: nothing of the world is under `at`, or the world cannot be loaded.
    """
    import mujoco

    try:
        model = mujoco.MjModel.from_xml_path(str(world))
    except Exception as e:  # MuJoCo raises ValueError with its parser's message
        raise WorldError(f"{world}: MuJoCo cannot load the world: {str(e).splitlines()[0]}") from None
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    tops = data.geom_xpos[:, 2] + model.geom_rbound
    high = float(np.max(tops[model.geom_rbound > 0], initial=0.0)) + 1.0
    geom = np.zeros(1, np.int32)
    start, ray = np.array([at[0], at[1], high]), np.array([0.0, 0.0, -1.0])
    down = mujoco.mj_ray(model, data, start, ray, None, 1, -1, geom)  # pyright: ignore[reportAttributeAccessIssue]
    if down < 0:
        raise WorldError(f"{world}: nothing under ({at[0]:g}, {at[1]:g}) to stand the object on")
    top = high - float(down)
    shift = np.array([at[0], at[1], top])
    moved = lambda pos: tuple(float(v) for v in np.asarray(pos, float) + shift)  # noqa: E731
    bodies = tuple(dataclasses.replace(b, pos=moved(b.pos)) for b in scene.bodies)
    prims = tuple(dataclasses.replace(p, pos=moved(p.pos)) for p in scene.primitives)
    robot = None if scene.robot is None else dataclasses.replace(scene.robot, base_pos=moved(scene.robot.base_pos))
    scene = dataclasses.replace(
        scene, bodies=bodies, primitives=prims, robot=robot, mjcf=str(world), ground_height=None
    )
    return scene, top


@dataclasses.dataclass(frozen=True)
class PushPlan:
    """The pushes of an experiment: the scene at the camera's rate with the DANO at rest, the
    pusher's start positions (n, 3) and the actuator forces (n, T - 1, 3), N."""

    scene: Scene
    starts: np.ndarray
    ctrls: np.ndarray


def push_plan(
    scene: Scene, n_pushes: int, fps: float, n_frames: int, force: tuple[float, float], seed: int
) -> PushPlan:
    """Random pushes (see `push_recordings`), the same for every engine that replays them."""
    rng = np.random.default_rng(seed)
    scene = at_rate(at_rest(scene), fps)
    home = np.asarray(scene.primitives[0].pos)
    centre = np.asarray(scene.bodies[0].pos)
    distance = np.linalg.norm(home[:2] - centre[:2])
    starts, ctrls = [], []
    for _ in range(n_pushes):
        bearing = np.pi + rng.uniform(-np.pi / 3, np.pi / 3)
        where = centre + distance * np.array([np.cos(bearing), np.sin(bearing), 0.0])
        where[2] = home[2]
        direction = (centre - where) * np.array([1.0, 1.0, 0.0])
        direction /= np.linalg.norm(direction)
        ctrl = np.zeros((n_frames - 1, 3))
        ctrl[: (n_frames - 1) // 2] = rng.uniform(*force) * direction
        starts.append(where)
        ctrls.append(ctrl)
    return PushPlan(scene, np.stack(starts), np.stack(ctrls))


def reference_drop_scene(
    collider: str | Path,
    sliding_friction: float,
    duration: float = 7.0,
    integrator: Integrator | str = Integrator.explicit,
):
    """The scene of the reference's `bunny_trajectory_<mu>.csv` runs (Dojo.jl `bunny.jl`, commit c8ccf20e).

    Bunny collider with the second moment as inertia, ground z = 0, h = 2 ms, impact spring 1e5,
    damper 1e6, sliding drag 0.01, torsional and rolling friction 0.01, the Coulomb law without its
    2/pi (as those files were made), the hard inside test and the force at the overlap centroid; COM
    starts at (0, 0, 1.1), q = normalize(1, 0.6, 0, 0.5), v = (2, 2, 1) m/s, body angular velocity
    (0.5, 1, 1) rad/s. One MuJoCo step per frame, so free flight integrates exactly as Dojo's does.
    The paper's explicit contact by default (the scheme those files were compared with in the
    paper); `integrator="implicit"` for dano's default step (README: both against the files).
    """
    bunny = load_reference(collider, inertia="second_moment")
    q0 = np.array([1.0, 0.6, 0.0, 0.5]) / np.linalg.norm([1.0, 0.6, 0.0, 0.5])
    w_world = np.asarray(quat_to_mat(jnp.asarray(q0))) @ np.array([0.5, 1.0, 1.0])
    contact = ContactParams(
        impact_spring=1e5, impact_damper=1e6, sliding_drag=0.01, sliding_friction=sliding_friction,
        torsional_friction=0.01, rolling_friction=0.01, coulomb_gain=1.0, indicator_width=0.0,
    )  # fmt: skip
    body = DanoBody("bunny", bunny, pos=(0.0, 0.0, 1.1), quat=tuple(q0), vel=(2.0, 2.0, 1.0), angvel=tuple(w_world))
    return Scene(timestep=0.002, substeps=1, duration=duration, bodies=(body,), contact=contact,
                 force_mode=ForceMode.centroid, integrator=integrator)  # fmt: skip
