"""Profile-likelihood intervals (`identify(interval="profile")`, `dano sysid --interval`): the search
for each end against closed forms, and the flags that say when the Gauss-Newton stderr misleads."""

import numpy as np
import pytest
from scipy.stats import chi2

from dano.sysid.intervals import _flags, profile_bound

Q = float(np.sqrt(chi2.ppf(0.95, 1)))  # 1.96


def _counted(deviance):
    calls = []

    def f(v):
        calls.append(v)
        return deviance(v)

    return f, calls


@pytest.mark.parametrize("step", [0.0123, 1e-5, 3.0])  # the stderr right, 1000x too small, 100x too large
def test_a_quadratic_profile_ends_at_z_stderr_on_both_sides(step):
    theta, se = 0.5, 0.0123
    deviance, calls = _counted(lambda v: ((v - theta) / se) ** 2)
    for direction, limit in ((-1, 0.0), (1, 2.0)):
        end = profile_bound(deviance, theta, direction, Q * step, limit, Q)
        assert not end.at_limit and end.lowest == 0.0
        assert end.value == pytest.approx(theta + direction * Q * se, abs=1e-2 * se)
    assert len(calls) <= 40  # a handful of refits per side, even from a stderr 1000x off


def test_an_asymmetric_profile_gets_each_end_right():
    """Friction near a stick-slip change: the loss rises 5x faster on one side than on the other."""
    theta, below, above = 0.3, 0.05, 0.01
    deviance = lambda v: ((v - theta) / (below if v < theta else above)) ** 2  # noqa: E731
    low = profile_bound(deviance, theta, -1, Q * 0.02, 0.0, Q)
    high = profile_bound(deviance, theta, 1, Q * 0.02, 2.0, Q)
    assert low.value == pytest.approx(theta - Q * below, abs=1e-2 * Q * below)  # 1 % of the half-width
    assert high.value == pytest.approx(theta + Q * above, abs=1e-2 * Q * above)
    flags = _flags("friction", theta, 0.02, Q, [low, high])
    assert len(flags) == 2 and "too small" in flags[0] and "too large" in flags[1]


def test_a_flat_profile_is_cut_at_the_bound_and_flagged():
    """μ = 0.01 on a loss flat from 0 to 0.015 (issue 18): the interval reaches the bound 0."""
    deviance = lambda v: 0.0 if v < 0.015 else ((v - 0.015) / 0.001) ** 2  # noqa: E731
    low = profile_bound(deviance, 0.01, -1, Q * 6e-4, 0.0, Q)
    high = profile_bound(deviance, 0.01, 1, Q * 6e-4, 2.0, Q)
    assert low.at_limit and low.value == 0.0
    assert not high.at_limit and high.value == pytest.approx(0.015 + Q * 0.001, abs=1e-2 * (0.005 + Q * 0.001))
    flags = _flags("friction", 0.01, 6e-4, Q, [low, high])
    assert any("low end of the interval is cut at 0" in f for f in flags)
    assert any("high end" in f and "too small" in f for f in flags)


def test_a_rough_profile_ends_at_its_first_crossing_and_a_lower_loss_is_reported():
    """A loss that is not monotone about the optimum (issue 18's μ = 0.9): the first crossing of the
    threshold, found on a fine grid, is the end; a dip below the optimum's loss is a flag."""
    theta, se = 0.9, 0.01

    def deviance(v):
        return ((v - theta) / se) ** 2 * (1.0 + 0.8 * np.sin(300.0 * (v - theta)))

    high = profile_bound(deviance, theta, 1, Q * se, 2.0, Q)
    grid = np.linspace(theta, 1.0, 200_001)
    first = grid[np.argmax(np.sqrt(np.maximum([deviance(v) for v in grid], 0.0)) >= Q)]
    assert high.value == pytest.approx(first, abs=1e-5)
    low = profile_bound(deviance, theta, -1, Q * se, 0.0, Q)
    assert low.lowest == 0.0
    dipped = profile_bound(lambda v: -1.0 if v > 0.905 else ((v - theta) / se) ** 2, theta, 1, 1e-3, 2.0, Q, evals=6)
    assert dipped.lowest < 0 and dipped.at_limit
    assert "lower loss" in _flags("friction", theta, se, Q, [low, dipped])[0]


def test_agreeing_stderr_is_not_flagged():
    deviance = lambda v: ((v - 0.5) / 0.01) ** 2  # noqa: E731
    sides = [profile_bound(deviance, 0.5, d, Q * 0.01, (0.0, 2.0)[d > 0], Q) for d in (-1, 1)]
    assert _flags("friction", 0.5, 0.011, Q, sides) == []


# Robust losses (`identify(loss=...)`, `dano sysid --loss`)


@pytest.mark.parametrize("loss", ["huber", "cauchy"])
def test_robust_residuals_square_to_the_robust_loss_and_differentiate(loss):
    import jax
    import jax.numpy as jnp

    from dano.sysid.objective import ROBUST_SCALE, robust
    from helpers import central_difference

    c = ROBUST_SCALE
    r = jnp.asarray(np.random.default_rng(0).normal(0.0, 3.0, (40, 6)))
    u = np.sum(np.asarray(r).reshape(40, 2, 3) ** 2, axis=-1)
    rho = {
        "huber": np.where(u <= c * c, u, 2 * c * np.sqrt(u) - c * c),
        "cauchy": c * c * np.log1p(u / (c * c)),
    }[loss]
    assert float(jnp.sum(robust(r, loss) ** 2)) == pytest.approx(float(np.sum(rho)), rel=1e-12)
    inliers = np.all(u <= c * c, axis=-1)
    if loss == "huber":  # inliers keep their residuals exactly
        np.testing.assert_array_equal(np.asarray(robust(r, loss))[inliers], np.asarray(r)[inliers])

    def f(x):
        return jnp.sum(robust(x, loss) ** 2)

    g = jax.grad(f)(r)
    for i, j in ((0, 0), (7, 4), (31, 2)):
        fd = central_difference(lambda h, i=i, j=j: f(r.at[i, j].add(h)), 0.0, 1e-6)
        assert float(g[i, j]) == pytest.approx(float(fd), rel=1e-6, abs=1e-9)
    zero = jax.jacfwd(lambda x: robust(x, loss))(jnp.zeros((1, 6)))  # smooth at 0, the identity there
    np.testing.assert_allclose(np.asarray(zero).reshape(6, 6), np.eye(6), atol=1e-12)


def test_a_bad_loss_name_is_refused():
    import jax.numpy as jnp

    from dano.sysid.configs import SysidError
    from dano.sysid.objective import robust

    with pytest.raises(SysidError, match="'l2', 'huber' or 'cauchy'"):
        robust(jnp.zeros((1, 6)), "l1")


@pytest.mark.slow
def test_a_robust_loss_shrugs_off_tracking_failures():
    """The 33-frame soap slide with 1 mm noise, the initial state fitted, and 3 frames where the
    tracker jumped 2 cm ahead: least squares is pulled off by them (measured: μ 0.566, the Huber loss
    0.517, Cauchy 0.509; all three 0.507 on the clean track); the Cauchy loss stays within 3 %."""
    import dano
    from dano.fields import BoxField
    from dano.scenarios import slide_scene
    from dano.sysid import Recording, identify, make_problem
    from dano.sysid.experiments import slide_track

    bar = dano.build_dano(BoxField(size=(0.09, 0.06, 0.03)), mass=0.1, n_points=600)
    scene = slide_scene(bar, friction=0.5)
    track = slide_track(scene, fps=120.0, n_frames=33, noise=1e-3, seed=0)
    pos = track.pos.copy()
    pos[[20, 21, 22]] += np.array([0.02, 0.0, 0.0])
    import dataclasses

    outliers = Recording({"object": dataclasses.replace(track, pos=pos)})
    problem = make_problem(scene, [outliers], ["friction"], initial="state")
    fits = {loss: identify(problem, init={"friction": 0.2}, progress=False, loss=loss) for loss in ("l2", "cauchy")}
    plain, robust = fits["l2"].params["sliding_friction"], fits["cauchy"].params["sliding_friction"]
    assert abs(robust - 0.5) < 0.03 * 0.5
    assert abs(plain - 0.5) > 3 * abs(robust - 0.5)
    assert fits["cauchy"].loss_function == "cauchy" and fits["cauchy"].summary()["loss_function"] == "cauchy"
