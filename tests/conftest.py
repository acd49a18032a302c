"""Physics tests run in float64 (DESIGN.md: "Tests of physics run in float64").

Each test module's compiled executables and cached constants are dropped after it: a
pytest-xdist worker runs hundreds of tests in one process, and JAX's caches would
otherwise grow with every shape compiled (over 10 GB per worker by the end of the suite).
"""

import gc

import jax
import pytest

jax.config.update("jax_enable_x64", True)


@pytest.fixture(autouse=True, scope="module")
def _free_jax_caches():
    yield
    jax.clear_caches()
    gc.collect()
