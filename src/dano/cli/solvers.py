"""`dano sysid` and `dano trajopt`: real-to-sim and sim-to-robot."""

import argparse
import json

import numpy as np

from dano.cli.arguments import (
    _POSITIVE,
    PLOT,
    VIDEO,
    _checked,
    _existing,
    _float,
    _frames,
    _gravity,
    _int,
    _level,
    _numbers,
    _output,
    _parse_pairs,
    _vector,
    _vector_part,
)
from dano.cli.configs import add_config, from_args
from dano.cli.reports import add_report
from dano.errors import DanoError
from dano.sysid.configs import Interval, SysidConfig


def _add_sysid(sub) -> None:
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
    add_report(y, "the estimates with their intervals, the fit's picture")
    y.add_argument("--init", help="initial guesses name=value,... (default: the scene's values)")
    y.add_argument("--bounds", help="bounds name=low:high,... (default: Table I ranges, widened)")
    add_config(
        y, SysidConfig, skip=("fit", "init", "bounds"),
        names={"window": ("--window-frames", "--window"), "initial": ("--fit-initial",),
               "max_steps": ("--max-iterations", "--max-steps")},
        types={"fps": (_POSITIVE, "FPS"), "scale": (_POSITIVE, "X"), "size": (_POSITIVE, "M"),
               "sigma": (_POSITIVE, "M"), "gravity": (_checked(_gravity), "GX,GY,GZ|fit"), "window": (_int(1), "N"),
               "max_steps": (_int(1), "N"), "rotation_weight": (_float(0.0), "X"), "settle": (_float(0.0), "M"),
               "frames": (_checked(_frames), "FIRST:STOP"), "level": (_checked(_level), "P")},
        defaults={"interval": Interval.profile},  # the command reports honest intervals; the library, fast ones
    )  # fmt: skip
    y.set_defaults(run=_sysid)


def _add_trajopt(sub) -> None:
    t = sub.add_parser("trajopt", help="trajectory optimisation: a robot pushes a DANO to a goal (constrained iLQR)")
    t.add_argument("task", choices=["push"])
    t.add_argument("--robot", choices=["sphere", "panda"], default="sphere")
    t.add_argument("--dano", help="the object, a .dano.npz (default: the Stanford bunny, 0.5 kg, 200 points)")
    t.add_argument("--goal", type=_checked(_vector_part), nargs="+", default=[(0.1,), (0.0,)], metavar="X,Y",
                   help="where the object should end, m, relative to where it rests (default 0.1 0)")  # fmt: skip
    t.add_argument("--world", type=_checked(_existing), help="an MJCF world to push in (its table, its actuators)")
    t.add_argument("--at", type=_checked(_vector_part), nargs="+", default=[(0.0,), (0.0,)], metavar="X,Y",
                   help="where in the world the object starts, on what is under it (default 0 0)")  # fmt: skip
    t.add_argument("--horizon", type=_int(1), default=10, help="frames (default 10)")
    t.add_argument("--dt", type=_POSITIVE, default=0.08, help="seconds per frame (default 0.08)")
    t.add_argument("--friction", type=_float(0.0), default=0.3)
    t.add_argument(
        "--goal-cost", action="store_true", help="the goal as a cost, not a constraint (the Panda's default)"
    )
    t.add_argument("--max-iterations", type=_int(1), default=150)
    t.add_argument("--video", type=_output(*VIDEO), help="render the open-loop replay to this .mp4 or .gif")
    t.add_argument("--contacts", action="store_true",
                   help="draw each contact's force as an arrow in the video (its weight: half its size)")  # fmt: skip
    t.add_argument("--style", choices=["surface", "points"], default="surface",
                   help="draw the DANO as its surface (default) or its surface points")  # fmt: skip
    t.add_argument("--json", action="store_true",
                   help="one JSON object (final_error_m, iterations, seconds, max_violation, ...)")  # fmt: skip
    add_report(t, "the solution's figures and the replay's video (with --video)")
    t.set_defaults(run=_trajopt)


def _sysid(args: argparse.Namespace) -> None:
    import dataclasses

    from dano.plotting import plot_identification
    from dano.sysid.configs import Initial
    from dano.sysid.pipeline import identify_files

    if (args.scene is None) == (args.scene_option is None):
        raise DanoError("give the scene once: dano sysid SCENE.toml ... (--scene SCENE.toml is the old spelling)")
    args.scene = args.scene or args.scene_option
    fit = tuple(n.strip() for n in args.fit.split(",") if n.strip())
    if not fit:
        raise DanoError("--fit names at least one parameter, e.g. --fit friction,mass_scale")
    config = from_args(
        SysidConfig, args, fit=fit, init=_parse_pairs(args.init, "--init", 1),
        bounds=_parse_pairs(args.bounds, "--bounds", 2),
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
        from dano.vision.observation import MaskConfig
        from dano.vision.pixels import identify_mask_files

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
        if not hasattr(args, "config_initial"):  # from masks alone the pose is unknown too
            config = dataclasses.replace(config, initial=Initial.state)
        problem, result = identify_mask_files(
            args.scene, args.masks, args.camera, config, start=args.traj[0] if args.traj else None,
            start_pose=start_pose, field=args.field, progress=not args.json,
            mask_config=MaskConfig(refine=tuple(r for r in (args.refine_frames or "").split(",") if r)),
        )  # fmt: skip
        if args.plot:
            plot_masks(problem, result, args.plot)
    if args.report:
        _sysid_report(args, problem, result)
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
    for path in (args.plot, args.report):
        if path:
            print(f"wrote {path}")


def _sysid_report(args: argparse.Namespace, problem, result) -> None:
    from dano.cli.reports import picture, write_command_report
    from dano.plotting import plot_identification, plot_masks
    from dano.report import Section

    rows = [("parameter", "estimate", "standard error", f"{result.level:.0%} interval ({result.interval})")]
    for name, value in result.params.items():
        low, high = result.intervals[name]
        rows.append((name, f"{value:.6g}", f"{result.stderr[name]:.3g}", f"[{low:.6g}, {high:.6g}]"))
    text = (f"Loss {result.loss[0]:.4g} to {result.loss[-1]:.4g} in {result.iterations} iterations "
            f"({result.message}), {result.seconds:.2f} s; {problem.n_windows} window(s) of {problem.n_frames} "
            f"frames. " + " ".join(f"Note: {flag}." for flag in result.flags))  # fmt: skip
    draw = plot_identification if args.masks is None else plot_masks
    with picture(args.plot, lambda path: draw(problem, result, path)) as png:
        write_command_report(args, "dano sysid", [Section("Identification", text, rows, [png])])


def _trajopt(args: argparse.Namespace) -> None:
    import dataclasses

    from dano.io import load_dano
    from dano.trajopt.push import PushTask, default_options, push_problem, render_push, solve_push

    x, y = _vector(args.goal, 2, "--goal", "X,Y")
    goal = (x, y)
    obj = load_dano(args.dano) if args.dano else _default_bunny()
    goal_as_constraint = False if args.goal_cost else None  # None: the robot's default
    task = PushTask(goal=goal, horizon=args.horizon, dt=args.dt, goal_as_constraint=goal_as_constraint)
    x0, y0 = _vector(args.at, 2, "--at", "X,Y") if args.world else (0.0, 0.0)
    push = push_problem(obj, args.robot, task, friction=args.friction, world=args.world, at=(x0, y0))
    options = dataclasses.replace(default_options(args.robot), max_iterations=args.max_iterations)
    result = solve_push(push, options, progress=not args.json)
    if args.video:
        render_push(push, result, args.video, progress=not args.json, style=args.style, contacts=args.contacts)
    if args.report:
        _trajopt_report(args, push, result)
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
    for path in (args.video, args.report):
        if path:
            print(f"wrote {path}")


def _trajopt_report(args: argparse.Namespace, push, result) -> None:
    from dano.cli.reports import write_command_report
    from dano.report import Section

    s = result.solution
    rows = [("goal [m]", "converged", "iterations", "cost", "max violation", "object error [mm]",
             "end effector error [mm]", "replay gap [m]", "seconds (with JIT)"),
            (push.goal_world.round(4).tolist(), s.converged, s.iterations, f"{s.cost:.4g}", f"{s.max_violation:.2e}",
             f"{result.final_error_m * 1e3:.2f}", f"{result.ee_error_m * 1e3:.1f}", f"{result.replay_gap_m:.1e}",
             f"{s.seconds:.1f}")]  # fmt: skip
    media = [args.video] if args.video and args.video.lower().endswith(".mp4") else []
    text = f"The {args.robot} pushes the object: {s.message}. The video is the open-loop replay of the controls."
    write_command_report(args, "dano trajopt push", [Section("Trajectory optimisation", text, rows, media)])


def _default_bunny():
    """The Stanford bunny as a 0.5 kg, 200-point DANO (the trajectory optimisation default)."""
    from dano.assets import bunny_mesh
    from dano.build import build_dano
    from dano.fields import mesh_field

    return build_dano(mesh_field(bunny_mesh(), resolution=64, progress=False), n_points=200, mass=0.5)
