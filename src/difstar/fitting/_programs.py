"""The compiled programs an image fit keeps between its stages: a stage run again (a
repeat's rounds, a hop's tries, the next star of a field with the same window) finds
its solver, χ² and Jacobian programs here instead of tracing and compiling them again.

A program is keyed by everything its trace depends on besides its arguments
(:func:`trace_key`): the model's construction and options, each capture's window shape,
exposure and light, each target's kind, the PSF plans, and what the caller adds (the
free parameters and their bounds). The values, σ, masks, spike windows and the solver's
tolerances are the programs' arguments, so they may change between calls.

Memory is bounded by design: at most :data:`MAX_PROGRAMS` programs are kept; when one
more is needed, all are dropped together with JAX's own caches (which keep a program's
constants after its function is gone)."""

from __future__ import annotations

import gc
from collections import OrderedDict
from collections.abc import Callable, Hashable

import jax
import numpy as np

#: How many compiled programs the process keeps (an automatic JWST fit's re-run stages
#: use four: the spike stage's solver and Jacobian, the whole-image solver and χ²).
MAX_PROGRAMS = 16

_PROGRAMS: OrderedDict = OrderedDict()


def program(key: Hashable, make: Callable, keep=()):
    """The program cached under ``key``; on a miss ``make()`` builds it. ``keep``: the
    objects whose ``id`` the key holds, kept alive with the program so that no other
    object can take their ``id`` while the key is in use."""
    hit = _PROGRAMS.get(key)
    if hit is not None:
        _PROGRAMS.move_to_end(key)
        return hit[0]
    if len(_PROGRAMS) >= MAX_PROGRAMS:
        release_programs()
    made = make()
    _PROGRAMS[key] = (made, keep)
    return made


def release_programs() -> None:
    """Drop every kept program and JAX's compiled programs and traces (their constants
    stay in JAX's caches after the functions are gone: about 0.4 GB a stage on the JWST
    star when each stage traced closures over its data)."""
    _PROGRAMS.clear()
    jax.clear_caches()
    gc.collect()


def _light_key(light):
    if light is None:
        return None
    return (tuple(np.ravel(np.asarray(light.wavelengths, float)).tolist()),
            tuple(np.ravel(np.asarray(light.weights, float)).tolist()))


def trace_key(model, datas, targets):
    """(key, keep) of what a trace of ``model`` on ``datas`` (each with its target)
    depends on besides the programs' arguments: :meth:`ImageModel.trace_key`, each
    capture's window shape, exposure and light, each target's
    :attr:`signature`, and the PSF plans (by value: all their fields are static, so
    plans made for other Zernike values that came out the same serve one program)."""
    plans = [model.plan(model.padded_shape(d.image.shape), d.light) for d in datas]
    key = (model.trace_key(),
           tuple((tuple(d.image.shape), float(d.exposure), _light_key(d.light))
                 for d in datas),
           tuple(t.signature for t in targets),
           tuple(plans))
    return key, (model.plan_cache,)


__all__ = ["MAX_PROGRAMS", "program", "release_programs", "trace_key"]
