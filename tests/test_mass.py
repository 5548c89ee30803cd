from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import dano
from dano.fields import BoxField, CallableField, CapsuleField, SphereField, TransformedField
from dano.mass import mass_properties, mass_properties_from_points, sample_points
from dano.math import quat_to_mat
from helpers import analytic_fields, central_difference, rel_err

ANALYTIC = analytic_fields()


@pytest.mark.parametrize("field", ANALYTIC, ids=lambda f: type(f).__name__)
def test_analytic_mass_properties_match_closed_form(field):
    exact = field.exact_mass_properties(alpha=2.0)
    props = mass_properties(field, alpha=2.0)
    size = float(np.max(np.asarray(field.bounds[1]) - np.asarray(field.bounds[0])))
    # Acceptance: 1 %. RQMC with 2^18 points does far better; its standard error must be honest too.
    assert float(props.mass) == pytest.approx(float(exact.mass), rel=0.01)
    assert np.linalg.norm(props.com) < 0.01 * size
    assert rel_err(props.inertia, exact.inertia) < 0.01
    assert abs(float(props.mass - exact.mass)) < 6 * float(props.mass_stderr)


def test_closed_form_sphere_limit():
    # As the soft edge shrinks the closed form tends to the solid ball: m = 4/3 pi r^3 rho, J = 2/5 m r^2.
    f = SphereField(0.05, width=1e-6, peak=1000.0)
    ex = f.exact_mass_properties()
    m = 4 / 3 * np.pi * 0.05**3 * 1000
    assert float(ex.mass) == pytest.approx(m, rel=1e-6)
    np.testing.assert_allclose(ex.inertia, 0.4 * m * 0.05**2 * np.eye(3), rtol=1e-6)


def test_mass_fixes_alpha():
    f = SphereField(0.05)
    props = mass_properties(f, mass=0.5)
    assert float(props.mass) == pytest.approx(0.5, rel=1e-12)
    assert float(props.alpha) == pytest.approx(0.5 / float(f.exact_mass_properties().mass), rel=1e-3)


def test_rigid_motion_moves_estimates_as_physics_says():
    box = BoxField([0.1, 0.06, 0.03], width=0.003)
    R = np.asarray(quat_to_mat(jnp.asarray([0.9, 0.2, -0.3, 0.25])))
    t = np.array([0.3, -0.2, 0.5])
    base = mass_properties(box)
    moved = mass_properties(TransformedField(box, R, t))
    # Tolerance: the moved box is sampled in its (larger) axis-aligned box, so it is a different
    # Monte Carlo estimate; both carry ~1e-4 relative error.
    assert float(moved.mass) == pytest.approx(float(base.mass), rel=2e-3)
    np.testing.assert_allclose(moved.com, R @ np.asarray(base.com) + t, atol=2e-4)
    assert rel_err(moved.inertia, R @ np.asarray(base.inertia) @ R.T) < 5e-3


def test_grad_of_mass_properties_matches_finite_differences():
    points = sample_points(SphereField(0.05), log2_samples=12, replicates=4, seed=0)
    bounds = ((-0.07,) * 3, (0.07,) * 3)

    def props(radius, shift):
        sphere = SphereField(radius, width=0.01, bounds=bounds)
        moved = CallableField(lambda x: sphere(x - jnp.stack([shift, 0.0, 0.0])[None, :]), bounds)
        return mass_properties_from_points(moved, points, alpha=1.0)[0]

    fns = {
        "mass": lambda r: props(r, 0.0).mass,
        "Izz": lambda r: props(r, 0.0).inertia[2, 2],
        "com_x": lambda r: props(0.05, r).com[0],
    }
    for name, fn in fns.items():
        x0 = 0.05 if name != "com_x" else 0.003
        grad = float(jax.grad(fn)(x0))
        fd = central_difference(lambda r, fn=fn: float(fn(r)), x0, rel_step=1e-6)
        assert grad == pytest.approx(fd, rel=1e-5), name
        assert grad != 0.0


def test_same_seed_same_numbers_other_seed_other_numbers():
    f = CapsuleField(0.02, 0.05)
    a, b, c = mass_properties(f, seed=3), mass_properties(f, seed=3), mass_properties(f, seed=4)
    np.testing.assert_array_equal(a.inertia, b.inertia)
    assert float(a.mass) != float(c.mass)


def test_bad_fields_and_masses_raise_named_errors():
    bounds = ((-1.0,) * 3, (1.0,) * 3)
    with pytest.raises(dano.EmptyFieldError):
        mass_properties(CallableField(lambda x: jnp.zeros(x.shape[0]), bounds))
    with pytest.raises(dano.NonFiniteFieldError):
        mass_properties(CallableField(lambda x: jnp.full(x.shape[0], jnp.nan), bounds))
    with pytest.raises(dano.FieldError, match="negative"):
        mass_properties(CallableField(lambda x: x[:, 0], bounds))
    cases: list[dict[str, Any]] = [{"mass": -1.0}, {"alpha": 0.0}, {"mass": float("nan")}]
    for kwargs in cases:
        with pytest.raises(dano.InvalidMassError):
            mass_properties(SphereField(0.05), **kwargs)


def test_bunny_inertia_matches_exact_polyhedral_integrals(bunny_mesh, bunny_field):
    props = mass_properties(bunny_field, mass=1.0)
    exact = bunny_mesh.copy()
    exact.density = 1.0 / bunny_mesh.volume
    # Acceptance: 2 %. The remaining gap is the soft edge's curvature term and the 80^3 grid.
    assert rel_err(props.inertia, exact.moment_inertia) < 0.02
    assert np.linalg.norm(np.asarray(props.com) - exact.center_mass) < 0.002 * np.max(bunny_mesh.extents)


def test_principal_extents_measure_a_box_turned_off_the_field_axes():
    """The size `dano info` prints and `sysid --size` uses: a 9 x 6 x 3 cm box built turned 45° and 20°
    off the field's axes measures 9, 6 and 3 cm along its principal axes, while the bounding box of
    the field's own frame is larger (the frame-aligned extent the old `--size` used)."""
    from scipy.spatial.transform import Rotation

    turn = Rotation.from_euler("zy", [45.0, 20.0], degrees=True).as_matrix()
    field = TransformedField(BoxField(size=(0.09, 0.06, 0.03)), rotation=turn)
    obj = dano.build_dano(field, mass=0.1, n_points=2000)
    extents = np.asarray(obj.principal_extents())
    np.testing.assert_allclose(np.sort(extents), [0.03, 0.06, 0.09], rtol=0.03)
    assert np.argmax(extents) == np.argmin(np.asarray(obj.principal_moments()))  # longest axis turns easiest
    frame_box = np.ptp(np.asarray(obj.points), axis=0)
    assert frame_box.max() > 1.1 * extents.max()
