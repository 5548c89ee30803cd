import numpy as np
import pytest

import dano
from dano.fields import SphereField
from dano.io import load_dano, save_dano


@pytest.fixture(scope="module")
def ball():
    return dano.build_dano(SphereField(0.05), n_points=500, mass=0.3, log2_samples=12, replicates=4)


def test_save_load_is_exact_and_atomic(tmp_path, ball):
    save_dano(tmp_path / "ball.dano.npz", ball)
    loaded = load_dano(tmp_path / "ball.dano.npz")
    for name in ("mass", "com", "inertia", "points", "densities", "normals", "alpha", "window", "inertia_stderr"):
        np.testing.assert_array_equal(getattr(loaded, name), getattr(ball, name))
    assert loaded.source == ball.source
    assert [p.name for p in tmp_path.iterdir()] == ["ball.dano.npz"]  # no temporary file left behind


def test_same_seed_same_dano():
    a = dano.build_dano(SphereField(0.05), n_points=300, seed=7, log2_samples=12, replicates=4)
    b = dano.build_dano(SphereField(0.05), n_points=300, seed=7, log2_samples=12, replicates=4)
    np.testing.assert_array_equal(a.points, b.points)
    np.testing.assert_array_equal(a.inertia, b.inertia)


def test_corrupt_and_wrong_version_files(tmp_path, ball):
    path = tmp_path / "b.dano.npz"
    save_dano(path, ball)
    data = dict(np.load(path, allow_pickle=False))
    np.savez(tmp_path / "v2.npz", **{**data, "version": np.int64(99)})
    with pytest.raises(dano.DanoFileError, match="version 99"):
        load_dano(tmp_path / "v2.npz")
    np.savez(tmp_path / "neg.npz", **{**data, "mass": np.float64(-1.0)})
    with pytest.raises(dano.DanoFileError, match="mass must be positive"):
        load_dano(tmp_path / "neg.npz")
    np.savez(tmp_path / "nan.npz", **{**data, "com": np.array([np.nan, 0, 0])})
    with pytest.raises(dano.DanoFileError, match="finite"):
        load_dano(tmp_path / "nan.npz")
    np.savez(tmp_path / "shape.npz", **(data | {"normals": data["normals"][:10]}))
    with pytest.raises(dano.DanoFileError, match="normals"):
        load_dano(tmp_path / "shape.npz")
    (tmp_path / "cut.npz").write_bytes(path.read_bytes()[:200])
    with pytest.raises(dano.DanoFileError):
        load_dano(tmp_path / "cut.npz")
    np.savez(tmp_path / "obj.npz", format=np.array([{"a": 1}], dtype=object), version=np.int64(1))
    with pytest.raises(dano.DanoFileError):
        load_dano(tmp_path / "obj.npz")


def test_negative_mass_is_refused(ball):
    with pytest.raises(dano.InvalidMassError):
        ball.with_mass(-2.0)


@pytest.mark.parametrize("name", ["bunny", "bluesoap", "halfsoap"])
def test_reference_colliders_load(dojo, name):
    ref = dano.load_reference(dojo / "colliders" / f"{name}_collider.npz")
    raw = np.load(dojo / "colliders" / f"{name}_collider.npz")
    S = raw["inertia"]
    np.testing.assert_allclose(ref.inertia, np.trace(S) * np.eye(3) - S)
    assert ref.n_points == 5000 and float(ref.mass) == pytest.approx(float(raw["mass"]))
    np.testing.assert_allclose(np.linalg.norm(ref.normals, axis=1), 1.0, rtol=1e-12)
    np.testing.assert_allclose(ref.weights.sum(), ref.mass)
    keep = dano.load_reference(dojo / "colliders" / f"{name}_collider.npz", inertia="second_moment")
    np.testing.assert_array_equal(keep.inertia, S)


def test_estimated_normals_agree_with_stored_gradients(dojo):
    from dano.reference import _fill_zero_gradients

    raw = np.load(dojo / "colliders" / "bunny_collider.npz")
    stored = -raw["density_gradients"] / np.linalg.norm(raw["density_gradients"], axis=1, keepdims=True)
    estimate = -_fill_zero_gradients(raw["particles"], raw["densities"], np.zeros((5000, 3)))
    estimate /= np.linalg.norm(estimate, axis=1, keepdims=True)
    cos = np.sum(stored * estimate, axis=1)
    assert np.median(cos) > 0.9 and np.mean(cos > 0) > 0.8


def test_a_failed_write_leaves_nothing_behind(tmp_path):
    from dano.io import atomic_write

    target = tmp_path / "out.csv"
    with pytest.raises(RuntimeError), atomic_write(target) as tmp:
        tmp.write_text("half a file")
        raise RuntimeError("crash mid-write")
    assert list(tmp_path.iterdir()) == []
    with atomic_write(target) as tmp:
        tmp.write_text("whole")
    assert target.read_text() == "whole" and list(tmp_path.iterdir()) == [target]
