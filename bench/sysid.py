"""Identification speed: friction from a 33-frame slide (120 Hz, ~0.27 s), cold and warm.

The paper reports 2.0 s on a laptop CPU to fit the soap's friction from its video. Here, on the
same kind of data (a 9 x 6 x 3 cm bar of soap, 2000 surface points, per-point contact, the default
implicit step: five 1.67 ms steps per 120 Hz frame; noise-free so every solver must reach the truth):

- dano.sysid.identify (projected LM, block Jacobians), friction only, initial state from the data
  (the paper's setting) and with the initial velocity fitted too;
- optimistix.LevenbergMarquardt on the same residuals (bounds by a sigmoid reparameterisation,
  Jacobian of the whole residual vector), the library we would otherwise use.

Cold = first call, JIT compilation included; warm = the same problem solved again; and ours on a
newly made problem of the same structure (its compiled functions are JAX's, keyed by structure).
Run: `python bench/sysid.py`.
"""

import time

import jax
import jax.numpy as jnp
import optimistix as optx

from dano import build_dano
from dano.fields import BoxField
from dano.scenarios import slide_scene
from dano.sysid import Recording, identify, make_problem, residuals
from dano.sysid.experiments import slide_track

MU = 0.5


def ours(make, init):
    """Cold, warm, then on a newly made problem of the same structure (the compiled program reused)."""
    first = make()
    out = []
    for problem in (first, first, make()):
        result = identify(problem, init=init, progress=False)
        out.append((result.seconds, result.iterations, result.params["sliding_friction"]))
    return out


def optimistix_lm(problem, mu0):
    """optimistix LM over (u, δ) with friction = 2 sigmoid(u) in (0, 2)."""
    n, s = problem.n_windows, problem.n_state

    def fn(y, args):
        u, delta = y
        theta = 2.0 * jax.nn.sigmoid(u)
        return residuals(problem, theta, delta, args).reshape(-1)

    solver = optx.LevenbergMarquardt(rtol=1e-6, atol=1e-6)

    def solve(y0, w):
        sol = optx.least_squares(fn, solver, y0, args=w, max_steps=100, throw=False)
        return sol.value, sol.stats["num_steps"]

    solve = jax.jit(solve)
    u0 = jnp.log(jnp.array([mu0 / (2.0 - mu0)]))
    y0 = (u0, jnp.zeros((n, s)))
    out = []
    for _ in range(2):
        start = time.perf_counter()
        value, steps = jax.block_until_ready(solve(y0, problem.windows))
        seconds = time.perf_counter() - start
        out.append((seconds, int(steps), float(2.0 * jax.nn.sigmoid(value[0][0]))))
    return out


def main():
    bar = build_dano(BoxField(size=(0.09, 0.06, 0.03)), mass=0.1, n_points=2000)
    scene = slide_scene(bar, friction=MU)
    track = slide_track(scene, fps=120.0, n_frames=33)
    print(f"slide: {track.n_frames} frames at {1 / track.dt:.0f} Hz, bar of 2000 points, true friction {MU}")
    print(f"{'solver':<44} {'initial state':<14} {'cold s':>8} {'warm s':>8} {'iters':>6} {'friction':>10}")
    rows = []
    for initial in ("none", "velocity"):
        (cold, _, _), (warm, iters, mu), (again, _, _) = ours(
            lambda: make_problem(scene, [Recording({"object": track})], ["friction"], initial=initial),  # noqa: B023
            {"sliding_friction": 0.2},
        )
        rows.append(("dano.sysid.identify (projected LM)", initial, cold, warm, iters, mu))
        print(f"dano.sysid.identify, initial={initial}: a newly made problem of the same structure {again:.2f} s")
        problem = make_problem(scene, [Recording({"object": track})], ["friction"], initial=initial)
        (cold, _, _), (warm, iters, mu) = optimistix_lm(problem, 0.2)
        rows.append(("optimistix.LevenbergMarquardt (sigmoid bounds)", initial, cold, warm, iters, mu))
    for name, initial, cold, warm, iters, mu in rows:
        print(f"{name:<44} {initial:<14} {cold:>8.2f} {warm:>8.2f} {iters:>6d} {mu:>10.5f}")
    ratio = rows[1][3] / rows[0][3], rows[3][3] / rows[2][3]
    print(f"warm time optimistix / ours: {ratio[0]:.2f} (state from data), {ratio[1]:.2f} (velocity fitted)")
    print(f"paper (Dojo, laptop i7-8750H): 2.0 s; ours warm / paper: {rows[0][3] / 2.0:.2f}")


if __name__ == "__main__":
    jax.config.update("jax_enable_x64", True)
    main()
