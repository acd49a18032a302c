"""Physics tests run in float64 (DESIGN.md: "Tests of physics run in float64").

JAX's persistent compilation cache lives in a folder of the session's own (never the
user's ``~/.cache``).

Each test module's compiled executables and cached constants are dropped after it: a
pytest-xdist worker runs hundreds of tests in one process, and JAX's caches would
otherwise grow with every shape compiled (over 10 GB per worker by the end of the suite).
"""

import os

import jax
import pytest

# the command line's cache in the user's folder is never touched by the tests: off until
# the session fixture below gives it a folder of the test session's own
os.environ["DIFSTAR_COMPILATION_CACHE"] = "off"

jax.config.update("jax_enable_x64", True)


@pytest.fixture(autouse=True, scope="session")
def _session_compilation_cache(tmp_path_factory):
    """JAX's persistent compilation cache in a fresh folder of this test session, shared
    by its xdist workers, for the tests and the commands they start: a program compiled
    once (a fit's stage run again in a repeat or a hop, the same model in another test or
    on the other worker) is loaded, not compiled again. JAX locks the folder for each
    read and write (its size limit makes it use ``filelock``), so the workers may share
    it. A loaded program is the program compiled, so no result changes; the folder
    starts empty, so nothing carries over between sessions.
    tests/test_compilation_cache.py checks a run from the cache against one without."""
    from difstar._compilation_cache import ENV, enable_compilation_cache

    base = tmp_path_factory.getbasetemp()
    # under xdist each worker's base is a folder of the session's own (popen-gw0, ...)
    shared = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base
    folder = shared / "jax-compilation-cache"
    folder.mkdir(exist_ok=True)
    os.environ[ENV] = str(folder)
    enable_compilation_cache(folder)
    # within one process JAX keeps its programs anyway: the tests store only those that
    # take a while to compile (the command line stores every one, for the next run)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    yield
    os.environ[ENV] = "off"


@pytest.fixture(autouse=True, scope="module")
def _free_jax_caches():
    yield
    from difstar.fitting._programs import release_programs

    release_programs()  # the fits' kept programs, and JAX's caches
