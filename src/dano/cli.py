"""The `dano` command: thin subcommands that parse, call the library and print."""

import argparse
import json
import os
import re
import sys
import warnings
from pathlib import Path

import numpy as np

from dano import validate
from dano.errors import DanoError


class UsageError(DanoError):
    """A command-line argument that is missing, malformed or out of range (exit status 2)."""


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors: `dano CMD: UsageError: argument --x: ... (see dano CMD --help)`."""

    def error(self, message: str):  # type: ignore[override]
        print(f"{self.prog}: UsageError: {message} (see {self.prog} --help)", file=sys.stderr)
        sys.exit(2)


def _checked(check):
    """An argparse `type=` from a `dano.validate`-style check: its `DanoError` becomes argparse's."""

    def parse(text: str):
        try:
            return check(text)
        except DanoError as e:
            raise argparse.ArgumentTypeError(str(e)) from None

    return parse


def _int(low: int):
    def check(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise UsageError(f"must be a whole number, got {text!r}") from None
        return validate.integer(value, "", UsageError, low=low)

    return _checked(check)


def _float(low: float | None = None, strict: bool = False):
    def check(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise UsageError(f"must be a number, got {text!r}") from None
        return validate.number(value, "", UsageError, low=low, strict=strict)

    return _checked(check)


_POSITIVE = _float(0.0, strict=True)


def _output(*suffixes: str):
    """An output file: its folder exists, it is not a folder, and (if given) its suffix is allowed.
    Checked when the command line is parsed, before any work, so nothing is half done."""

    def check(text: str) -> str:
        path = Path(text)
        if suffixes and not text.lower().endswith(suffixes):
            raise UsageError(f"{text!r} must end with {' or '.join(suffixes)}")
        if path.is_dir():
            raise UsageError(f"{text!r} is a folder; give a file name")
        return _in_a_folder(text)

    return _checked(check)


def _in_a_folder(text: str) -> str:
    """A path whose folder exists (an output file, or a folder the command creates)."""
    parent = Path(text).parent
    if not parent.is_dir():
        raise UsageError(f"folder {str(parent)!r} of {text!r} does not exist")
    return text


def _numbers(n: int, form: str, quaternion_at: int | None = None):
    """A check of `n` comma-separated numbers (e.g. `x,y,z,qw,qx,qy,qz`); a quaternion part must be
    non-zero. Wrap it with `_checked` for argparse."""

    def check(text: str) -> tuple[float, ...]:
        try:
            values = tuple(float(v) for v in text.split(","))
        except ValueError:
            values = ()
        if len(values) != n or not all(np.isfinite(values)):
            raise UsageError(f"takes {n} comma-separated numbers {form}, got {text!r}")
        if quaternion_at is not None and not any(values[quaternion_at:]):
            raise UsageError(f"the quaternion of {text!r} is zero")
        return values

    return check


def _vector_part(text: str) -> tuple[float, ...]:
    """One token of a vector written `X,Y` (or, the older way, `X Y`): its comma-separated numbers."""
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise UsageError(f"takes comma-separated numbers, got {text!r}") from None
    if not all(np.isfinite(values)):
        raise UsageError(f"takes finite numbers, got {text!r}")
    return values


def _vector(parts: list[tuple[float, ...]], n: int, option: str, form: str) -> tuple[float, ...]:
    """The vector of `_vector_part` tokens: `n` numbers in all."""
    values = tuple(v for part in parts for v in part)
    if len(values) != n:
        raise UsageError(f"{option} takes {n} numbers {form}, got {' '.join(','.join(map(str, p)) for p in parts)}")
    return values


def _frames(text: str) -> tuple[int, int | None]:
    first, colon, stop = text.partition(":")
    try:
        if not colon:
            raise ValueError
        span = (int(first or 0), int(stop) if stop else None)
    except ValueError:
        raise UsageError(f"takes FIRST:STOP row numbers, e.g. 400:901, got {text!r}") from None
    if span[0] < 0 or (span[1] is not None and span[1] <= span[0]):
        raise UsageError(f"needs 0 <= FIRST < STOP, got {text!r}")
    return span


def _level(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise UsageError(f"must be a number, got {text!r}") from None
    if not 0.0 < value < 1.0:
        raise UsageError(f"a confidence level is between 0 and 1, got {text}")
    return value


def _gravity(text: str):
    return text if text == "fit" else _numbers(3, "gx,gy,gz (or 'fit')")(text)


VIDEO = (".mp4", ".gif")
PLOT = (".png", ".pdf", ".svg", ".jpg")


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


def _parse_window(text: str | None) -> tuple[float, float] | None:
    if text is None:
        return None
    try:
        low, high = (float(v) for v in text.split(","))
    except ValueError:
        raise DanoError(f"--window takes LOW,HIGH densities, got {text!r}") from None
    return low, high


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

    scene = load_scene(args.scene)
    sim = Simulation.from_scene(scene)
    n = scene.n_steps if args.steps is None else args.steps
    print(f"simulating {n} frames of {scene.timestep} s ({scene.substeps} substeps) ...", file=sys.stderr)
    traj = sim.run(n)
    write_csv(args.output, traj, sim)
    bodies = len(sim.world.names) + sum(p.qpos >= 0 for p in sim.world.prims)
    summary: dict = {"output": args.output, "frames": n + 1, "bodies": int(bodies), "video": args.video}
    human = [f"wrote {args.output}: {n + 1} frames x {bodies} bodies"]
    if args.video:
        from dano.sim.render import render_video

        human.append(f"wrote {render_video(sim, traj, args.video, progress=not args.json)}")
    if args.profile:
        import dataclasses

        from dano.sim.run import profile

        timing = profile(sim, n)
        summary["profile"] = {**dataclasses.asdict(timing), "contact": timing.contact}
        human += timing.lines()
    print(json.dumps(summary) if args.json else "\n".join(human))


def _sysid(args: argparse.Namespace) -> None:
    import dataclasses

    from dano.plotting import plot_identification
    from dano.sysid.pipeline import SysidConfig, identify_files

    if (args.scene is None) == (args.scene_option is None):
        raise DanoError("give the scene once: dano sysid SCENE.toml ... (--scene SCENE.toml is the old spelling)")
    args.scene = args.scene or args.scene_option
    fit = tuple(n.strip() for n in args.fit.split(",") if n.strip())
    if not fit:
        raise DanoError("--fit names at least one parameter, e.g. --fit friction,mass_scale")
    config = SysidConfig(
        fit=fit, fps=args.fps, scale=args.scale, size=args.size, gravity=args.gravity, body=args.body,
        window=args.window, initial=args.fit_initial or "none", sigma=args.sigma,
        init=_parse_pairs(args.init, "--init", 1),
        bounds=_parse_pairs(args.bounds, "--bounds", 2), max_steps=args.max_steps,
        rotation_weight=args.rotation_weight, settle=args.settle, interval=args.interval, level=args.level,
        frames=args.frames, loss=args.loss, orientation=args.orientation,
    )  # fmt: skip
    if args.masks is None:
        if args.camera is not None or args.field is not None or args.start_pose is not None or args.refine_frames:
            raise DanoError("--camera, --field, --start-pose and --refine-frames go with --masks")
        if not args.traj:
            raise DanoError("give the observations: --traj POSES.csv, or --masks DIR with --camera CAMERA.json")
        problem, result = identify_files(args.scene, args.traj, config, progress=not args.json)
        if args.plot:
            plot_identification(problem, result, args.plot)
    else:
        from dano.plotting import plot_masks
        from dano.vision.pixels import MaskConfig, identify_mask_files

        if args.camera is None:
            raise DanoError("--masks needs the camera that filmed them: --camera CAMERA.json")
        if len(args.traj or []) > 1:
            raise DanoError("with --masks, --traj is one pose CSV of the first frames (the initial state)")
        if args.init_from == "track" and not args.traj:
            raise DanoError("--init-from track needs the track: --traj POSES.csv (e.g. from dano track)")
        if args.init_from == "first-frames" and args.traj:
            raise DanoError("--init-from first-frames tracks the first masks itself: drop --traj")
        pose = args.start_pose
        start_pose = None if pose is None else (np.asarray(pose[:3]), np.asarray(pose[3:]))
        config = dataclasses.replace(config, initial=args.fit_initial or "state")
        problem, result = identify_mask_files(
            args.scene, args.masks, args.camera, config, start=args.traj[0] if args.traj else None,
            start_pose=start_pose, field=args.field, progress=not args.json,
            mask_config=MaskConfig(refine=tuple(r for r in (args.refine_frames or "").split(",") if r)),
        )  # fmt: skip
        if args.plot:
            plot_masks(problem, result, args.plot)
    if args.json:
        print(json.dumps(result.summary()))
        return
    span = f"{result.level:.0%} interval ({result.interval})"
    print(f"{'parameter':<20} {'estimate':>12} {'stderr':>12}   {span}")
    for name, value in result.params.items():
        low, high = result.intervals[name]
        print(f"{name:<20} {value:>12.6g} {result.stderr[name]:>12.3g}   [{low:.6g}, {high:.6g}]")
    rotation = "not fitted" if result.rms_rotation is None else f"{np.degrees(result.rms_rotation):.3g} deg"
    if result.rms_position is None:
        fitted_to = f"observation {result.rms_observation:.3g} (noise units)"
    else:
        fitted_to = f"position {result.rms_position * 1e3:.3g} mm, rotation {rotation}"
    print(
        f"loss {result.loss[0]:.4g} -> {result.loss[-1]:.4g} in {result.iterations} iterations ({result.message}), "
        f"{result.seconds:.2f} s; rms error: {fitted_to}; "
        f"{problem.n_windows} window(s) of {problem.n_frames} frames"
    )
    for kind, change in result.adjustments.items():
        print(f"adjusted {kind}: {json.dumps(change)}")
    for flag in result.flags:
        print(f"note: {flag}")
    if args.plot:
        print(f"wrote {args.plot}")


def _trajopt(args: argparse.Namespace) -> None:
    import dataclasses

    from dano.io import load_dano
    from dano.trajopt.push import PushTask, default_options, push_problem, render_push, solve_push

    x, y = _vector(args.goal, 2, "--goal", "X,Y")
    goal = (x, y)
    obj = load_dano(args.dano) if args.dano else _default_bunny()
    goal_as_constraint = False if args.goal_cost else None  # None: the robot's default
    task = PushTask(goal=goal, horizon=args.horizon, dt=args.dt, goal_as_constraint=goal_as_constraint)
    push = push_problem(obj, args.robot, task, friction=args.friction)
    options = dataclasses.replace(default_options(args.robot), max_iterations=args.max_iterations)
    result = solve_push(push, options, progress=not args.json)
    if args.video:
        render_push(push, result, args.video, progress=not args.json)
    if args.json:
        params = {"friction": args.friction, "goal": list(goal), "horizon": args.horizon, "dt": args.dt}
        adjustments = {"goal_world": push.goal_world.tolist()}  # --goal is relative to where the object rests
        print(json.dumps(result.summary(params, adjustments)))
        return
    s = result.solution
    print(f"{args.robot} push to {push.goal_world.round(4).tolist()} m: {s.message}")
    print(f"iterations {s.iterations} ({s.outer} multiplier updates), cost {s.cost:.4g}, "
          f"max constraint violation {s.max_violation:.2e}, final object error {result.final_error_m * 1e3:.2f} mm, "
          f"end effector {result.ee_error_m * 1e3:.1f} mm from its goal, {s.seconds:.1f} s (with JIT); "
          f"open-loop replay ends {result.replay_gap_m:.1e} m from the optimiser")  # fmt: skip
    if args.video:
        print(f"wrote {args.video}")


def _default_bunny():
    """The Stanford bunny as a 0.5 kg, 200-point DANO (the trajectory optimisation default)."""
    from dano.assets import bunny_mesh
    from dano.build import build_dano
    from dano.fields import mesh_field

    return build_dano(mesh_field(bunny_mesh(), resolution=64, progress=False), n_points=200, mass=0.5)


def _parse_pairs(text: str | None, option: str, n: int) -> dict:
    """`name=value,name=value` (n = 1) or `name=low:high,...` (n = 2)."""
    out: dict = {}
    for item in (text or "").split(","):
        if not item.strip():
            continue
        try:
            name, value = item.split("=")
            values = [float(v) for v in value.split(":")]
        except ValueError:
            values = []
        if len(values) != n:
            form = "name=value" if n == 1 else "name=low:high"
            raise DanoError(f"{option} takes {form}[,...], got {item!r}")
        out[name.strip()] = values[0] if n == 1 else tuple(values)
    return out


def _demo(args: argparse.Namespace) -> None:
    from dano.demo import run_demo

    if not args.json:
        run_demo(args.out, resolution=args.resolution, seed=args.seed, simulate=not args.no_sim)
        return
    import contextlib

    with contextlib.redirect_stdout(sys.stderr):  # the demo's own lines; stdout carries the one object
        summary = run_demo(args.out, resolution=args.resolution, seed=args.seed, simulate=not args.no_sim)
    print(json.dumps({"output": args.out, **summary}))


def _compare(args: argparse.Namespace) -> None:
    from dano.baselines import compare as C

    scenarios = C.Scenarios(
        friction=args.friction, drop_s=args.drop_seconds, slide_speed=args.slide_speed, push_speed=args.push_speed
    )
    knobs = {
        "decomposition": args.decomposition,
        "threshold": args.threshold,
        "max_hulls": args.max_hulls,
        "max_faces": args.max_faces,
    }
    if args.source in C.REFERENCE_LEVELS and not Path(args.source).exists():
        if args.data_dir is None:
            raise C.CompareError(f"{args.source} is reference data: give --data-dir (the folder with colliders/)")
        models, dano_model = C.reference_models(args.source, args.data_dir, **knobs)
        models.append(dano_model)
        truth = dano_model  # no better truth for a scanned object: the authors' own DANO
    else:
        models, truth = _field_models(args, knobs)
    result = C.compare(models, truth, scenarios)
    if args.plot:
        from dano.plotting import plot_rests

        plot_rests(result, args.plot, title=f"{args.source}: at rest after {scenarios.drop_s:g} s")
    if args.json:
        print(json.dumps({"source": args.source, "truth": None if truth is None else truth.label, "rows": result.rows}))
    else:
        print(f"{args.source}: against {'no truth' if truth is None else truth.label}")
        print(C.format_table(result.rows))
        if args.plot:
            print(f"wrote {args.plot}")


def _render_views(args: argparse.Namespace) -> None:
    from dano.fields import load_mesh
    from dano.vision.synthetic import render_views

    mesh = load_mesh(args.mesh, repair=args.repair, scale=args.scale)
    out = render_views(mesh, args.output, n_views=args.views, resolution=args.resolution, seed=args.seed,
                       overwrite=args.overwrite)  # fmt: skip
    if args.json:
        print(json.dumps({"output": str(out), "views": args.views, "image_size": args.resolution}))
    else:
        print(f"wrote {out}: {args.views} views of {args.resolution} x {args.resolution} px with masks")


def _fit_field(args: argparse.Namespace) -> None:
    import jax

    from dano.fields import GridField, save_grid
    from dano.vision.datasets import load_nerf_synthetic
    from dano.vision.fit import FitConfig, fit_field, solidify

    views = load_nerf_synthetic(args.dataset, split=args.split, downscale=args.downscale)
    config = FitConfig(steps=args.steps, resolution=args.resolution, n_samples=args.samples)
    result = fit_field(views, config, key=jax.random.key(args.seed), progress=not args.json)
    assert isinstance(result.field, GridField)  # the default model, "grid"
    solid = solidify(result.field, views)
    save_grid(args.output, solid.field)
    if args.raw:
        save_grid(args.raw, result.field)
    psnr = float(result.psnr[-50:].mean())
    summary = {"output": args.output, "views": views.n_views, "steps": args.steps, "psnr_db": psnr,
               "seconds": result.seconds, "bounds": result.bounds.tolist()}  # fmt: skip
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"wrote {args.output}: the solid (density 1000 inside; build a DANO with dano build)")
        print(f"{views.n_views} views, {args.steps} steps in {result.seconds:.1f} s, PSNR {summary['psnr_db']:.1f} dB")


def _track(args: argparse.Namespace) -> None:
    from dano.build import field_from_source
    from dano.sysid.data import Track, write_track
    from dano.types import DANO
    from dano.vision.camera import load_camera
    from dano.vision.media import load_frames, load_masks
    from dano.vision.track import TrackConfig, track

    camera = load_camera(args.camera)
    frames, _ = load_frames(args.video)
    masks = load_masks(args.masks, len(frames), (camera.height, camera.width))
    field = field_from_source(args.field, scale=args.scale)
    if isinstance(field, DANO):
        raise DanoError(f"{args.field}: tracking needs a field (grid, checkpoint, mesh, spec), not a DANO")
    init = None
    if args.init:
        init = (np.asarray(args.init[:3]), np.asarray(args.init[3:]))
    config = TrackConfig(iterations=args.iterations, refine_iterations=args.refine)
    result = track(field, camera, masks, config, init=init, progress=not args.json)
    positions = result.positions
    if args.frame == "com":  # what `dano sysid` reads: the centre of mass
        from dano.mass import mass_properties
        from dano.math import quat_to_mat

        com = np.asarray(mass_properties(field).com)
        positions = positions + np.einsum("tij,j->ti", np.asarray(quat_to_mat(result.quats)), com)
    poses = np.concatenate([positions, result.quats], axis=1)
    write_track(args.output, Track.from_poses(poses, 1.0 / args.fps, source=args.video))
    per_frame = result.seconds / len(frames)
    if args.json:
        summary = {"output": args.output, "frames": len(frames), "frame": args.frame, "seconds": result.seconds,
                   "seconds_per_frame": per_frame, "mean_mask_loss": float(np.mean(result.losses))}  # fmt: skip
        print(json.dumps(summary))
        return
    print(f"wrote {args.output}: {len(frames)} poses (position of the {args.frame}) in {result.seconds:.1f} s "
          f"({per_frame:.2f} s per frame), mean mask loss {float(np.mean(result.losses)):.2e}")  # fmt: skip


def _field_models(args: argparse.Namespace, knobs: dict):
    import time

    from dano.baselines import compare as C
    from dano.build import build_dano, field_from_source
    from dano.fields import MESH_SUFFIXES, load_mesh, mesh_field
    from dano.surface import field_peak
    from dano.types import DANO

    truth = None
    if args.source.lower().endswith(MESH_SUFFIXES):
        mesh = load_mesh(args.source, repair=args.repair, scale=args.scale)
        truth = C.mesh_model("truth (mesh)", mesh, progress=True, **knobs)
        field = mesh_field(mesh, resolution=args.resolution)
    else:
        field = field_from_source(args.source, scale=args.scale, resolution=args.resolution)
        if isinstance(field, DANO):
            raise C.CompareError("compare needs the field the DANO comes from (a mesh, grid, checkpoint or spec)")
    levels = _parse_levels(args.levels, field_peak(field, args.seed))
    models = C.level_set_models(field, levels, args.resolution, clean=args.clean, **knobs)
    start = time.perf_counter()
    dano = build_dano(field, n_points=args.points, seed=args.seed)
    models.append(C.dano_model("DANO", dano, time.perf_counter() - start))
    return models, truth


def _parse_levels(text: str | None, peak: float) -> list[float]:
    if text is None:
        return [0.03 * peak, 0.5 * peak, 0.95 * peak]
    try:
        return [float(v) for v in text.split(",")]
    except ValueError:
        raise DanoError(f"--levels takes comma-separated densities, got {text!r}") from None


def parser() -> argparse.ArgumentParser:
    from dano import __version__

    p = _Parser(prog="dano", description="Dynamics-Augmented Neural Objects")
    p.add_argument("--version", action="version", version=f"dano {__version__}")
    sub = p.add_subparsers(dest="command", required=True)

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

    i = sub.add_parser("info", help="print a DANO's mass properties")
    i.add_argument("file")
    i.add_argument("--json", action="store_true", help="one JSON object (keys mass, com, inertia, n_points, ...)")
    i.set_defaults(run=_info)

    s = sub.add_parser("simulate", help="simulate a scene TOML file, write the trajectory CSV (and a video)")
    s.add_argument("scene", help="scene .toml (see README)")
    s.add_argument("-o", "--output", required=True, type=_output(), help="trajectory CSV: t,body,x,y,z,qw,qx,qy,qz")
    s.add_argument("--video", type=_output(*VIDEO), help="render to this .mp4 or .gif")
    s.add_argument("--steps", type=_int(1), help="frames to simulate (default: duration / timestep)")
    s.add_argument("--json", action="store_true", help="one JSON object (output, frames, bodies, video, profile)")
    s.add_argument("--profile", action="store_true",
                   help="also time the rollout apart: compile, run, and its DANO contact vs the engine")  # fmt: skip
    s.set_defaults(run=_simulate)

    y = sub.add_parser("sysid", help="identify friction, mass scale, ... from pose trajectories or object masks")
    y.add_argument("scene", nargs="?", help="scene .toml: the object, the table, contact parameters")
    y.add_argument("--scene", dest="scene_option", help=argparse.SUPPRESS)  # the old spelling
    y.add_argument("--traj", action="append",
                   help="pose CSV t,x,y,z,qw,qx,qy,qz (repeatable); with --masks: the first frames' poses")  # fmt: skip
    y.add_argument("--masks", help="folder of one object mask per frame (white = object, name order; all black: "
                   "no mask that frame): identify end to end, simulating and rendering the silhouette")  # fmt: skip
    y.add_argument("--camera", help="with --masks: camera JSON {width, height, fx, fy, cx, cy, c2w} (metric)")
    y.add_argument("--init-from", choices=["track", "first-frames"],
                   help="with --masks: the initial state from --traj (track) or from tracking the first "
                   "masks (first-frames; the default without --traj)")  # fmt: skip
    y.add_argument("--start-pose", type=_checked(_numbers(7, "x,y,z,qw,qx,qy,qz", 3)),
                   help="with --masks: the field frame's pose in the first frame, where tracking the first "
                   "frames starts (default: a guess from the first mask)")  # fmt: skip
    y.add_argument("--field", help="with --masks: the field the silhouette is rendered from, in the DANO's frame "
                   "(grid/checkpoint .npz, mesh, spec; default: the DANO's baked grid)")  # fmt: skip
    y.add_argument("--refine-frames", help="with --masks, comma-separated: also fit small corrections to the camera's "
                   "extrinsics (camera) and the field's pose in the DANO's frame (object)")  # fmt: skip
    y.add_argument("--fit", required=True, help="comma-separated: friction, mass_scale, inertia_scale, contact keys")
    y.add_argument(
        "--json",
        action="store_true",
        help='one JSON object {"params", "stderr", "intervals", "interval", "loss", "iterations", "converged", '
        '"message", "rms", "seconds", "flags", "adjustments"}',
    )
    y.add_argument("--plot", type=_output(*PLOT),
                   help="PNG of observed vs fitted trajectories (with --masks: masks, simulated silhouettes and "
                   "their difference) and the loss")  # fmt: skip
    y.add_argument("--fps", type=_POSITIVE, help="frame rate of files without a t column")
    y.add_argument("--scale", type=_POSITIVE, help="metres per unit of the positions in the files")
    y.add_argument(
        "--size",
        type=_POSITIVE,
        help="the object's real longest dimension along its principal axes, m, as `dano info` "
        "prints it in the DANO's units (DANO and data share units)",
    )
    y.add_argument(
        "--gravity",
        type=_checked(_gravity),
        help="gravity direction gx,gy,gz in the data's frame, or 'fit' (plane of motion)",
    )
    y.add_argument("--body", help="the scene body that files without a body column observe")
    y.add_argument("--window-frames", "--window", dest="window", type=_int(1),
                   help="frame intervals per shooting window (default: whole trajectories)")  # fmt: skip
    y.add_argument("--fit-initial", choices=["none", "velocity", "state"],
                   help="also fit each window's initial velocity, or pose and velocity (default: none; "
                   "with --masks: state)")  # fmt: skip
    y.add_argument("--sigma", type=_POSITIVE, default=1e-3, help="tracking noise, m (default 0.001)")
    y.add_argument("--init", help="initial guesses name=value,... (default: the scene's values)")
    y.add_argument("--bounds", help="bounds name=low:high,... (default: Table I ranges, widened)")
    y.add_argument("--max-iterations", "--max-steps", dest="max_steps", type=_int(1), default=50,
                   help="Levenberg-Marquardt iterations at most (default 50)")  # fmt: skip
    y.add_argument("--rotation-weight", type=_float(0.0), default=1.0,
                   help="weight of the orientation residuals (0: positions only, for a tracker that could "
                   "not resolve rotation; default 1)")  # fmt: skip
    y.add_argument("--settle", type=_float(0.0),
                   help="m: a body this near the ground at a window's start is put on it (default 3 sigma; "
                   "0: the data as they are)")  # fmt: skip
    y.add_argument("--interval", choices=["profile", "gauss-newton"], default="profile",
                   help="profile: refit with each parameter held, where the loss rises by the chi-square "
                   "quantile (honest on rough or flat losses; ~6 refits per parameter); gauss-newton: "
                   "estimate +/- z stderr, free (default profile)")  # fmt: skip
    y.add_argument("--loss", choices=["l2", "huber", "cauchy"], default="l2",
                   help="least squares (default), or a robust loss for outliers (impacts, tracking failures): "
                   "frames off by more than 2.8 sigma pull less (huber) or hardly at all (cauchy)")  # fmt: skip
    y.add_argument(
        "--orientation",
        choices=["track", "resting"],
        default="track",
        help="track: the files' quaternions (default); resting: the tracker could not resolve "
        "rotation: the object lies on the stable face and heading that fit best (positions only)",
    )
    y.add_argument("--frames", type=_checked(_frames), metavar="FIRST:STOP",
                   help="rows of each file to fit, 0-based, STOP excluded (e.g. 400:901; default all)")  # fmt: skip
    y.add_argument("--level", type=_checked(_level), default=0.95, help="confidence level (default 0.95)")
    y.set_defaults(run=_sysid)

    t = sub.add_parser("trajopt", help="trajectory optimisation: a robot pushes a DANO to a goal (constrained iLQR)")
    t.add_argument("task", choices=["push"])
    t.add_argument("--robot", choices=["sphere", "panda"], default="sphere")
    t.add_argument("--dano", help="the object, a .dano.npz (default: the Stanford bunny, 0.5 kg, 200 points)")
    t.add_argument("--goal", type=_checked(_vector_part), nargs="+", default=[(0.1,), (0.0,)], metavar="X,Y",
                   help="where the object should end, m, relative to where it rests (default 0.1 0)")  # fmt: skip
    t.add_argument("--horizon", type=_int(1), default=10, help="frames (default 10)")
    t.add_argument("--dt", type=_POSITIVE, default=0.08, help="seconds per frame (default 0.08)")
    t.add_argument("--friction", type=_float(0.0), default=0.3)
    t.add_argument(
        "--goal-cost", action="store_true", help="the goal as a cost, not a constraint (the Panda's default)"
    )
    t.add_argument("--max-iterations", type=_int(1), default=150)
    t.add_argument("--video", type=_output(*VIDEO), help="render the open-loop replay to this .mp4 or .gif")
    t.add_argument("--json", action="store_true",
                   help="one JSON object (final_error_m, iterations, seconds, max_violation, ...)")  # fmt: skip
    t.set_defaults(run=_trajopt)

    c = sub.add_parser("compare", help="the mesh path (level sets, convex pieces, MuJoCo) against the DANO, measured")
    c.add_argument("source", help="a mesh file (also the truth), a field (grid or neural .npz, spec), or reference "
                   "data: bluesoap, halfsoap or bunny with --data-dir")  # fmt: skip
    c.add_argument("--levels", help="density levels a,b,c (default 3%%, 50%%, 95%% of the field's peak)")
    c.add_argument("--data-dir", help="the reference data folder (with colliders/ and meshes/)")
    c.add_argument("--resolution", type=_int(4), default=100, help="grid nodes along the longest side (default 100)")
    c.add_argument("--clean", action="store_true", help="keep each level set's largest component, repair it")
    c.add_argument("--repair", action="store_true", help="make a non-watertight source mesh watertight")
    c.add_argument("--scale", type=_POSITIVE, default=1.0, help="multiply the source's lengths by this (m per unit)")
    c.add_argument("--decomposition", choices=["coacd", "vhacd"], default="coacd")
    c.add_argument("--threshold", type=_POSITIVE, default=0.05, help="CoACD concavity (V-HACD: volume error / 100)")
    c.add_argument("--max-hulls", type=_int(-1), default=-1, help="cap on convex pieces (-1: none)")
    c.add_argument(
        "--max-faces", type=_int(4), default=10000, help="decimate meshes to this many faces before decomposing"
    )
    c.add_argument("--points", type=_int(1), default=3000, help="DANO surface points (default 3000)")
    c.add_argument("--friction", type=_float(0.0), default=0.5)
    c.add_argument("--drop-seconds", type=_POSITIVE, default=1.0, help="settling time after the drop (default 1)")
    c.add_argument("--slide-speed", type=_float(0.0), default=0.5, help="m/s (default 0.5)")
    c.add_argument("--push-speed", type=_float(0.0), default=0.2, help="m/s of the pushing sphere (default 0.2)")
    c.add_argument("--seed", type=_int(0), default=0)
    c.add_argument("--plot", type=_output(*PLOT), help="PNG of every model at rest on the floor (the paper's Fig. 8)")
    c.add_argument("--json", action="store_true", help='one JSON object {"source", "truth", "rows": [...]}')
    c.set_defaults(run=_compare)

    r = sub.add_parser("render-views", help="render a mesh from around it into a NeRF-synthetic dataset (with masks)")
    r.add_argument("mesh", help="mesh file (.ply .obj .stl ...)")
    r.add_argument("-o", "--output", required=True, type=_checked(_in_a_folder), help="dataset folder to create")
    r.add_argument("--views", type=_int(1), default=50)
    r.add_argument(
        "--image-size", "--resolution", dest="resolution", type=_int(8), default=64, help="image side, px (default 64)"
    )
    r.add_argument("--json", action="store_true", help="one JSON object (output, views, image_size)")
    r.add_argument("--scale", type=_POSITIVE, default=1.0, help="multiply lengths by this (m per unit)")
    r.add_argument("--repair", action="store_true", help="make a non-watertight mesh watertight first")
    r.add_argument("--seed", type=_int(0), default=0)
    r.add_argument("--overwrite", action="store_true")
    r.set_defaults(run=_render_views)

    f = sub.add_parser("fit-field", help="fit a density field to posed images (volume rendering), as a solid grid")
    f.add_argument("dataset", help="folder in the NeRF-synthetic layout (transforms.json, images, masks)")
    f.add_argument(
        "-o", "--output", required=True, type=_output(".npz"), help="the solid field, a grid .npz (dano build reads it)"
    )
    f.add_argument("--steps", type=_int(1), default=1000)
    f.add_argument("--resolution", type=_int(4), default=64, help="grid nodes along the box's longest side")
    f.add_argument("--samples", type=_int(2), default=128, help="samples per ray (default 128)")
    f.add_argument("--downscale", type=_int(1), default=1, help="box-average the images by this factor")
    f.add_argument("--split", default="train")
    f.add_argument("--raw", type=_output(".npz"), help="also write the fitted optical density (1/m) as a grid .npz")
    f.add_argument("--seed", type=_int(0), default=0)
    f.add_argument("--json", action="store_true", help="one JSON object (psnr_db, seconds, bounds, ...)")
    f.set_defaults(run=_fit_field)

    k = sub.add_parser("track", help="track an object's pose through a video from its masks")
    k.add_argument("video", help="a video file or a folder of frames")
    k.add_argument("--field", required=True, help="the object's field: grid/checkpoint .npz, mesh, or spec")
    k.add_argument("--camera", required=True, help="camera JSON {width, height, fx, fy, cx, cy, c2w}")
    k.add_argument("--masks", required=True, help="folder of one mask PNG per frame (white = object)")
    k.add_argument(
        "-o", "--output", required=True, type=_output(), help="pose CSV t,x,y,z,qw,qx,qy,qz (as dano sysid reads)"
    )
    k.add_argument("--frame", choices=["com", "field"], default="com",
                   help="positions of the centre of mass (default; sysid reads it) or of the field origin")  # fmt: skip
    k.add_argument("--fps", type=_POSITIVE, default=30.0)
    k.add_argument("--scale", type=_POSITIVE, default=1.0, help="multiply the field's lengths by this")
    k.add_argument(
        "--init",
        type=_checked(_numbers(7, "x,y,z,qw,qx,qy,qz", 3)),
        help="first frame's pose x,y,z,qw,qx,qy,qz (default: a guess from the first mask)",
    )
    k.add_argument(
        "--steps", "--iterations", dest="iterations", type=_int(1), default=60, help="Adam steps per frame (default 60)"
    )
    k.add_argument("--json", action="store_true", help="one JSON object (output, frames, seconds, mean_mask_loss, ...)")
    k.add_argument("--refine", type=_int(0), default=0, help="steps of joint refinement over all frames (default 0)")
    k.set_defaults(run=_track)

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
    return p


RENAMED = {
    ("demo", "--out"): "-o/--output",
    ("sysid", "--scene"): "the positional SCENE (dano sysid SCENE.toml ...)",
    ("sysid", "--max-steps"): "--max-iterations",
    ("sysid", "--window"): "--window-frames",
    ("render-views", "--resolution"): "--image-size",
    ("track", "--iterations"): "--steps",
}
"""Old spellings still accepted for one release (they go in 0.3), each with a note on stderr: one
word per concept across commands (`-o` for output, `--max-iterations` for a solver's cap, `--steps`
for a fixed count, `--resolution` for grid nodes, `--window` for a density window)."""


def _renamed_notes(command: str, argv: list[str]) -> None:
    for token in argv:
        new = RENAMED.get((command, token.split("=", 1)[0]))
        if new is not None:
            print(f"dano {command}: note: {token.split('=', 1)[0]} is now {new} (the old name goes in 0.3)",
                  file=sys.stderr)  # fmt: skip


CACHE_VARIABLE = "DANO_COMPILATION_CACHE"
"""Environment variable: the folder of the command line's persistent compilation cache (default
`~/.cache/dano/jax`), or `off`."""


def compilation_cache() -> str | None:
    """Turns on JAX's persistent compilation cache for this command (not on import: a library
    changes no process setting) and returns its folder, or None when `DANO_COMPILATION_CACHE=off`.
    A second run of the same command with the same shapes then loads its XLA programs from disk
    instead of compiling them (a simulation's rollout, an identification's Jacobians)."""
    import jax

    path = os.environ.get(CACHE_VARIABLE) or str(Path.home() / ".cache" / "dano" / "jax")
    if path.lower() in ("off", "0", "none"):
        return None
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    return path


def attach_negative_values(argv: list[str]) -> list[str]:
    """`--gravity -0.27,-0.27,-0.92` as `--gravity=-0.27,...`: argparse takes a token that starts with
    '-' and is not a plain number for an option, so comma-separated negative values need the '='."""
    out: list[str] = []
    for token in argv:
        if out and out[-1].startswith("--") and "=" not in out[-1] and re.match(r"-[\d.]", token) and "," in token:
            out[-1] = f"{out[-1]}={token}"
        else:
            out.append(token)
    return out


def _warning_line(command: str):
    """Warnings as one line on stderr, like errors: `dano sysid: UnitsWarning: ...`."""

    def show(message, category, filename, lineno, file=None, line=None):
        print(f"dano {command}: {category.__name__}: {message}", file=sys.stderr if file is None else file)

    return show


def main(argv: list[str] | None = None) -> int:
    argv = attach_negative_values(sys.argv[1:] if argv is None else list(argv))
    try:
        args = parser().parse_args(argv)
    except SystemExit as e:  # --help, --version (0) or a usage error (2, its one line already printed)
        return e.code if isinstance(e.code, int) else 2
    _renamed_notes(args.command, argv)
    import jax  # after parsing: `dano --help` and usage errors need no JAX

    # Float64 throughout, as the tests run: identification needs it (in float32 the Gauss-Newton
    # Hessian of a stiff contact overflows), and one precision keeps every command's numbers alike.
    jax.config.update("jax_enable_x64", True)
    compilation_cache()
    try:
        with warnings.catch_warnings():  # restored on the way out: the caller's process is left as it was
            warnings.showwarning = _warning_line(args.command)
            args.run(args)
    except DanoError as e:
        print(f"dano {args.command}: {type(e).__name__}: {e}", file=sys.stderr)
        return 2
    except OSError as e:  # the disk: full, read-only, permissions (outputs are written atomically)
        print(f"dano {args.command}: {type(e).__name__}: {e}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
