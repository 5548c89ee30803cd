"""Test configuration: float64, strict shapes and dtypes, shared fixtures."""

import gc
import os
import shutil
import tempfile
from pathlib import Path

import jax
import pytest

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
jax.config.update("jax_numpy_dtype_promotion", "strict")
QUICK_XLA = "DANO_TEST_XLA"
"""How the test run compiles. By default (`quick`) XLA spends little time optimising machine code
(`jax_disable_most_optimizations`) and, as dano's own jits do (`dano.sim.run.compiler_options`),
leaves XLA CPU's fusion emitters off in the tests' own jits too: most tests run their programs a
few times, so compiling them is most of their time (measured on eight compile-bound tests with two
workers: 274 s as XLA's defaults compile, 202 s with the emitters off, 153 s with both). A test
marked `optimized` runs its programs long enough (a field fitted over hundreds of steps, an iLQR
solve) that full optimisation pays, and gets it (`_xla_effort`). The programs are the same, so are
the answers to within rounding; `DANO_TEST_XLA=default` compiles every test as a user's process
does. Set before the backend starts, for this process and the `dano` command lines tests start."""
QUICK = os.environ.setdefault(QUICK_XLA, "quick") == "quick"
if QUICK:
    os.environ["JAX_DISABLE_MOST_OPTIMIZATIONS"] = "1"
    if "xla_cpu_use_fusion_emitters" not in os.environ.get("XLA_FLAGS", ""):
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_cpu_use_fusion_emitters=false").strip()
    jax.config.update("jax_disable_most_optimizations", True)


@pytest.fixture(autouse=True)
def _xla_effort(request, monkeypatch):
    """A test marked `optimized` compiles with XLA's full optimisation (`QUICK_XLA`), in this
    process and in the `dano` command lines it starts."""
    if not (QUICK and request.node.get_closest_marker("optimized")):
        yield
        return
    monkeypatch.setenv("JAX_DISABLE_MOST_OPTIMIZATIONS", "0")
    jax.config.update("jax_disable_most_optimizations", False)
    try:
        yield
    finally:
        jax.config.update("jax_disable_most_optimizations", True)


RUN_CACHE = "DANO_TEST_COMPILATION_CACHE"
"""A test run's own persistent compilation cache: a fresh folder per run (never the user's
`~/.cache/dano/jax`), shared by the run's xdist workers and the command lines its tests start, so
that a program compiled once in the run (a scene's rollout, an identification's Jacobians) is
loaded, not compiled again, by the next test, worker or `dano` process that builds the same one.
The programs are the same either way: XLA's compiled code, keyed by the program, the options and
the versions; only the compile time is saved. `DANO_TEST_COMPILATION_CACHE=off` compiles
everything in every test."""


def pytest_configure(config):
    """The run's cache folder: made by the controlling process (xdist's workers and the command
    lines the tests start inherit it through the environment) and used by every process."""
    if not hasattr(config, "workerinput") and os.environ.get(RUN_CACHE) is None:
        os.environ[RUN_CACHE] = tempfile.mkdtemp(prefix="dano-test-jax-cache-")
        config.dano_owns_cache = True
    path = os.environ[RUN_CACHE]
    if path.lower() == "off":
        os.environ["DANO_COMPILATION_CACHE"] = "off"
        return
    os.environ["DANO_COMPILATION_CACHE"] = path  # `dano.cli.compilation_cache`: the same folder
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)


def pytest_sessionstart(session):
    """One lane per process (`dano.lanes`) unless `DANO_LANES` says otherwise: the run's xdist
    workers already hold the cores, and a second lane's rollouts (the line search's speculative
    step sizes) would take time from the other worker. The tests of the lanes ask for counts."""
    os.environ.setdefault("DANO_LANES", "1")


def pytest_collection_modifyitems(config, items):
    """The tests marked `slow` first (each module's in its order: `sort` is stable), then the rest;
    with xdist handing tests out one at a time as a worker frees up (`--maxschedchunk=1` in
    pyproject's addopts), the long tests are shared between the workers from the start and the
    short ones fill in at the end. In collection order, with xdist's default chunks of a quarter of
    a worker's share, a long test could be queued behind others on one worker while the other ran
    out (a run of 453 tests: one worker finished 55 s after the other)."""
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)


def pytest_unconfigure(config):
    if getattr(config, "dano_owns_cache", False):
        shutil.rmtree(os.environ.pop(RUN_CACHE), ignore_errors=True)


SHARED = Path(os.environ.get("DANO_SHARED", Path(__file__).resolve().parents[1] / ".." / "shared")).resolve()
DOJO = SHARED / "data" / "dojo"


@pytest.fixture(scope="module", autouse=True)
def _release_compiled_programs():
    """After each test module, JAX's compiled programs are let go. Every jitted function keeps what
    it compiled for as long as the process lives (JAX's design, right for a program that reuses
    them); a test worker runs some 200 tests' worth of distinct programs, and kept together they
    grow past the kernel's memory-map limit (vm.max_map_count, 65530: measured 30k maps and 5.4 GB
    halfway through a worker), where XLA's next compilation aborts the process."""
    yield
    gc.collect()
    jax.clear_caches()


@pytest.fixture(scope="session")
def dojo() -> Path:
    """The reference data folder, or a skip saying why it is missing."""
    if not (DOJO / "colliders").is_dir():
        pytest.skip(f"reference data not found at {DOJO} (set DANO_SHARED to the shared/ folder)")
    return DOJO


@pytest.fixture(scope="session")
def bunny_mesh():
    from dano.assets import bunny_mesh

    return bunny_mesh()


@pytest.fixture(scope="session")
def bunny_field(bunny_mesh):
    from dano.fields import mesh_field

    return mesh_field(bunny_mesh, resolution=80, progress=False)
