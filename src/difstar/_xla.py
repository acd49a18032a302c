"""XLA's CPU compiler, in one place: working around its fusion heuristics, the options
the solvers' programs are compiled with, and its YNNPACK fusions turned off where they
compute wrongly.

XLA fuses a cheap producer into every consumer that reads it. When a value feeds
several consumers (several reductions, a slice beside an FFT, an output beside the next
stage), each consumer re-evaluates it; and an expensive operation inside it (a division,
a square root, an exponential) that thereby gains several users is instead stored as a
whole array per use. On the CPU, where these arrays are large and memory is slow, this
made parts of the chain 3–10× slower than their arithmetic (:func:`stored`).

A fit's solver programs (a Levenberg–Marquardt step with its batched Jacobian, the
covariance's Jacobian) are large and run a few to a few dozen times each, so on a CPU
their compile is most of a first fit's time. XLA's older fusion code generator compiles
an image fit's about 35 % faster (the RAW fit's step no faster), and they run as fast
(:func:`solver_jit_options`).

jaxlib 0.10.2 turned on XLA's YNNPACK fusions on the CPU, and they compute a product
summed over an axis wrongly under ``vmap`` (jax#39103). ``import difstar`` turns them
off for the process where it can (:func:`turn_off_ynn_fusions`), and the solvers'
programs are compiled without them (:data:`SOLVER_CPU_OPTIONS`).
"""

from __future__ import annotations

import functools
import os

import jax
import jax.numpy as jnp

#: The XLA options a solver's programs are compiled with on a CPU: the older fusion code
#: generator (``xla_cpu_use_fusion_emitters``). Measured on the 2-core machine, each
#: automatic fit from an empty compilation cache: the Spitzer star 49.8 → 36.0 s, the
#: JWST star 48.6 → 37.8 s, with the same answers and, from the cache, the same times
#: (24.9 and 28.3 s against 26.8 and 28.1 s). Not for the PSF and image programs: those
#: run hundreds of times (a rotation scan) or are timed by users (a plain ``psf`` call),
#: and there the newer code generator's programs run up to 1.3× faster.
SOLVER_CPU_OPTIONS = {"xla_cpu_use_fusion_emitters": False,
                      # no YNNPACK fusions (empty: none of their kinds). jaxlib 0.10.2
                      # turned them on, and they compute a product summed over an axis
                      # wrongly under vmap at a solver's sizes (jax#39103; found here
                      # in a field's compressed Jacobian, tests/test_lm.py), and took
                      # seconds for it; the fits' answers and times are the same without
                      # them (BENCHMARKS.md)
                      "xla_cpu_experimental_ynn_fusion_type": ""}


#: XLA's flag that turns off its YNNPACK fusions on a CPU (an empty list of their kinds)
YNN_OFF_FLAG = "--xla_cpu_experimental_ynn_fusion_type="
#: the jaxlib versions that fuse with YNNPACK by default and know the flag: 0.10.2
#: turned the fusions on; later versions are left as they are (the flag may go)
YNN_JAXLIBS = ((0, 10, 2), (0, 12, 0))
#: set (to anything) to leave ``XLA_FLAGS`` as it is
KEEP_FLAGS_ENV = "DIFSTAR_KEEP_XLA_FLAGS"


def turn_off_ynn_fusions(environ=os.environ) -> bool:
    """Turn off XLA's YNNPACK fusions on the CPU for this process, by adding
    :data:`YNN_OFF_FLAG` to ``XLA_FLAGS``, where jaxlib is one of :data:`YNN_JAXLIBS`,
    ``XLA_FLAGS`` does not name the flag already, :data:`KEEP_FLAGS_ENV` is unset and
    JAX's backends have not started (XLA reads ``XLA_FLAGS`` once, as they start:
    ``import difstar`` before any JAX computation). Returns whether it did.

    jaxlib 0.10.2's fusions compute a product summed over an axis wrongly under vmap at
    sizes a fit reaches (jax#39103; tests/test_xla.py has one such product), with no
    error. The solvers' programs are compiled without them in any case
    (:data:`SOLVER_CPU_OPTIONS`); this covers the forward model's programs and the
    user's own jits of difstar's functions. Measured on difstar's benchmarks, the plain
    PSF calls and the fits take the same time without them (BENCHMARKS.md)."""
    flags = environ.get("XLA_FLAGS", "")
    if environ.get(KEEP_FLAGS_ENV) or "xla_cpu_experimental_ynn_fusion_type" in flags:
        return False
    try:
        import jaxlib

        version = tuple(int(p) for p in jaxlib.__version__.split(".")[:3])
        from jax._src import xla_bridge

        started = xla_bridge.backends_are_initialized()
    except (ImportError, AttributeError, ValueError):
        return False  # a jaxlib or jax this does not know: left as it is
    lo, hi = YNN_JAXLIBS
    if started or not lo <= version < hi:
        return False
    environ["XLA_FLAGS"] = f"{flags} {YNN_OFF_FLAG}".strip()
    return True


def stored(fn, operands, key):
    """``fn(operands)``, evaluated apart so that XLA computes it once and stores it.

    It is evaluated inside a conditional, whose result XLA cannot fuse into consumers.
    The predicate (``key`` is NaN, in which case the result is NaN as well) only has to
    be one that XLA cannot fold; ``key`` should be a scalar the result depends on.
    Under ``vmap`` with a batched ``key`` the conditional becomes a select: still
    correct, but no longer a barrier.

    The NaN branch is made of constants of ``fn``'s output shapes, not of ``fn`` again:
    JAX transforms both branches of a conditional (the JVP, the linearisation, vmap,
    the transpose), and a second copy of ``fn`` doubled that work at trace time (a RAW
    fit's first solver step came 4 s later, its run-time the same). A plain
    ``lax.optimization_barrier`` also traces once, but measured 10–80 % slower gradients
    (it blocks fusion in the backward pass too)."""
    shapes = jax.eval_shape(fn, operands)

    def nan(o):
        return jax.tree.map(lambda s: jnp.full(s.shape, jnp.nan, s.dtype), shapes)

    return jax.lax.cond(jnp.isnan(key), nan, fn, operands)


@functools.cache
def solver_jit_options() -> dict:
    """Keyword arguments for ``jax.jit`` / ``eqx.filter_jit`` of a solver's programs:
    those of :data:`SOLVER_CPU_OPTIONS` this jaxlib knows, where the default backend is
    a CPU (a tiny program is compiled with them once per process to find out, with each
    alone where not all are known); nothing
    elsewhere (GPUs compile otherwise) or where ``jax.jit`` takes none (an older jax)."""
    if jax.default_backend() != "cpu":
        return {}

    def compiles(options) -> bool:
        try:
            jax.jit(lambda x: x + 1, compiler_options=options).lower(
                jnp.zeros(())).compile()
        except (jax.errors.JaxRuntimeError, TypeError):
            # "No such compile option" (a jaxlib without it), or a jax whose jit takes
            # no compiler options: compiled without it
            return False
        return True

    # all at once (one compile), else each alone
    known = dict(SOLVER_CPU_OPTIONS) if compiles(SOLVER_CPU_OPTIONS) else {
        name: value for name, value in SOLVER_CPU_OPTIONS.items() if compiles({name: value})}
    return {"compiler_options": known} if known else {}
