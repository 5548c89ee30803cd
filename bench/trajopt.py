"""Trajectory optimisation: solve time and iterations of the push, sphere and Panda, side by side.

    python bench/trajopt.py [--points 200] [--horizon 10] [--robots sphere,panda]

Each push is solved twice: cold (JIT compilation included) and warm (the same problem again). The
object is the Stanford bunny DANO (0.5 kg), goal 10 cm ahead (sphere) or 8 cm aside (Panda).
"""

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)

import dano  # noqa: E402
from dano.demo import bunny_mesh  # noqa: E402
from dano.fields import mesh_field  # noqa: E402
from dano.trajopt import PushTask, push_problem, solve_push  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--points", type=int, default=200)
    parser.add_argument("--horizon", type=int, default=10)
    parser.add_argument("--robots", default="sphere,panda")
    args = parser.parse_args()
    bunny = dano.build_dano(mesh_field(bunny_mesh(), resolution=64, progress=False), n_points=args.points, mass=0.5)
    goals = {"sphere": (0.1, 0.0), "panda": (0.0, 0.08)}
    rows = []
    for robot in args.robots.split(","):
        start = time.perf_counter()
        push = push_problem(bunny, robot, PushTask(goal=goals[robot], horizon=args.horizon))
        setup = time.perf_counter() - start
        cold = solve_push(push)
        warm = solve_push(push)
        s = warm.solution
        rows.append((robot, setup, cold.solution.seconds, s.seconds, s.iterations, s.outer, s.max_violation,
                     warm.final_error_m, s.converged))  # fmt: skip
        print(f"{robot}: {s.message}", flush=True)
    print(f"\nbunny DANO, {args.points} points, horizon {args.horizon} frames of 0.08 s (0.5 ms substeps)")
    print(f"{'robot':8} {'setup s':>8} {'cold s':>8} {'warm s':>8} {'iters':>6} {'outer':>6} {'violation':>10} "
          f"{'error mm':>9} converged")  # fmt: skip
    for robot, setup, cold_s, warm_s, its, outer, viol, err, ok in rows:
        times = f"{setup:8.1f} {cold_s:8.1f} {warm_s:8.1f}"
        print(f"{robot:8} {times} {its:6d} {outer:6d} {viol:10.2e} {err * 1e3:9.3f} {ok}")
    if len(rows) == 2:
        print(f"warm time panda / sphere: {rows[1][3] / rows[0][3]:.2f}")


if __name__ == "__main__":
    main()
