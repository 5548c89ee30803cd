"""`dano build`, `info`, `simulate` and `demo`: objects and scenes."""

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from dano.cli.arguments import (
    _POSITIVE,
    VIDEO,
    UsageError,
    _checked,
    _in_a_folder,
    _int,
    _output,
    _parse_window,
)
from dano.errors import DanoError


def _add_build(sub) -> None:
    b = sub.add_parser("build", help="build a DANO from a field, mesh, grid, checkpoint or reference collider")
    b.add_argument("source", help="mesh file, grid .npz, neural checkpoint .npz, reference collider .npz, or a spec "
                   "such as sphere:r=0.05, box:size=0.1,0.06,0.03, capsule:r=0.02,half_length=0.05")  # fmt: skip
    b.add_argument("-o", "--output", required=True, type=_output(".npz"), help="output .dano.npz")
    b.add_argument("--points", type=_int(1), default=5000, help="candidate surface points (default 5000)")
    b.add_argument("--mass", type=_POSITIVE, help="total mass in kg (fixes the mass scale alpha)")
    b.add_argument("--alpha", type=_POSITIVE, help="mass scale alpha, kg per (density unit m^3) (default 1)")
    b.add_argument("--scale", type=_POSITIVE, default=1.0, help="multiply lengths by this (m per source unit)")
    b.add_argument("--seed", type=_int(0), default=0)
    b.add_argument("--window", help="density window LOW,HIGH (default 0.1,0.9 x the field's peak)")
    b.add_argument("--normals", choices=["autodiff", "fd"], default="autodiff")
    b.add_argument("--resolution", type=_int(4), default=96, help="grid nodes along a mesh's longest side")
    b.add_argument("--repair", action="store_true", help="make a non-watertight mesh watertight with pymeshfix")
    b.add_argument(
        "--json", action="store_true", help="one JSON object: output and the DANO's mass properties (dano info)"
    )
    b.add_argument("--reference-inertia", choices=["tensor", "second-moment"], default="tensor",
                   help="a reference collider's inertia: the tensor (default), or its second moment as the "
                   "reference's simulator used it (to reproduce the authors' trajectories)")  # fmt: skip
    b.set_defaults(run=_build)


def _build(args: argparse.Namespace) -> None:
    from dano.build import build_dano, field_from_source
    from dano.io import save_dano
    from dano.types import DANO

    if args.mass is not None and args.alpha is not None:
        raise DanoError("give --mass or --alpha, not both")
    window = _parse_window(args.window)
    source = field_from_source(
        args.source, scale=args.scale, resolution=args.resolution, repair=args.repair,
        reference_inertia=args.reference_inertia.replace("-", "_"),
    )  # fmt: skip
    if isinstance(source, DANO):
        dano = source if args.mass is None else source.with_mass(args.mass)
        if args.alpha is not None:
            dano = dano.with_mass(float(dano.mass) * args.alpha / float(dano.alpha))
    else:
        alpha = 1.0 if args.alpha is None else args.alpha
        if args.mass is None and args.alpha is None:
            print("note: no --mass or --alpha: mass scale alpha = 1 (mass is known only up to alpha)", file=sys.stderr)
        dano = build_dano(
            source, n_points=args.points, alpha=alpha, mass=args.mass, window=window, seed=args.seed,
            normals=args.normals, source=args.source,
        )  # fmt: skip
    save_dano(args.output, dano)
    if args.json:
        print(json.dumps({"output": args.output, **info_dict(dano)}))
    else:
        print(f"wrote {args.output}: mass {float(dano.mass):.6g} kg, {dano.n_points} points")


def _add_info(sub) -> None:
    i = sub.add_parser("info", help="print a DANO's mass properties")
    i.add_argument("file")
    i.add_argument("--json", action="store_true", help="one JSON object (keys mass, com, inertia, n_points, ...)")
    i.set_defaults(run=_info)


def _add_simulate(sub) -> None:
    s = sub.add_parser("simulate", help="simulate a scene TOML file, write the trajectory CSV (and a video)")
    s.add_argument("scene", help="scene .toml (see README)")
    s.add_argument("-o", "--output", required=True, type=_output(), help="trajectory CSV: t,body,x,y,z,qw,qx,qy,qz")
    s.add_argument("--video", type=_output(*VIDEO), help="render to this .mp4 or .gif")
    s.add_argument("--style", choices=["surface", "points"], default="surface",
                   help="draw each DANO as its surface (default) or its surface points")  # fmt: skip
    s.add_argument("--view", type=_output(".html"),
                   help="write an interactive 3D view of the run (dano view's page, every geom moving)")  # fmt: skip
    s.add_argument("--contacts", action="store_true",
                   help="draw contact forces as arrows in the video and the view (weight: half the size)")  # fmt: skip
    s.add_argument("--steps", type=_int(1), help="frames to simulate (default: duration / timestep)")
    s.add_argument("--json", action="store_true", help="one JSON object (output, frames, bodies, video, profile)")
    s.add_argument("--profile", action="store_true",
                   help="also time the rollout apart: compile, run, and its DANO contact vs the engine")  # fmt: skip
    s.set_defaults(run=_simulate)


def _add_export(sub) -> None:
    e = sub.add_parser("export", help="write a scene TOML file as an MJCF for plain MuJoCo (DANOs as meshes)")
    e.add_argument("scene", help="scene .toml (see README)")
    e.add_argument("-o", "--output", required=True, type=_output(".xml"),
                   help="the MJCF file (the DANOs' meshes inline, a robot's copied beside it): each DANO a body with "
                   "its mass and full inertia, its "
                   "surface as a visual mesh and its convex decomposition as collision geoms (the mesh path's "
                   "approximation of its contact)")  # fmt: skip
    e.add_argument("--method", choices=["coacd", "vhacd"], default="coacd", help="convex decomposition (default coacd)")
    e.add_argument("--threshold", type=_POSITIVE, default=0.05,
                   help="CoACD's concavity threshold; V-HACD's volume error, 100x it in %% (default 0.05)")  # fmt: skip
    e.add_argument("--resolution", type=_int(8), default=64,
                   help="marching-cubes nodes along the longest side of each DANO's grid box (default 64)")  # fmt: skip
    e.add_argument("--trajectory", help="a `dano simulate` CSV of the scene, written as one keyframe per frame")
    e.add_argument("--json", action="store_true", help="one JSON object (output, bodies, bytes)")
    e.set_defaults(run=_export)


def _export(args: argparse.Namespace) -> None:
    from dano.baselines.export import export_scene
    from dano.sim import load_scene

    scene = load_scene(args.scene)
    path = export_scene(scene, args.output, method=args.method, threshold=args.threshold,
                        resolution=args.resolution, progress=not args.json, trajectory=args.trajectory)  # fmt: skip
    summary = {"output": str(path), "bodies": [b.name for b in scene.bodies], "bytes": path.stat().st_size}
    human = f"wrote {path}: {len(scene.bodies)} DANO(s) as meshes, {summary['bytes']} bytes (plain MuJoCo loads it)"
    print(json.dumps(summary) if args.json else human)


def _add_view(sub) -> None:
    v = sub.add_parser("view", help="an interactive 3D view in the browser: one HTML page (WebGL) that opens from disk")
    v.add_argument("source", help="a .dano.npz (the object) or a scene .toml (its DANOs where they start)")
    v.add_argument("-o", "--output", required=True, type=_output(".html"), help="the page, .html")
    v.add_argument("--trajectory", help="with a scene: a `dano simulate` CSV of it, played on a timeline")
    v.add_argument("--points", type=_int(1), default=3000, help="surface points shown per DANO (default 3000)")
    v.add_argument("--resolution", type=_int(8), default=64,
                   help="marching-cubes nodes along the longest side of each DANO's grid box (default 64)")  # fmt: skip
    v.add_argument("--json", action="store_true", help="one JSON object (output, bodies, frames, bytes)")
    v.set_defaults(run=_view)


def _view(args: argparse.Namespace) -> None:
    from dano.io import load_dano
    from dano.viewer import ViewerError, view_scene, write_view

    knobs = {"max_points": args.points, "resolution": args.resolution}
    if args.source.lower().endswith(".toml"):
        from dano.sim import load_scene

        scene = load_scene(args.source)
        path = view_scene(args.output, scene, args.trajectory, title=Path(args.source).name, **knobs)
        bodies = [b.name for b in scene.bodies]
    else:
        if args.trajectory is not None:
            raise ViewerError("--trajectory needs the scene it was simulated in: dano view SCENE.toml --trajectory CSV")
        name = Path(args.source).name.removesuffix(".npz").removesuffix(".dano")
        path = write_view(args.output, {name: load_dano(args.source)}, title=Path(args.source).name, **knobs)
        bodies = [name]
    summary = {"output": str(path), "bodies": bodies, "bytes": path.stat().st_size}
    print(json.dumps(summary) if args.json else f"wrote {path}: open it in a browser (drag to orbit, scroll to zoom)")


def info_dict(dano) -> dict:
    """The `dano info --json` object."""
    return {
        "mass": float(dano.mass),
        "com": np.asarray(dano.com).tolist(),
        "inertia": np.asarray(dano.inertia).tolist(),
        "principal_moments": np.asarray(dano.principal_moments()).tolist(),
        "principal_extents": np.asarray(dano.principal_extents()).tolist(),
        "n_points": dano.n_points,
        "window": np.asarray(dano.window).tolist(),
        "alpha": float(dano.alpha),
        "mass_stderr": float(dano.mass_stderr),
        "com_stderr": np.asarray(dano.com_stderr).tolist(),
        "inertia_stderr": np.asarray(dano.inertia_stderr).tolist(),
        "source": dano.source,
    }


def _info(args: argparse.Namespace) -> None:
    from dano.io import load_dano

    d = info_dict(load_dano(args.file))
    if args.json:
        print(json.dumps(d))
        return
    vec = lambda v: "  ".join(f"{x:+.6e}" for x in v)  # noqa: E731
    print(f"file               {args.file}  (source: {d['source'] or 'unknown'})")
    print(f"mass               {d['mass']:.6g} kg  (+/- {d['mass_stderr']:.2g}, alpha {d['alpha']:.6g})")
    print(f"centre of mass     {vec(d['com'])} m  (+/- {max(d['com_stderr']):.2g})")
    print("inertia about COM  " + "\n                   ".join(vec(row) for row in d["inertia"]) + "  kg m^2")
    print(f"principal moments  {vec(d['principal_moments'])} kg m^2")
    print(f"principal extents  {vec(d['principal_extents'])} m  (size along the principal axes; sysid --size)")
    print(f"surface points     {d['n_points']}, density window [{d['window'][0]:.6g}, {d['window'][1]:.6g}]")


def _simulate(args: argparse.Namespace) -> None:
    from dano.sim import load_scene
    from dano.sim.run import Simulation, write_csv

    if args.contacts and not (args.video or args.view):
        raise UsageError("--contacts draws the contact forces in the video or the view: give --video or --view too")
    scene = load_scene(args.scene)
    sim = Simulation.from_scene(scene)
    n = scene.n_steps if args.steps is None else args.steps
    print(f"simulating {n} frames of {scene.timestep} s ({scene.substeps} substeps) ...", file=sys.stderr)
    traj = sim.run(n)
    write_csv(args.output, traj, sim)
    bodies = len(sim.world.names) + sum(p.qpos >= 0 for p in sim.world.prims)
    summary: dict = {"output": args.output, "frames": n + 1, "bodies": int(bodies), "video": args.video}
    human = [f"wrote {args.output}: {n + 1} frames x {bodies} bodies"]
    contacts = None
    if args.contacts:
        from dano.sim.contacts import contact_forces

        contacts = contact_forces(sim, traj)
    if args.video:
        from dano.sim.render import render_video

        video = render_video(sim, traj, args.video, progress=not args.json, style=args.style, contacts=contacts)
        human.append(f"wrote {video}")
    if args.view:
        from dano.viewer import view_simulation

        human.append(f"wrote {view_simulation(args.view, sim, traj, contacts=contacts, title=Path(args.scene).name)}")
        summary["view"] = args.view
    if args.profile:
        import dataclasses

        from dano.sim.run import profile

        timing = profile(sim, n)
        summary["profile"] = {**dataclasses.asdict(timing), "contact": timing.contact}
        human += timing.lines()
    print(json.dumps(summary) if args.json else "\n".join(human))


def _add_demo(sub) -> None:
    d = sub.add_parser("demo", help="build and plot a DANO of the Stanford bunny")
    d.add_argument(
        "-o",
        "--output",
        "--out",
        dest="out",
        type=_checked(_in_a_folder),
        default="dano-demo",
        help="output folder (default dano-demo)",
    )
    d.add_argument("--json", action="store_true", help="one JSON object: what the demo measured (also summary.json)")
    d.add_argument("--resolution", type=_int(8), default=96)
    d.add_argument("--seed", type=_int(0), default=0)
    d.add_argument("--no-sim", action="store_true", help="only build and plot the DANO")
    d.set_defaults(run=_demo)


def _demo(args: argparse.Namespace) -> None:
    from dano.demo import run_demo

    if not args.json:
        run_demo(args.out, resolution=args.resolution, seed=args.seed, simulate=not args.no_sim)
        return
    import contextlib

    with contextlib.redirect_stdout(sys.stderr):  # the demo's own lines; stdout carries the one object
        summary = run_demo(args.out, resolution=args.resolution, seed=args.seed, simulate=not args.no_sim)
    print(json.dumps({"output": args.out, **summary}))
