"""XLA's CPU compiler settings that cut compile time, in one place: which, where they were
checked, and when a process gets them.

A fit's first step waits for its step program to compile (the paper camera's RAW fit: 6.4
of its 14 s on 2 cores; BENCHMARKS.md, "Whole fits"). XLA's CPU backend generates each
fused loop either through its newer MLIR fusion emitters (the default) or through its
older elemental emitters; for difstar's programs the older ones compile in 5.1 s what the
newer ones compile in 6.4 s, and the programs run as fast (the RAW fit's steps: 3.2 s either
way). Both emitters compute the same operations; the tests pass under either.

XLA reads its flags once, from ``XLA_FLAGS``, when JAX first starts its CPU backend, and
aborts the process on a flag it does not know. So the flags are added only

- where the running jaxlib's version is one they were checked on (:data:`CHECKED`),
- before the backend has started (afterwards they would do nothing),
- where ``XLA_FLAGS`` does not already set the same flag (the user's choice stands), and
- unless ``DIFSTAR_XLA_FLAGS=off``.

The command line and the test suite call :func:`use_quick_compile_flags`; a library user
may call it first thing (``difstar.use_quick_compile_flags()``) or set ``XLA_FLAGS``.
"""

from __future__ import annotations

import os

#: The environment variable that turns the flags off (``off``).
ENV = "DIFSTAR_XLA_FLAGS"

#: The flags: name → value.
FLAGS = {"xla_cpu_use_fusion_emitters": "false"}

#: (major, minor) versions of jaxlib on which :data:`FLAGS` were checked to exist.
CHECKED = ((0, 10),)


def _jaxlib_version() -> tuple[int, int] | None:
    try:
        import jaxlib

        major, minor = (int(v) for v in jaxlib.__version__.split(".")[:2])
    except (ImportError, ValueError, AttributeError):
        return None
    return major, minor


def _backend_started() -> bool:
    try:
        from jax._src import xla_bridge

        return bool(xla_bridge._backends)
    except (ImportError, AttributeError):  # another jax: assume it has
        return True


def use_quick_compile_flags() -> bool:
    """Add :data:`FLAGS` to ``XLA_FLAGS`` for this process (see the module's docstring for
    when). Returns whether they are in effect."""
    if os.environ.get(ENV, "").strip().lower() == "off":
        return False
    if _jaxlib_version() not in CHECKED or _backend_started():
        return False
    given = os.environ.get("XLA_FLAGS", "")
    names = {part.lstrip("-").split("=", 1)[0] for part in given.split()}
    extra = [f"--{k}={v}" for k, v in FLAGS.items() if k not in names]
    if extra:
        os.environ["XLA_FLAGS"] = " ".join([given.strip(), *extra]).strip()
    return True
