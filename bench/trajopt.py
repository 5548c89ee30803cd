"""Trajectory optimisation: solve time and iterations of the push, sphere and Panda, side by side.

    python bench/trajopt.py [--points 200] [--horizon 10] [--robots sphere,panda] [--warm]
                            [--step INTEGRATOR:SECONDS]

Each push is solved cold (JIT compilation included) and, with --warm, again (the same problem,
compiled); with --step (e.g. explicit:0.0005) each robot is solved again at that simulator step,
a row of its own beside its default's. The set-up's and the cold solve's XLA compile times are
printed apart (JAX's `backend_compile_duration` events: the compilation proper, not the Python
tracing before it); "all s" is the set-up and the cold solve together.
The object is the Stanford bunny DANO (0.5 kg), goal 10 cm ahead (sphere) or 8 cm aside (Panda);
each robot's default goal handling (a constraint for the sphere, a cost for the Panda).
"""

import argparse
import contextlib
import time

import jax

jax.config.update("jax_enable_x64", True)

import dano  # noqa: E402
from dano.assets import bunny_mesh  # noqa: E402
from dano.fields import mesh_field  # noqa: E402
from dano.sim.scene import Integrator  # noqa: E402
from dano.trajopt import PushTask, push_problem, solve_push  # noqa: E402
from dano.trajopt.push import default_options  # noqa: E402
from dano.trajopt.pushers import ROBOT_STEP  # noqa: E402


@contextlib.contextmanager
def xla_seconds():
    """The seconds XLA spends compiling inside the block: `[total]`, filled in as it runs."""
    total = [0.0]

    def listen(event: str, duration_secs: float, **kwargs: str | int) -> None:
        if event == "/jax/core/compile/backend_compile_duration":
            total[0] += duration_secs

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        yield total
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--points", type=int, default=200)
    parser.add_argument("--horizon", type=int, default=10)
    parser.add_argument("--robots", default="sphere,panda")
    parser.add_argument("--warm", action="store_true", help="solve each push a second time, compiled")
    parser.add_argument("--step", help="INTEGRATOR:SECONDS, a second row per robot at this simulator step")
    args = parser.parse_args()
    steps: list[tuple[str, float] | None] = [None]  # None: the robot's default step
    if args.step:
        integrator, _, seconds = args.step.partition(":")
        try:
            step = (Integrator(integrator).value, float(seconds))
        except ValueError:
            parser.error(f"--step must be INTEGRATOR:SECONDS (e.g. explicit:0.0005), got {args.step!r}")
        if not step[1] > 0:
            parser.error(f"--step's seconds must be > 0, got {seconds}")
        steps.append(step)
    bunny = dano.build_dano(mesh_field(bunny_mesh(), resolution=64, progress=False), n_points=args.points, mass=0.5)
    goals = {"sphere": (0.1, 0.0), "panda": (0.0, 0.08)}
    rows = []
    for robot, step in ((r, s) for r in args.robots.split(",") for s in steps):
        label = robot if step is None else f"{robot} ({step[0]} {step[1] * 1e3:g} ms)"
        integrator, substep = (None, None) if step is None else step
        task = PushTask(goal=goals[robot], horizon=args.horizon, integrator=integrator, substep=substep)
        start = time.perf_counter()
        with xla_seconds() as setup_xla:
            push = push_problem(bunny, robot, task)
        setup = time.perf_counter() - start
        with xla_seconds() as cold_xla:
            cold = solve_push(push, default_options(robot), progress=True)
        print(
            f"{label}: XLA compile {setup_xla[0]:.1f} s of the set-up, {cold_xla[0]:.1f} s of the cold solve "
            "and its replay",
            flush=True,
        )
        result = solve_push(push, default_options(robot)) if args.warm else cold  # the figures come from the last solve
        s = result.solution
        warm_s = s.seconds if args.warm else float("nan")
        errors = (result.final_error_m, result.ee_error_m, result.replay_gap_m)
        counts = (s.iterations, s.outer, s.max_violation)
        rows.append((label, setup, cold.solution.seconds, warm_s, *counts, *errors, s.converged))
        print(f"{label}: {s.message}", flush=True)
    defaults = ", ".join(f"{r} {i} {h * 1e3:g} ms" for r, (i, h) in ROBOT_STEP.items())
    print(f"\nbunny DANO, {args.points} points, horizon {args.horizon} frames of 0.08 s (default steps: {defaults})")
    w = max(8, *(len(row[0]) for row in rows))
    print(f"{'robot':{w}} {'setup s':>8} {'cold s':>8} {'all s':>8} {'warm s':>8} {'iters':>6} {'outer':>6} "
          f"{'violation':>10} {'error mm':>9} {'hand mm':>8} {'replay mm':>10} converged")  # fmt: skip
    for robot, setup, cold_s, warm_s, its, outer, viol, err, ee, gap, ok in rows:
        times = f"{setup:8.1f} {cold_s:8.1f} {setup + cold_s:8.1f} {warm_s:8.1f}"
        mm = f"{err * 1e3:9.3f} {ee * 1e3:8.2f} {gap * 1e3:10.2e}"
        print(f"{robot:{w}} {times} {its:6d} {outer:6d} {viol:10.2e} {mm} {ok}")
    column = 3 if args.warm else 2
    for row in rows[1:]:
        print(f"{('warm' if args.warm else 'cold')} time {row[0]} / {rows[0][0]}: {row[column] / rows[0][column]:.2f}")


if __name__ == "__main__":
    main()
