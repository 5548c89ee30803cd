"""`dano view`: an interactive 3D page (WebGL), opened in a real browser (headless Chromium)."""

import json
import re

import numpy as np
import pytest

from dano import build_dano, save_dano
from dano.cli import main
from dano.fields import BoxField
from dano.sim import DanoBody, Scene
from dano.viewer import Frames, ViewerError, view_scene, write_view
from helpers import browser_screenshot


@pytest.fixture(scope="module")
def soap():
    return build_dano(BoxField(size=(0.09, 0.06, 0.03)), mass=0.1, n_points=800)


def _data(page) -> dict:
    found = re.search(r"const DATA = (\{.*?\});\n", page.read_text())
    assert found is not None, "the page holds no data"
    return json.loads(found.group(1))


def _surface_share(shot: np.ndarray) -> float:
    """The share of the picture's middle that is the surface's orange (shaded), not the background."""
    h, w = shot.shape[:2]
    rgb = shot[h // 4 : 3 * h // 4, w // 4 : 3 * w // 4, :3].astype(int)
    return float(np.mean((rgb[..., 0] > rgb[..., 1] + 20) & (rgb[..., 1] > rgb[..., 2] + 10) & (rgb[..., 0] > 90)))


def test_a_dano_is_shown_as_its_surface_with_no_console_message(soap, tmp_path):
    page = write_view(tmp_path / "view.html", {"soap": soap})
    data = _data(page)
    assert [b["name"] for b in data["bodies"]] == ["soap"] and data["t"] == [0.0]
    body = data["bodies"][0]
    assert len(body["points"]) == 3 * 800 and len(body["faces"]) > 0 and len(body["vertices"]) % 3 == 0
    shot, console = browser_screenshot(page, tmp_path / "view.png", size=(800, 600))
    assert console == []
    assert _surface_share(shot) > 0.2  # the bar fills the middle of the picture
    # Its surface switched off by the page's own checkbox state is not tested here; its points alone:
    page.write_text(page.read_text().replace('id="surface" checked', 'id="surface"'))
    shot, console = browser_screenshot(page, tmp_path / "points.png", size=(800, 600))
    assert console == [] and _surface_share(shot) < 0.02


def test_a_simulated_trajectory_plays_on_a_timeline(soap, tmp_path):
    from dano.sim.run import Simulation, write_csv

    scene = Scene(duration=0.1, bodies=(DanoBody("soap", soap, pos=(0.0, 0.0, 0.015), vel=(0.4, 0.0, 0.0)),))
    sim = Simulation.from_scene(scene)
    write_csv(tmp_path / "traj.csv", sim.run(), sim)
    page = view_scene(tmp_path / "view.html", scene, tmp_path / "traj.csv")
    data = _data(page)
    rows = np.genfromtxt(tmp_path / "traj.csv", delimiter=",", skip_header=1, usecols=(0, 2, 3, 4, 5, 6, 7, 8))
    assert data["scene"] is True and len(data["t"]) == len(rows) == 51
    np.testing.assert_allclose(data["poses"]["soap"], rows[:, 1:], atol=1e-6)
    assert rows[-1, 1] > rows[0, 1] + 0.01  # it slid: the frames are the motion
    shot, console = browser_screenshot(page, tmp_path / "view.png", size=(800, 600))
    assert console == [] and _surface_share(shot) > 0.05


def test_bad_views_are_named_errors_and_write_nothing(soap, tmp_path, capsys):
    with pytest.raises(ViewerError, match="must end in .html"):
        write_view(tmp_path / "view.htm", {"soap": soap})
    with pytest.raises(ViewerError, match="no DANO"):
        write_view(tmp_path / "view.html", {})
    frames = Frames(np.zeros(1), {"bar": np.zeros((1, 7))})
    with pytest.raises(ViewerError, match=r"bodies \['bar'\] are not in the scene"):
        write_view(tmp_path / "view.html", {"soap": soap}, frames=frames)
    save_dano(tmp_path / "soap.dano.npz", soap)
    code = main(["view", str(tmp_path / "soap.dano.npz"), "-o", str(tmp_path / "v.html"), "--trajectory", "t.csv"])
    assert code == 2 and "needs the scene" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["soap.dano.npz"]
    assert main(["view", str(tmp_path / "soap.dano.npz"), "-o", str(tmp_path / "v.html"), "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["bodies"] == ["soap"] and summary["bytes"] == (tmp_path / "v.html").stat().st_size


def _red_share(shot: np.ndarray) -> float:
    rgb = shot[..., :3].astype(int)
    return float(np.mean((rgb[..., 0] > 180) & (rgb[..., 1] < 90) & (rgb[..., 2] < 90)))


def test_a_simulation_is_shown_with_its_scene_geoms_and_contact_forces(soap, tmp_path):
    # The soap dropped onto a static box (a table): the table is in the view, where the scene put
    # it, and the soap's contact with it is an arrow up from its bottom face at the end.
    from dano.sim import Primitive
    from dano.sim.contacts import contact_forces
    from dano.sim.run import Simulation
    from dano.viewer import view_simulation

    table = Primitive("table", "box", (0.1, 0.08, 0.02), pos=(0.0, 0.0, 0.02))
    scene = Scene(duration=0.3, bodies=(DanoBody("soap", soap, pos=(0.0, 0.0, 0.07)),), primitives=(table,))
    sim = Simulation.from_scene(scene)
    traj = sim.run()
    forces = contact_forces(sim, traj)
    page = view_simulation(tmp_path / "view.html", sim, traj, contacts=forces)
    data = _data(page)
    (solid,) = [s for s in data["solids"] if s["name"] == "table"]
    vertices = np.asarray(solid["vertices"]).reshape(-1, 3)
    np.testing.assert_allclose(np.ptp(vertices, axis=0), [0.2, 0.16, 0.04], atol=1e-9)
    np.testing.assert_allclose(solid["poses"][-1], [0.0, 0.0, 0.02, 1.0, 0.0, 0.0, 0.0], atol=1e-9)
    assert len(data["arrows"]) == len(data["t"]) == 151 and data["arrows"][0] == []  # in the air at first
    ((start, end),) = np.asarray(data["arrows"][-1]).reshape(-1, 2, 3)  # the table's only: the floor's is 0
    np.testing.assert_allclose(start[2], 0.04, atol=2e-3)  # the table's top
    assert end[2] > start[2] + 0.03  # up, half the soap's size for its weight (0.045 m)
    shot, console = browser_screenshot(page, tmp_path / "view.png", size=(800, 600))
    assert console == [] and _surface_share(shot) > 0.01
    # The page opens at the first frame: no force yet. At the last frame the arrow shows in red.
    last = page.read_text().replace("let frame = 0;", f"let frame = {len(data['t']) - 1};")
    (tmp_path / "last.html").write_text(last)
    shot, console = browser_screenshot(tmp_path / "last.html", tmp_path / "last.png", size=(800, 600))
    assert console == []
    page.write_text(last.replace('id="arrows" checked', 'id="arrows"'))
    off, console = browser_screenshot(page, tmp_path / "off.png", size=(800, 600))
    assert console == [] and _red_share(shot) > _red_share(off) + 2e-4  # (the centre-of-mass cross is red too)
