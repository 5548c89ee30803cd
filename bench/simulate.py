"""Simulation speed on this machine, side by side in one run.

- steps/s of the bunny DANO (5000 points) resting on the ground: single rollout, vmapped 64 and
  1024 environments, per-point and centroid force modes; JIT compile time apart;
- the same scene in MuJoCo C with the bunny as a CoACD convex decomposition (the mesh path);
- a DANO-DANO step with the partner's density from its neural network vs from the baked grid.

Run: `python bench/simulate.py`. A "step" is one MuJoCo step (a frame has `substeps` of them).
"""

import time

import equinox as eqx
import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from dano import build_dano
from dano.baselines.mesh import convex_decomposition, mujoco_mesh_model
from dano.demo import bunny_mesh
from dano.fields import NeuralField, mesh_field
from dano.sim import DanoBody, Scene
from dano.sim.run import Simulation
from dano.sim.step import rollout


def timed_rollout(sim: Simulation, frames: int, batch: int | None = None):
    d = sim.data
    if batch is None:
        fn = eqx.filter_jit(lambda d: rollout(sim.world, sim.params, sim.mjx_model, d, frames).qpos[-1])
    else:
        d = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (batch, *x.shape)), d)
        d = d.replace(qvel=d.qvel.at[:, 0].set(jnp.linspace(0.0, 0.5, batch)))
        fn = eqx.filter_jit(jax.vmap(lambda d: rollout(sim.world, sim.params, sim.mjx_model, d, frames).qpos[-1]))
    t0 = time.perf_counter()
    jax.block_until_ready(fn(d))
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    jax.block_until_ready(fn(d))
    run = time.perf_counter() - t0
    steps = frames * sim.world.substeps * (batch or 1)
    return steps / run, first - run


def integrators() -> None:
    """The explicit step (4 substeps of 0.5 ms per 2 ms frame, the first wave's default) beside the
    implicit one (one 2 ms step, the default): cost per frame, simulated seconds per second, JIT
    compile, and the largest energy gain over the run (J above the start; > 0 is energy from nowhere),
    for a 5000-point flat box at rest, sliding at 1 m/s (mu 0.5) and dropped flat from 0.3 m."""
    from dano.fields import BoxField
    from dano.sim.run import mechanical_energy

    box = build_dano(BoxField([0.1, 0.1, 0.05]), n_points=5000, mass=1.0, log2_samples=13, grid_resolution=0)
    lift = -float(np.min(np.asarray(box.body_points)[:, 2]))
    cases = (("at rest", (0, 0, lift), (0, 0, 0)), ("sliding", (0, 0, lift), (1, 0, 0)),
             ("dropped 0.3 m", (0, 0, lift + 0.3), (0, 0, 0)))  # fmt: skip
    head = f"{'flat box, 5000 points, 1 kg':34}{'ms / 2 ms frame':>16}{'sim s / s':>12}{'JIT [s]':>10}"
    print(f"{head}{'max E gain [J]':>16}")
    for label, pos, vel in cases:
        for integrator, substeps in (("explicit", 4), ("implicit", 1)):
            body = DanoBody("box", box, pos=pos, vel=vel)
            sim = Simulation.from_scene(Scene(bodies=(body,), integrator=integrator, substeps=substeps))
            rate, compile_s = timed_rollout(sim, 200)
            frame_ms = 1e3 * substeps / rate
            traj = eqx.filter_jit(lambda d: rollout(sim.world, sim.params, sim.mjx_model, d, 500))(sim.data)  # noqa: B023
            _, kinetic, potential = mechanical_energy(sim, sim.params, np.asarray(traj.qpos), np.asarray(traj.qvel))
            energy = (kinetic + potential).sum(axis=1)
            gain = np.nanmax(energy - energy[0]) if np.all(np.isfinite(energy)) else float("inf")
            name = f"{integrator} x{substeps}, {label}"
            print(f"{name:34}{frame_ms:>16.2f}{2.0 / frame_ms:>12.2f}{compile_s:>10.1f}{gain:>16.3g}")


def main() -> None:
    import sys

    if "--integrators" in sys.argv:
        integrators()
        return
    mesh = bunny_mesh()
    bunny = build_dano(mesh_field(mesh, resolution=80, progress=False), n_points=5000)
    lift = -float(np.min(np.asarray(bunny.body_points)[:, 2]))
    rows = []
    for mode in ("points", "centroid"):
        sim = Simulation.from_scene(Scene(bodies=(DanoBody("bunny", bunny, pos=(0, 0, lift)),), force_mode=mode))
        for batch, frames in ((None, 500), (64, 50), (1024, 5)):
            rate, compile_s = timed_rollout(sim, frames, batch)
            rows.append((f"DANO bunny, {mode}, {batch or 1} env", rate, compile_s))

    pieces = convex_decomposition(mesh.simplify_quadric_decimation(face_count=8000), threshold=0.08, max_hulls=16)
    model = mujoco_mesh_model(pieces, float(bunny.mass), pos=(0, 0, 0.1), timestep=0.0005)
    data = mujoco.MjData(model)
    for _ in range(2000):
        mujoco.mj_step(model, data)
    t0 = time.perf_counter()
    for _ in range(4000):
        mujoco.mj_step(model, data)
    c_rate = 4000 / (time.perf_counter() - t0)
    rows.append((f"MuJoCo C, CoACD bunny ({len(pieces)} hulls)", c_rate, 0.0))

    # DANO-DANO: two bunnies touching; the partner's density from a network vs its baked grid.
    network = NeuralField(bunny.grid_bounds, key=jax.random.key(0))
    for label, field in (("baked grid", None), ("network 8x128", network)):
        bodies = (
            DanoBody("a", bunny, pos=(0, 0, lift), field=field),
            DanoBody("b", bunny, pos=(0.12, 0, lift), field=field),
        )
        sim = Simulation.from_scene(Scene(bodies=bodies))
        rate, compile_s = timed_rollout(sim, 20)
        rows.append((f"two DANO bunnies, {label}", rate, compile_s))

    print(f"{'scene':44}{'steps/s':>14}{'JIT compile [s]':>18}{'ratio to MuJoCo C':>20}")
    for name, rate, compile_s in rows:
        print(f"{name:44}{rate:>14,.0f}{compile_s:>18.1f}{rate / c_rate:>20.2f}")


if __name__ == "__main__":
    main()
