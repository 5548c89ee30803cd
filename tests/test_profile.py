"""Where the time goes (`dano.sim.run.profile`, `dano simulate --profile`), the implicit step's
shortcuts (no `mjx.step` where MuJoCo moves nothing, no solve where nothing touches) and the command
line's compilation cache."""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dano
import dano.sim.implicit as implicit
from dano.cli import CACHE_VARIABLE, compilation_cache, main
from dano.fields import BoxField
from dano.sim import DanoBody, Primitive, Scene
from dano.sim.run import Simulation, profile
from dano.sim.step import rollout
from dano.sim.toml import load_scene


@pytest.fixture(scope="module")
def box():
    return dano.build_dano(BoxField([0.06, 0.04, 0.03]), n_points=400, mass=0.3, log2_samples=12, grid_resolution=0)


def _resting(box, **scene):
    lift = -float(np.min(np.asarray(box.body_points)[:, 2]))
    body = DanoBody("box", box, pos=(0, 0, lift - 2e-4), vel=(0.3, 0.0, 0.0), angvel=(0.0, 0.0, 2.0))
    return Simulation.from_scene(Scene(bodies=(body,), **scene))


def test_profile_times_the_parts_and_its_engine_run_has_no_contact(box):
    sim = _resting(box)
    prof = profile(sim, 20, repeats=1)
    assert prof.frames == 20
    for value in (prof.lower, prof.compile, prof.run, prof.engine, prof.contact):
        assert np.isfinite(value) and value >= 0.0
    assert prof.lower > 0 and prof.compile > 0 and prof.run > 0
    assert any("contact" in line and "engine" in line for line in prof.lines())
    # The engine-only world has no pair: the box resting on the ground falls through it.
    free = dataclasses.replace(sim.world, contact=False)
    params = dataclasses.replace(sim.params, contact=())
    z = rollout(free, params, sim.mjx_model, sim.data, 20).qpos[:, 2]
    assert float(z[-1]) < float(z[0]) - 0.5 * 9.81 * 0.04**2 * 0.9
    held = rollout(sim.world, sim.params, sim.mjx_model, sim.data, 20).qpos[:, 2]
    assert abs(float(held[-1] - held[0])) < 1e-3


def test_simulate_cli_profile_prints_the_split(box, tmp_path, capsys):
    dano.save_dano(tmp_path / "box.dano.npz", box)
    lift = -float(np.min(np.asarray(box.body_points)[:, 2]))
    (tmp_path / "scene.toml").write_text(
        f'[sim]\ntimestep = 0.002\nduration = 0.02\n[ground]\nheight = 0.0\n[[body]]\nname = "box"\n'
        f'dano = "box.dano.npz"\npos = [0.0, 0.0, {lift}]\n'
    )
    assert main(["simulate", str(tmp_path / "scene.toml"), "-o", str(tmp_path / "t.csv"), "--profile"]) == 0
    out = capsys.readouterr().out
    assert "XLA" in out and "ms per frame" in out and "contact" in out and "engine" in out


@pytest.mark.parametrize("with_sphere", [False, True])
def test_skipping_mujocos_step_changes_nothing(box, monkeypatch, with_sphere):
    """A DANO among static geometry: the step skips `mjx.step` (nothing there moves); forcing it
    gives the same trajectory. With a free sphere MuJoCo moves something, and the step is taken."""
    prims = (Primitive("ball", "sphere", (0.02,), pos=(-0.07, 0, 0.02), mode="free", mass=0.2, vel=(0.5, 0, 0)),)
    sim = _resting(box, primitives=prims if with_sphere else ())
    assert implicit.mujoco_moves(sim.world, sim.mjx_model) == with_sphere

    def run():
        return jax.jit(lambda d: rollout(sim.world, sim.params, sim.mjx_model, d, 30))(sim.data)

    skipped = run()
    monkeypatch.setattr(implicit, "mujoco_moves", lambda world, m: True)
    taken = run()
    # two programs, so the same to within rounding (XLA may order a sum differently in each)
    np.testing.assert_allclose(np.asarray(skipped.qpos), np.asarray(taken.qpos), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(np.asarray(skipped.qvel), np.asarray(taken.qvel), rtol=1e-12, atol=1e-14)
    assert float(jnp.abs(skipped.qvel[-1, :6] - skipped.qvel[0, :6]).max()) > 0.01  # contact acted


@pytest.mark.parametrize("collide", [False, True])
def test_an_actuated_pusher_that_does_not_collide_is_integrated_as_mujoco_would(box, monkeypatch, collide):
    """An actuated sphere with MuJoCo's own collisions off: the step integrates its slides itself
    and skips `mjx.step`; forcing `mjx.step` gives the same trajectory. Colliding, it is taken."""
    pusher = Primitive("pusher", "sphere", (0.02,), pos=(-0.06, 0, 0.025), mode="actuated", mass=0.5, collide=collide)
    sim = _resting(box, primitives=(pusher,))
    assert implicit.mujoco_moves(sim.world, sim.mjx_model) == collide
    if collide:
        return
    ctrl = jnp.tile(jnp.array([10.0, 1.0, 0.0]), (40, 1))

    def run():
        return jax.jit(lambda d, u: rollout(sim.world, sim.params, sim.mjx_model, d, 40, ctrl=u))(sim.data, ctrl)

    skipped = run()
    monkeypatch.setattr(implicit, "mujoco_moves", lambda world, m: True)
    taken = run()
    np.testing.assert_allclose(np.asarray(skipped.qpos), np.asarray(taken.qpos), rtol=0, atol=1e-10)
    np.testing.assert_allclose(np.asarray(skipped.qvel), np.asarray(taken.qvel), rtol=0, atol=1e-8)
    v = sim.world.prims[0].qvel
    assert float(skipped.qvel[-1, v]) < 0.9 * 10.0 / 0.5 * 40 * 0.002  # the box held it back: contact acted


def test_a_scene_files_primitive_collide_must_be_a_bool(tmp_path):
    path = tmp_path / "scene.toml"
    path.write_text('[[primitive]]\nname = "p"\ntype = "sphere"\nsize = [0.02]\nmode = "actuated"\ncollide = 1\n')
    with pytest.raises(dano.sim.SceneError, match="collide must be true or false"):
        load_scene(path)


def test_a_body_in_the_air_follows_the_free_motion_exactly(box):
    """Nothing touches: the step's answer is the free motion (no solve), in value and in gradient."""
    body = DanoBody("box", box, pos=(0, 0, 0.5), vel=(0.2, -0.1, 0.3), angvel=(1.0, -2.0, 0.5))
    sim = Simulation.from_scene(Scene(bodies=(body,)))

    def z(vz):
        d = sim.data.replace(qvel=sim.data.qvel.at[2].set(vz))
        return rollout(sim.world, sim.params, sim.mjx_model, d, 10).qpos[-1, 2]

    t = 10 * 0.002
    assert float(z(0.3)) == pytest.approx(0.5 + 0.3 * t - 0.5 * 9.81 * t * (t + 0.002), abs=1e-12)
    assert float(jax.grad(z)(0.3)) == pytest.approx(t, abs=1e-12)


def test_the_command_lines_compilation_cache_folder(tmp_path, monkeypatch):
    before = jax.config.jax_compilation_cache_dir  # pyright: ignore[reportAttributeAccessIssue]
    try:
        monkeypatch.setenv(CACHE_VARIABLE, str(tmp_path / "cache"))
        assert compilation_cache() == str(tmp_path / "cache")
        assert jax.config.jax_compilation_cache_dir == str(tmp_path / "cache")  # pyright: ignore[reportAttributeAccessIssue]
        monkeypatch.setenv(CACHE_VARIABLE, "off")
        jax.config.update("jax_compilation_cache_dir", before)
        assert compilation_cache() is None and jax.config.jax_compilation_cache_dir == before  # pyright: ignore[reportAttributeAccessIssue]
    finally:
        jax.config.update("jax_compilation_cache_dir", before)
