import jax.numpy as jnp
import numpy as np
import pytest

import dano
from dano.fields import BoxField, SphereField
from dano.surface import sample_surface


def test_sphere_points_in_window_with_outward_normals():
    f = SphereField(0.05, width=0.005)
    s = sample_surface(f, 2000, seed=1)
    d = np.asarray(s.densities)
    low, high = np.asarray(s.window)
    assert low == pytest.approx(0.1 * float(f.peak)) and high == pytest.approx(0.9 * float(f.peak))
    assert np.all((d >= low) & (d <= high))
    np.testing.assert_allclose(f(s.points), d)
    p = np.asarray(s.points)
    cos = np.sum(p / np.linalg.norm(p, axis=1, keepdims=True) * np.asarray(s.normals), axis=1)
    assert cos.min() > 0.95
    assert len(np.unique(p, axis=0)) == 2000  # no repeats


def test_points_spread_over_the_whole_surface():
    # Evenly spread: each octant of a centred sphere gets close to 1/8 of the points.
    s = sample_surface(SphereField(0.05, width=0.005), 4000, seed=0)
    octant = (np.asarray(s.points) > 0) @ np.array([1, 2, 4])
    counts = np.bincount(octant, minlength=8)
    assert np.all(np.abs(counts - 500) < 60)


def test_finite_difference_normals_agree_with_autodiff():
    f = BoxField([0.1, 0.06, 0.04], width=0.004)
    a = sample_surface(f, 500, seed=2)
    b = sample_surface(f, 500, seed=2, normals="fd", fd_step=1e-6)
    np.testing.assert_array_equal(a.points, b.points)
    assert np.min(np.sum(np.asarray(a.normals) * np.asarray(b.normals), axis=1)) > 0.999


def test_window_errors():
    f = SphereField(0.05)
    with pytest.raises(dano.EmptyWindowError, match="no point"):
        sample_surface(f, 100, window=(2000.0, 3000.0), max_candidates=1 << 17)
    with pytest.raises(dano.EmptyWindowError, match="only"):
        sample_surface(f, 100_000, max_candidates=1 << 17)
    with pytest.raises(dano.EmptyWindowError, match="low <= high"):
        sample_surface(f, 100, window=(0.9, 0.1))


def test_bunny_normals_follow_the_mesh(bunny_mesh, bunny_field):
    import trimesh

    s = sample_surface(bunny_field, 1000, seed=0)
    _, _, tri = trimesh.proximity.closest_point(bunny_mesh, np.asarray(s.points))
    cos = np.sum(bunny_mesh.face_normals[tri] * np.asarray(s.normals), axis=1)
    assert np.median(cos) > 0.95 and np.mean(cos > 0) > 0.97


def test_field_with_nan_inside_window_search():
    from dano.fields import CallableField

    f = CallableField(lambda x: jnp.where(x[:, 0] > 0.5, jnp.nan, 1.0), ((-1.0,) * 3, (1.0,) * 3))
    with pytest.raises(dano.NonFiniteFieldError):
        sample_surface(f, 10, window=(0.5, 1.5))
