"""Time to build a 5000-point DANO (mass properties + surface sampling + normals) on this machine.

Two fields of the same Stanford bunny: the mesh-occupancy grid field, and a neural field
(8 x 128 MLP, positional encoding) distilled from it. First call (with JIT compilation) and warm
call are timed separately. Run: `python bench/build.py`.
"""

import time

import jax
import numpy as np

from dano import build_dano
from dano.assets import bunny_mesh
from dano.fields import NeuralField, NeuralFieldConfig, distill, mesh_field


def timed(fn):
    t = time.perf_counter()
    out = fn()
    jax.block_until_ready(out)
    return out, time.perf_counter() - t


def main(n_points: int = 5000, distill_steps: int = 600) -> None:
    mesh = bunny_mesh()
    grid, bake = timed(lambda: mesh_field(mesh, resolution=96, progress=False))
    config = NeuralFieldConfig()
    student = NeuralField(grid.bounds, config, key=jax.random.key(0))
    neural, fit = timed(lambda: distill(student, grid, steps=distill_steps, key=jax.random.key(1), progress=False))
    rows = []
    for name, field in [("bunny mesh -> grid 96", grid), (f"neural {config.depth}x{config.width} (distilled)", neural)]:
        first, cold = timed(lambda f=field: build_dano(f, n_points=n_points, mass=1.0))
        second, warm = timed(lambda f=field: build_dano(f, n_points=n_points, mass=1.0, seed=1))
        moments = np.linalg.eigvalsh(np.asarray(second.inertia))
        rows.append((name, cold, warm, moments))
    print(f"bunny mesh bake (occupancy + surface distance, 96 nodes across): {bake:.2f} s")
    print(f"neural field distillation ({distill_steps} Adam steps of 4096 points): {fit:.2f} s (not part of a build)")
    print(f"\n{'field':36}{'first build [s]':>18}{'warm build [s]':>18}   principal moments / mass [m^2]")
    for name, cold, warm, moments in rows:
        shown = "  ".join(f"{v:.3e}" for v in moments)
        print(f"{name:36}{cold:>18.3f}{warm:>18.3f}   {shown}")
    print(
        f"\nratio neural / grid (warm): {rows[1][2] / rows[0][2]:.1f}x   ({n_points} points, 2^18 Monte Carlo samples)"
    )


if __name__ == "__main__":
    main()
