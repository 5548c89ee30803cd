"""The mesh path against the DANO (`dano.baselines`): level sets, clean-up, decomposition, scenarios.

The object is a 10 x 6 x 4 cm box field with a faint Gaussian "floater" (5 % of the box's density,
sigma 6 mm) just under one end, the kind of artefact a NeRF leaves. Its centre is 5 mm below the
box's bottom face and 2 cm beyond its end, so every level below 5 % of the peak wraps the floater
and reaches ~1 cm below the box: a rigid object made of both rests on the floater's bottom and the
box's far edge, tilted by about atan(1 cm / 12 cm) ~ 5-7 degrees. The box's own level sets are flat.
"""

import json

import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

import dano
from dano.baselines import compare as C
from dano.baselines import models as M
from dano.baselines.mesh import clean_mesh, convex_decomposition
from dano.errors import MeshError
from dano.fields import BoxField, CallableField
from dano.surface import level_set_mesh

SIZE = (0.10, 0.06, 0.04)
BOX = BoxField(SIZE, width=0.002)  # peak 1000
FLOATER = jnp.asarray([0.07, 0.0, -0.025])


def _with_floater(x):
    return BOX(x) + 50.0 * jnp.exp(-jnp.sum((x - FLOATER[None, :]) ** 2, axis=-1) / (2 * 0.006**2))


FIELD = CallableField(_with_floater, ((-0.06, -0.035, -0.045), (0.09, 0.035, 0.025)))


def test_level_sets_keep_the_floater_only_below_its_density(tmp_path):
    low = level_set_mesh(FIELD, 10.0, resolution=60)
    high = level_set_mesh(FIELD, 500.0, resolution=60)
    assert len(low.split(only_watertight=False)) == 2  # box + floater
    assert len(high.split(only_watertight=False)) == 1
    assert low.bounds[0, 2] < -0.03 and low.bounds[1, 0] > 0.075  # the floater reaches under and beyond
    np.testing.assert_allclose(high.bounds, [np.negative(SIZE) / 2, np.asarray(SIZE) / 2], atol=2.5e-3)
    assert high.volume == pytest.approx(np.prod(SIZE), rel=0.03)
    cleaned = clean_mesh(low)
    assert cleaned.is_watertight and cleaned.bounds[1, 0] < 0.055  # largest component: the box alone
    with pytest.raises(MeshError, match="no surface at level 2000"):
        level_set_mesh(FIELD, 2000.0, resolution=30)


def test_decompositions_are_cached_and_vhacd_works(tmp_path):
    mesh = level_set_mesh(FIELD, 10.0, resolution=40)
    first = convex_decomposition(mesh, "coacd", threshold=0.1, cache_dir=tmp_path, progress=False)
    assert len(list(tmp_path.glob("coacd-*.npz"))) == 1
    again = convex_decomposition(mesh, "coacd", threshold=0.1, cache_dir=tmp_path, progress=False)
    assert len(first) == len(again) >= 2
    np.testing.assert_array_equal(first[0].vertices, again[0].vertices)
    pieces = convex_decomposition(mesh, "vhacd", threshold=0.1, cache_dir=tmp_path, progress=False)
    assert len(pieces) >= 2 and all(p.volume > 0 for p in pieces)
    with pytest.raises(MeshError, match="method"):
        convex_decomposition(mesh, "blender", cache_dir=None)


def test_low_level_rests_tilted_on_the_floater_while_the_dano_rests_flat(tmp_path):
    models = M.level_set_models(FIELD, [10.0, 500.0], resolution=60, threshold=0.1, cache_dir=tmp_path, progress=False)
    models.append(M.dano_model("DANO", dano.build_dano(FIELD, n_points=3000, mass=0.5)))
    truth = M.mesh_model("truth", trimesh.creation.box(SIZE))
    result = C.compare(models, truth)
    low, high, ours = result.rows
    assert result.truth_outcome is not None
    # Flat box on the floor: its centre 2 cm up; tilted on the floater: 5-7 degrees.
    assert result.truth_outcome.tilt_deg < 0.2
    assert result.truth_outcome.rest[2] == pytest.approx(0.02, abs=1e-3)
    assert 4.0 < low["rest_tilt_deg"] < 9.0
    assert low["mass_error"] > 0.1  # the floater's volume counts fully in a mesh
    assert high["rest_tilt_deg"] < 0.5 and abs(high["mass_error"]) < 0.03
    # The DANO weighs the floater by its density (5 %) and samples contact points in [10 %, 90 %]
    # of the peak: it rests flat to within its sampling noise, at the right height and mass.
    assert ours["rest_tilt_deg"] < 2.0
    assert ours["rest_height_m"] == pytest.approx(0.02, abs=2e-3)
    assert abs(ours["mass_error"]) < 0.02 and ours["inertia_error"] < 0.03
    assert ours["rest_angle_diff_deg"] < low["rest_angle_diff_deg"] / 2
    # The push: a 2 cm sphere moving 16 cm from 5 mm behind the box pushes it ~11 cm and then some
    # (the contact launches it ahead). The DANO is pushed about as far as the true box.
    assert 0.10 < result.truth_outcome.push_m < 0.18
    assert ours["push_m"] == pytest.approx(result.truth_outcome.push_m, rel=0.15)
    table = C.format_table(result.rows)
    assert "level 10" in table and "DANO" in table


def test_cli_compare_on_an_analytic_box(tmp_path, capsys):
    from dano.cli import main

    plot = tmp_path / "rests.png"
    args = ["compare", "box:size=0.1,0.06,0.04", "--levels", "500", "--resolution", "30", "--points", "500"]
    assert main([*args, "--json", "--plot", str(plot), "--report", str(tmp_path / "r.html")]) == 0
    out = json.loads(capsys.readouterr().out)
    assert [r["model"] for r in out["rows"]] == ["level 500", "DANO"]
    page = (tmp_path / "r.html").read_text()
    assert "<td>level 500</td>" in page and page.count("data:image/png;base64,") == 1 and "dano compare box:" in page
    assert all(r["rest_tilt_deg"] < 2.0 for r in out["rows"])
    assert plot.stat().st_size > 10_000
    assert main(["compare", "bluesoap"]) == 2
    assert "--data-dir" in capsys.readouterr().err


def test_the_authors_level_3_decomposition_is_read_as_145_convex_pieces(dojo):
    from dano.baselines.models import _obj_groups

    pieces = _obj_groups(dojo / "meshes" / "levelsets" / "bluesoap_level_3_decomposed.obj")
    assert len(pieces) == 145
    assert all(p.is_convex and p.volume > 0 for p in pieces)
