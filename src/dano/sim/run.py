"""Host-side driver: compile a scene, roll it out, check it, and write the trajectory.

Penalty contact is stiff: when the time step is too large for the spring and damper, the state
grows without bound. `check_trajectory` turns that into a `SimulationError` that names the first
bad frame and the likely cause, instead of returning NaNs.
"""

import csv
import dataclasses
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from mujoco import mjx

from dano.errors import DanoError
from dano.io import atomic_write
from dano.sim.scene import Scene, compile_scene
from dano.sim.step import Trajectory, rollout


class SimulationError(DanoError):
    """The simulation blew up (non-finite state or runaway speed)."""


MAX_SPEED = 100.0
"""m/s (or rad/s * 0.1 m): beyond this a tabletop scene has certainly blown up."""


@dataclasses.dataclass(frozen=True)
class Simulation:
    """A compiled scene ready to roll out: the MuJoCo model, the MJX model and data, the world."""

    scene: Scene
    model: object
    mjx_model: mjx.Model
    data: mjx.Data
    world: object
    params: object
    _compiled: dict = dataclasses.field(default_factory=dict, repr=False, compare=False)

    @classmethod
    def from_scene(cls, scene: Scene) -> "Simulation":
        model, world, params, qpos, qvel = compile_scene(scene)
        m = mjx.put_model(model)
        d = mjx.make_data(m).replace(qpos=jnp.asarray(qpos), qvel=jnp.asarray(qvel))
        return cls(scene, model, m, d, world, params)

    def run(self, n_frames: int | None = None, params=None, ctrl=None, mocap_pos=None, external=None) -> Trajectory:
        """Rolls out (jitted) and checks the result; raises `SimulationError` on a blow-up.

        `ctrl` (n_frames, nu), `mocap_pos` (n_frames, nmocap, 3) and `external` (n_frames, nbody, 6)
        are optional per-frame inputs (see `rollout`).
        """
        n = self.scene.n_steps if n_frames is None else n_frames

        if n not in self._compiled:

            def go(params, d, ctrl, mocap_pos, external):
                return rollout(self.world, params, self.mjx_model, d, n, ctrl, mocap_pos, external)

            self._compiled[n] = jax.jit(go, compiler_options=compiler_options(self.world))
        fn = self._compiled[n]
        traj = fn(self.params if params is None else params, self.data, ctrl, mocap_pos, external)
        check_trajectory(traj, self.scene)
        return traj


def compiler_options(world) -> dict | None:
    """XLA options for jitting a rollout of `world` on this backend.

    On CPU, XLA's fusion emitters make MJX's kinematic-tree code very slow: a 9-hinge chain steps in
    8.1 ms with them and 1.0 ms without, the Panda's kinematics in 54 ms vs 0.6 ms (measured here),
    while they speed up the DANO contact code (bunny, per-point: 10.2k vs 7.2k steps/s). So they are
    switched off for scenes with an articulated robot only. Pass the result to
    `jax.jit(..., compiler_options=...)` when jitting `rollout` yourself.
    """
    if world.links and jax.default_backend() == "cpu":
        return {"xla_cpu_use_fusion_emitters": False}
    return None


def check_trajectory(traj: Trajectory, scene: Scene) -> None:
    """Raises `SimulationError` at the first frame with a non-finite state or a runaway speed."""
    qpos, qvel = np.asarray(traj.qpos), np.asarray(traj.qvel)
    bad = ~np.all(np.isfinite(qpos), axis=1) | ~np.all(np.isfinite(qvel), axis=1)
    bad |= np.max(np.abs(np.nan_to_num(qvel, nan=np.inf)), axis=1) > MAX_SPEED
    if bad.any():
        frame = int(np.argmax(bad))
        raise SimulationError(
            f"the simulation blew up at frame {frame} (t = {frame * scene.timestep:.4g} s): the time step "
            f"{scene.timestep / scene.substeps:.3g} s is likely too large for the contact spring/damper; "
            "raise substeps or lower impact_spring / impact_damper"
        )


def body_poses(traj: Trajectory, sim: Simulation) -> dict[str, np.ndarray]:
    """Per DANO and free primitive: (T+1, 7) rows x, y, z, qw, qx, qy, qz (centre of mass, world)."""
    qpos = np.asarray(traj.qpos)
    w = sim.world
    out = {name: qpos[:, a : a + 7] for name, a in zip(w.names, w.dano_qpos, strict=True)}
    for name, a, mode, pos, quat in zip(w.prim_names, w.prim_qpos, w.prim_mode, w.prim_pos, w.prim_quat, strict=True):
        if mode == "free":
            out[name] = qpos[:, a : a + 7]
        elif mode == "actuated":
            fixed = np.broadcast_to(np.asarray(quat, dtype=float), (len(qpos), 4))
            out[name] = np.concatenate([np.asarray(pos) + qpos[:, a : a + 3], fixed], axis=1)
    return out


def write_csv(path: str | Path, traj: Trajectory, sim: Simulation) -> None:
    """Writes `t,body,x,y,z,qw,qx,qy,qz`, one row per frame per body, atomically."""
    poses = body_poses(traj, sim)
    with atomic_write(path) as tmp, open(tmp, "w", newline="") as f:
        out = csv.writer(f)
        out.writerow(["t", "body", "x", "y", "z", "qw", "qx", "qy", "qz"])
        n = next(iter(poses.values())).shape[0] if poses else 0
        for t in range(n):
            for name, rows in poses.items():
                out.writerow([f"{t * sim.scene.timestep:.6f}", name, *(f"{v:.9g}" for v in rows[t])])


def at_rest(scene: Scene, seconds: float = 0.5) -> Scene:
    """The scene with its DANOs moved to where they are after `seconds` of simulation (placed just
    above the table, they come to rest), so pushes start from a true equilibrium."""
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


def at_interval(scene: Scene, dt: float) -> Scene:
    """The scene with one frame per `dt` s, split into substeps no longer than the scene's own
    (`scene.timestep / scene.substeps`: the contact's Jacobian needs them short, see README)."""
    substeps = max(1, int(np.ceil(dt / (scene.timestep / scene.substeps) - 1e-9)))
    return dataclasses.replace(scene, timestep=dt, substeps=substeps)
