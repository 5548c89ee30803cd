"""System identification (paper Problem (17)): Jacobians, recovery of known parameters, bounds, the CLI."""

import dataclasses
import json
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import dano
from dano.baselines.pushes import mesh_push_recordings
from dano.cli import main
from dano.fields import BoxField
from dano.results import Result, SolverError
from dano.scenarios import at_rate, push_scene, slide_scene
from dano.sysid import Recording, Track, identify, make_problem, write_track
from dano.sysid.experiments import push_recordings, slide_track
from dano.sysid.pipeline import SysidConfig, identify_files
from dano.sysid.problem import window_residuals
from helpers import central_difference

MU = 0.5


@pytest.fixture(scope="module")
def bar():
    """A 9 x 6 x 3 cm bar of soap, 100 g, 600 surface points."""
    return dano.build_dano(BoxField(size=(0.09, 0.06, 0.03)), mass=0.1, n_points=600)


@pytest.fixture(scope="module")
def slide(bar):
    """The slide scene with friction MU and a noise-free 33-frame, 120 Hz track of it."""
    scene = slide_scene(bar, friction=MU)
    return scene, slide_track(scene, fps=120.0, n_frames=33)


def test_residual_jacobian_matches_central_differences(slide):
    scene, track = slide
    short = dataclasses.replace(track, t=track.t[:9], pos=track.pos[:9], quat=track.quat[:9])
    problem = make_problem(scene, [Recording({"object": short})], ["friction", "sliding_drag"], initial="velocity")
    w = jax.tree_util.tree_map(lambda x: x[0], problem.windows)
    theta = jnp.array([0.4, 0.02])
    delta = jnp.array([0.01, -0.02, 0.5])

    def f(theta, delta):
        return window_residuals(problem, theta, delta, w).reshape(-1)

    J_theta, J_delta = jax.jacfwd(f, argnums=(0, 1))(theta, delta)
    for k in range(2):
        fd = central_difference(lambda h, k=k: f(theta.at[k].add(h), delta), 1e-5)
        np.testing.assert_allclose(J_theta[:, k], fd, rtol=1e-4, atol=1e-4 * float(jnp.max(jnp.abs(fd))))
    for k in range(3):
        fd = central_difference(lambda h, k=k: f(theta, delta.at[k].add(h)), 1e-6)
        np.testing.assert_allclose(J_delta[:, k], fd, rtol=1e-4, atol=1e-4 * float(jnp.max(jnp.abs(fd))))


def test_slide_recovers_friction_exactly_from_noise_free_data(slide):
    scene, track = slide
    problem = make_problem(scene, [Recording({"object": track})], ["friction"], initial="velocity")
    result = identify(problem, init={"sliding_friction": 0.2}, progress=False)
    assert result.converged
    assert abs(result.params["sliding_friction"] - MU) < 1e-3 * MU  # same simulator: 0.1 %
    assert result.loss[-1] < 1e-3 * result.loss[0]
    cut = identify(problem, init={"sliding_friction": 0.2}, max_steps=1, progress=False)  # the same, one step
    assert cut.result is Result.max_steps_reached and not cut.converged and cut.message == "iteration limit"
    with pytest.raises(SolverError, match="^identification did not converge: iteration limit reached"):
        identify(problem, init={"sliding_friction": 0.2}, max_steps=1, progress=False, throw=True)


def test_slide_with_1mm_noise_is_within_its_standard_error(slide, bar):
    scene, _ = slide
    errors = []
    for seed in (0, 1):
        track = slide_track(scene, fps=120.0, n_frames=33, noise=1e-3, seed=seed)
        problem = make_problem(scene, [Recording({"object": track})], ["friction"], initial="velocity")
        result = identify(problem, init={"sliding_friction": 0.2}, progress=False)
        error = result.params["sliding_friction"] - MU
        # 1 mm noise on 33 frames: the standard error is ~1 % of mu; allow 3 of them
        assert abs(error) < 3 * result.stderr["sliding_friction"] + 1e-3, (seed, result.params, result.stderr)
        assert 1e-4 < result.stderr["sliding_friction"] < 0.05
        errors.append(abs(error) / MU)
    assert max(errors) < 0.05


def test_estimates_never_leave_their_bounds(slide):
    scene, track = slide
    problem = make_problem(scene, [Recording({"object": track})], ["friction"])
    high = identify(problem, init={"sliding_friction": 0.1}, bounds={"sliding_friction": (0.0, 0.3)}, progress=False)
    low = identify(problem, init={"sliding_friction": 0.9}, bounds={"sliding_friction": (0.7, 1.0)}, progress=False)
    assert high.params["sliding_friction"] == pytest.approx(0.3, abs=1e-12)
    assert low.params["sliding_friction"] == pytest.approx(0.7, abs=1e-12)
    assert 0.0 <= high.params["sliding_friction"] <= 0.3
    assert 0.7 <= low.params["sliding_friction"] <= 1.0


def test_multiple_shooting_windows_recover_friction(slide):
    scene, track = slide
    problem = make_problem(scene, [Recording({"object": track})], ["friction"], window=8, initial="velocity")
    assert problem.n_windows == 4
    result = identify(problem, init={"sliding_friction": 0.9}, progress=False)
    assert abs(result.params["sliding_friction"] - MU) < 2e-3 * MU


def test_windows_split_over_lanes_give_the_same_normal_equations(slide, monkeypatch):
    """The objective's windows shared out over parallel lanes (`dano.lanes`: 2 lanes, 2 windows
    each; 4 lanes, one each) give the loss, residuals and normal equations one lane gives."""
    from dano import lanes
    from dano.sysid.objective import Jacobian, compiled

    scene, track = slide
    problem = make_problem(scene, [Recording({"object": track})], ["friction"], window=8, initial="velocity")
    theta = jnp.array([0.4])
    delta = 0.01 * jnp.asarray(np.random.default_rng(3).normal(size=(problem.n_windows, problem.n_state)))
    results = {}
    for k in (1, 2, 4):
        monkeypatch.setattr(lanes, "count", lambda requested=None, k=k: k)
        loss_fn, normal_fn = compiled(problem, Jacobian.fwd)
        results[k] = (loss_fn(theta, delta, problem.windows), *normal_fn(theta, delta, problem.windows))
    loss, plain, parts = results[1]
    assert float(loss) > 0 and float(jnp.max(jnp.abs(parts[2]))) > 0  # the windows' own gradients
    for k in (2, 4):
        other_loss, other_plain, other_parts = results[k]
        np.testing.assert_allclose(other_loss, loss, rtol=1e-12)
        np.testing.assert_allclose(other_plain, plain, rtol=0, atol=1e-12)
        for a, b in zip(other_parts, parts, strict=True):
            np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-12 * float(jnp.max(jnp.abs(b))))


def _camera_view(track: Track, R: np.ndarray, offset: np.ndarray, units_per_m: float) -> Track:
    """The track as a camera would report it: rotated, shifted, in other units."""
    from dano.sysid.data import rotate, to_metric

    return to_metric(rotate(track, R, offset), units_per_m)


@pytest.mark.slow
@pytest.mark.optimized
def test_cli_sysid_from_a_tilted_camera_with_unknown_units(slide, bar, tmp_path, capsys):
    """The real-data path: two throws seen by a camera (tilted, positions in cm), gravity fitted from
    the plane they span, metres from --scale; the JSON is keyed by the names as typed."""
    scene, track = slide
    thrown = dataclasses.replace(scene.bodies[0], vel=(-0.4, 1.5, 0.0))
    other = slide_track(dataclasses.replace(scene, bodies=(thrown,)))
    dano.save_dano(tmp_path / "bar.dano.npz", bar)
    (tmp_path / "scene.toml").write_text(
        '[sim]\ntimestep = 0.002\nsubsteps = 4\n[ground]\nheight = 0.0\n'
        '[[body]]\nname = "soap"\ndano = "bar.dano.npz"\n[contact]\nsliding_friction = 0.2\n'
    )  # fmt: skip
    R = Rotation.from_euler("xyz", [110.0, 20.0, -35.0], degrees=True).as_matrix()
    for name, tr in (("a", track), ("b", other)):
        write_track(tmp_path / f"{name}.csv", _camera_view(tr, R, np.array([0.1, -0.3, 0.8]), 100.0))
    code = main([
        "sysid", str(tmp_path / "scene.toml"), "--traj", str(tmp_path / "a.csv"),
        "--traj", str(tmp_path / "b.csv"), "--fit", "friction", "--scale", "0.01", "--gravity", "fit",
        "--fit-initial", "velocity", "--json", "--plot", str(tmp_path / "fit.png"),
        "--report", str(tmp_path / "r.html"),
    ])  # fmt: skip
    assert code == 0
    out = json.loads(capsys.readouterr().out)
    assert set(out) == {
        "params", "stderr", "intervals", "interval", "loss", "iterations", "converged", "message", "rms", "seconds",
        "flags", "adjustments", "loss_function",
    }  # fmt: skip
    assert out["converged"] is True and out["iterations"] >= 1 and out["rms"]["position"] < 5e-3
    assert set(out["params"]) == set(out["intervals"]) == {"friction"}
    assert abs(out["params"]["friction"] - MU) < 2e-3 * MU
    # noise-free data: a narrow profile interval about the estimate, agreeing with the stderr (no flags)
    low, high = out["intervals"]["friction"]
    assert out["interval"] == {"method": "profile", "level": 0.95} and out["flags"] == []
    assert out["loss_function"] == "l2"
    assert low < out["params"]["friction"] < high and high - low < 0.01 * MU
    # nothing hidden: the data's scale, the fitted gravity and ground, the simulator's step
    adjusted = out["adjustments"]
    assert adjusted["scale"] == {"m_per_unit": 0.01, "objects": False}
    assert adjusted["gravity"]["fitted"] is True and adjusted["timestep"]["frame_s"] == pytest.approx(1 / 120)
    down = R @ np.array([0.0, 0.0, -1.0])
    assert np.dot(adjusted["gravity"]["vector"], down) == pytest.approx(9.81, rel=1e-3)
    assert out["loss"][-1] < out["loss"][0]
    assert (tmp_path / "fit.png").stat().st_size > 10_000
    page = (tmp_path / "r.html").read_text()  # the same estimate, its picture and the command line
    assert f"{out['params']['friction']:.6g}" in page and page.count("data:image/png;base64,") == 1
    assert "dano sysid " in page and "--fit-initial velocity" in page


def test_cli_sysid_names_a_bad_trajectory_file(tmp_path, capsys, bar):
    dano.save_dano(tmp_path / "bar.dano.npz", bar)
    (tmp_path / "scene.toml").write_text('[[body]]\nname = "soap"\ndano = "bar.dano.npz"\n')
    rows = ["t,x,y,z,qw,qx,qy,qz", "0,0,0,0,1,0,0,0", "0.01,0,0,nan,1,0,0,0", "0.02,0,0,0,1,0,0,0"]
    (tmp_path / "bad.csv").write_text("\n".join(rows) + "\n")
    code = main(["sysid", str(tmp_path / "scene.toml"), "--traj", str(tmp_path / "bad.csv"), "--fit", "mu"])
    assert code == 2
    err = capsys.readouterr().err
    assert "bad.csv" in err and "line 3" in err and "NaN" in err


def test_unknown_parameter_is_refused(slide):
    scene, track = slide
    with pytest.raises(dano.DanoError, match="unknown parameter 'frction'"):
        make_problem(scene, [Recording({"object": track})], ["frction"])


def test_gravity_can_be_given_instead_of_fitted(slide, bar, tmp_path):
    scene, track = slide
    dano.save_dano(tmp_path / "bar.dano.npz", bar)
    (tmp_path / "scene.toml").write_text('[[body]]\nname = "soap"\ndano = "bar.dano.npz"\n[ground]\nheight = 0.0\n')
    R = Rotation.from_euler("x", 90.0, degrees=True).as_matrix()  # camera y points down
    write_track(tmp_path / "soap.csv", _camera_view(track, R, np.zeros(3), 1.0))
    down = R @ np.array([0.0, 0.0, -1.0])
    config = SysidConfig(fit=("friction",), gravity=list(down), initial="velocity", init={"friction": 0.3})
    problem, result = identify_files(tmp_path / "scene.toml", [tmp_path / "soap.csv"], config, progress=False)
    assert np.allclose(problem.scene.gravity, 9.81 * down)
    assert abs(result.params["friction"] - MU) < 2e-3 * MU


@pytest.mark.slow
@pytest.mark.optimized
def test_push_identifies_mass_scale_and_friction(bunny_field):
    """Paper Fig. 6b: pushes by a 1 kg sphere under a known force (4 here, 10 in the paper), same
    simulator, noise-free. The explicit step's fit reached the truth to < 0.1 %; at the implicit
    default (one 2 ms step) LM converges (ftol 1e-10: the same point) to a minimum where the fitted
    initial velocities absorb what is left: alpha -0.34 %, mu -0.05 % with six 31-frame pushes,
    +0.008 %, -0.02 % with these four of 21 frames (measured; a quarter of the time). Held to 0.5 %."""
    bunny = dano.build_dano(bunny_field, n_points=400, mass=0.5)
    scene = push_scene(bunny, friction=0.3)
    truth = {"mass_scale": 1.3, "sliding_friction": 0.35}
    recordings = push_recordings(scene, truth, n_pushes=4, n_frames=21)
    problem = make_problem(scene, recordings, ["mass_scale", "friction"], initial="velocity", settle=0.0)
    result = identify(problem, init={"mass_scale": 1.0, "sliding_friction": 0.5}, progress=False)
    for name, value in truth.items():
        assert abs(result.theta[problem.names.index(name)] - value) < 5e-3 * value, result.params


@pytest.mark.slow
def test_pushes_replayed_by_mujoco_c_on_the_mesh_move_the_object_alike(tmp_path):
    """The other engine's data (the push experiment's MuJoCo C path): same starts and forces, an
    8 cm cube as CoACD pieces under MuJoCo's own contacts vs the cube's DANO under ours."""
    import trimesh

    cube = dano.build_dano(BoxField(size=(0.08, 0.08, 0.08)), mass=0.3, n_points=400)
    scene = push_scene(cube, friction=0.3)
    mesh = trimesh.creation.box(extents=(0.08, 0.08, 0.08))
    theirs = mesh_push_recordings(scene, mesh, mass=0.3, friction=0.3, n_pushes=4, n_frames=31, seed=1)
    ours = push_recordings(scene, {"sliding_friction": 0.3}, n_pushes=4, n_frames=31, seed=1)
    for a, b in zip(theirs, ours, strict=True):
        np.testing.assert_array_equal(a.ctrl, b.ctrl)
        np.testing.assert_allclose(a.tracks["pusher"].pos[0], b.tracks["pusher"].pos[0], atol=1e-9)
        moved_a = np.linalg.norm(a.tracks["object"].pos[-1] - a.tracks["object"].pos[0])
        moved_b = np.linalg.norm(b.tracks["object"].pos[-1] - b.tracks["object"].pos[0])
        assert moved_b > 0.01  # every push reaches the cube
        assert moved_a == pytest.approx(moved_b, rel=0.25)
        assert np.linalg.norm(a.tracks["object"].pos[-1] - b.tracks["object"].pos[-1]) < 0.2 * moved_b + 5e-3


def test_same_rate_scene_is_not_resampled(slide):
    scene, track = slide
    problem = make_problem(scene, [Recording({"object": track})], ["friction"])
    assert problem.scene.timestep == pytest.approx(1 / 120)
    assert problem.scene.substeps == at_rate(scene, 120.0).substeps == 5  # 1/120 s in steps <= 2 ms


def test_float32_is_refused_with_a_named_error(slide):
    scene, track = slide
    with jax.enable_x64(False), pytest.raises(dano.DanoError, match="float64"):
        make_problem(scene, [Recording({"object": track})], ["friction"])


def test_a_constant_orientation_track_is_warned_about_and_fitted_from_positions(slide):
    """A tracker that could not resolve rotation writes a constant quaternion: the fit is warned,
    and with `rotation_weight=0` (`--rotation-weight 0`) positions alone give the friction."""
    from dano.sysid.problem import ConstantOrientationWarning

    scene, track = slide
    noise = np.random.default_rng(0).normal(0.0, 1e-3, track.pos.shape)
    flat = dataclasses.replace(track, pos=track.pos + noise, quat=np.tile(track.quat[0], (track.n_frames, 1)))
    with pytest.warns(ConstantOrientationWarning, match=r"constant over 33 frames .* \(--rotation-weight 0"):
        make_problem(scene, [Recording({"object": flat})], ["friction"], initial="velocity")
    problem = make_problem(scene, [Recording({"object": flat})], ["friction"], initial="velocity", rotation_weight=0)
    result = identify(problem, init={"friction": 0.2}, progress=False)
    assert abs(result.params["sliding_friction"] - MU) < 0.03 * MU
    assert result.rms_rotation is None and result.summary()["rms"]["rotation"] is None


@pytest.mark.slow
def test_nerf_units_with_size_give_the_metric_friction(slide, bar, tmp_path):
    """Issue 18's units case: the DANO built from a NeRF without --scale and the track in the same
    units (3x metres here). `--size` with the soap's ruler length (9 cm) rescales both: the same
    friction as the metric fit, to 1 %."""
    from dano.build import scale_lengths
    from dano.sysid.data import to_metric

    scene, _ = slide
    track = slide_track(scene, fps=120.0, n_frames=33, noise=1e-3, seed=0)
    dano.save_dano(tmp_path / "metric.dano.npz", bar)
    dano.save_dano(tmp_path / "nerf.dano.npz", scale_lengths(bar, 3.0))
    for units in ("metric", "nerf"):
        (tmp_path / f"{units}.toml").write_text(
            f'[sim]\ntimestep = 0.002\nsubsteps = 4\n[ground]\nheight = 0.0\n[[body]]\nname = "soap"\n'
            f'dano = "{units}.dano.npz"\n[contact]\nsliding_friction = 0.2\n'
        )
    write_track(tmp_path / "metric.csv", track)
    write_track(tmp_path / "nerf.csv", to_metric(track, 3.0))
    config = SysidConfig(fit=("friction",), initial="velocity")
    fits = {}
    for units, size in (("metric", None), ("nerf", 0.09)):
        files = (tmp_path / f"{units}.toml", [tmp_path / f"{units}.csv"])
        fits[units] = identify_files(*files, dataclasses.replace(config, size=size), progress=False)[1]
    metric, nerf = fits["metric"].params["friction"], fits["nerf"].params["friction"]
    assert abs(metric - MU) < 0.02 * MU
    assert nerf == pytest.approx(metric, rel=0.01)


def test_mixed_units_are_warned_about(slide, bar):
    """A track in mm against a metric DANO, and a DANO in mm: `UnitsWarning`, with the advice."""
    from dano.build import scale_lengths
    from dano.sysid.data import to_metric
    from dano.sysid.frames import UnitsWarning
    from dano.sysid.pipeline import prepare

    scene, track = slide
    config = SysidConfig(fit=("friction",))
    with pytest.warns(UnitsWarning, match=r"spans .* times the DANO's .* both in metres"):
        prepare(scene, [Recording({"object": to_metric(track, 1000.0)})], config)
    body = dataclasses.replace(scene.bodies[0], dano=scale_lengths(bar, 1000.0))
    with pytest.warns(UnitsWarning, match=r"is 90.* m long along its principal axes"):
        prepare(dataclasses.replace(scene, bodies=(body,)), [Recording({"object": track})], config)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        prepare(scene, [Recording({"object": track})], config)  # metric both: silent


@pytest.mark.parametrize("turned", [False, True])
def test_resting_poses_of_a_bar_are_its_six_faces(bar, turned):
    """Also for the bar built turned 45° and 20° off its field's axes, lying on a tilted table: the
    same six heights, each pose putting its face flat on the table."""
    from dano.fields import TransformedField
    from dano.sysid.frames import lying_on, resting_poses

    turn = Rotation.from_euler("zy", [45.0, 20.0], degrees=True)
    obj = dano.build_dano(TransformedField(BoxField(size=(0.09, 0.06, 0.03)), rotation=turn.as_matrix()),
                          mass=0.1, n_points=600) if turned else bar  # fmt: skip
    up = turn.apply([0.0, 0.3, 1.0]) / np.linalg.norm([0.0, 0.3, 1.0]) if turned else np.array([0.0, 0.0, 1.0])
    poses = resting_poses(obj, up=up)
    heights = [p.height for p in poses]
    np.testing.assert_allclose(heights, [0.015, 0.015, 0.03, 0.03, 0.045, 0.045], rtol=0.03)
    points = np.array(obj.body_points)  # a writable copy (scipy refuses read-only buffers)
    for p in poses:  # each turns its face's normal down the table's, the face's points lowest
        w, x, y, z = p.quat
        R = Rotation.from_quat([x, y, z, w])
        np.testing.assert_allclose(R.apply(p.normal), -up, atol=1e-9)
        assert np.min(R.apply(points) @ up) == pytest.approx(-p.height, abs=1e-3)
    track = Track.from_poses(np.tile([0.0, 0.0, 0.02, 1.0, 0.0, 0.0, 0.0], (4, 1)), 0.01)
    q = lying_on(track, poses[2], np.radians(30.0), up=up).quat  # turned about the table's normal: still flat
    assert q.shape == (4, 4) and np.allclose(q, q[0])
    w, x, y, z = q[0]
    np.testing.assert_allclose(Rotation.from_quat([x, y, z, w]).apply(poses[2].normal), -up, atol=1e-9)


@pytest.mark.slow
@pytest.mark.optimized
def test_a_slide_whose_orientation_the_tracker_lost_is_fitted_lying_on_a_face(slide, bar, tmp_path):
    """Issue 18: the tracker wrote a constant, wrong orientation (the bar standing on its side).
    `--orientation resting` tries the bar's six resting faces at four headings, keeps the one that
    fits, and gives μ within 3 % with an RMS at the noise (measured: 0.5075, 1.7 mm; the wrong
    orientation with positions only: 0.512 ± 0.055 at 10 mm RMS)."""
    from dano.sysid.pipeline import SysidConfig, identify_files

    scene, _ = slide
    track = slide_track(scene, fps=120.0, n_frames=33, noise=1e-3, seed=0)
    x, y, z, w = Rotation.from_euler("x", 90.0, degrees=True).as_quat()
    write_track(tmp_path / "lost.csv", dataclasses.replace(track, quat=np.tile([w, x, y, z], (track.n_frames, 1))))
    dano.save_dano(tmp_path / "bar.dano.npz", bar)
    (tmp_path / "scene.toml").write_text(
        '[sim]\ntimestep = 0.002\nsubsteps = 4\n[ground]\nheight = 0.0\n[[body]]\nname = "soap"\n'
        'dano = "bar.dano.npz"\n[contact]\nsliding_friction = 0.2\n'
    )
    config = SysidConfig(fit=("friction",), initial="state", orientation="resting")
    _, result = identify_files(tmp_path / "scene.toml", [tmp_path / "lost.csv"], config, progress=False)
    assert abs(result.params["friction"] - MU) < 0.03 * MU
    assert result.rms_position is not None and result.rms_position < 2.5e-3 and result.rms_rotation is None
    chosen = result.adjustments["orientation"]
    assert abs(chosen["normal"][2]) > 0.99 and chosen["candidates"] == 24  # lying flat, as it slid


def test_a_track_started_just_above_the_ground_is_settled_without_rocking(slide):
    """A body read 6 mm above the table and rocking about a horizontal axis (noise in tracked poses)
    is started on the table, sliding: its height by the contact's load balance, its velocity along
    the normal and its spin about the table's axes dropped, its spin about the normal kept."""
    scene, track = slide
    t = track.t - track.t[0]
    rocking = Rotation.from_rotvec(np.outer(t, [2.0, -1.0, 0.0]))  # world axes, rad/s · s
    quat = (rocking * Rotation.from_quat(track.quat[:, [1, 2, 3, 0]])).as_quat()[:, [3, 0, 1, 2]]
    lifted = dataclasses.replace(track, pos=track.pos + [0.0, 0.0, 0.006], quat=quat)
    recordings = [Recording({"object": lifted})]
    free = make_problem(scene, recordings, ["friction"], initial="state", settle=0.0)
    settled = make_problem(scene, recordings, ["friction"], initial="state", settle=0.01)
    (report,) = settled.adjustments["settle"]
    w_free, w_settled = (np.asarray(p.windows.qvel[0, 3:6]) for p in (free, settled))
    n_body = Rotation.from_quat(np.asarray(settled.windows.qpos[0, [4, 5, 6, 3]])).as_matrix().T @ [0.0, 0.0, 1.0]
    tilt = w_free - (w_free @ n_body) * n_body
    assert np.linalg.norm(tilt) > 1.0  # the rocking read from the poses
    np.testing.assert_allclose(w_settled, w_free - tilt, atol=1e-12)
    assert report["tilt_rate_dropped_rad_s"] == pytest.approx(np.linalg.norm(tilt))
    assert float(settled.windows.qvel[0, 2]) == 0.0 and float(free.windows.qvel[0, 2]) != 0.0
    assert -0.008 < report["moved_m"] < -0.004  # back down by about the 6 mm it was read above
    assert settled.n_state < free.n_state  # planar corrections only
