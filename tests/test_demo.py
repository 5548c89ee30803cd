import json

import numpy as np
import pytest

from dano.demo import run_demo
from dano.io import load_dano
from dano.results import RESULT_KEYS
from helpers import browser_screenshot


@pytest.mark.slow
@pytest.mark.optimized
def test_demo_writes_a_bunny_dano_and_its_picture(tmp_path, capsys):
    summary = run_demo(tmp_path, resolution=64)
    assert "principal moments" in capsys.readouterr().out
    dano = load_dano(tmp_path / "bunny.dano.npz")
    assert dano.n_points == 5000
    assert (tmp_path / "bunny_points.png").stat().st_size > 10_000
    assert json.loads((tmp_path / "summary.json").read_text())["mass_kg"] == pytest.approx(summary["mass_kg"])
    # A 64-node grid: the soft edge spans ~4 % of the bunny, so allow 3 % (the 96-node default gets 0.6 %).
    assert summary["inertia_rel_error"] < 0.03
    assert summary["mass_kg"] == pytest.approx(summary["mass_of_water_bunny_kg"], rel=0.02)
    for name in ("bunny_drop", "fig5_sphere_hits_two_bunnies"):
        assert (tmp_path / f"{name}.mp4").stat().st_size > 10_000
        assert summary[name]["final_speed_m_s"] < 1e-3  # everything comes to rest within 1.5 s
        # Drawn as surfaces and framed: together the bunnies cover at least 5 % of the last picture.
        assert sum(summary[name]["frame_covered"].values()) > 0.05, summary[name]["frame_covered"]
    assert (tmp_path / "sysid_soap_slide.png").stat().st_size > 10_000
    fit = summary["sysid_soap_slide"]
    assert abs(fit["friction"] - fit["true"]) < 3 * fit["stderr"] + 0.01  # 1 mm noise: ~1 % standard error
    # Sim-to-robot, and issue 5's "small pushing problem": the sphere pushes a 100-point bunny 8 cm
    # in 8 frames. The violation bound covers the force limits; the replay is the same dynamics.
    push = summary["trajopt_push"]
    assert set(RESULT_KEYS) - {"message"} <= set(push)  # the JSON shape `dano sysid` shares
    assert push["rms"] == {"position": push["final_error_m"], "rotation": None}
    assert push["converged"] and push["final_error_m"] < 0.01 and push["max_violation"] <= 1e-4
    assert push["replay_gap_m"] < 1e-9
    assert (tmp_path / "push.mp4").stat().st_size > 10_000
    assert sum(push["frame_covered"].values()) > 0.05, push["frame_covered"]  # the pushed bunny, framed
    # The report: one page holding every picture and video, shown by a browser with no console message;
    # the bunny's points (coloured by density) are in view.
    text = (tmp_path / "report.html").read_text()
    assert text.count("data:video/mp4;base64,") == 3 and text.count("data:image/png;base64,") == 2
    shot, console = browser_screenshot(tmp_path / "report.html", tmp_path / "report.png")
    assert console == []
    rgb = shot[..., :3].astype(int)
    assert np.mean(rgb.max(axis=-1) - rgb.min(axis=-1) > 80) > 0.003  # coloured pixels: the points, not text
