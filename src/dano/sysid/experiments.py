"""The paper's identification experiments as synthetic data generators (Sec. V-A, Fig. 6).

- Slide: a DANO thrown onto a table slides and stops; a camera samples its pose (soap bar).
- Push: an end effector of known mass, driven by a known force, pushes a DANO resting on the
  table (bunny); both are tracked. Contact forces scale with the DANO's mass (ψ is in kg), so a
  DANO's own motion cannot tell its mass scale α: the pusher's known mass and force do (footnote 1).

Used by the tests, `bench/sysid.py`, the examples and `dano demo`.
"""

import dataclasses
from typing import Literal

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import trimesh

from dano._mjx import mjx
from dano.contact import ContactParams
from dano.sim.compile import compile_scene
from dano.sim.run import Simulation, at_interval, at_rest, body_poses, compiler_options
from dano.sim.scene import DanoBody, Primitive, Scene
from dano.sim.step import rollout
from dano.sysid.data import Track
from dano.sysid.problem import Recording, with_values
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
    force_mode: Literal["points", "centroid"] = "points",
) -> Scene:
    """A DANO launched along the table z = 0 with `velocity` (m/s) and `spin` (rad/s about z)."""
    body = DanoBody("object", dano, pos=(0.0, 0.0, resting_height(dano)), vel=(*velocity, 0.0), angvel=(0.0, 0.0, spin))
    return Scene(bodies=(body,), contact=ContactParams(sliding_friction=friction), force_mode=force_mode)


def slide_track(
    scene: Scene, fps: float = 120.0, n_frames: int = 33, lead: int = 12, noise: float = 0.0, seed: int = 0
) -> Track:
    """The slide seen by a camera: `n_frames` poses at `fps` after `lead` frames (the landing),
    with Gaussian position noise of `noise` m per axis."""
    sim = Simulation.from_scene(at_rate(scene, fps))
    poses = body_poses(sim.run(lead + n_frames - 1), sim)[scene.bodies[0].name][lead:]
    poses = poses.copy()
    poses[:, :3] += np.random.default_rng(seed).normal(0.0, noise, poses[:, :3].shape)
    return Track.from_poses(poses, 1.0 / fps, source=f"synthetic slide, noise {noise} m, seed {seed}")


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
    pusher = Primitive(PUSHER, "sphere", (radius,), pos=(x, y, z), mode="actuated", mass=mass, collide=False)
    return Scene(
        bodies=(DanoBody("object", dano, pos=(0.0, 0.0, z)),), primitives=(pusher,),
        contact=ContactParams(sliding_friction=friction),
    )  # fmt: skip


def push_recordings(
    scene: Scene,
    truth: dict[str, float],
    n_pushes: int = 10,
    fps: float = 100.0,
    n_frames: int = 41,
    force: tuple[float, float] = (2.0, 5.0),
    seed: int = 0,
) -> list[Recording]:
    """`n_pushes` pushes simulated with the parameters `truth` (e.g. {"mass_scale": 1.3,
    "sliding_friction": 0.35}), each from the DANO at rest: the pusher starts at a random bearing
    (within ±60° of -x, at the same distance) and is driven towards the DANO's centre by a constant
    known force of random magnitude in `force` (N) for the first half, then coasts.

    Returns one `Recording` per push: tracks of the DANO and the pusher, and the controls.
    """
    plan = push_plan(scene, n_pushes, fps, n_frames, force, seed)
    scene = plan.scene
    model, world, params, qpos0, qvel0 = compile_scene(scene)
    params = with_values(params, tuple(truth), jnp.asarray(list(truth.values()), dtype=float))
    m = mjx.put_model(model)
    a = world.prims[0].qpos
    home = np.asarray(scene.primitives[0].pos)
    starts = np.tile(qpos0, (n_pushes, 1))
    starts[:, a : a + 3] = plan.starts - home

    def one(qpos, ctrl):
        d = mjx.make_data(m).replace(qpos=qpos, qvel=jnp.asarray(qvel0))
        return rollout(world, params, m, d, n_frames - 1, ctrl=ctrl).qpos

    jitted = jax.jit(jax.vmap(one), compiler_options=compiler_options(world))
    qpos = np.asarray(jitted(jnp.asarray(starts), jnp.asarray(plan.ctrls)))
    d = world.dano_qpos[0]
    return [
        _push_recording(q[:, d : d + 7], q[:, a : a + 3] + home, ctrl, fps, "synthetic push")
        for q, ctrl in zip(qpos, plan.ctrls, strict=True)
    ]


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


def _push_recording(obj: np.ndarray, pusher: np.ndarray, ctrl: np.ndarray, fps: float, source: str) -> Recording:
    """A push's recording from the DANO's poses (T, 7) and the pusher's positions (T, 3)."""
    fixed = np.tile([1.0, 0.0, 0.0, 0.0], (len(pusher), 1))
    return Recording(
        {"object": Track.from_poses(obj, 1.0 / fps, source=source),
         PUSHER: Track.from_poses(np.concatenate([pusher, fixed], axis=1), 1.0 / fps, source=source)},
        ctrl=ctrl,
    )  # fmt: skip


def mesh_push_recordings(
    scene: Scene,
    mesh: trimesh.Trimesh,
    mass: float,
    friction: float,
    n_pushes: int = 10,
    fps: float = 100.0,
    n_frames: int = 41,
    force: tuple[float, float] = (2.0, 5.0),
    seed: int = 0,
    timestep: float = 0.001,
    max_hulls: int = 16,
) -> list[Recording]:
    """The pushes of `push_recordings` (same seed, same starts and forces) simulated by another
    engine: MuJoCo C with the object's true shape, `mesh` (in the frame of the field the scene's
    DANO was built from), as a CoACD convex decomposition of `mass` kg (inertia from the pieces)
    and MuJoCo's own soft contacts with `friction` on every geom.

    The object is first left to settle on the table for 0.5 s; its tracked pose is that of the
    frame at the DANO's centre of mass, as a tracker would report a fixed frame on the object.
    """
    from dano.baselines.mesh import convex_decomposition

    plan = push_plan(scene, n_pushes, fps, n_frames, force, seed)
    dano, pusher = plan.scene.bodies[0], plan.scene.primitives[0]
    pieces = [p.apply_translation(-np.asarray(dano.dano.com)) for p in convex_decomposition(mesh, max_hulls=max_hulls)]
    model = _mesh_push_model(pieces, mass, friction, dano, pusher, timestep)
    data = mujoco.MjData(model)
    per_frame = max(1, round(1.0 / (fps * timestep)))
    mujoco.mj_forward(model, data)
    for _ in range(round(0.5 / timestep)):
        mujoco.mj_step(model, data)
    rest_qpos = data.qpos.copy()
    obj_body, pusher_body = model.body("object").id, model.body(PUSHER).id
    out = []
    for where, ctrl in zip(plan.starts, plan.ctrls, strict=True):
        mujoco.mj_resetData(model, data)
        data.qpos[:] = rest_qpos
        data.qpos[7:10] = where - np.asarray(pusher.pos)
        mujoco.mj_forward(model, data)
        obj, tip = [], []
        for k in range(n_frames):
            obj.append(np.concatenate([data.xpos[obj_body], data.xquat[obj_body]]))
            tip.append(data.xpos[pusher_body].copy())
            if k < n_frames - 1:
                data.ctrl[:] = ctrl[k]
                for _ in range(per_frame):
                    mujoco.mj_step(model, data)
        out.append(_push_recording(np.stack(obj), np.stack(tip), ctrl, fps, "MuJoCo C, CoACD mesh"))
    return out


def _mesh_push_model(pieces, mass: float, friction: float, dano: DanoBody, pusher: Primitive, timestep: float):
    """MuJoCo C model of a push: ground, the object as convex pieces, the actuated sphere."""
    from dano.baselines.mesh import mujoco_mesh_spec

    spec = mujoco_mesh_spec(pieces, mass, dano.pos, dano.quat, friction, timestep)
    mu = [friction, 0.005, 0.0001]
    tip = spec.worldbody.add_body(name=PUSHER, pos=list(pusher.pos))
    tip.gravcomp = 1.0
    for axis, vector in zip("xyz", np.eye(3), strict=True):
        tip.add_joint(name=f"slide{axis}", type=mujoco.mjtJoint.mjJNT_SLIDE, axis=vector.tolist())
        spec.add_actuator(name=f"force{axis}", target=f"slide{axis}", trntype=mujoco.mjtTrn.mjTRN_JOINT).set_to_motor()
    tip.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[pusher.size[0], 0, 0], mass=pusher.mass, friction=mu)
    return spec.compile()
