"""From pixels on this machine: training time to a given IoU, and tracking time per frame.

1. Fit: the Stanford bunny rendered from 50 views at 64 px (`render_views`), fitted with the voxel
   model; every `--every` steps the solidified field's IoU with the mesh's occupancy is measured
   (on 200 000 uniform points of the box). Prints steps, seconds (training only) and IoU, and the
   seconds to reach `--iou`. Both models ("grid" and "mlp") are timed per step side by side.
2. Track: a 30-frame 128 x 96 video of the bunny sliding 15 cm and turning 60 degrees
   (`render_mesh_video`), tracked from its masks with the first pose given, in a window at full
   resolution and downsampled to 32 px; prints seconds per frame and the mean position (fraction
   of the bunny's size) and orientation errors.

Run: `python bench/vision.py [--iou 0.85] [--every 250] [--steps 1000] [--parts fit,track]`.
"""

import argparse
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from dano.assets import bunny_mesh
from dano.fields import mesh_field
from dano.math import quat_exp
from dano.vision import camera_from_fov, load_masks, load_nerf_synthetic, look_at, render_mesh_video, render_views
from dano.vision.fit import FitConfig, fit_field, solidify
from dano.vision.track import TrackConfig, track


def fit_bench(mesh, folder: Path, target: float, every: int, steps: int) -> None:
    render_views(mesh, folder / "views", n_views=50, resolution=64, progress=False)
    views = load_nerf_synthetic(folder / "views")
    truth = mesh_field(mesh, resolution=80, progress=False)
    lo, hi = np.asarray(truth.bounds)
    x = jnp.asarray(lo + (hi - lo) * np.random.default_rng(0).uniform(size=(200_000, 3)))
    inside = np.asarray(truth(x)) > 500
    print(f"fit: 50 views, 64 px; IoU of the solid against the mesh's occupancy (target {target})")
    reached = None
    for n in range(every, steps + 1, every):
        result = fit_field(views, FitConfig(steps=n), key=jax.random.key(0), progress=False)
        start = time.perf_counter()
        solid = solidify(result.field, views)
        carve = time.perf_counter() - start
        ours = np.asarray(solid.field(x)) > 500
        iou = float((ours & inside).sum() / (ours | inside).sum())
        print(f"  {n:5d} steps  train {result.seconds:6.1f} s  solidify {carve:5.1f} s  "
              f"PSNR {result.psnr[-20:].mean():5.1f} dB  IoU {iou:.3f}")  # fmt: skip
        if reached is None and iou >= target:
            reached = result.seconds + carve
    print(f"  time to IoU {target}: " + ("not reached" if reached is None else f"{reached:.1f} s"))
    for model, rate in (("grid", 0.1), ("mlp", 5e-3)):
        short = fit_field(views, FitConfig(model=model, steps=40, learning_rate=rate), key=jax.random.key(0),
                          progress=False)  # fmt: skip
        longer = fit_field(views, FitConfig(model=model, steps=80, learning_rate=rate), key=jax.random.key(0),
                           progress=False)  # fmt: skip
        per_step = (longer.seconds - short.seconds) / 40
        print(f"  model {model}: {1e3 * per_step:.0f} ms per step (2048 rays x 128 samples)")


def track_bench(mesh, folder: Path) -> None:
    n = 30
    t = np.linspace(0.0, 1.0, n)
    pos = np.stack([0.15 * t, 0.02 * np.sin(3 * t), np.full(n, -mesh.bounds[0, 2])], axis=1)
    yaw = np.radians(60.0) * t
    quat = np.asarray(quat_exp(jnp.asarray(np.stack([0 * yaw, 0 * yaw, yaw], axis=1))))
    camera = camera_from_fov(128, 96, np.radians(50.0), look_at([0.07, -0.55, 0.3], [0.07, 0.0, 0.05]))
    render_mesh_video(mesh, np.concatenate([pos, quat], axis=1), camera, folder / "video", floor=True, progress=False)
    masks = load_masks(folder / "video" / "masks", n, (96, 128))
    field = mesh_field(mesh, resolution=128, progress=False)
    size = float(np.linalg.norm(np.ptp(mesh.vertices, axis=0)))
    for config in (TrackConfig(), TrackConfig(max_size=32)):
        r = track(field, camera, masks, config, init=(pos[0], quat[0]), progress=False)
        err = np.linalg.norm(r.positions - pos, axis=1) / size
        angle = np.degrees(2 * np.arccos(np.clip(np.abs(np.sum(r.quats * quat, axis=1)), 0.0, 1.0)))
        print(f"track {n} frames at max {config.max_size} px: {r.seconds / n:.2f} s per frame; position error "
              f"mean {err.mean():.3f} of the size (max {err.max():.3f}); angle mean {angle.mean():.2f} deg "
              f"(max {angle.max():.2f})")  # fmt: skip


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--iou", type=float, default=0.85)
    p.add_argument("--every", type=int, default=250)
    p.add_argument("--steps", type=int, default=1000)
    p.add_argument("--parts", default="fit,track", help="which benchmarks to run (comma-separated)")
    args = p.parse_args()
    parts = args.parts.split(",")
    jax.config.update("jax_enable_x64", True)
    mesh = bunny_mesh()
    with tempfile.TemporaryDirectory() as tmp:
        if "fit" in parts:
            fit_bench(mesh, Path(tmp), args.iou, args.every, args.steps)
        if "track" in parts:
            track_bench(mesh, Path(tmp))


if __name__ == "__main__":
    main()
