"""`dano demo`: the main job on a built-in default, the Stanford bunny.

Builds a DANO of the bunny that pymeshfix ships, compares its mass properties with trimesh's exact
polyhedral integrals of the same mesh, writes the DANO and a picture of its points and normals,
then simulates it: dropped with a spin, and the paper's Fig. 5 (a sphere hitting two bunnies),
rendered to MP4; identifies the friction of a sliding bar of soap from a noisy 120 Hz track
(real-to-sim, paper Sec. V-A) and plots observed vs fitted motion; finally pushes the bunny to a goal
with a sphere end effector by constrained iLQR (sim-to-robot, Sec. V-B), rendered to MP4.
"""

import json
import time
from pathlib import Path

import numpy as np
import trimesh

from dano.assets import BUNNY_SCALE, WATER, bunny_mesh, bunny_path
from dano.build import build_dano
from dano.fields import mesh_field
from dano.io import atomic_write, save_dano
from dano.plotting import plot_dano


def compare_with_mesh(dano, mesh: trimesh.Trimesh) -> dict:
    """Mass properties of the DANO beside the exact ones of the mesh at the same mass."""
    exact = mesh.copy()
    exact.density = float(dano.mass) / mesh.volume
    j_dano, j_mesh = np.asarray(dano.inertia), np.asarray(exact.moment_inertia)
    return {
        "mass_kg": float(dano.mass),
        "mass_of_water_bunny_kg": WATER * mesh.volume,
        "com_m": np.asarray(dano.com).tolist(),
        "com_exact_m": exact.center_mass.tolist(),
        "com_error_m": float(np.linalg.norm(np.asarray(dano.com) - exact.center_mass)),
        "principal_moments": np.linalg.eigvalsh(j_dano).tolist(),
        "principal_moments_exact": np.linalg.eigvalsh(j_mesh).tolist(),
        "inertia_rel_error": float(np.linalg.norm(j_dano - j_mesh) / np.linalg.norm(j_mesh)),
    }


def run_demo(
    out_dir: str | Path = "dano-demo", resolution: int = 96, n_points: int = 5000, seed: int = 0, simulate: bool = True
) -> dict:
    out = Path(out_dir)
    t0 = time.perf_counter()
    mesh = bunny_mesh()
    print(f"bunny: {len(mesh.faces)} triangles, watertight after pymeshfix, scaled by {BUNNY_SCALE} m/unit")
    field = mesh_field(mesh, resolution=resolution, peak=WATER)
    t1 = time.perf_counter()
    dano = build_dano(field, n_points=n_points, seed=seed, source=f"{bunny_path().name} x{BUNNY_SCALE}")
    t2 = time.perf_counter()
    save_dano(out / "bunny.dano.npz", dano)
    picture = plot_dano(dano, out / "bunny_points.png", title="Stanford bunny DANO: points (density) and normals")
    summary = compare_with_mesh(dano, mesh) | {"bake_seconds": t1 - t0, "build_seconds": t2 - t1}
    print(_table(dano, summary))
    print(f"wrote {out / 'bunny.dano.npz'} and {picture}")
    if simulate:
        summary |= simulate_demos(dano, out)
        summary |= identification_demo(out)
        summary |= push_demo(out, seed=seed, field=field)
    with atomic_write(out / "summary.json") as tmp:
        tmp.write_text(json.dumps(summary, indent=2))
    print(f"wrote {demo_report(out, summary, resolution, n_points, seed)}")
    return summary


def demo_report(out: Path, summary: dict, resolution: int, n_points: int, seed: int) -> Path:
    """`out/report.html`: what the demo measured and wrote, on one self-contained page."""
    from dano.report import Section, write_report

    v = lambda xs: "(" + ", ".join(f"{x:.5g}" for x in xs) + ")"  # noqa: E731
    call = f"run_demo('{out}', resolution={resolution}, n_points={n_points}, seed={seed})"
    sections = [
        Section(
            "The bunny as a DANO: mass properties (eqs. 1-4)",
            f"The Stanford bunny that pymeshfix ships, scaled by {BUNNY_SCALE} m/unit, density of water, "
            f"{n_points} surface points; beside trimesh's exact polyhedral integrals of the same mesh at the "
            "same mass.",
            [("", "DANO (Monte Carlo)", "mesh (exact)"),
             ("mass [kg]", f"{summary['mass_kg']:.5g}", f"{summary['mass_of_water_bunny_kg']:.5g}"),
             ("centre of mass [m]", v(summary["com_m"]), v(summary["com_exact_m"])),
             ("principal moments [kg m²]", v(summary["principal_moments"]), v(summary["principal_moments_exact"])),
             ("inertia, relative error", f"{summary['inertia_rel_error']:.3%}", ""),
             ("centre of mass, error [mm]", f"{summary['com_error_m'] * 1e3:.3f}", "")],
            [out / "bunny_points.png"],
            f"dano demo -o {out}   # or: from dano.demo import run_demo; {call}",
        )
    ]  # fmt: skip
    sims = [k for k in ("bunny_drop", "fig5_sphere_hits_two_bunnies") if k in summary]
    if sims:
        rows = [("scene", "first DANO ends at [m]", "final speed [m/s]", "seconds (with JIT)", "picture covered")]
        for k in sims:
            r = summary[k]
            covered = sum(r.get("frame_covered", {}).values())
            rows.append(
                (k, v(r["final_position_m"]), f"{r['final_speed_m_s']:.2e}", f"{r['seconds']:.1f}", f"{covered:.1%}")
            )
        sections.append(Section(
            "Simulation: the bunny dropped with a spin, and the paper's Fig. 5",
            "Each DANO drawn as its surface (marching cubes of its density grid); contact by the DANO model.",
            rows, [out / f"{k}.mp4" for k in sims],
            f"from dano.demo import simulate_demos; simulate_demos(bunny, Path('{out}'))",
        ))  # fmt: skip
    if "sysid_soap_slide" in summary:
        r = summary["sysid_soap_slide"]
        sections.append(Section(
            "Real-to-sim: friction of a sliding bar of soap (Sec. V-A)",
            "33 frames of a 120 Hz track with 1 mm noise; friction and the initial velocity fitted from 0.2.",
            [("friction", "standard error", "true", "seconds (with JIT)"),
             (f"{r['friction']:.4f}", f"{r['stderr']:.4f}", f"{r['true']:g}", f"{r['seconds']:.1f}")],
            [out / "sysid_soap_slide.png"],
            f"from dano.demo import identification_demo; identification_demo(Path('{out}'))",
        ))  # fmt: skip
    if "trajopt_push" in summary:
        r = summary["trajopt_push"]
        sections.append(Section(
            "Sim-to-robot: a sphere pushes the bunny 8 cm (Sec. V-B)",
            "Constrained iLQR through the simulator; the video is the open-loop replay of its controls.",
            [("converged", "iterations", "final error [mm]", "max violation", "seconds (with JIT)"),
             (r["converged"], r["iterations"], f"{r['final_error_m'] * 1e3:.2f}", f"{r['max_violation']:.1e}",
              f"{r['seconds']:.1f}")],
            [out / "push.mp4"], f"from dano.demo import push_demo; push_demo(Path('{out}'), seed={seed})",
        ))  # fmt: skip
    note = "Written by dano demo; the numbers are this run's (also in summary.json)."
    return write_report(out / "report.html", "dano demo", sections, note)


def simulate_demos(bunny, out: Path, video: bool = True) -> dict:
    """The bunny dropped with a spin, and the paper's Fig. 5 (a sphere hitting two bunnies)."""
    from dano.sim import DanoBody, Primitive, Scene
    from dano.sim.render import coverage, render_video
    from dano.sim.run import Simulation
    from dano.sim.scene import Mode

    lift = -float(np.min(np.asarray(bunny.body_points)[:, 2]))
    tilt = (0.97, 0.2, 0.1, 0.0)
    drop = Scene(duration=1.5, bodies=(DanoBody("bunny", bunny, pos=(0, 0, lift + 0.1), quat=tilt, angvel=(0, 0, 4)),))
    ball = Primitive("ball", "sphere", (0.04,), pos=(-0.35, 0.0, 0.04), mode=Mode.free, mass=1.0, vel=(2.5, 0, 0))
    fig5 = Scene(
        duration=1.5,
        bodies=(
            DanoBody("bunny_a", bunny, pos=(0.0, 0.02, lift)),
            DanoBody("bunny_b", bunny, pos=(0.17, -0.02, lift), quat=(0.92, 0, 0, 0.38)),
        ),
        primitives=(ball,),
    )
    results = {}
    for name, scene in (("bunny_drop", drop), ("fig5_sphere_hits_two_bunnies", fig5)):
        sim = Simulation.from_scene(scene)
        t0 = time.perf_counter()
        traj = sim.run()
        seconds = time.perf_counter() - t0
        final = np.asarray(traj.qpos[-1])
        speed = float(np.linalg.norm(np.asarray(traj.qvel[-1, :3])))
        where = ", ".join(f"{v:.3f}" for v in final[:3])
        print(f"{name}: {scene.n_steps} frames in {seconds:.1f} s (with JIT); first DANO ends at ({where}) m, "
              f"speed {speed:.2e} m/s")  # fmt: skip
        results[name] = {"final_position_m": final[:3].tolist(), "final_speed_m_s": speed, "seconds": seconds}
        if video:
            print(f"wrote {render_video(sim, traj, out / f'{name}.mp4')}")
            results[name]["frame_covered"] = coverage(sim, traj)  # by each bunny, in the last picture
    return results


def identification_demo(out: Path, noise: float = 1e-3, seed: int = 0) -> dict:
    """Real-to-sim on synthetic data: a bar of soap slides on a table (mu = 0.5), a 120 Hz camera
    tracks it for 33 frames with 1 mm noise; fit mu and the initial velocity from mu = 0.2."""
    from dano.fields import BoxField
    from dano.plotting import plot_identification
    from dano.scenarios import slide_scene
    from dano.sysid import Recording, identify, make_problem
    from dano.sysid.experiments import slide_track

    soap = build_dano(BoxField(size=(0.09, 0.06, 0.03)), mass=0.1, n_points=1000, seed=seed)
    scene = slide_scene(soap, friction=0.5)
    track = slide_track(scene, fps=120.0, n_frames=33, noise=noise, seed=seed)
    problem = make_problem(scene, [Recording({"object": track})], ["friction"], initial="velocity", sigma=noise)
    result = identify(problem, init={"sliding_friction": 0.2})
    mu, err = result.params["sliding_friction"], result.stderr["sliding_friction"]
    path = plot_identification(problem, result, out / "sysid_soap_slide.png")
    print(f"sysid: soap slide, 33 frames at 120 Hz, {noise * 1e3:g} mm noise: friction {mu:.4f} +/- {err:.4f} "
          f"(true 0.5) in {result.iterations} iterations, {result.seconds:.1f} s (with JIT); wrote {path}")  # fmt: skip
    return {"sysid_soap_slide": {"friction": mu, "stderr": err, "true": 0.5, "seconds": result.seconds}}


def push_demo(out: Path, seed: int = 0, field=None) -> dict:
    """Sim-to-robot (paper Sec. V-B): a sphere end effector pushes a 100-point bunny 8 cm along x,
    by constrained iLQR through the simulator; the open-loop replay rendered to MP4. `field`: the
    bunny's density field (`run_demo` passes the one it baked), or None to bake one of 48 nodes."""
    from dano.sim.render import coverage
    from dano.trajopt.push import PushTask, push_problem, render_push, replay_frames, solve_push

    if field is None:
        field = mesh_field(bunny_mesh(), resolution=48, progress=False)
    bunny = build_dano(field, n_points=100, mass=0.5, seed=seed)
    push = push_problem(bunny, "sphere", PushTask(goal=(0.08, 0.0), horizon=8))
    result = solve_push(push)
    s = result.solution
    video = render_push(push, result, out / "push.mp4", progress=False)
    print(
        f"trajopt: sphere pushes the bunny 8 cm: {s.message}; {s.iterations} iterations, final error "
        f"{result.final_error_m * 1e3:.2f} mm, max violation {s.max_violation:.1e}, {s.seconds:.1f} s (with JIT)"
    )
    print(f"wrote {video}")
    summary = {k: v for k, v in result.summary().items() if k != "message"}
    summary["frame_covered"] = coverage(*replay_frames(push, result)[:2])  # the bunny, in the last picture
    return {"trajopt_push": summary}


def _table(dano, s: dict) -> str:
    fmt = lambda v: "(" + ", ".join(f"{x:.5g}" for x in v) + ")"  # noqa: E731
    return "\n".join(
        [
            f"{'':24}{'DANO (Monte Carlo)':>40}  {'mesh (exact)':>40}",
            f"{'mass [kg]':24}{s['mass_kg']:>40.5g}  {s['mass_of_water_bunny_kg']:>40.5g}",
            f"{'centre of mass [m]':24}{fmt(s['com_m']):>40}  {fmt(s['com_exact_m']):>40}",
            f"{'principal moments':24}{fmt(s['principal_moments']):>40}  {fmt(s['principal_moments_exact']):>40}",
            f"inertia relative error {s['inertia_rel_error']:.3%} (mass-matched), centre of mass off by "
            f"{s['com_error_m'] * 1e3:.3f} mm; mass standard error {float(dano.mass_stderr):.2g} kg",
            f"surface points {dano.n_points}, density window "
            f"[{float(dano.window[0]):.4g}, {float(dano.window[1]):.4g}]; "
            f"mesh bake {s['bake_seconds']:.1f} s, DANO build {s['build_seconds']:.1f} s",
        ]
    )
