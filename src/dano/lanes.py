"""Parallel lanes: independent programs run at once, each from a thread of its own.

On the CPU backend an XLA execution of dano's small sequential programs (a rollout, a frame's
Jacobian) keeps to one core, and XLA lets go of the GIL while it runs one, so programs started
from different threads run on different cores: two rollouts from two threads take the wall time
of one (`python bench/simulate.py`, README). An accelerator runs one program at a time, so there
the lanes are one and batches are vmapped instead (`mapped`). Nothing here runs at import: the
thread pool is made on first use.
"""

import concurrent.futures
import os
import threading
from collections.abc import Callable, Sequence
from typing import TypeVar

import jax
import numpy as np

from dano.errors import InvalidValueError

__all__ = ["VARIABLE", "count", "in_lanes", "in_parallel", "mapped", "shares"]

_T = TypeVar("_T")
_POOL: list[concurrent.futures.ThreadPoolExecutor] = []
_POOL_LOCK = threading.Lock()


VARIABLE = "DANO_LANES"
"""The environment variable that sets the lanes when no count is asked for (e.g. 1 where several
dano processes already share the cores, as a test run's workers do)."""


def count(requested: int | None = None) -> int:
    """How many programs to run at once: `requested`; or `DANO_LANES` where set; or on the CPU
    backend one per core this process may use, elsewhere 1.

    Raises:
        InvalidValueError: `requested` or `DANO_LANES` not a whole number >= 1.
    """
    if requested is None and os.environ.get(VARIABLE, "").strip():
        text = os.environ[VARIABLE].strip()
        if not text.isdigit() or int(text) < 1:
            raise InvalidValueError(f"{VARIABLE} must be a whole number >= 1, got {text!r}")
        return int(text)
    if requested is not None:
        if isinstance(requested, bool) or not isinstance(requested, int) or requested < 1:
            raise InvalidValueError(f"lanes must be a whole number >= 1, got {requested!r}")
        return requested
    if jax.default_backend() != "cpu":
        return 1
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def in_parallel(calls: Sequence[Callable[[], _T]]) -> list[_T]:
    """Each call's result, once all are ready (`jax.block_until_ready`): the first made in this
    thread, the others from threads of a pool made on first use, under this thread's JAX settings
    that its own context managers can change (`jax.enable_x64`, `jax.default_device`,
    `jax.numpy_dtype_promotion`, `jax.numpy_rank_promotion`: a thread starts from the global
    ones, so a call made in `with jax.enable_x64(True):` would otherwise trace in float32)."""
    if len(calls) == 1:
        return [jax.block_until_ready(calls[0]())]
    with _POOL_LOCK:
        if not _POOL:
            _POOL.append(concurrent.futures.ThreadPoolExecutor(thread_name_prefix="dano-lane"))
    settings = _settings()
    futures = [_POOL[0].submit(_under, settings, c) for c in calls[1:]]
    first = jax.block_until_ready(calls[0]())
    return [first, *(future.result() for future in futures)]


def _settings() -> tuple:
    """This thread's values of the JAX settings `in_parallel` carries into its pool's threads."""
    c = jax.config
    return (c.jax_enable_x64, c.jax_default_device, c.jax_numpy_dtype_promotion, c.jax_numpy_rank_promotion)  # pyright: ignore[reportAttributeAccessIssue]


def _under(settings: tuple, call: Callable[[], _T]) -> _T:
    x64, device, dtypes, ranks = settings
    with jax.enable_x64(x64), jax.default_device(device), jax.numpy_dtype_promotion(dtypes):
        with jax.numpy_rank_promotion(ranks):
            return jax.block_until_ready(call())


def in_lanes(calls: Sequence[Callable[[], _T]], lanes: int | None = None) -> list[_T]:
    """Each call's result, in order, `count(lanes)` calls at a time (`in_parallel`)."""
    k = count(lanes)
    return [r for i in range(0, len(calls), k) for r in in_parallel(calls[i : i + k])]


def shares(size: int, lanes: int) -> np.ndarray:
    """Indices (k, per) that split `size` items into k <= `lanes` equal shares, one per lane (one
    program for every share), the last padded with the last item."""
    k = max(1, min(lanes, size))
    per = -(-size // k)
    k = -(-size // per)
    return np.minimum(np.arange(k * per), size - 1).reshape(k, per)


def mapped(fn: Callable, *batched):
    """fn over the leading axis of `batched` (pytrees of independent items: windows, pushes,
    environments) inside a traced function: on the CPU backend one item after another
    (`jax.lax.map`), elsewhere `jax.vmap`. Under `vmap` a simulated step's branches (`lax.cond`:
    contact or none, the broad phase) become selects that run both sides, and every loop runs as
    long as the longest item's, which a CPU pays in full; an accelerator runs the items at once."""
    if jax.default_backend() == "cpu":
        return jax.lax.map(lambda args: fn(*args), batched)
    return jax.vmap(fn)(*batched)
