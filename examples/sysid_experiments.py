"""The identification experiments of the paper (Sec. V-A) that need more than the test suite runs.

    python examples/sysid_experiments.py reference [--shared ../shared]   # Dojo.jl's bunny drops
    python examples/sysid_experiments.py mesh-push                        # data from MuJoCo C
    python examples/sysid_experiments.py soap [--shared ../shared]        # the reference bluesoap
    python examples/sysid_experiments.py drops [--integrator explicit]    # Dojo.jl's drops, simulated

reference: identify μ from the paper authors' simulated `bunny_trajectory_<μ>.csv` (500 Hz, rows
    from the first bounce on), in shooting windows of 25 frames restarted from the file's poses.
mesh-push: ten pushes of the bunny by a 1 kg sphere under a known force, simulated by MuJoCo C with
    the bunny mesh (CoACD pieces, 0.65 kg, μ = 0.35); identify α and μ of a 0.5 kg DANO.
drops: the three bunny drops simulated whole at the files' 2 ms, one step per frame (or
    --substeps), against the files: distance travelled and the rest pose.
soap: the reference bluesoap DANO scaled to 9 cm slides on a table (μ = 0.5, 33 frames at 120 Hz,
    1 mm noise, three seeds); identify μ and the initial velocity.
"""

import argparse
import dataclasses
import time
from pathlib import Path

import jax
import numpy as np

from dano.sysid import Recording, identify, make_problem
from dano.sysid.data import read_tracks

jax.config.update("jax_enable_x64", True)
DEFAULT_SHARED = Path(__file__).resolve().parents[1] / ".." / "shared"


def reference(shared: Path, first: int, frames: int, window: int, substeps: int | None, integrator: str) -> None:
    from dano.scenarios import reference_drop_scene

    dojo = shared / "data" / "dojo"
    if substeps is None:
        substeps = 1 if integrator == "implicit" else 8
    print(f"rows {first}..{first + frames - 1} at 500 Hz, windows of {window} frames, "
          f"{integrator} step, {substeps} per 2 ms frame")  # fmt: skip
    for mu in (0.1, 0.3, 0.7):
        track = read_tracks(dojo / "trajectories" / f"bunny_trajectory_{mu}.csv", fps=500.0)[""]
        track = track.frames(first, first + frames)
        scene = reference_drop_scene(dojo / "colliders" / "bunny_collider.npz", 0.5, integrator=integrator)
        scene = dataclasses.replace(scene, substeps=substeps)
        # the file is noise-free and the stiff bounces need exact starts: no settling onto the floor
        problem = make_problem(scene, [Recording({"bunny": track})], ["friction"], window=window, settle=0.0)
        r = identify(problem, init={"friction": 0.5}, progress=False)
        fit, err = r.params["sliding_friction"], r.stderr["sliding_friction"]
        print(f"  mu {mu}: fitted {fit:.4f} +/- {err:.4f} ({fit / mu - 1:+.1%}), {r.iterations} iterations, "
              f"{r.seconds:.1f} s, RMS position {r.rms_position * 1e3:.2f} mm")  # fmt: skip


def drops(shared: Path, substeps: int | None, integrator: str) -> None:
    from dano.scenarios import reference_drop_scene
    from dano.sim.run import Simulation

    dojo = shared / "data" / "dojo"
    for mu in (0.1, 0.3, 0.7):
        data = np.loadtxt(dojo / "trajectories" / f"bunny_trajectory_{mu}.csv", delimiter=",", skiprows=1)
        scene = reference_drop_scene(dojo / "colliders" / "bunny_collider.npz", mu, integrator=integrator)
        scene = dataclasses.replace(scene, substeps=substeps or 1)
        q = np.asarray(Simulation.from_scene(scene).run(len(data) - 1).qpos)
        ours, theirs = float(np.linalg.norm(q[-1, :2])), float(np.linalg.norm(data[-1, :2]))
        dot = abs(float(q[-1, 3:7] @ data[-1, 3:7]))
        print(f"  mu {mu}: travelled {ours:.2f} vs {theirs:.2f} m, at rest {q[-1, 2]:.4f} vs {data[-1, 2]:.4f} m "
              f"high, orientation |q . q_ref| = {dot:.3f}")  # fmt: skip


def mesh_push() -> None:
    import dano
    from dano.assets import bunny_mesh
    from dano.baselines.pushes import mesh_push_recordings
    from dano.fields import mesh_field
    from dano.scenarios import push_scene
    from dano.sysid.experiments import push_recordings

    mesh = bunny_mesh()
    bunny = dano.build_dano(mesh_field(mesh, resolution=80, progress=False), n_points=800, mass=0.5)
    scene = push_scene(bunny, friction=0.3)
    truth = {"mass_scale": 1.3, "sliding_friction": 0.35}
    start = time.perf_counter()
    data = {
        "MuJoCo C, bunny mesh (CoACD)": mesh_push_recordings(scene, mesh, mass=1.3 * 0.5, friction=0.35),
        "dano (same simulator)": push_recordings(scene, truth),
    }
    print(f"data simulated in {time.perf_counter() - start:.0f} s (CoACD included, cached after the first run)")
    for source, recordings in data.items():  # initial states from the data, as the paper does
        problem = make_problem(scene, recordings, ["mass_scale", "friction"])
        r = identify(problem, init={"mass_scale": 1.0, "sliding_friction": 0.5}, progress=False)
        errors = ", ".join(f"{k} {r.params[k]:.4f} ({r.params[k] / v - 1:+.2%})" for k, v in truth.items())
        print(f"  {source}: {errors}; {r.iterations} iterations, {r.seconds:.0f} s, "
              f"RMS {r.rms_position * 1e3:.2f} mm {r.rms_rotation or 0.0:.3f} rad")  # fmt: skip


def soap(shared: Path, seeds: int) -> None:
    from dano.build import scale_lengths
    from dano.reference import load_reference
    from dano.scenarios import slide_scene
    from dano.sysid.experiments import slide_track

    soap = load_reference(shared / "data" / "dojo" / "colliders" / "bluesoap_collider.npz")
    soap = scale_lengths(soap, 0.09 / float(np.max(np.ptp(np.asarray(soap.body_points), axis=0))))
    scene = slide_scene(soap, friction=0.5)
    for seed in range(seeds):
        track = slide_track(scene, fps=120.0, n_frames=33, noise=1e-3, seed=seed)
        problem = make_problem(scene, [Recording({"object": track})], ["friction"], initial="velocity")
        r = identify(problem, init={"friction": 0.2}, progress=False)
        fit, err = r.params["sliding_friction"], r.stderr["sliding_friction"]
        print(f"  seed {seed}: friction {fit:.4f} +/- {err:.4f} (true 0.5), "
              f"{r.iterations} iterations, {r.seconds:.1f} s")  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("experiment", choices=["reference", "mesh-push", "soap", "drops"])
    parser.add_argument("--shared", type=Path, default=DEFAULT_SHARED, help="the shared/ folder (reference data)")
    parser.add_argument("--first", type=int, default=400, help="reference: first row (first bounce near 230)")
    parser.add_argument("--frames", type=int, default=501, help="reference: rows used")
    parser.add_argument("--window", type=int, default=25, help="reference: frames per shooting window")
    steps = ["implicit", "explicit"]
    parser.add_argument("--integrator", choices=steps, default="implicit", help="reference, drops: step")
    parser.add_argument("--substeps", type=int, help="steps per frame (reference: 1 implicit, 8 explicit; drops: 1)")
    parser.add_argument("--seeds", type=int, default=3, help="soap: noise seeds")
    args = parser.parse_args()
    if args.substeps is not None and args.substeps < 1:
        parser.error(f"--substeps must be at least 1, got {args.substeps}")
    if args.experiment != "mesh-push" and not (args.shared / "data" / "dojo").is_dir():
        parser.error(f"reference data not found under {args.shared} (pass --shared)")
    if args.experiment == "reference":
        reference(args.shared, args.first, args.frames, args.window, args.substeps, args.integrator)
    elif args.experiment == "drops":
        drops(args.shared, args.substeps, args.integrator)
    elif args.experiment == "mesh-push":
        mesh_push()
    else:
        soap(args.shared, args.seeds)


if __name__ == "__main__":
    main()
