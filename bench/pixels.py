"""Torques to pixels: friction from masks, two-stage (track, then pose sysid) against end to end.

Each case simulates an object sliding and turning on a table at a known friction (the DANO in
`dano.sim`), films it with MuJoCo (`render_mesh_video`, 128 x 96 px, from the object's mesh) and
identifies μ from the masks two ways, both from the same files and the same initial guess (μ 0.25):

- two-stage: `dano track` (every frame, the tracker's first-pose guess) writes a pose CSV, then
  `dano sysid --fit-initial state` fits μ and the initial state to it;
- end to end: `dano sysid --masks` (the first 6 frames tracked for the initial state, then μ and the
  initial state fitted to the masks through simulation and rendering, `dano.vision.pixels`).

Masks are clean, or noisy: every frame's edge eroded or dilated by 1-2 px (at random), 8 false
pixels per frame, and one frame dropped (all black: end to end it carries no residuals; the
tracker, which needs every frame, is given the frame before in its place). The box is symmetric:
the tracker may report it turned by 180°, which the pose fit reads as a rotation; the column
`flips` counts frames tracked more than 90° from the truth. Prints one row per case, then the mean
relative error of each pipeline over the noisy cases and their ratio.

Run: `python bench/pixels.py [--objects box,bunny] [--fps 30,60,120] [--noise clean,noisy]`
(the 8 cases at 30 and 60 fps: 55 min on 2 cores with tests running beside it for 25 of them).
"""

import argparse
import tempfile
import time
from pathlib import Path

import imageio.v3 as iio
import jax
import numpy as np
import trimesh
from scipy import ndimage

jax.config.update("jax_enable_x64", True)

from dano.assets import bunny_mesh  # noqa: E402
from dano.build import build_dano  # noqa: E402
from dano.contact.wrench import ContactParams  # noqa: E402
from dano.fields import mesh_field  # noqa: E402
from dano.io import save_dano  # noqa: E402
from dano.math import quat_to_mat  # noqa: E402
from dano.sim import DanoBody, Scene  # noqa: E402
from dano.sim.run import Simulation, body_poses  # noqa: E402
from dano.sysid.data import Track, write_track  # noqa: E402
from dano.sysid.pipeline import SysidConfig, identify_files  # noqa: E402
from dano.vision import camera_from_fov, load_masks, look_at, render_mesh_video  # noqa: E402
from dano.vision.pixels import identify_mask_files  # noqa: E402
from dano.vision.track import track  # noqa: E402

MU = 0.4
GUESS = 0.25
DURATION = 0.3  # s: the slide stops at v / (mu g) = 0.31 s


def objects() -> dict[str, trimesh.Trimesh]:
    bunny = bunny_mesh()
    bunny.apply_translation(-bunny.bounds.mean(axis=0))
    return {"box": trimesh.creation.box((0.09, 0.06, 0.03)), "bunny": bunny}


def film(mesh: trimesh.Trimesh, fps: float, folder: Path):
    """Simulates the slide at MU, renders it; writes the DANO, the scene TOML (friction GUESS)."""
    field = mesh_field(mesh, resolution=96, progress=False)
    obj = build_dano(field, n_points=800, mass=0.15)
    com = np.asarray(obj.com)
    height = com[2] - mesh.bounds[0, 2]
    substeps = int(round(480 / fps))
    body = DanoBody("object", obj, pos=(0.0, 0.0, height), vel=(1.2, 0.25, 0.0), angvel=(0.0, 0.0, 5.0))
    scene = Scene(timestep=1 / fps, substeps=substeps, bodies=(body,), contact=ContactParams(sliding_friction=MU))
    sim = Simulation.from_scene(scene)
    n = int(round(DURATION * fps)) + 1
    poses = body_poses(sim.run(n - 1), sim)["object"]
    rot = np.asarray(quat_to_mat(poses[:, 3:]))
    origin = poses[:, :3] - rot @ com
    camera = camera_from_fov(128, 96, np.radians(55.0), look_at([0.1, -0.28, 0.3], [0.1, 0.03, 0.0]))
    video = render_mesh_video(mesh, np.concatenate([origin, poses[:, 3:]], axis=1), camera, folder / "video",
                         fps=fps, progress=False)  # fmt: skip
    save_dano(folder / "object.dano.npz", obj)
    (folder / "scene.toml").write_text(
        f'[sim]\ntimestep = {1 / fps}\nsubsteps = {substeps}\n[ground]\nheight = 0.0\n[[body]]\nname = "object"\n'
        f'dano = "object.dano.npz"\npos = [0, 0, {height}]\n[contact]\nsliding_friction = {GUESS}\n'
    )
    return field, com, camera, video, poses


def noisy(masks: np.ndarray, seed: int) -> tuple[np.ndarray, int]:
    """Edges eroded or dilated by 1-2 px, 8 false pixels per frame, one frame dropped (all black)."""
    rng = np.random.default_rng(seed)
    out = []
    for m in masks > 0.5:
        grow = int(rng.integers(1, 3))
        change = ndimage.binary_dilation if rng.random() < 0.5 else ndimage.binary_erosion
        m = change(m, iterations=grow)
        m = m.copy()
        m[rng.integers(0, m.shape[0], 8), rng.integers(0, m.shape[1], 8)] = True
        out.append(m.astype(float))
    out = np.stack(out)
    dropped = len(out) // 2
    out[dropped] = 0.0
    return out, dropped


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(2 * np.arccos(np.clip(np.abs(np.sum(a * b, axis=1)), 0.0, 1.0)))


def run_case(name: str, mesh: trimesh.Trimesh, fps: float, noise: str, root: Path) -> dict:
    folder = root / f"{name}-{fps:g}-{noise}"
    folder.mkdir()
    field, com, camera, video, truth = film(mesh, fps, folder)
    masks = load_masks(video / "masks", None, (camera.height, camera.width))
    dropped = None
    if noise == "noisy":
        masks, dropped = noisy(masks, seed=int(fps))
    (folder / "masks").mkdir()
    for k, m in enumerate(masks):
        iio.imwrite(folder / "masks" / f"{k:06d}.png", (255 * m).astype(np.uint8))
    config = SysidConfig(fit=("friction",), fps=fps, initial="state", interval="gauss-newton")

    start = time.perf_counter()  # two-stage: dano track, then dano sysid on its CSV
    tracked_masks = masks.copy()
    if dropped is not None:
        tracked_masks[dropped] = tracked_masks[dropped - 1]
    tracked = track(field, camera, tracked_masks, progress=False)
    pos = tracked.positions + np.einsum("tij,j->ti", np.asarray(quat_to_mat(tracked.quats)), com)
    write_track(folder / "tracked.csv", Track(t=np.arange(len(pos)) / fps, pos=pos, quat=tracked.quats))
    _, two = identify_files(folder / "scene.toml", [folder / "tracked.csv"],
                            SysidConfig(fit=("friction",), initial="state"), progress=False)  # fmt: skip
    two_seconds = time.perf_counter() - start
    flips = int(np.sum(angle_deg(tracked.quats, truth[:, 3:]) > 90.0))

    start = time.perf_counter()  # end to end: dano sysid --masks
    _, one = identify_mask_files(folder / "scene.toml", folder / "masks", video / "camera.json", config, progress=False)
    one_seconds = time.perf_counter() - start
    return {
        "case": f"{name} {fps:g} fps {noise}", "frames": len(masks), "flips": flips,
        "two": two.params["friction"], "two_s": two_seconds, "one": one.params["friction"], "one_s": one_seconds,
    }  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--objects", default="box,bunny")
    parser.add_argument("--fps", default="30,60,120")
    parser.add_argument("--noise", default="clean,noisy")
    args = parser.parse_args()
    meshes = objects()
    rows = []
    print(f"true friction {MU}, initial guess {GUESS}; errors relative to the truth")
    print(f"{'case':<24} {'frames':>6} {'flips':>5}  {'two-stage mu':>12} {'err':>7} {'s':>6}  "
          f"{'end-to-end mu':>13} {'err':>7} {'s':>6}")  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.objects.split(","):
            for fps in (float(f) for f in args.fps.split(",")):
                for noise in args.noise.split(","):
                    r = run_case(name, meshes[name], fps, noise, Path(tmp))
                    rows.append(r)
                    print(f"{r['case']:<24} {r['frames']:>6} {r['flips']:>5}  {r['two']:>12.4f} "
                          f"{abs(r['two'] / MU - 1):>7.1%} {r['two_s']:>6.1f}  {r['one']:>13.4f} "
                          f"{abs(r['one'] / MU - 1):>7.1%} {r['one_s']:>6.1f}", flush=True)  # fmt: skip
    for noise in args.noise.split(","):
        chosen = [r for r in rows if r["case"].endswith(noise)]
        two = float(np.mean([abs(r["two"] / MU - 1) for r in chosen]))
        one = float(np.mean([abs(r["one"] / MU - 1) for r in chosen]))
        print(f"{noise}: mean error two-stage {two:.1%}, end to end {one:.1%} (ratio end-to-end / two-stage "
              f"{one / max(two, 1e-12):.2f}) over {len(chosen)} cases")  # fmt: skip


if __name__ == "__main__":
    main()
