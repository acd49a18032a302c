"""JAX's persistent compilation cache, in one place: where it lives and when it is on.

A fit, a prediction or a design compiles its programs (the forward model, its Jacobian,
the solver's step) before its first step; on a 2-core CPU that is about half of a small
fit's time (the Spitzer campaign: 35 of 80 s). The persistent cache keeps each compiled
program on disk, keyed by the program and the compiler's options, so a later run of the
same shapes (the same campaign again, another stage of the same size, a study's starts)
loads it instead. Nothing is downloaded; results do not change (a program loaded is the
program compiled).

The command line turns it on (:func:`enable_compilation_cache`); library users call it
themselves. ``DIFSTAR_COMPILATION_CACHE``: a folder to use instead of the default
(``$XDG_CACHE_HOME/difstar/jax``, else ``~/.cache/difstar/jax``), or ``off``.
"""

from __future__ import annotations

import os
from pathlib import Path

#: The environment variable that moves the cache or turns it off (``off``).
ENV = "DIFSTAR_COMPILATION_CACHE"

#: Programs that compile faster than this (seconds) are not stored. 0: every program,
#: the small ones too. A fit's set-up runs a few hundred small operations outside its
#: solver (each compiled once per process, 5-30 ms each); stored, they cost the paper
#: camera's RAW fit 1.9 MB of cache and bring its first step from 9.4 to 7.4 s on a
#: second run (BENCHMARKS.md, "Whole fits").
MIN_COMPILE_SECONDS = 0.0

#: The cache's size limit in bytes: JAX drops the least recently used programs beyond it.
MAX_BYTES = 2 * 1024**3


def cache_folder() -> Path | None:
    """Where the cache lives (None: turned off by ``DIFSTAR_COMPILATION_CACHE=off``)."""
    given = os.environ.get(ENV, "").strip()
    if given.lower() == "off":
        return None
    if given:
        return Path(given).expanduser()
    base = os.environ.get("XDG_CACHE_HOME", "").strip() or str(Path.home() / ".cache")
    return Path(base) / "difstar" / "jax"


def enable_compilation_cache(folder: str | os.PathLike | None = None) -> Path | None:
    """Turn on JAX's persistent compilation cache in ``folder`` (default:
    :func:`cache_folder`) for this process's next compiles. Returns the
    folder, or None where the cache is off or its folder cannot be made (a read-only home:
    the run goes on, compiling as before)."""
    import jax

    path = cache_folder() if folder is None else Path(folder)
    if path is None:
        return None
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    if not os.access(path, os.W_OK):
        return None
    jax.config.update("jax_compilation_cache_dir", str(path))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_SECONDS)
    jax.config.update("jax_compilation_cache_max_size", MAX_BYTES)
    # JAX decides at its first compile whether this process has a cache (importing
    # difstar compiles a little): let it decide again at the next
    from jax.experimental.compilation_cache import compilation_cache

    compilation_cache.reset_cache()
    return path
