"""Working around XLA's CPU fusion heuristics, in one place.

XLA fuses a cheap producer into every consumer that reads it. When a value feeds
several consumers (several reductions, a slice beside an FFT, an output beside the next
stage), each consumer re-evaluates it; and an expensive operation inside it (a division,
a square root, an exponential) that thereby gains several users is instead stored as a
whole array per use. On the CPU, where these arrays are large and memory is slow, this
made parts of the chain 3–10× slower than their arithmetic.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


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
