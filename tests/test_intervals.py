"""Profile-likelihood intervals (`identify(interval="profile")`, `dano sysid --interval`): the search
for each end against closed forms, and the flags that say when the Gauss-Newton stderr misleads."""

import numpy as np
import pytest
from scipy.stats import chi2

from dano.sysid.solve import _flags, profile_bound

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
