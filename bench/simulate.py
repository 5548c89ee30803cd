"""Simulation speed on this machine, side by side in one run.

- the bunny DANO (5000 points) at rest on the ground and sliding at 1 m/s, one env, on equal
  simulated seconds: the implicit step (one 2 ms step per frame, the default) over each pair's
  active set (the default) and over all points (`contact_budget` = all), beside MuJoCo C with the
  bunny as a CoACD convex decomposition (the mesh path) at its default 2 ms step and at 0.5 ms;
- batched: vmapped over 1, 64 and 256 environments (and sharded over every local device), and
  64 and 256 environments one after another, the batch split over the cores
  (`Simulation.run_batch(vmap=False)`, `dano.lanes`); "x single" divides by the single env at rest;
- JIT compile of a 500-frame rollout, lowering and compiling apart;
- a DANO-DANO step with the partner's density from its neural network vs from the baked grid.

Run: `python bench/simulate.py` (`--integrators`: explicit vs implicit on a flat box). Rates are
simulated seconds per wall-clock second (medians of 5 runs); "ratio" divides by MuJoCo C's at 2 ms.
"""

import time

import equinox as eqx
import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from dano import build_dano, lanes
from dano.assets import bunny_mesh
from dano.baselines.mesh import convex_decomposition, mujoco_mesh_model
from dano.fields import NeuralField, mesh_field
from dano.sim import DanoBody, Scene
from dano.sim.run import Simulation, rollout_lanes, shard_batch
from dano.sim.step import rollout


def _median_seconds(fn, *args, repeats: int = 5) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def timed_rollout(sim: Simulation, frames: int, batch: int | None = None, repeats: int = 5):
    """(steps per second, JIT seconds (lower + compile)) of `frames` frames, one env or `batch`
    environments (vmapped, sharded over the local devices along the batch)."""
    d = sim.data
    if batch is None:
        fn = jax.jit(lambda d: rollout(sim.world, sim.params, sim.mjx_model, d, frames).qpos[-1])
    else:
        d = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (batch, *x.shape)), d)
        d = d.replace(qvel=d.qvel.at[:, 0].set(jnp.linspace(0.0, 0.5, batch)))
        d = shard_batch(d)
        fn = jax.jit(jax.vmap(lambda d: rollout(sim.world, sim.params, sim.mjx_model, d, frames).qpos[-1]))
    t0 = time.perf_counter()
    compiled = fn.lower(d).compile()
    compile_s = time.perf_counter() - t0
    run = _median_seconds(compiled, d, repeats=repeats)
    steps = frames * sim.world.substeps * (batch or 1)
    return steps / run, compile_s


def timed_lanes(sim: Simulation, frames: int, batch: int, repeats: int = 3):
    """(steps per second, first call less a run) of `frames` frames of `batch` environments, one
    after another, the batch split over the cores (`rollout_lanes`)."""
    d = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (batch, *x.shape)), sim.data)
    d = d.replace(qvel=d.qvel.at[:, 0].set(jnp.linspace(0.0, 0.5, batch)))
    fn = lambda d: rollout_lanes(sim.world, sim.params, sim.mjx_model, d, frames).qpos  # noqa: E731
    t0 = time.perf_counter()
    jax.block_until_ready(fn(d))
    first = time.perf_counter() - t0
    run = _median_seconds(fn, d, repeats=repeats)
    return frames * sim.world.substeps * batch / run, max(first - run, 0.0)


def mujoco_rate(model, vx: float = 0.0, steps: int = 4000) -> float:
    """MuJoCo C steps per second (median of 5), from a settled state with velocity vx."""
    data = mujoco.MjData(model)
    for _ in range(int(0.5 / model.opt.timestep)):
        mujoco.mj_step(model, data)
    rates = []
    for _ in range(5):
        data.qvel[:] = 0.0
        data.qvel[0] = vx
        t0 = time.perf_counter()
        for _ in range(steps):
            mujoco.mj_step(model, data)
        rates.append(steps / (time.perf_counter() - t0))
    return float(np.median(rates))


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
    pieces = convex_decomposition(mesh.simplify_quadric_decimation(face_count=8000), threshold=0.08, max_hulls=16)
    mj = {dt: mujoco_mesh_model(pieces, float(bunny.mass), pos=(0, 0, 0.1), timestep=dt) for dt in (0.002, 0.0005)}
    print(f"{jax.device_count()} {jax.default_backend()} device(s); bunny DANO {bunny.n_points} points")

    print(f"\n{'single env, equal simulated seconds':52}{'sim s / s':>12}{'ms / 2 ms':>12}{'JIT [s]':>9}{'ratio':>8}")
    unbatched = {}
    for label, vx in (("at rest", 0.0), ("sliding 1 m/s", 1.0)):
        c_rate = mujoco_rate(mj[0.002], vx) * 0.002
        rows = []
        for name, budget in (("active set", None), ("all points", bunny.n_points)):
            body = DanoBody("bunny", bunny, pos=(0, 0, lift), vel=(vx, 0, 0))
            sim = Simulation.from_scene(Scene(bodies=(body,), contact_budget=budget))
            rate, compile_s = timed_rollout(sim, 250)
            seconds = rate * sim.scene.timestep / sim.world.substeps
            rows.append((f"DANO implicit 2 ms, {name}, {label}", seconds, compile_s))
        rows.append((f"MuJoCo C CoACD ({len(pieces)} hulls) 2 ms, {label}", c_rate, 0.0))
        rows.append((f"MuJoCo C CoACD 0.5 ms, {label}", mujoco_rate(mj[0.0005], vx) * 0.0005, 0.0))
        unbatched[label] = rows[0][1]  # over its active set
        for name, rate, compile_s in rows:
            print(f"{name:52}{rate:>12.2f}{2e3 / rate * 1e-3:>12.3f}{compile_s:>9.1f}{rate / c_rate:>8.3f}")

    at_rest = unbatched["at rest"]
    head = f"{'batched':52}{'sim s / s':>12}{'per env':>12}"
    print(f"\n{head}{'JIT [s]':>9}{'x 1 env':>8}{'x single':>9}")
    body = DanoBody("bunny", bunny, pos=(0, 0, lift))
    sim = Simulation.from_scene(Scene(bodies=(body,)))
    single = None
    cases = [("vmap", 1, 100), ("vmap", 64, 20), ("vmap", 256, 10), ("lanes", 64, 20), ("lanes", 256, 10)]
    for how, batch, frames in cases:
        if how == "vmap":
            rate, compile_s = timed_rollout(sim, frames, batch, repeats=3)
            name = f"DANO bunny at rest, {batch} envs, vmapped ({jax.device_count()} devices)"
        else:
            rate, compile_s = timed_lanes(sim, frames, batch)
            name = f"DANO bunny at rest, {batch} envs, on {lanes.count()} lanes"
        rate = rate * sim.scene.timestep / sim.world.substeps
        single = single or rate
        ratios = f"{rate / single:>8.2f}{rate / at_rest:>9.2f}"
        print(f"{name:52}{rate:>12.2f}{rate / batch:>12.3f}{compile_s:>9.1f}{ratios}")

    # DANO-DANO: two bunnies touching; the partner's density from a network vs its baked grid.
    print(f"\n{'two DANO bunnies touching':52}{'sim s / s':>12}{'JIT [s]':>9}")
    network = NeuralField(bunny.grid_bounds, key=jax.random.key(0))
    for label, field in (("baked grid", None), ("network 8x128", network)):
        bodies = (
            DanoBody("a", bunny, pos=(0, 0, lift), field=field),
            DanoBody("b", bunny, pos=(0.12, 0, lift), field=field),
        )
        sim = Simulation.from_scene(Scene(bodies=bodies))
        rate, compile_s = timed_rollout(sim, 20, repeats=3)
        print(f"{label:52}{rate * sim.scene.timestep / sim.world.substeps:>12.3f}{compile_s:>9.1f}")


if __name__ == "__main__":
    main()
