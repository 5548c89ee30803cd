"""The paper's identification experiments as synthetic data generators (Sec. V-A, Fig. 6).

- Slide: a DANO thrown onto a table slides and stops; a camera samples its pose (soap bar).
- Push: an end effector of known mass, driven by a known force, pushes a DANO resting on the
  table (bunny); both are tracked. Contact forces scale with the DANO's mass (ψ is in kg), so a
  DANO's own motion cannot tell its mass scale α: the pusher's known mass and force do (footnote 1).

Used by the tests, `bench/sysid.py`, the examples and `dano demo`.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from mujoco import mjx

from dano.contact import ContactParams
from dano.sim.run import Simulation, body_poses, check_trajectory
from dano.sim.scene import DanoBody, Primitive, Scene, compile_scene
from dano.sim.step import rollout
from dano.sysid.data import Track
from dano.sysid.problem import Recording, at_interval, with_values
from dano.types import DANO


def at_rate(scene: Scene, fps: float) -> Scene:
    """The scene with one frame per camera frame (see `dano.sysid.problem.at_interval`)."""
    return at_interval(scene, 1.0 / fps)


def resting_height(dano: DANO) -> float:
    """Height of the centre of mass that puts the DANO's lowest surface point 0.1 mm above z = 0."""
    return float(-np.min(np.asarray(dano.body_points)[:, 2])) + 1e-4


def slide_scene(
    dano: DANO,
    friction: float = 0.5,
    velocity: tuple[float, float] = (1.6, 0.3),
    spin: float = 2.0,
    force_mode: str = "points",
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


def push_scene(dano: DANO, friction: float = 0.3, radius: float = 0.03, mass: float = 1.0) -> Scene:
    """A DANO at rest on the table and a sphere end effector (actuated along x, y, z, weight
    compensated, known `mass`) at its centre of mass's height, 0.1 m + radius away along -x."""
    z = resting_height(dano)
    reach = float(np.max(np.linalg.norm(np.asarray(dano.body_points)[:, :2], axis=1)))
    pusher = Primitive(PUSHER, "sphere", (radius,), pos=(-(reach + radius + 0.02), 0.0, z), mode="actuated", mass=mass)
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
    rng = np.random.default_rng(seed)
    settled = _at_rest(scene)
    scene = at_rate(settled, fps)
    model, world, params, qpos0, qvel0 = compile_scene(scene)
    params = with_values(params, tuple(truth), jnp.asarray(list(truth.values()), dtype=float))
    m = mjx.put_model(model)
    home = np.asarray(scene.primitives[0].pos)
    centre = np.asarray(scene.bodies[0].pos)
    a = world.prim_qpos[0]
    starts, ctrls = [], []
    for _ in range(n_pushes):
        bearing = np.pi + rng.uniform(-np.pi / 3, np.pi / 3)
        distance = np.linalg.norm(home[:2] - centre[:2])
        where = centre + distance * np.array([np.cos(bearing), np.sin(bearing), 0.0])
        where[2] = home[2]
        qpos = qpos0.copy()
        qpos[a : a + 3] = where - home
        direction = (centre - where) * np.array([1.0, 1.0, 0.0])
        direction /= np.linalg.norm(direction)
        ctrl = np.zeros((n_frames - 1, model.nu))
        ctrl[: (n_frames - 1) // 2, -3:] = rng.uniform(*force) * direction
        starts.append(qpos)
        ctrls.append(ctrl)

    def one(qpos, ctrl):
        d = mjx.make_data(m).replace(qpos=qpos, qvel=jnp.asarray(qvel0))
        return rollout(world, params, m, d, n_frames - 1, ctrl=ctrl).qpos

    qpos = np.asarray(jax.jit(jax.vmap(one))(jnp.asarray(np.stack(starts)), jnp.asarray(np.stack(ctrls))))
    out = []
    for q, ctrl in zip(qpos, ctrls, strict=True):
        d = world.dano_qpos[0]
        obj = Track.from_poses(q[:, d : d + 7], 1.0 / fps, source="synthetic push")
        pusher_pos = q[:, a : a + 3] + home
        fixed = np.tile([1.0, 0.0, 0.0, 0.0], (len(q), 1))
        pusher = Track.from_poses(np.concatenate([pusher_pos, fixed], axis=1), 1.0 / fps, source="synthetic push")
        out.append(Recording({"object": obj, PUSHER: pusher}, ctrl=ctrl))
    return out


def _at_rest(scene: Scene, seconds: float = 0.5) -> Scene:
    """The scene with its DANOs moved to where they come to rest after `seconds` (dropped from
    0.1 mm up), so pushes start from a true equilibrium."""
    sim = Simulation.from_scene(dataclasses.replace(scene, duration=seconds))
    traj = sim.run()
    check_trajectory(traj, sim.scene)
    poses = body_poses(traj, sim)
    bodies = tuple(
        dataclasses.replace(b, pos=tuple(float(v) for v in poses[b.name][-1, :3]),
                            quat=tuple(float(v) for v in poses[b.name][-1, 3:]))
        for b in scene.bodies
    )  # fmt: skip
    return dataclasses.replace(scene, bodies=bodies)
