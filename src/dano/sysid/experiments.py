"""The paper's identification experiments as synthetic data generators (Sec. V-A, Fig. 6), simulated
by dano's own step on the shared scenes of `dano.scenarios`.

- Slide: a DANO thrown onto a table slides and stops; a camera samples its pose (soap bar).
- Push: an end effector of known mass, driven by a known force, pushes a DANO resting on the
  table (bunny); both are tracked. Contact forces scale with the DANO's mass (ψ is in kg), so a
  DANO's own motion cannot tell its mass scale α: the pusher's known mass and force do (footnote 1).

The same pushes simulated by MuJoCo C on the mesh are `dano.baselines.pushes.mesh_push_recordings`.
"""

import jax
import jax.numpy as jnp
import numpy as np

from dano import lanes
from dano._mjx import mjx
from dano.scenarios import PUSHER, at_rate, push_plan
from dano.sim.compile import compile_scene
from dano.sim.run import Simulation, body_poses, compiler_options
from dano.sim.scene import Scene
from dano.sim.step import rollout
from dano.sysid.data import Track
from dano.sysid.params import with_values
from dano.sysid.windows import Recording


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

    jitted = jax.jit(lambda q, c: lanes.mapped(one, q, c), compiler_options=compiler_options(world))
    qpos = np.asarray(jitted(jnp.asarray(starts), jnp.asarray(plan.ctrls)))
    d = world.dano_qpos[0]
    return [
        push_recording(q[:, d : d + 7], q[:, a : a + 3] + home, ctrl, fps, "synthetic push")
        for q, ctrl in zip(qpos, plan.ctrls, strict=True)
    ]


def push_recording(obj: np.ndarray, pusher: np.ndarray, ctrl: np.ndarray, fps: float, source: str) -> Recording:
    """A push's recording from the DANO's poses (T, 7) and the pusher's positions (T, 3)."""
    fixed = np.tile([1.0, 0.0, 0.0, 0.0], (len(pusher), 1))
    return Recording(
        {"object": Track.from_poses(obj, 1.0 / fps, source=source),
         PUSHER: Track.from_poses(np.concatenate([pusher, fixed], axis=1), 1.0 / fps, source=source)},
        ctrl=ctrl,
    )  # fmt: skip
