"""From pixels to friction with the command line (issue 18's worked example; README "Real-to-sim").

1. `dano build`: a 9 x 6 x 3 cm bar of soap, 100 g. A scene TOML launches it along a table at
   1.6 m/s, spinning at 2 rad/s, with friction 0.5; `dano simulate` writes its motion at 120 Hz.
2. The video: 33 frames (after the first 12, while it slides) rendered with the existing video maker,
   `dano.vision.render_mesh_video` (128 x 96 px, a camera looking down at the table from 30 cm; the only step in
   Python: a synthetic video has no command).
3. `dano track`: the poses from the masks, the first pose given.
4. `dano sysid`: the friction from the tracked poses, the initial state fitted, profile interval.

Every command is printed before it runs. Run: `python examples/pixels_to_friction.py [--out DIR]`
(about 5 minutes on 2 cores, most of it tracking).
"""

import argparse
import csv
import shlex
import sys
from pathlib import Path

import numpy as np

from dano.cli import main as dano

MU, FPS, LEAD, FRAMES = 0.5, 120.0, 12, 33
SIZE = (0.09, 0.06, 0.03)


def run(*argv: str) -> None:
    print("$ dano " + " ".join(shlex.quote(a) for a in argv), flush=True)
    code = dano(list(argv))
    if code:
        sys.exit(code)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("pixels-demo"))
    out = ap.parse_args().out
    out.mkdir(parents=True, exist_ok=True)
    box = f"box:size={','.join(str(s) for s in SIZE)}"
    run("build", box, "-o", str(out / "soap.dano.npz"), "--mass", "0.1", "--points", "600")
    height = SIZE[2] / 2 + 1e-4
    (out / "slide.toml").write_text(
        f"[sim]\ntimestep = {1 / FPS!r}\nsubsteps = 5\nduration = {(LEAD + FRAMES - 1) / FPS!r}\n"
        f"[ground]\nheight = 0.0\n[contact]\nsliding_friction = {MU}\n"
        f'[[body]]\nname = "soap"\ndano = "soap.dano.npz"\npos = [0.0, 0.0, {height}]\n'
        "vel = [1.6, 0.3, 0.0]\nangvel = [0.0, 0.0, 2.0]\n"
    )
    run("simulate", str(out / "slide.toml"), "-o", str(out / "truth.csv"))

    import trimesh

    from dano.vision import camera_from_fov, look_at, render_mesh_video

    with open(out / "truth.csv") as f:
        poses = np.array([[float(v) for v in row[2:]] for row in list(csv.reader(f))[1:]])[LEAD : LEAD + FRAMES]
    camera = camera_from_fov(128, 96, np.radians(45.0), look_at([0.2, -0.12, 0.3], [0.2, 0.035, 0.0]))
    print(f"rendering {FRAMES} frames of 128 x 96 px (dano.vision.render_mesh_video)", flush=True)
    video = out / "video"
    render_mesh_video(trimesh.creation.box(extents=SIZE), poses, camera, video, fps=FPS, floor=True, overwrite=True)
    init = ",".join(f"{v:.6g}" for v in poses[0])
    run(
        "track", str(video / "frames"), "--field", box, "--camera", str(video / "camera.json"),
        "--masks", str(video / "masks"), "-o", str(out / "track.csv"), "--fps", str(FPS), "--init", init,
    )  # fmt: skip
    with open(out / "track.csv") as f:
        tracked = np.array([[float(v) for v in row[1:]] for row in list(csv.reader(f))[1:]])
    error = np.linalg.norm(tracked[:, :3] - poses[:, :3], axis=1)
    angle = np.degrees(2 * np.arccos(np.clip(np.abs(np.sum(tracked[:, 3:] * poses[:, 3:], axis=1)), 0, 1)))
    print(f"tracking error: position {1e3 * error.mean():.2f} mm mean ({1e3 * error.max():.2f} max), "
          f"orientation {angle.mean():.2f} deg mean ({angle.max():.2f} max)")  # fmt: skip
    run(
        "sysid", "--scene", str(out / "slide.toml"), "--traj", str(out / "track.csv"), "--fit", "friction",
        "--init", "friction=0.2", "--fit-initial", "state", "--sigma", f"{max(error.std(), 1e-4):.2g}",
        "--json",
    )  # fmt: skip
    print(f"true friction {MU}")


if __name__ == "__main__":
    main()
