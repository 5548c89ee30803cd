import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dano
from dano.fields import (
    BoxField,
    CallableField,
    CapsuleField,
    GridField,
    NeuralField,
    NeuralFieldConfig,
    SphereField,
    TransformedField,
    as_field,
    from_spec,
    load_grid,
    load_mesh,
    load_neural_field,
    save_grid,
    save_neural_field,
)
from dano.fields.grid import grid_nodes
from helpers import analytic_fields

ANALYTIC = analytic_fields()


@pytest.mark.parametrize("field", ANALYTIC, ids=lambda f: type(f).__name__)
def test_analytic_soft_boundary(field):
    # Deep inside: peak; half level on the surface; zero beyond the soft edge and on the box.
    w = float(field.width)
    assert float(field(jnp.zeros((1, 3)))[0]) == pytest.approx(float(field.peak))
    x_axis = float(field.bounds[1][0]) - w  # the surface point on +x
    on_surface = jnp.asarray([[x_axis, 0.0, 0.0]])
    assert float(field(on_surface)[0]) == pytest.approx(float(field.peak) / 2, rel=1e-9)
    outside = jnp.asarray([[x_axis + 1.01 * w, 0.0, 0.0]])
    assert float(field(outside)[0]) == 0.0
    corners = jnp.asarray(grid_nodes(field.bounds, (2, 2, 2)).reshape(-1, 3))
    assert np.all(np.asarray(field(corners)) == 0.0)


@pytest.mark.parametrize("field", ANALYTIC, ids=lambda f: type(f).__name__)
def test_fields_are_jit_grad_vmap_able(field):
    x = jnp.asarray(np.random.default_rng(0).uniform(-0.05, 0.05, (64, 3)))
    np.testing.assert_allclose(eqx.filter_jit(field)(x), field(x), rtol=1e-12)
    batched = jax.vmap(lambda p: field(p[None])[0])(x)
    np.testing.assert_allclose(batched, field(x), rtol=1e-12)
    g = jax.grad(lambda p: jnp.sum(field(p)))(x)
    assert g.shape == x.shape and np.all(np.isfinite(g))


def test_grid_trilinear_is_exact_for_linear_functions(tmp_path):
    bounds = ((-1.0, -0.5, 0.0), (1.0, 0.5, 2.0))
    nodes = grid_nodes(bounds, (5, 4, 7))
    linear = lambda p: 3.0 + p[..., 0] - 2 * p[..., 1] + 0.5 * p[..., 2]  # noqa: E731
    grid = GridField(jnp.asarray(linear(nodes)), bounds)
    x = np.random.default_rng(1).uniform([-1, -0.5, 0], [1, 0.5, 2], (200, 3))
    np.testing.assert_allclose(grid(jnp.asarray(x)), linear(x), rtol=1e-12)
    assert float(grid(jnp.asarray([[1.5, 0.0, 1.0]]))[0]) == 0.0  # outside the box
    save_grid(tmp_path / "g.npz", grid)
    loaded = load_grid(tmp_path / "g.npz")
    assert loaded.bounds == grid.bounds
    np.testing.assert_array_equal(loaded.density, grid.density)


def test_grid_file_errors(tmp_path):
    np.savez(tmp_path / "flat.npz", density=np.ones((4, 4)), bounds=np.array([[0, 0, 0], [1, 1, 1.0]]))
    with pytest.raises(dano.DanoFileError, match="3-D"):
        load_grid(tmp_path / "flat.npz")
    np.savez(tmp_path / "nan.npz", density=np.full((3, 3, 3), np.nan), bounds=np.array([[0, 0, 0], [1, 1, 1.0]]))
    with pytest.raises(dano.DanoFileError, match="finite"):
        load_grid(tmp_path / "nan.npz")
    np.savez(tmp_path / "nokey.npz", rho=np.ones((3, 3, 3)))
    with pytest.raises(dano.DanoFileError, match="missing"):
        load_grid(tmp_path / "nokey.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(dano.DanoFileError, match="not a readable"):
        load_grid(tmp_path / "junk.npz")


def test_user_callable_and_transform():
    sphere = SphereField(0.05, width=0.005)
    user = as_field(lambda x: sphere(x), bounds=sphere.bounds)
    assert isinstance(user, CallableField)
    x = jnp.asarray(np.random.default_rng(2).uniform(-0.06, 0.06, (50, 3)))
    np.testing.assert_allclose(user(x), sphere(x))
    with pytest.raises(dano.FieldError, match="bounds"):
        as_field(lambda x: x[:, 0])
    moved = TransformedField(sphere, translation=jnp.asarray([1.0, 2.0, 3.0]), scale=2.0)
    np.testing.assert_allclose(moved(2 * x + jnp.asarray([[1.0, 2.0, 3.0]])), sphere(x), rtol=1e-12)
    np.testing.assert_allclose(moved.bounds[0], np.array([1, 2, 3.0]) - 0.11, rtol=1e-12)


def test_spec_parsing():
    box = from_spec("box:size=0.1,0.06,0.03,width=0.002")
    assert isinstance(box, BoxField)
    np.testing.assert_allclose(box.half_size, [0.05, 0.03, 0.015])
    assert float(box.width) == 0.002
    cap = from_spec("capsule:r=0.02,half_length=0.05,peak=800")
    assert isinstance(cap, CapsuleField)
    assert float(cap.peak) == 800 and float(cap.half_length) == 0.05
    for bad, msg in [("sphere:r=abc", "not a number"), ("sphere:q=1", "unknown key"), ("cone:r=1", "cannot parse"),
                     ("sphere:r=0.01,width=0.05", "exceeds"), ("sphere:r=-1", "positive")]:  # fmt: skip
        with pytest.raises(dano.DanoError, match=msg):
            from_spec(bad)


def test_neural_field_checkpoint_roundtrip(tmp_path):
    config = NeuralFieldConfig(width=32, depth=3, n_frequencies=4, density_scale=10.0)
    field = NeuralField(((-0.1,) * 3, (0.1,) * 3), config, key=jax.random.key(0))
    x = jnp.asarray(np.random.default_rng(3).uniform(-0.1, 0.1, (100, 3)))
    values = field(x)
    assert values.shape == (100,) and np.all(np.asarray(values) >= 0)
    assert float(field(jnp.asarray([[0.2, 0.0, 0.0]]))[0]) == 0.0
    save_neural_field(tmp_path / "f.npz", field)
    loaded = load_neural_field(tmp_path / "f.npz")
    np.testing.assert_array_equal(loaded(x), values)
    # gradient w.r.t. points and weights exist and are finite
    g = jax.grad(lambda p: jnp.sum(loaded(p)))(x)
    assert np.all(np.isfinite(g)) and np.any(g != 0)
    # tampered weights are refused, not silently reshaped
    data = dict(np.load(tmp_path / "f.npz", allow_pickle=False))
    data["leaf_000"] = data["leaf_000"][:, :-1]
    np.savez(tmp_path / "bad.npz", **data)
    with pytest.raises(dano.DanoFileError, match="leaf_000"):
        load_neural_field(tmp_path / "bad.npz")


def test_non_watertight_mesh_names_the_remedy(tmp_path):
    import trimesh

    box = trimesh.creation.box()
    open_box = trimesh.Trimesh(box.vertices, box.faces[:-2])
    open_box.export(tmp_path / "open.stl")
    with pytest.raises(dano.MeshNotWatertightError, match="pymeshfix"):
        load_mesh(tmp_path / "open.stl")
    with pytest.raises(dano.MeshError, match="no such file"):
        load_mesh(tmp_path / "missing.stl")
