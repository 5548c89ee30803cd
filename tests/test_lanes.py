"""Parallel lanes (`dano.lanes`): results in order, the caller's JAX settings carried into the
lanes' threads, bad lane counts refused."""

import os
import threading

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from dano import lanes
from dano.errors import InvalidValueError


def test_results_come_back_in_order_from_threads_of_their_own():
    names = []

    def call(i):
        names.append(threading.current_thread().name)
        return jnp.full(3, float(i)) ** 2

    out = lanes.in_lanes([lambda i=i: call(i) for i in range(7)], 3)
    np.testing.assert_array_equal(np.stack(out)[:, 0], np.arange(7.0) ** 2)
    assert any(n.startswith("dano-lane") for n in names)  # not all made in this thread


def test_the_callers_jax_settings_hold_in_every_lane():
    """The suite runs with float64 and rank promotion raising (conftest); a caller's `with` blocks
    overriding both hold in the lanes' threads too, and the global settings again after them."""

    def call():
        return (jnp.ones(2) + jnp.ones((3, 1))).dtype  # rank promotion, then the default dtype

    with jax.enable_x64(False), jax.numpy_rank_promotion("allow"):
        assert lanes.in_parallel([call, call, call]) == [jnp.float32] * 3
    with pytest.raises(ValueError, match="jax_numpy_rank_promotion=.raise."):
        lanes.in_parallel([lambda: jnp.ones(1), call])
    assert lanes.in_parallel([lambda: jnp.ones(1).dtype] * 2) == [jnp.float64] * 2


def test_a_failing_call_raises_in_the_caller():
    def bad():
        raise InvalidValueError("no")

    with pytest.raises(InvalidValueError, match="no"):
        lanes.in_parallel([lambda: jnp.ones(1), bad])


def test_the_lane_count_asked_for_then_dano_lanes_then_the_cores(monkeypatch):
    monkeypatch.delenv(lanes.VARIABLE, raising=False)
    assert lanes.count() == len(os.sched_getaffinity(0))  # the CPU backend: one per core
    assert lanes.count(3) == 3
    monkeypatch.setenv(lanes.VARIABLE, "5")
    assert lanes.count() == 5 and lanes.count(2) == 2
    for bad in (0, -2, True):
        with pytest.raises(InvalidValueError, match="lanes must be a whole number >= 1"):
            lanes.count(bad)
    for text in ("0", "two", "-1", "1.5"):
        monkeypatch.setenv(lanes.VARIABLE, text)
        with pytest.raises(InvalidValueError, match="DANO_LANES must be a whole number >= 1"):
            lanes.count()


def test_shares_cover_every_item_once_in_order_in_equal_lengths():
    for size in (1, 2, 5, 10, 20):
        for k in (1, 2, 3, 7, 30):
            idx = lanes.shares(size, k)
            assert idx.shape[0] <= min(k, size)
            flat = idx.reshape(-1)
            np.testing.assert_array_equal(flat[:size], np.arange(size))  # in order, each once
            assert np.all(flat[size:] == size - 1)  # the padding repeats the last item
    assert lanes.shares(10, 3).shape == (3, 4) and lanes.shares(20, 3).shape == (3, 7)


def test_mapped_equals_vmap():
    xs = jnp.linspace(0.0, 1.0, 5)
    np.testing.assert_allclose(
        jax.jit(lambda x: lanes.mapped(lambda a, b: jnp.sin(a) * b, x, 2 * x))(xs), jnp.sin(xs) * 2 * xs, rtol=1e-15
    )
