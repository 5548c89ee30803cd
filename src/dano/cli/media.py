"""`dano render-views`, `fit-field`, `track` and `compare`: pixels and the mesh path."""

import argparse
import json
from pathlib import Path

import numpy as np

from dano.cli.arguments import (
    _POSITIVE,
    PLOT,
    _checked,
    _float,
    _in_a_folder,
    _int,
    _numbers,
    _output,
    _parse_levels,
)
from dano.cli.configs import add_config, from_args
from dano.cli.reports import add_report
from dano.errors import DanoError
from dano.vision.configs import FitConfig, GridModel, TrackConfig


def _add_render_views(sub) -> None:
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


def _add_fit_field(sub) -> None:
    f = sub.add_parser("fit-field", help="fit a density field to posed images (volume rendering), as a solid grid")
    f.add_argument("dataset", help="folder in the NeRF-synthetic layout (transforms.json, images, masks)")
    f.add_argument(
        "-o", "--output", required=True, type=_output(".npz"), help="the solid field, a grid .npz (dano build reads it)"
    )
    add_config(f.add_argument_group("fitting (FitConfig)"), FitConfig, names={"n_samples": ["--samples"]})
    add_config(f.add_argument_group("the grid (GridModel)"), GridModel)
    f.add_argument("--downscale", type=_int(1), default=1, help="box-average the images by this factor")
    f.add_argument("--split", default="train")
    f.add_argument("--raw", type=_output(".npz"), help="also write the fitted optical density (1/m) as a grid .npz")
    f.add_argument("--seed", type=_int(0), default=0)
    f.add_argument("--json", action="store_true", help="one JSON object (psnr_db, seconds, bounds, ...)")
    f.set_defaults(run=_fit_field)


def _add_track(sub) -> None:
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
    k.add_argument("--json", action="store_true", help="one JSON object (output, frames, seconds, mean_mask_loss, ...)")
    names = {"iterations": ["--steps", "--iterations"], "first_iterations": ["--first-steps"],
             "refine_iterations": ["--refine"], "n_samples": ["--samples"]}  # fmt: skip
    add_config(k.add_argument_group("tracking (TrackConfig)"), TrackConfig, names=names)
    k.set_defaults(run=_track)


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
    from dano.vision.fit import fit_field, solidify

    views = load_nerf_synthetic(args.dataset, split=args.split, downscale=args.downscale)
    config = from_args(FitConfig, args, model=from_args(GridModel, args))
    result = fit_field(views, config, key=jax.random.key(args.seed), progress=not args.json)
    assert isinstance(result.field, GridField)  # the default model, "grid"
    solid = solidify(result.field, views)
    save_grid(args.output, solid.field)
    if args.raw:
        save_grid(args.raw, result.field)
    psnr = float(result.psnr[-50:].mean())
    summary = {"output": args.output, "views": views.n_views, "steps": config.steps, "psnr_db": psnr,
               "seconds": result.seconds, "bounds": result.bounds.tolist()}  # fmt: skip
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"wrote {args.output}: the solid (density 1000 inside; build a DANO with dano build)")
        print(
            f"{views.n_views} views, {config.steps} steps in {result.seconds:.1f} s, PSNR {summary['psnr_db']:.1f} dB"
        )


def _track(args: argparse.Namespace) -> None:
    from dano.build import field_from_source
    from dano.sysid.data import Track, write_track
    from dano.types import DANO
    from dano.vision.camera import load_camera
    from dano.vision.media import load_frames, load_masks
    from dano.vision.track import track

    camera = load_camera(args.camera)
    frames, _ = load_frames(args.video)
    masks = load_masks(args.masks, len(frames), (camera.height, camera.width))
    field = field_from_source(args.field, scale=args.scale)
    if isinstance(field, DANO):
        raise DanoError(f"{args.field}: tracking needs a field (grid, checkpoint, mesh, spec), not a DANO")
    init = None
    if args.init:
        init = (np.asarray(args.init[:3]), np.asarray(args.init[3:]))
    config = from_args(TrackConfig, args)
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


def _add_compare(sub) -> None:
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
    add_report(c, "the table of every model against the truth, the models at rest")
    c.set_defaults(run=_compare)


def _compare(args: argparse.Namespace) -> None:
    from dano.baselines import compare as C
    from dano.baselines import models as M

    scenarios = C.Scenarios(
        friction=args.friction, drop_s=args.drop_seconds, slide_speed=args.slide_speed, push_speed=args.push_speed
    )
    knobs = {
        "decomposition": args.decomposition,
        "threshold": args.threshold,
        "max_hulls": args.max_hulls,
        "max_faces": args.max_faces,
    }
    if args.source in M.REFERENCE_LEVELS and not Path(args.source).exists():
        if args.data_dir is None:
            raise M.CompareError(f"{args.source} is reference data: give --data-dir (the folder with colliders/)")
        models, dano_model = M.reference_models(args.source, args.data_dir, **knobs)
        models.append(dano_model)
        truth = dano_model  # no better truth for a scanned object: the authors' own DANO
    else:
        models, truth = _field_models(args, knobs)
    result = C.compare(models, truth, scenarios)
    if args.plot:
        from dano.plotting import plot_rests

        plot_rests(result, args.plot, title=f"{args.source}: at rest after {scenarios.drop_s:g} s")
    if args.report:
        _compare_report(args, result, truth, scenarios)
    if args.json:
        print(json.dumps({"source": args.source, "truth": None if truth is None else truth.label, "rows": result.rows}))
    else:
        print(f"{args.source}: against {'no truth' if truth is None else truth.label}")
        print(C.format_table(result.rows))
        for path in (args.plot, args.report):
            if path:
                print(f"wrote {path}")


def _compare_report(args: argparse.Namespace, result, truth, scenarios) -> None:
    from dano.cli.reports import picture, write_command_report
    from dano.plotting import plot_rests
    from dano.report import Section

    header = list(result.rows[0]) if result.rows else []
    rows = [header] + [["" if row[k] is None else row[k] for k in header] for row in result.rows]
    text = f"{args.source} against {'no truth' if truth is None else truth.label}: the drop, the slide and the push."
    title = f"{args.source}: at rest after {scenarios.drop_s:g} s"
    with picture(args.plot, lambda path: plot_rests(result, path, title=title)) as png:
        write_command_report(args, "dano compare", [Section("The mesh path against the DANO", text, rows, [png])])


def _field_models(args: argparse.Namespace, knobs: dict):
    import time

    from dano.baselines import models as M
    from dano.build import build_dano, field_from_source
    from dano.fields import MESH_SUFFIXES, load_mesh, mesh_field
    from dano.surface import field_peak
    from dano.types import DANO

    truth = None
    if args.source.lower().endswith(MESH_SUFFIXES):
        mesh = load_mesh(args.source, repair=args.repair, scale=args.scale)
        truth = M.mesh_model("truth (mesh)", mesh, progress=True, **knobs)
        field = mesh_field(mesh, resolution=args.resolution)
    else:
        field = field_from_source(args.source, scale=args.scale, resolution=args.resolution)
        if isinstance(field, DANO):
            raise M.CompareError("compare needs the field the DANO comes from (a mesh, grid, checkpoint or spec)")
    levels = _parse_levels(args.levels, field_peak(field, args.seed))
    models = M.level_set_models(field, levels, args.resolution, clean=args.clean, **knobs)
    start = time.perf_counter()
    dano = build_dano(field, n_points=args.points, seed=args.seed)
    models.append(M.dano_model("DANO", dano, time.perf_counter() - start))
    return models, truth
