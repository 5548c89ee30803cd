"""Batched rollouts sharded over several devices equal unsharded ones (two CPU devices, forced)."""

import subprocess
import sys
import textwrap

import pytest

SCRIPT = textwrap.dedent(
    """
    import os
    os.environ["XLA_FLAGS"] = "--xla_force_host_platform_device_count=2"
    import jax
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np
    import dano
    from dano.fields import BoxField
    from dano.sim import DanoBody, Scene
    from dano.sim.run import Simulation, SimulationError, shard_batch
    from dano.sim.step import rollout

    assert jax.local_device_count() == 2
    box = dano.build_dano(BoxField([0.05, 0.04, 0.02]), n_points=300, mass=0.5, log2_samples=11, grid_resolution=0)
    lift = -float(np.min(np.asarray(box.body_points)[:, 2]))
    sim = Simulation.from_scene(Scene(bodies=(DanoBody("b", box, pos=(0, 0, lift)),)))
    batch = sim.batch_data(4)
    batch = batch.replace(qvel=batch.qvel.at[:, 0].set(jnp.asarray([0.0, 0.3, 0.6, 0.9])))
    traj = sim.run_batch(batch, 30)
    assert len(traj.qpos.sharding.device_set) == 2, traj.qpos.sharding
    one = jax.jit(lambda d: rollout(sim.world, sim.params, sim.mjx_model, d, 30))
    for i in range(4):
        alone = one(jax.tree.map(lambda x: x[i], batch))
        np.testing.assert_allclose(np.asarray(traj.qpos[i]), np.asarray(alone.qpos), rtol=0, atol=1e-12)
    slid = np.asarray(traj.qpos[:, -1, 0])
    assert np.all(np.diff(slid) > 0.001), slid  # faster starts slide further: the envs differ
    try:
        shard_batch(sim.batch_data(3))
    except SimulationError as e:
        assert "does not divide over 2 devices" in str(e)
    else:
        raise AssertionError("a batch of 3 over 2 devices was accepted")
    print("sharded ok")
    """
)


@pytest.mark.slow
def test_sharded_batched_rollouts_equal_unsharded_ones():
    """`Simulation.run_batch` over two forced CPU devices: the batch is split across both, each
    environment equals its own unsharded rollout, and an uneven batch is refused by name."""
    done = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "sharded ok" in done.stdout
