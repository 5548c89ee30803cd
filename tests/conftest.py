"""Test configuration: float64, strict shapes and dtypes, shared fixtures."""

import gc
import os
from pathlib import Path

import jax
import pytest

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
jax.config.update("jax_numpy_dtype_promotion", "strict")
# The command line's persistent compilation cache (`dano.cli.compilation_cache`) stays off in the
# tests that call `dano.cli.main`: each test compiles what it runs, whatever ran before.
os.environ["DANO_COMPILATION_CACHE"] = "off"

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
