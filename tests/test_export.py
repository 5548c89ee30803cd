"""`dano export`: a scene written for plain MuJoCo, loaded in a fresh process that cannot import dano."""

import json
import subprocess
import sys

import equinox as eqx
import numpy as np
import pytest

pytest.importorskip("vhacdx", reason="the mesh path's extra (pip install 'dano[baselines]')")

from dano import build_dano  # noqa: E402
from dano.baselines.export import ExportError, export_scene  # noqa: E402
from dano.fields import BoxField  # noqa: E402
from dano.sim.scene import DanoBody, Scene  # noqa: E402

# MuJoCo's loader, alone: `dano` made unimportable, so nothing of it can be used.
LOAD = """
import json, sys
sys.modules["dano"] = None
import mujoco, numpy as np
m = mujoco.MjModel.from_xml_path(sys.argv[1])
d = mujoco.MjData(m)
i = m.body("soap").id
R = np.zeros(9)
mujoco.mju_quat2Mat(R, m.body_iquat[i])
R = R.reshape(3, 3)
inertia = R @ np.diag(m.body_inertia[i]) @ R.T
for _ in range(int(sys.argv[2])):
    mujoco.mj_step(m, d)
a = m.jnt_qposadr[m.body("soap").jntadr[0]]
print(json.dumps({
    "mass": float(m.body_mass[i]), "inertia": inertia.tolist(), "qpos": d.qpos[a : a + 7].tolist(),
    "speed": float(np.abs(d.qvel).max()), "time": d.time, "visual": int(m.geom_contype[m.body_geomadr[i]]),
}))
"""


@pytest.fixture(scope="module")
def soap():
    """A bar of soap whose inertia tensor is turned off its axes (a full tensor, all six entries
    different), so that writing the diagonal, or the principal frame at six digits, would show."""
    d = build_dano(BoxField(size=(0.09, 0.06, 0.03)), mass=0.1, n_points=300)
    c, s = np.cos(0.4), np.sin(0.4)
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])
    turned = R @ np.asarray(d.inertia) @ R.T
    return eqx.tree_at(lambda x: x.inertia, d, turned)


def test_an_exported_scene_loads_and_simulates_in_plain_mujoco_with_the_danos_mass_and_inertia(soap, tmp_path):
    scene = Scene(bodies=(DanoBody("soap", soap, pos=(0.0, 0.0, 0.05), quat=(0.9, 0.1, 0.3, 0.2)),))
    path = export_scene(scene, tmp_path / "scene.xml", method="vhacd", resolution=20, progress=False)
    run = subprocess.run([sys.executable, "-c", LOAD, str(path), "1500"], capture_output=True, text=True, check=True)
    got = json.loads(run.stdout)
    want = np.asarray(soap.inertia)
    assert abs(np.asarray(want)[0, 1]) > 1e-6 and abs(want[1, 2]) > 1e-6  # the test's premise: off its axes
    assert got["mass"] == pytest.approx(float(soap.mass), rel=1e-9)
    assert np.allclose(got["inertia"], want, rtol=0.0, atol=1e-9 * np.abs(want).max())
    # Dropped tilted from 5 cm, it comes to rest on the ground on one of its faces (MuJoCo's contact on
    # the convex pieces): its centre at half a side's height (1.5, 3 or 4.5 cm), within 2 mm.
    assert got["time"] == pytest.approx(3.0) and got["speed"] < 1e-3
    assert min(abs(got["qpos"][2] - h) for h in (0.015, 0.03, 0.045)) < 2e-3, got["qpos"]
    assert got["visual"] == 0  # the surface mesh is drawn, not collided with


def test_bad_exports_are_named_errors_and_write_nothing(soap, tmp_path):
    scene = Scene(bodies=(DanoBody("soap", soap),))
    with pytest.raises(ExportError, match="must end in .xml"):
        export_scene(scene, tmp_path / "scene.mjcf", method="vhacd", progress=False)
    blind = DanoBody("blind", eqx.tree_at(lambda x: x.grid, soap, None, is_leaf=lambda x: x is None))
    with pytest.raises(ExportError, match="no density grid to mesh"):
        export_scene(Scene(bodies=(blind,)), tmp_path / "blind.xml", method="vhacd", progress=False)
    assert list(tmp_path.iterdir()) == []


def test_dano_export_writes_the_scene_file_and_refuses_a_wrong_output(soap, tmp_path, capsys):
    from dano.cli import main
    from dano.io import save_dano

    save_dano(tmp_path / "soap.dano.npz", soap)
    scene = tmp_path / "scene.toml"
    scene.write_text('[[body]]\nname = "soap"\ndano = "soap.dano.npz"\npos = [0.0, 0.0, 0.05]\n')
    out = tmp_path / "scene.xml"
    argv = ["export", str(scene), "-o", str(out), "--method", "vhacd", "--resolution", "20", "--json"]
    assert main(argv) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["bodies"] == ["soap"] and summary["bytes"] == out.stat().st_size > 0
    assert main(["export", str(scene), "-o", str(tmp_path / "scene.mjcf")]) == 2
    assert "scene.mjcf" in capsys.readouterr().err and not (tmp_path / "scene.mjcf").exists()


def test_a_trajectory_is_exported_as_one_keyframe_per_frame(soap, tmp_path):
    import mujoco

    from dano.sim.run import Simulation, write_csv

    scene = Scene(duration=0.1, bodies=(DanoBody("soap", soap, pos=(0.0, 0.0, 0.03), vel=(0.3, 0.0, 0.0)),))
    sim = Simulation.from_scene(scene)
    write_csv(tmp_path / "traj.csv", sim.run(), sim)
    rows = np.genfromtxt(tmp_path / "traj.csv", delimiter=",", skip_header=1, usecols=(0, 2, 3, 4, 5, 6, 7, 8))
    path = export_scene(scene, tmp_path / "scene.xml", method="vhacd", resolution=20, progress=False,
                        trajectory=tmp_path / "traj.csv")  # fmt: skip
    model = mujoco.MjModel.from_xml_path(str(path))
    data = mujoco.MjData(model)
    assert model.nkey == len(rows) == 51
    for k in (0, 25, 50):
        mujoco.mj_resetDataKeyframe(model, data, k)  # pyright: ignore[reportAttributeAccessIssue]  (not in the stubs)
        assert data.time == pytest.approx(rows[k, 0])
        assert np.allclose(data.qpos[:7], rows[k, 1:], atol=1e-9)  # the CSV's 9 digits, written with 12
    assert rows[50, 1] > rows[0, 1] + 0.01  # it slid: the keys are the motion, not one pose repeated
    renamed = (tmp_path / "traj.csv").read_text().replace(",soap,", ",bar,")
    (tmp_path / "other.csv").write_text(renamed)
    with pytest.raises(ExportError, match=r"bodies \['bar'\] are not the scene's free bodies \['soap'\]"):
        export_scene(scene, tmp_path / "other.xml", method="vhacd", resolution=20, progress=False,
                     trajectory=tmp_path / "other.csv")  # fmt: skip
    assert not (tmp_path / "other.xml").exists()


def test_a_robots_mesh_files_travel_with_the_exported_file(soap, tmp_path):
    import shutil
    from pathlib import Path

    import trimesh

    from dano.sim.scene import Robot

    # A one-link MJCF arm whose link is a mesh file in a folder of its own.
    (tmp_path / "robot" / "meshes").mkdir(parents=True)
    trimesh.creation.box((0.2, 0.04, 0.04)).export(tmp_path / "robot" / "meshes" / "link.stl")
    (tmp_path / "robot" / "arm.xml").write_text(
        """<mujoco><compiler meshdir="meshes"/><asset><mesh name="link" file="link.stl"/></asset>
        <worldbody><body name="link" pos="0 0 0.2"><joint name="hinge" axis="0 0 1"/>
        <geom type="mesh" mesh="link" mass="0.5"/></body></worldbody></mujoco>"""
    )
    scene = Scene(
        bodies=(DanoBody("soap", soap, pos=(0.3, 0.0, 0.05)),), robot=Robot(str(tmp_path / "robot" / "arm.xml"))
    )
    export_scene(scene, tmp_path / "out" / "scene.xml", method="vhacd", resolution=20, progress=False)
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["scene.xml", "scene_assets"]
    shutil.rmtree(tmp_path / "robot")  # the original meshes are gone ...
    moved = Path(shutil.move(tmp_path / "out", tmp_path / "elsewhere"))  # ... and the export moved
    run = subprocess.run([sys.executable, "-c", LOAD, str(moved / "scene.xml"), "10"], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert json.loads(run.stdout)["mass"] == pytest.approx(float(soap.mass), rel=1e-9)


def test_a_scene_in_an_mjcf_world_is_exported_with_the_worlds_bodies_actuators_and_keyframes(soap, tmp_path):
    import shutil

    import mujoco

    (tmp_path / "world").mkdir()
    (tmp_path / "world" / "world.xml").write_text(
        """<mujoco><worldbody><geom name="floor" type="plane" size="1 1 0.1"/>
        <body name="lid" pos="0.3 0 0.2"><joint name="hinge" axis="1 0 0"/>
        <geom type="box" size="0.05 0.05 0.005" mass="0.1"/></body></worldbody>
        <actuator><position name="motor" joint="hinge" kp="2"/></actuator>
        <keyframe><key name="open" qpos="0.7" ctrl="0.7"/></keyframe></mujoco>"""
    )
    scene = Scene(mjcf=str(tmp_path / "world" / "world.xml"), ground_height=None,
                  bodies=(DanoBody("soap", soap, pos=(0.0, 0.0, 0.05)),))  # fmt: skip
    export_scene(scene, tmp_path / "out" / "scene.xml", method="vhacd", resolution=20, progress=False)
    shutil.rmtree(tmp_path / "world")  # the world's file is not needed: the export holds it
    model = mujoco.MjModel.from_xml_path(str(tmp_path / "out" / "scene.xml"))
    assert model.nu == 1 and model.nkey == 1 and model.key("open").qpos[0] == 0.7
    assert model.body_mass[model.body("soap").id] == pytest.approx(float(soap.mass), rel=1e-9)
    data = mujoco.MjData(model)
    for _ in range(1500):
        mujoco.mj_step(model, data)
    a = model.jnt_qposadr[model.body("soap").jntadr[0]]
    assert min(abs(data.qpos[a + 2] - h) for h in (0.015, 0.03, 0.045)) < 2e-3  # on the world's floor
