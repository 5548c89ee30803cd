"""Why dano sets `XLA_FLAGS=--xla_cpu_use_fusion_emitters=false` (see `dano._env`).

    python bench/xla_fusion.py

Times MJX forward kinematics (jitted, compiled ahead) with XLA's CPU fusion emitters on and off,
each in its own process (the flag is read when JAX starts): a 9-link hinge chain with identity and
with rotated body frames, and the Franka Panda. Prints milliseconds per call and the ratio.
"""

import json
import os
import subprocess
import sys

CHILD = r"""
import json, sys, time
import jax
import mujoco
from mujoco import mjx

def chain(quat):
    bodies = "".join(
        f'<body pos="0 0 0.1" quat="{quat}"><joint type="hinge" axis="0 0 1"/><geom size=".02 .05" type="capsule"/>'
        for _ in range(9)
    )
    return mujoco.MjModel.from_xml_string(f"<mujoco><worldbody>{bodies}{'</body>' * 9}</worldbody></mujoco>")

def panda():
    from dano.sim.scene import _robot_spec, panda
    return _robot_spec(panda()).compile()

def per_call(model, repeats=5):
    m = mjx.put_model(model)
    d = mjx.make_data(m)
    with jax.numpy_dtype_promotion("standard"), jax.numpy_rank_promotion("allow"):
        f = jax.jit(lambda d: mjx.kinematics(m, d).xpos).lower(d).compile()
    jax.block_until_ready(f(d))
    start = time.perf_counter()
    for _ in range(repeats):
        out = f(d)
    jax.block_until_ready(out)
    return (time.perf_counter() - start) / repeats * 1e3

models = {"chain, identity frames": chain("1 0 0 0"), "chain, rotated frames": chain("0.8 0.6 0 0"), "Panda": panda()}
print(json.dumps({name: per_call(model) for name, model in models.items()}))
"""


def measure(emitters: bool) -> dict[str, float]:
    flags = f"--xla_cpu_use_fusion_emitters={'true' if emitters else 'false'}"
    env = {**os.environ, "XLA_FLAGS": flags, "PYTHONWARNINGS": "ignore"}
    out = subprocess.run([sys.executable, "-c", CHILD], env=env, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    on, off = measure(True), measure(False)
    print(f"{'MJX kinematics, ms per call':<28} {'emitters on':>12} {'off (dano)':>12} {'ratio':>10}")
    for name in on:
        print(f"{name:<28} {on[name]:12.3f} {off[name]:12.3f} {on[name] / off[name]:10.0f}x")


if __name__ == "__main__":
    main()
