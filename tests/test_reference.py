"""Reproduction of the paper authors' simulated bunny trajectories (../shared/data/dojo)."""

import dataclasses

import numpy as np
import pytest

from dano.build import scale_lengths
from dano.reference import load_reference
from dano.scenarios import reference_drop_scene, slide_scene
from dano.sim.run import Simulation
from dano.sysid import Recording, identify, make_problem, read_tracks
from dano.sysid.experiments import slide_track


@pytest.mark.parametrize("mu", [0.3, 0.7])
def test_reference_bunny_trajectories(dojo, mu):
    data = np.loadtxt(dojo / "trajectories" / f"bunny_trajectory_{mu}.csv", delimiter=",", skiprows=1)
    scene = reference_drop_scene(dojo / "colliders" / "bunny_collider.npz", mu)
    # (230 frames: after the first contact the explicit step at one step per 2 ms frame makes energy,
    # +54 J at frame 243 for mu = 0.7, which `Simulation.run`'s energy audit refuses.)
    q = np.asarray(Simulation.from_scene(scene).run(230).qpos)
    # Free flight (before the first contact near row 240), one step per frame: the same
    # semi-implicit translation update as Dojo, so positions agree to round-off; with the inertial
    # frame compiled as the DANO's principal frame the rotations agree too (7e-10; 4e-3 when MuJoCo
    # ignored body_iquat).
    np.testing.assert_allclose(q[:230, :3], data[:230, :3], atol=1e-9)
    assert np.max(1 - np.abs(np.sum(q[:230, 3:7] * data[:230, 3:7], axis=1))) < 1e-8
    # After contact the runs part: Dojo solves contact implicitly in the next velocity, this scene
    # applies it explicitly, and the bouncing bunny is chaotic. With 4 substeps (0.5 ms) it comes to
    # rest on the same side (height) and as far (measured: 3.39 vs 3.33 m, 3.11 vs 3.02 m).
    q = np.asarray(Simulation.from_scene(dataclasses.replace(scene, substeps=4)).run(len(data) - 1).qpos)
    assert q[-1, 2] == pytest.approx(data[-1, 2], abs=1e-3)
    travelled, reference = np.linalg.norm(q[-1, :2]), np.linalg.norm(data[-1, :2])
    assert travelled == pytest.approx(reference, rel=0.05)


@pytest.mark.slow
@pytest.mark.optimized
def test_friction_identified_from_the_reference_trajectory(dojo):
    """Paper authors' simulator, μ = 0.7: rows 400-900 (after the bounces), 25-frame windows,
    0.25 ms substeps (Dojo's implicit contact at 2 ms behaves like the fine-step limit, our explicit
    one at 2 ms does not). From mu = 0.6: with the inertial frame right, the loss of the tumbling
    bunny is 32 at the truth but rough, and from 0.5 (loss 397) the solver stops on a flat stretch
    (measured). examples/sysid_experiments.py reports all three files."""
    track = read_tracks(dojo / "trajectories" / "bunny_trajectory_0.7.csv", fps=500.0)[""].frames(400, 901)
    scene = dataclasses.replace(reference_drop_scene(dojo / "colliders" / "bunny_collider.npz", 0.5), substeps=8)
    problem = make_problem(scene, [Recording({"bunny": track})], ["friction"], window=25, settle=0.0)
    result = identify(problem, init={"sliding_friction": 0.6}, progress=False)
    assert result.params["sliding_friction"] == pytest.approx(0.7, rel=0.01)


@pytest.mark.slow
@pytest.mark.optimized
def test_reference_soap_slide_friction_is_identified(dojo):
    """The slide experiment with the authors' bluesoap DANO scaled to 9 cm: 120 Hz, 33 frames, 1 mm noise."""
    soap = load_reference(dojo / "colliders" / "bluesoap_collider.npz")
    soap = scale_lengths(soap, 0.09 / float(np.max(np.ptp(np.asarray(soap.body_points), axis=0))))
    scene = slide_scene(soap, friction=0.5)
    track = slide_track(scene, fps=120.0, n_frames=33, noise=1e-3, seed=0)
    problem = make_problem(scene, [Recording({"object": track})], ["friction"], initial="velocity")
    result = identify(problem, init={"friction": 0.2}, progress=False)
    assert result.params["sliding_friction"] == pytest.approx(0.5, rel=0.05)


REFERENCE_SCENE = """\
[sim]
timestep = 0.002
substeps = 1
force_mode = "centroid"
integrator = "implicit"

[ground]
height = 0.0

[[body]]
name = "bunny"
dano = "bunny.dano.npz"

[contact]
impact_spring = 1e5
impact_damper = 1e6
sliding_drag = 0.01
sliding_friction = 0.5
torsional_friction = 0.01
rolling_friction = 0.01
coulomb_gain = 1.0
indicator_width = 0.0
"""


@pytest.mark.slow
@pytest.mark.optimized
def test_the_command_line_alone_identifies_the_reference_friction_as_python_does(dojo, tmp_path, capsys):
    """Issue 18: the authors' μ = 0.3 trajectory through `dano build` and `dano sysid` only (the scene
    as TOML, the CSV as it is) gives the Python experiment's friction (`examples/sysid_experiments.py
    reference`, rows 400-600 here) to 1 %."""
    import json

    from dano.cli import main

    collider = dojo / "colliders" / "bunny_collider.npz"
    csv = dojo / "trajectories" / "bunny_trajectory_0.3.csv"
    dano_file = tmp_path / "bunny.dano.npz"
    assert main(["build", str(collider), "-o", str(dano_file), "--reference-inertia", "second-moment"]) == 0
    (tmp_path / "scene.toml").write_text(REFERENCE_SCENE)
    capsys.readouterr()
    code = main([
        "sysid", str(tmp_path / "scene.toml"), "--traj", str(csv), "--fps", "500", "--frames", "400:601",
        "--window-frames", "25", "--fit", "friction", "--init", "friction=0.5", "--settle", "0",
        "--interval", "gauss-newton",
        "--json",
    ])  # fmt: skip
    assert code == 0
    out = json.loads(capsys.readouterr().out)
    assert out["adjustments"]["frames"] == [400, 601] and "settle" not in out["adjustments"]

    track = read_tracks(csv, fps=500.0)[""].frames(400, 601)
    scene = reference_drop_scene(collider, 0.5, integrator="implicit")
    problem = make_problem(scene, [Recording({"bunny": track})], ["friction"], window=25, settle=0.0)
    python = identify(problem, init={"friction": 0.5}, progress=False).params["sliding_friction"]
    assert out["params"]["friction"] == pytest.approx(python, rel=0.01)
    # the fit itself (measured): 0.349 on these 200 rows, 0.280 on rows 400-900 (README, the bias
    # against the authors' simulator is not yet explained)
    assert python == pytest.approx(0.3, rel=0.25)
