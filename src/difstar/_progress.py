"""Progress of long loops outside jit (solver and optimiser steps) on stderr: one tqdm
bar per loop that shows the step, its figures and the time left, and is gone when the
loop ends. The one place that decides how difstar draws a step-by-step progress line."""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Callable, Iterator

import jax
import numpy as np


@contextlib.contextmanager
def step_bar(label: str | None, total: int) -> Iterator[Callable[[str], None] | None]:
    """Yield ``update(text)``, which counts one step and shows ``text`` beside the bar
    (tqdm's rate and time left included); ``label`` None: yield None (quiet)."""
    if label is None:
        yield None
        return
    from tqdm.auto import tqdm

    bar = tqdm(total=total, desc=label, unit="step", leave=False, file=sys.stderr,
               dynamic_ncols=True)
    # the first step of a program not yet compiled is the silent part of a run: said
    bar.set_postfix_str("first step: tracing, compiling or loading the programs")

    def update(text: str = "") -> None:
        bar.set_postfix_str(text, refresh=False)
        bar.update(1)
        bar.refresh()  # every step drawn: a step takes far longer than drawing it

    try:
        yield update
    finally:
        bar.close()


def moved_most(before, after) -> tuple[str, float]:
    """The leaf of two like PyTrees whose largest element changed most, as
    (its path, the change); ("", 0.0) for trees without elements."""
    name, most = "", 0.0
    leaves = jax.tree_util.tree_leaves_with_path(after)
    for (path, a), b in zip(leaves, jax.tree_util.tree_leaves(before)):
        change = float(np.max(np.abs(np.asarray(a, float) - np.asarray(b, float)),
                              initial=0.0))
        if change > most:
            name, most = jax.tree_util.keystr(path, simple=True, separator="."), change
    return name, most


def ticking(callback: Callable | None, tick: Callable[[str], None], start) -> Callable:
    """A :func:`difstar.design` callback that ticks ``tick`` with the objective and the
    parameter that moved most since the last step (from ``start``), then calls
    ``callback`` (which may stop the run by returning True)."""
    last = [start]

    def each(step, params, value, aux):
        name, change = moved_most(last[0], params)
        last[0] = params
        tick(f"objective {value:.6g}, moved most: {name or '-'} ({change:.2g})")
        return callback is not None and callback(step, params, value, aux)

    return each
