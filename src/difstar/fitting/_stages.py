"""The checks of a fit's stages and inputs, all made before anything solves: keys,
options, scans, hops, repeats, memory."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from .._param import ForwardModel
from .._psf import _edges, psf_bytes
from .._validate import fmt_bytes, memory_budget
from ._analysis import _scan, _scan_problem, spike_target
from ._data import FitData, noise_from_residuals, reject_outliers
from ._detector import SourceImage
from ._model import ImageModel
from ._params import _PITCH, FitInputError, _finite, _whole
from ._solve import linear_names


def _keyword_names(fn, leave_out=()) -> frozenset:
    """The keyword-only arguments of ``fn``: the options a stage may give it."""
    import inspect

    return frozenset(q for q, p in inspect.signature(fn).parameters.items()
                     if p.kind is p.KEYWORD_ONLY and q not in leave_out)

def _stage_options() -> dict:
    """A solving stage's keys, each with the options it takes (None: a value, not a
    mapping of options). Hop and repeat stages are only ``hop`` or only ``repeat``."""
    return {"free": None, "fix": None, "set": None, "half": None, "annulus": None,
            "max_steps": None, "rtol": None,
            "spikes": _keyword_names(spike_target, ("model_image",)),
            "noise_from_residuals": _keyword_names(noise_from_residuals),
            "reject": _keyword_names(reject_outliers),
            "scan": _keyword_names(_scan)}

def _check_stage_keys(si: int, st: Any) -> None:
    """Refuses a stage with a key, or an option, that the fit does not know (a typo
    would otherwise be passed over in silence), naming the known ones."""
    if not isinstance(st, Mapping):
        raise FitInputError(f"fit: stage {si} must be a mapping (e.g. {{'free': 'all'}}); "
                            f"got {st!r}.")
    for only in ("hop", "repeat"):
        if only in st and set(st) != {only}:
            raise FitInputError(f"fit: stage {si} is a {only} stage and takes no other key; "
                                f"got {sorted(set(st) - {only})}. Put them in a stage of "
                                "their own.")
    if "hop" in st or "repeat" in st:
        return
    known = _stage_options()
    bad = sorted(set(st) - set(known))
    if bad:
        raise FitInputError(f"fit: stage {si}: unknown keys {bad}; a stage takes "
                            f"{sorted(known)}, or is only 'hop' or only 'repeat'.")
    for key, opts in known.items():
        given = st.get(key)
        if opts is None or given is None:
            continue
        if not isinstance(given, Mapping):
            raise FitInputError(f"fit: stage {si}: {key} must be a mapping of options "
                                f"({sorted(opts)}); got {given!r}.")
        bad = sorted(set(given) - opts)
        if bad:
            raise FitInputError(f"fit: stage {si}: {key} has unknown options {bad}; "
                                f"known: {sorted(opts)}.")

def _check_repeat(model: ForwardModel, si: int, r: Any, n_solving: int,
                  families: Sequence[str] | None = None) -> None:
    """Refuses a ``repeat`` stage that cannot be right, naming what to fix (a
    family's name, ``families``, default the per-capture names, stands for each of its
    members)."""
    families = model.per_capture if families is None else families
    given, r = r, (r if isinstance(r, Mapping) else {})
    k, until, max_rounds = r.get("stages", 2), r.get("until"), r.get("max_rounds", 6)
    bad = [] if isinstance(until, Mapping) and until else ["until (missing or empty)"]
    if isinstance(until, Mapping):
        bad += [f"until.{q}" for q, tol in until.items()
                if q not in model.params and q not in families
                or isinstance(tol, bool)
                or not isinstance(tol, (int, float)) or not math.isfinite(tol) or tol <= 0]
    bad += sorted(set(r) - {"stages", "until", "max_rounds"})

    def count(x, lo, hi):
        return not isinstance(x, bool) and isinstance(x, int) and lo <= x <= hi

    if not count(k, 1, n_solving):
        bad.append(f"stages={k!r}")
    if not count(max_rounds, 1, 1000):
        bad.append(f"max_rounds={max_rounds!r}")
    if bad:
        raise FitInputError(f"fit: stage {si}: repeat needs 'until' (the model's parameters → "
                            "tolerances > 0, e.g. {'until': {'rotation': 0.002}}), 1 <= "
                            f"stages <= {n_solving} (the solving stages before it) and "
                            f"1 <= max_rounds <= 1000; got {given!r} "
                            f"(bad: {', '.join(bad)}).")

#: the most combinations of ``starts`` (each one a fit of the first stage)
MAX_STARTS = 1000

class _InputAt(FitInputError):
    """A refusal of a fit's input at a place: ``path`` as in a manifest (("stages", 1,
    "half"), ("starts", "x0")), ``detail`` what is wrong and the fix. The message says
    ``fit: stage 1: half: ...`` (or ``message``, where an older check's text is kept);
    :attr:`field` is the manifest's JSON path."""

    def __init__(self, path: tuple, detail: str, message: str | None = None):
        self.path, self.detail = tuple(path), detail
        if message is None:
            rest = "/".join(str(q) for q in self.path[2:])
            where = (f"stage {self.path[1]}" + (f": {rest}" if rest else "")
                     if self.path[:1] == ("stages",) and len(self.path) > 1
                     else "/".join(str(q) for q in self.path))
            message = f"fit: {where}: {detail}"
        super().__init__(message)

    @property
    def field(self) -> str:
        return "/".join(str(q) for q in self.path)

def _check_hop(model: ForwardModel, si: int, h: Any, n_solving: int) -> None:
    """A ``hop`` stage that cannot be right, refused before any fitting (the check the
    hop makes when it runs, made up front; its message)."""
    given, h = h, (h if isinstance(h, Mapping) else {})
    k = h.get("stages", 2)
    flips = h.get("flip", ())
    name = h.get("name")
    put = h.get("set", {})
    bad = sorted(str(q) for q in set(h) - {"name", "offsets", "flip", "stages", "set"})
    groups = []
    if not isinstance(flips, (list, tuple)):
        bad.append(f"flip={flips!r}")
        flips = ()
    for g in flips:
        g = (g,) if isinstance(g, str) else g
        if not isinstance(g, (list, tuple)) or not g:
            bad.append(f"{g!r} (an empty group)" if isinstance(g, (list, tuple)) else repr(g))
            continue
        groups.append(g)
    named = [q for g in groups for q in g] + (list(put) if isinstance(put, Mapping) else [])
    named += [name] if name is not None else []
    bad += [repr(q) for q in named if not isinstance(q, str) or q not in model.params]
    offsets = h.get("offsets")
    if name is not None and not (isinstance(offsets, (list, tuple)) and offsets
                                 and all(_finite(o) for o in offsets)):
        bad.append(f"offsets={offsets!r}")
    kinds = (name is not None) + bool(flips) + bool(put)
    if not isinstance(given, Mapping) or bad or kinds != 1 or not (
            _whole(k) and 1 <= k <= n_solving):
        raise _InputAt(("stages", si, "hop"), "needs one of: a parameter of the model with "
                       "offsets ({'name': ..., 'offsets': [...]}), a list of parameters to "
                       "negate, each a name or a list of names negated together ({'flip': "
                       "['z6', ['z4', 'z11']]}), or values to put ({'set': {name: value}}); "
                       f"and 1 <= stages <= {n_solving} earlier solving stages; got {given!r}"
                       + (f" (bad: {', '.join(bad)})" if bad else "") + ".")
    if put:
        try:
            _put(model, put, "set")
        except FitInputError as e:
            raise _InputAt(("stages", si, "hop", "set"), str(e).removeprefix("set: ")) from None

def _check_options(si: int, key: str, opts: Mapping) -> None:
    """A stage's ``spikes``, ``noise_from_residuals`` or ``reject`` options, checked
    before any fitting (each function checks them again when it runs)."""

    def need(ok, q, what):
        if not ok:
            raise _InputAt(("stages", si, key, q), f"must be {what}; got {opts[q]!r}.")

    def number(q, lo=None, lo_open=False, hi=None, hi_open=False, what=""):
        if q not in opts or (q == "relative" and opts[q] is None):
            return
        x = opts[q]
        ok = _finite(x) and (lo is None or (x > lo if lo_open else x >= lo)) and (
            hi is None or (x < hi if hi_open else x <= hi))
        lims = [f"{'>' if lo_open else '>='} {lo:g}" if lo is not None else "",
                f"{'<' if hi_open else '<='} {hi:g}" if hi is not None else ""]
        need(ok, q, "a finite number " + " and ".join(v for v in lims if v) + what)

    def whole(q, lo, hi=None):
        if q in opts:
            need(_whole(opts[q]) and opts[q] >= lo and (hi is None or opts[q] <= hi), q,
                 f"a whole number >= {lo}" + (f" and <= {hi}" if hi is not None else ""))

    def choice(q, allowed):
        if q in opts:
            need(isinstance(opts[q], str) and opts[q] in allowed, q, f"one of {allowed}")

    if key == "spikes":
        number("r_min", 0, what=" (pixels)")
        number("r_max", 0, True, what=" (pixels)")
        whole("n_spikes", 1, 64)
        number("half_width", 0, True, 90, what=" (degrees)")
        number("bin_width", 0, True, 90, what=" (degrees)")
        choice("directions", ("data", "model"))
        if "profiles" in opts:
            need(isinstance(opts["profiles"], bool), "profiles", "true or false")
        r_min, r_max = opts.get("r_min", 12.0), opts.get("r_max", 45.0)
        if not r_min < r_max:
            raise _InputAt(("stages", si, key, "r_max"), f"r_max {r_max:g} must exceed "
                           f"r_min {r_min:g} (the spikes' radii, pixels).")
    elif key == "noise_from_residuals":
        number("floor", 0)
        number("faint", 0, True, 1)
        whole("bins", 2, 1000)
        choice("intensity", ("model", "data"))
        number("relative", 0, True, 1, True, " (a fraction of the peak)")
    elif key == "reject":
        number("above", 0, True, what=" (in σ)")
        number("r_min", 0, what=" (pixels)")
        whole("grow", 0)
        number("relative", 0, True, 1, True, " (a fraction of the peak)")

def _check_solving_stage(model: ImageModel, datas: Sequence[FitData], si: int, st: Mapping,
                         n_cap: int) -> None:
    """A solving stage that cannot be right, refused before any fitting: unknown names,
    nothing free, a window that holds no used pixel (a negative half-width, an annulus
    inside out), solver limits out of range, a scan of too many points, options out of
    range, values to ``set`` that are not the model's or not numbers."""
    def fail(key, detail):
        raise _InputAt(("stages", si, key), detail)

    def names_of(key, given):
        if not (isinstance(given, (list, tuple)) and all(isinstance(q, str) for q in given)):
            fail(key, f"must be a list of parameter names; got {given!r}.")
        unknown = [q for q in given if q not in model.params]
        if unknown:
            fail(key, f"{unknown} are not parameters of the model; known: "
                      f"{sorted(model.params)}.")
        return model.expand(given, n_cap)

    free = st.get("free", "all")
    if free == "all":
        names = list(model.free)
    else:
        if isinstance(free, (list, tuple)) and not free:
            fail("free", "is empty: name the parameters this stage fits (or 'all').")
        names = names_of("free", free)
    fix = set(names_of("fix", st["fix"])) if st.get("fix") is not None else set()
    names = [k for k in names if k not in fix]
    bad = sorted(set(names) - set(model.free))
    if bad:
        fail("free", f"{bad} are not free parameters of the model (give them free: true, "
                     "or leave them out of the stage).")
    if not names:
        fail("free", f"nothing is free in this stage (free {free!r} minus fix "
                     f"{sorted(fix)}): free at least one of the model's free parameters "
                     f"{model.free}.")
    if "max_steps" in st and not (_whole(st["max_steps"]) and st["max_steps"] >= 1):
        fail("max_steps", f"must be a whole number >= 1; got {st['max_steps']!r}.")
    if "rtol" in st and not (_finite(st["rtol"]) and st["rtol"] > 0):
        fail("rtol", f"must be a finite number > 0; got {st['rtol']!r}.")
    half, ann = st.get("half"), st.get("annulus")
    if half is not None and not (_whole(half) and half >= 0):
        fail("half", f"must be a whole number of pixels >= 0 (the central (2 half + 1)² "
                     f"pixels) or null (the whole image); got {half!r}.")
    if ann is not None:
        if not (isinstance(ann, (list, tuple)) and len(ann) == 2 and all(map(_finite, ann))
                and 0 <= ann[0] < ann[1]):
            fail("annulus", f"must be [r_min, r_max] in pixels with 0 <= r_min < r_max; "
                            f"got {ann!r}.")
    total = 0
    for i, d in enumerate(datas):
        w = d if half is None else d.cropped(int(half))
        n_win = int(np.count_nonzero(w.mask))
        n = n_win if ann is None else int(np.count_nonzero(
            w.annulus(float(ann[0]), float(ann[1])).mask))
        if n == 0:
            fail("annulus" if ann is not None and n_win else "half",
                 f"the window (half {half}, annulus {ann}) holds no used pixel of capture "
                 f"{i} ({d.image.shape[0]} × {d.image.shape[1]} pixels, "
                 f"{int(np.count_nonzero(d.mask))} used): widen it.")
        total += n
    if total < len(names):
        fail("half" if ann is None else "annulus",
             f"the window (half {half}, annulus {ann}) holds {total} used pixels for "
             f"{len(names)} free parameters: widen it or free fewer.")
    if st.get("set") is not None:
        put = st["set"]
        if isinstance(put, Mapping):
            put = {q2: x for q, x in put.items()
                   for q2 in (model.expand([q], n_cap) if isinstance(q, str) else [q])}
        try:
            _put(model, put, "set")
        except FitInputError as e:
            fail("set", str(e).removeprefix("set: "))
    if st.get("scan") is not None:
        sc = st["scan"]
        why = _scan_problem(model, sc.get("name"), sc.get("half_range"), sc.get("step"))
        if why:
            fail("scan", why + ".")
    for key in ("spikes", "noise_from_residuals", "reject"):
        if st.get(key) is not None:
            _check_options(si, key, st[key])

def _check_fit_inputs(model: ImageModel, datas: Sequence[FitData], stages: Sequence,
                      *, starts=None, max_steps=100, rtol=1e-6) -> None:
    """Every mistake in a fit's stages and starts that can be found before any fitting
    (:func:`fit` and :func:`load_manifest` call it; ``model`` already made for the
    captures). Raises :class:`FitInputError` (an :class:`_InputAt` naming the stage and
    key)."""
    n_cap = len(datas)
    if not model.free:
        raise _InputAt(("params",), "no parameter is free; set free: true on at least one.",
                       "fit: no free parameter (set free=true on at least one).")
    if not (_whole(max_steps) and max_steps >= 1):
        raise _InputAt(("max_steps",), f"must be a whole number >= 1; got {max_steps!r}.")
    if not (_finite(rtol) and rtol > 0):
        raise _InputAt(("rtol",), f"must be a finite number > 0; got {rtol!r}.")
    if not isinstance(stages, (list, tuple)):
        raise _InputAt(("stages",), f"must be a list of stages; got {stages!r}.")
    if not stages:
        raise _InputAt(("stages",), "is empty: give one stage or more (e.g. [{'free': "
                       "'all'}]), or leave stages out.")
    n_solving = 0
    for si, st in enumerate(stages):
        try:
            _check_stage_keys(si, st)
            if st.get("repeat") is not None:
                _check_repeat(model, si, st["repeat"], n_solving)
        except _InputAt:
            raise
        except FitInputError as e:
            key = next((q for q in ("repeat", "hop") if isinstance(st, Mapping) and q in st),
                       None)
            detail = str(e).removeprefix(f"fit: stage {si}: ").removeprefix(f"fit: stage {si} ")
            raise _InputAt(("stages", si) + ((key,) if key else ()), detail, str(e)) from None
        if st.get("hop") is not None:
            _check_hop(model, si, st["hop"], n_solving)
        elif st.get("repeat") is None:
            _check_solving_stage(model, datas, si, st, n_cap)
            n_solving += 1
    if starts:
        if not isinstance(starts, Mapping):
            raise _InputAt(("starts",), f"must map parameter names to lists of start "
                           f"values; got {starts!r}.")
        combos = 1
        for k, vs in starts.items():
            if k not in model.params:
                raise _InputAt(("starts", k), f"not a parameter of the model; known: "
                               f"{sorted(model.params)}.")
            if not (isinstance(vs, (list, tuple)) and vs and all(_finite(x) for x in vs)):
                raise _InputAt(("starts", k), f"must be a non-empty list of finite numbers; "
                               f"got {vs!r}.")
            combos *= len(vs)
        if combos > MAX_STARTS:
            raise _InputAt(("starts",), f"{combos} combinations of start values, each a fit "
                           f"of the first stage; at most {MAX_STARTS}: give fewer.")
    if isinstance(model.source, SourceImage):  # inside every padded window
        sh, sw = model.source.shape
        for si, st in enumerate(stages):
            half = st.get("half") if st.get("hop") is None and st.get("repeat") is None \
                else None
            for d in datas:
                hp, wp = model.padded_shape(
                    d.image.shape if half is None else d.cropped(int(half)).image.shape)
                if sh > hp or sw > wp:
                    raise _InputAt(("source", "image"), f"the source image ({sh} × {sw}) is "
                                   f"larger than stage {si}'s padded window ({hp} × {wp}); "
                                   "crop it or raise detector pad.")
    _check_fit_memory(model, datas)

#: the fitted Jacobian's memory over :func:`~difstar._psf.psf_bytes` per free parameter
#: (jacfwd carries every intermediate once per parameter, and XLA keeps more): calibrated
#: on the Spitzer campaign (fit/spitzer-irac: 81² pixels, 17 free, measured peak 9.4 GB
#: against psf_bytes × 19 = 0.47 GB), rounded down so that the estimate stays a lower one
_JACOBIAN_FACTOR = 8
#: captures fitted together (the stars of a field): the solver holds the Jacobian,
#: every capture's pixels by each of its columns (float64), about this many times at
#: once, and each capture's own linearisation about ``_PER_CAPTURE_FACTOR`` × its
#: window's psf_bytes. The columns: every free parameter where the stars' windows
#: differ or a closed-form flux is shared (optimistix's QR on the dense Jacobian); only
#: the compressed directions (shared + one star's own) where the Jacobian has its block
#: structure (difstar._lm.with_batched_jacobian keeps them as they are). Measured on
#: the Spitzer star with 16, 40, 80 and 120 copies (``python benchmarks/joint_stars.py
#: --stars 16,40,80,120``): peak RSS 0.72, 0.86, 1.17 and 1.48 GB, about 6–8 MB a star
#: (psf_bytes 3.0 MB, 17 directions of 6561 pixels 0.9 MB) above the process's 0.6 GB;
#: the estimate 0.56, 0.71, 0.97 and 1.23 GB. Before the compressed directions were
#: kept (the P columns held, 3befa96): 0.77, 1.15, 2.14 and 3.56 GB, about 0.64 copies
#: of those Jacobians; rounded down, so that the estimate stays a lower one
_JACOBIAN_COPIES = 0.5
_PER_CAPTURE_FACTOR = 2


def fit_memory(model: ImageModel, datas: Sequence[FitData]) -> float:
    """A lower estimate of a fit's peak memory (bytes) from its shapes alone: the
    Jacobian's columns through the chain on the largest capture's padded window and,
    for captures fitted together, each capture's linearisation and the Jacobian the
    solver holds (every capture's pixels by its compressed directions where the stars'
    Jacobian has its block structure, else by every free parameter, which grows as the
    square of the captures). 0 where the window cannot be planned (the fit's first
    step reports that, named)."""
    return _memory_of_first(model, datas)(len(datas))


def _memory_of_first(model: ImageModel, datas: Sequence[FitData]):
    """:func:`fit_memory` of the first m of ``datas`` fitted together, as a function of
    m (the window planned once)."""
    h, w = max((d.image.shape for d in datas), key=lambda s: s[0] * s[1])
    shape = model.padded_shape((h, w))
    try:
        plan = model.plan(shape)
        one = psf_bytes(plan, shape, 1, _edges(model.concrete_pupil()), _PITCH)
    except (ValueError, TypeError):
        return lambda m: 0.0
    free = list(model.free)
    # each capture's own parameters (name@i) and the shared ones; several captures' own
    # columns share their directions (the Jacobian compressed)
    shared = sum("@" not in q for q in free)
    own = sum(q.endswith("@0") for q in free)
    pixels = np.cumsum([int(d.image.size) for d in datas])
    window = one * (2 if model.has_incoherent else 1)
    # the block structure (each star's columns zero on the other stars' pixels, the
    # solver then holding the compressed directions only): equal windows, and no shared
    # flux or background taken in closed form (it would couple the stars' residuals)
    coupled = any("@" not in q for q in linear_names(model, free))
    blocked = bool(own) and not coupled and len({d.image.shape for d in datas}) == 1

    def need(m: int) -> float:
        params = shared + own * m if model.per_capture else len(free)
        out = _JACOBIAN_FACTOR * ((params if m == 1 else shared + own) + 2) * window
        if m > 1:
            columns = shared + own if blocked else params
            out += (_PER_CAPTURE_FACTOR * one * m
                    + _JACOBIAN_COPIES * 8 * int(pixels[m - 1]) * columns)
        return float(out)

    return need


def _check_fit_memory(model: ImageModel, datas: Sequence[FitData]) -> None:
    """Refuse (before any compile) a fit that cannot fit in memory (:func:`fit_memory`,
    a lower estimate, so a refused fit would certainly not have fitted)."""
    need_of = _memory_of_first(model, datas)
    n = len(datas)
    need = need_of(n)
    budget = memory_budget()
    if need <= budget:
        return
    h, w = max((d.image.shape for d in datas), key=lambda s: s[0] * s[1])
    shape = model.padded_shape((h, w))
    k = len(model.free)
    if n > 1:
        fits = max((m for m in range(1, n) if need_of(m) <= budget), default=0)
        fix = (f"at most {fits} of them together, " if fits > 1 else "them one by one, ")
        raise _InputAt(
            ("data",), f"fitting {n} captures together ({k} free parameters, "
            f"{sum(int(d.image.size) for d in datas)} pixels) needs at least "
            f"{fmt_bytes(need)} of memory, more than the {fmt_bytes(budget)} available "
            "(DIFSTAR_MEMORY_LIMIT overrides): the solver holds each capture's "
            "linearisation and every pixel by the Jacobian's columns (by every free "
            "parameter where the windows differ in size, which grows as the square of "
            f"the captures); fit {fix}smaller windows (roi), or fewer parameters per "
            "capture (per_capture).",
            f"fit: {n} captures together need at least {fmt_bytes(need)} of memory, more "
            f"than the {fmt_bytes(budget)} available (DIFSTAR_MEMORY_LIMIT overrides); fit "
            f"{fix}smaller windows (roi) or fewer per_capture parameters.")
    side = max(8, int(min(h, w) * math.sqrt(budget / need)))
    raise _InputAt(
        ("data",), f"fitting {k} free parameters on the {h} × {w} pixel window (padded to "
        f"{shape[0]} × {shape[1]}) needs at least {fmt_bytes(need)} of memory, more than "
        f"the {fmt_bytes(budget)} available (DIFSTAR_MEMORY_LIMIT overrides); give a "
        f"smaller roi (about {side} × {side} may fit), fewer free parameters, or a "
        "larger accuracy.", f"fit: the Jacobian needs at least {fmt_bytes(need)}, more "
        f"than the {fmt_bytes(budget)} available; fit a smaller window (roi) or fewer "
        "free parameters.")


def _put(model: ForwardModel, put: Mapping[str, Any], where: str) -> dict[str, float]:
    """``put`` (name → value) checked against ``model`` (known names, finite numbers)
    and kept inside each parameter's bounds."""
    if not isinstance(put, Mapping) or not put:
        raise FitInputError(f"{where}: needs a non-empty mapping of parameter names to "
                            f"values; got {put!r}.")
    out = {}
    for q, x in put.items():
        if q not in model.params:
            raise FitInputError(f"{where}: unknown parameter {q!r}; known: "
                                f"{sorted(model.params)}.")
        if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
            raise FitInputError(f"{where}: {q} must be a finite number; got {x!r}.")
        p = model.params[q]
        v = float(x) if p.bounds is None else np.clip(float(x), *p.bounds)
        out[q] = float(v) if np.ndim(v) == 0 else v  # (a RAW fit's per-channel bounds)
    return out
