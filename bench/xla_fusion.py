"""XLA's CPU fusion emitters, per jit: why dano turns them off for articulated scenes only.

    python bench/xla_fusion.py

dano sets no process-wide `XLA_FLAGS`; `dano.sim.run.compiler_options(world)` passes
`xla_cpu_use_fusion_emitters=False` to the jits of scenes with a robot. This times, in one process,
MJX forward kinematics (a 9-link hinge chain with identity and with rotated body frames, the Franka
Panda) and one implicit step of the bunny DANO resting on the ground, each jitted with the emitters
on and off, compiled ahead. Prints the median milliseconds per call, the ratio, and compile seconds.
"""

import statistics
import time

import jax
import mujoco

from dano._mjx import mjx

jax.config.update("jax_enable_x64", True)
OFF = {"xla_cpu_use_fusion_emitters": False}
ON = {"xla_cpu_use_fusion_emitters": True}


def chain(quat: str) -> mujoco.MjModel:
    bodies = "".join(
        f'<body pos="0 0 0.1" quat="{quat}"><joint type="hinge" axis="0 0 1"/><geom size=".02 .05" type="capsule"/>'
        for _ in range(9)
    )
    return mujoco.MjModel.from_xml_string(f"<mujoco><worldbody>{bodies}{'</body>' * 9}</worldbody></mujoco>")


def panda() -> mujoco.MjModel:
    from dano.assets import panda
    from dano.sim.robots import robot_spec as _robot_spec

    return _robot_spec(panda()).compile()


def kinematics(model: mujoco.MjModel):
    m = mjx.put_model(model)
    d = mjx.make_data(m)
    return (lambda d: mjx.kinematics(m, d).xpos), d


def bunny_step():
    from dano.assets import bunny_mesh
    from dano.build import build_dano
    from dano.fields import mesh_field
    from dano.sim.run import Simulation, at_rest
    from dano.sim.scene import DanoBody, Scene

    obj = build_dano(mesh_field(bunny_mesh(), resolution=48, progress=False), mass=0.5)
    scene = at_rest(Scene(bodies=(DanoBody("bunny", obj, pos=(0.0, 0.0, 0.2)),)), seconds=0.3)
    sim = Simulation.from_scene(scene)
    from dano.sim.step import step

    return (lambda d: step(sim.world, sim.params, sim.mjx_model, d).qpos), sim.data


def per_call(fn, x, options: dict, repeats: int = 20) -> tuple[float, float]:
    with jax.numpy_dtype_promotion("standard"), jax.numpy_rank_promotion("allow"):
        start = time.perf_counter()
        f = jax.jit(fn, compiler_options=options).lower(x).compile()
        compile_s = time.perf_counter() - start
    jax.block_until_ready(f(x))
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(f(x))
        times.append(time.perf_counter() - start)
    return statistics.median(times) * 1e3, compile_s


def main() -> None:
    cases = {
        "chain, identity frames": kinematics(chain("1 0 0 0")),
        "chain, rotated frames": kinematics(chain("0.8 0.6 0 0")),
        "Panda kinematics": kinematics(panda()),
        "bunny at rest, one step": bunny_step(),
    }
    print(f"{'ms per call (median)':<26} {'emitters on':>12} {'off':>10} {'on/off':>8}   compile s on / off")
    for name, (fn, x) in cases.items():
        (on, c_on), (off, c_off) = per_call(fn, x, ON), per_call(fn, x, OFF)
        print(f"{name:<26} {on:12.3f} {off:10.3f} {on / off:8.2f}   {c_on:.2f} / {c_off:.2f}")


if __name__ == "__main__":
    main()
