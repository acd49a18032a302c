"""Physics tests run in float64 (DESIGN.md: "Tests of physics run in float64").

The command line's compilation cache is off (``DIFSTAR_COMPILATION_CACHE``).

Each test module's compiled executables and cached constants are dropped after it: a
pytest-xdist worker runs hundreds of tests in one process, and JAX's caches would
otherwise grow with every shape compiled (over 10 GB per worker by the end of the suite).
"""

import gc
import os

import jax
import pytest

# the command line's persistent compilation cache stays off in the tests (each test
# compiles as a first run would; tests/test_compilation_cache.py turns it on in a folder
# of its own)
os.environ["DIFSTAR_COMPILATION_CACHE"] = "off"

jax.config.update("jax_enable_x64", True)


@pytest.fixture(autouse=True, scope="module")
def _free_jax_caches():
    yield
    jax.clear_caches()
    gc.collect()
