"""Contact forces along a trajectory: where each pair pushes its DANO, and how hard.

For each frame of a rollout, each pair's force and torque on its DANO are those of the step that
starts from that frame's state, as the step computes them (the implicit step: the pair's part of
the solved backward-Euler forces, friction included; the explicit step: eqs. 11-16 at the state),
and the point where the force is drawn is where its normal force acts (the centroid of the points'
normal forces; the overlap centroid chi for the explicit step). Used by the renders' and the
viewer's arrows and for checks: on a body at rest the pairs' forces carry its weight.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from dano.sim.step import Trajectory, explicit_contacts, scaled_model
from dano.sim.world import pair_name, pairs


@dataclasses.dataclass(frozen=True)
class ContactForces:
    """Per frame (T+1, as the trajectory's states) and pair (P, `dano.sim.world.pairs`), world:

    Attributes:
        names: each pair's (DANO, partner) names ("ground" for the ground).
        point: (T+1, P, 3) where the pair's normal force acts, m (the DANO's centre without contact).
        force: (T+1, P, 3) the pair's force on the DANO, N.
        torque: (T+1, P, 3) its torque about the DANO's centre of mass, N m.
    """

    names: tuple[tuple[str, str], ...]
    point: np.ndarray
    force: np.ndarray
    torque: np.ndarray

    def largest(self) -> float:
        """The largest force over frames and pairs, N (0 without contact)."""
        return float(np.max(np.linalg.norm(self.force, axis=-1), initial=0.0))


def contact_forces(sim, traj: Trajectory, params=None, ctrl=None, mocap_pos=None, batch: int = 32) -> ContactForces:
    """The contact forces of every frame of `traj`, a rollout of `sim` (module docstring).

    Args:
        sim: the `dano.sim.run.Simulation` that produced `traj`.
        params: the parameters it ran with (default: the simulation's).
        ctrl, mocap_pos: the per-frame inputs it ran with (see `dano.sim.step.rollout`), if any.
        batch: frames computed at once (memory against speed).
    """
    world, params = sim.world, sim.params if params is None else params
    names = tuple(pair_name(world, p) for p in pairs(world))
    qpos, qvel = jnp.asarray(traj.qpos), jnp.asarray(traj.qvel)
    T = qpos.shape[0]
    d0 = sim.data
    # The inputs of the frame each state starts (the last state: the last frame's again, the mocap
    # bodies moving on as before). The step places the mocap bodies where its first substep ends.
    ctrl_t = _per_state(d0.ctrl, ctrl, T)
    target = _per_state(d0.mocap_pos, mocap_pos, T)[:-1]  # where the mocap bodies are a frame later
    at = jnp.concatenate([d0.mocap_pos[None], target])  # where they are at each state
    mocap_vel = (target - at[:-1]) / (world.dt * world.substeps)
    mocap_vel = jnp.concatenate([mocap_vel, mocap_vel[-1:] if T > 1 else jnp.zeros_like(d0.mocap_pos)[None]])
    mocap_first = at + world.dt * mocap_vel
    m = scaled_model(world, params, sim.mjx_model)

    def one(inputs):
        q, v, c, mp, mv = inputs
        d = d0.replace(qpos=q, qvel=v, ctrl=c, mocap_pos=mp)
        mv = mv if mp.shape[0] else None
        if world.integrator == "implicit":
            from dano.sim.implicit import implicit_contacts

            return implicit_contacts(world, params, m, d, mv)
        return explicit_contacts(world, params, m, d, mv)

    inputs = (qpos, qvel, ctrl_t, mocap_first, mocap_vel)
    wrench, point = jax.jit(lambda xs: jax.lax.map(one, xs, batch_size=batch))(inputs)
    wrench, point = np.asarray(wrench), np.asarray(point)
    return ContactForces(names, point, wrench[..., :3], wrench[..., 3:])


def _per_state(start, inputs, T: int):
    """Per state (T,): the input of the frame that starts from it; `inputs` has one row per frame
    (T - 1), the last state reuses the last row; none: `start` throughout."""
    if inputs is None or T < 2:
        return jnp.broadcast_to(start, (T, *jnp.shape(start)))
    inputs = jnp.asarray(inputs)
    return jnp.concatenate([inputs, inputs[-1:]])
