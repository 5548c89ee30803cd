"""How many surface points a DANO needs: accuracy and cost against the point count, side by side.

For each count, DANOs of the same fields (the Stanford bunny, 0.15 m; a 0.1 x 0.06 x 0.03 m box)
are built with that many points and simulated at the defaults (implicit step, one 2 ms step per
frame, each pair's active set) in four scenes:

- drop: the bunny dropped from 2 cm, upright and turned off its axes: its rest height (mm) after 1 s;
- slide: the bunny and the box launched at 1 m/s on the floor, mu = 0.5: the distance to rest,
  against the box's closed form v^2 / (2 mu g);
- incline: the box on a 20 degree slope: mu = 0.5 (it must stick: creep, mm/s) and mu = 0.3 (its
  acceleration against g (sin - mu cos));
- push: a free 0.2 kg sphere at 1 m/s hits the resting bunny, and the box: their displacement
  after 0.5 s (the sphere and the object solved jointly by the implicit step).

Each figure is given against the 5000-point DANO (the paper's count) and, where one exists, the
closed form; the last column is the cost per 2 ms frame of the bunny at rest (median of 5 runs).

Run: `python bench/points.py [--counts 250,500,1000,2000,5000]`.
"""

import argparse
import time

import jax
import numpy as np

from dano.assets import bunny_mesh
from dano.build import build_dano
from dano.contact.wrench import ContactParams
from dano.fields import BoxField, mesh_field
from dano.math import quat_to_mat
from dano.sim import DanoBody, Primitive, Scene
from dano.sim.run import Simulation, SimulationError
from dano.sim.step import rollout

G = 9.81
TURN = (0.8924, 0.2391, -0.3696, 0.1167)


def _lowest(obj, quat=(1.0, 0.0, 0.0, 0.0), normal=(0.0, 0.0, 1.0)) -> float:
    R = np.asarray(quat_to_mat(np.asarray(quat, dtype=float)))
    return float(np.min(np.asarray(obj.body_points) @ R.T @ np.asarray(normal)))


def _run(bodies, frames: int, **scene) -> np.ndarray:
    sim = Simulation.from_scene(Scene(bodies=bodies, **scene))
    return sim, sim.run(frames)


def drop(bunny, quat=(1.0, 0.0, 0.0, 0.0)) -> float:
    """The centre's height at rest (mm) after a 2 cm drop: upright (it lands on its base), or turned
    off its axes (it tumbles: which side it comes to rest on then depends on every bounce)."""
    body = DanoBody("b", bunny, pos=(0, 0, -_lowest(bunny, quat) + 0.02), quat=quat)
    _, traj = _run((body,), 500)
    return 1e3 * float(traj.qpos[-1, 2])


def slide(obj) -> float:
    body = DanoBody("b", obj, pos=(0, 0, -_lowest(obj)), vel=(1.0, 0, 0))
    _, traj = _run((body,), 400, contact=ContactParams(sliding_friction=0.5))
    return float(np.linalg.norm(np.asarray(traj.qpos[-1, :2] - traj.qpos[0, :2])))


def incline(box, mu: float) -> float:
    """mu = 0.5: creep along the slope over the last second, mm/s; mu = 0.3: acceleration, m/s^2."""
    th = np.radians(20.0)
    normal, quat = (np.sin(th), 0.0, np.cos(th)), (np.cos(th / 2), 0.0, np.sin(th / 2), 0.0)
    body = DanoBody("b", box, pos=tuple(-_lowest(box, quat, normal) * np.asarray(normal)), quat=quat)
    down = np.array([np.cos(th), 0.0, -np.sin(th)])
    _, traj = _run((body,), 750, ground_normal=normal, contact=ContactParams(sliding_friction=mu))
    if mu >= np.tan(th):
        x = np.asarray(traj.qpos[:, :3]) @ down
        return 1e3 * (x[-1] - x[250]) / 1.0
    v = np.asarray(traj.qvel[:, :3]) @ down
    return float(np.polyfit(np.arange(250, 700) * 0.002, v[250:700], 1)[0])


def push(obj) -> float:
    """A free 0.2 kg sphere at 1 m/s, 1.5 cm above the floor, hits the object: its displacement after
    0.5 s, mm."""
    lift = -_lowest(obj)
    start = float(np.min(np.asarray(obj.body_points)[:, 0])) - 0.03
    ball = Primitive("ball", "sphere", (0.015,), pos=(start, 0.0, 0.015), mode="free", mass=0.2, vel=(1.0, 0, 0))
    try:
        _, traj = _run((DanoBody("b", obj, pos=(0, 0, lift)),), 250, primitives=(ball,))
    except SimulationError as e:  # an energy error would be reported here, not hidden
        print(f"push, {obj.n_points} points: {str(e).split(';')[0]}")
        return float("nan")
    return 1e3 * float(np.linalg.norm(np.asarray(traj.qpos[-1, :2] - traj.qpos[0, :2])))


def frame_ms(bunny) -> float:
    sim = Simulation.from_scene(Scene(bodies=(DanoBody("b", bunny, pos=(0, 0, -_lowest(bunny))),)))
    fn = jax.jit(lambda d: rollout(sim.world, sim.params, sim.mjx_model, d, 200).qpos[-1]).lower(sim.data).compile()
    times = []
    for _ in range(5):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(sim.data))
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times)) / 200


def main() -> None:
    jax.config.update("jax_enable_x64", True)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--counts", default="250,500,1000,2000,5000")
    counts = sorted(int(c) for c in ap.parse_args().counts.split(","))
    bunny_field = mesh_field(bunny_mesh(), resolution=80, progress=False)
    box_field = BoxField([0.1, 0.06, 0.03])
    rows = {}
    for n in counts:
        bunny = build_dano(bunny_field, n_points=n)
        box = build_dano(box_field, n_points=n, mass=0.5, grid_resolution=0)
        rows[n] = {
            "bunny drop upright [mm]": drop(bunny),
            "bunny drop turned [mm]": drop(bunny, TURN),
            "bunny slide [m]": slide(bunny),
            "box slide [m]": slide(box),
            "box creep mu 0.5 [mm/s]": incline(box, 0.5),
            "box accel mu 0.3 [m/s2]": incline(box, 0.3),
            "bunny pushed [mm]": push(bunny),
            "box pushed [mm]": push(box),
            "bunny at rest [ms/frame]": frame_ms(bunny),
        }
        print(f"{n} points done", flush=True)
    th = np.radians(20.0)
    closed = {"box slide [m]": 1.0 / (2 * 0.5 * G), "box accel mu 0.3 [m/s2]": G * (np.sin(th) - 0.3 * np.cos(th))}
    ref = rows[max(counts)]
    print(f"\n{'points':>8}" + "".join(f"{k:>27}" for k in ref))
    for n in counts:
        cells = []
        for k, v in rows[n].items():
            if "creep" in k:
                cells.append(f"{v:>12.4g}            ")
            elif "ms/frame" in k:
                cells.append(f"{v:>10.3f} ({v / ref[k]:5.2f}x)      ")
            else:
                cells.append(f"{v:>12.5g} ({100 * (v / ref[k] - 1) if ref[k] else 0.0:+6.2f} %)  ")
        print(f"{n:>8}" + "".join(f"{c:>27}" for c in cells))
    for k, v in closed.items():
        print(f"closed form {k}: {v:.5g}")


if __name__ == "__main__":
    main()
