"""The public PSF: :func:`psf` (fraction of power per pixel on a window, by the engine
of :mod:`._psf_engine`) and :func:`plan_psf` (its plan, made outside jit)."""

from __future__ import annotations

import collections
import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._atf import SCALINGS
from ._custom_types import Array, Float
from ._psf_engine import (
    DEFAULT_ACCURACY,
    SAMPLINGS,
    PSFPlan,
    SamplingError,
    defocus_blur,
    evaluate,
    evaluate_each,
)
from ._psf_engine import plan_psf as plan_window
from ._pupil import AbstractPupil, Polygon, RegularPolygon
from ._validate import (
    MAX_EXACT_EDGES,
    InputError,
    check_memory,
    check_psf_inputs,
    check_pupil,
    check_pupil_cost,
    check_shape,
    check_wavelength_count,
    memory_budget,
)


def _concrete_all(*xs):
    """Python floats of ``xs`` (arrays flattened), or None if any is traced."""
    out = []
    for x in xs:
        try:
            out.append(np.asarray(x, dtype=float))
        except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError,
                TypeError):
            return None
    return out


#: a wavefront's OPD at given points as one compiled program (by the wavefront's kind and
#: terms): a plan looks at concrete wavefronts, which JAX would otherwise evaluate one
#: operation at a time, compiling each on a first run (about 1 s for 8 Zernike terms)
_opd_on = eqx.filter_jit(lambda wavefront, x, y: wavefront.opd(x, y))


def _wavefront_slope(wavefront, radius: float) -> float | None:
    """Largest |∇OPD| of a wavefront over the pupil's disc (concrete; None if traced)."""
    if wavefront is None:
        return 0.0
    k = 97
    xs = np.linspace(-radius, radius, k)
    try:
        opd = np.asarray(_opd_on(wavefront, jnp.asarray(xs)[None, :], jnp.asarray(xs)[:, None]),
                         dtype=float)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
        return None
    if not np.all(np.isfinite(opd)):
        raise ValueError("difstar.psf: wavefront OPD is not finite over the pupil; check "
                         "its coefficients.")
    gy, gx = np.gradient(opd, xs[1] - xs[0])
    inside = np.hypot(*np.meshgrid(xs, xs)) <= radius
    return float(np.max(np.hypot(gx, gy)[inside]))


def plan_psf(
    pupil: AbstractPupil,
    *,
    wavelength,
    z_image,
    defocus=0.0,
    pixel_pitch: float,
    shape: Any,  # (H, W) whole numbers: _check_shape refuses the rest, naming it
    sampling: str = "pixel",
    accuracy: float | None = None,
    wavefront=None,
    scaling: str = "fresnel",
    method: str | None = None,
    max_radius: float | None = None,
) -> PSFPlan:
    """The :class:`PSFPlan` :func:`psf` would use (call it outside jit with concrete
    values and pass it as ``psf(..., plan=...)`` where the pupil's size, the wavelength or
    Δz are traced). ``max_radius`` overrides the pupil's (e.g. a bound over a design
    family). Raises :class:`SamplingError` when the accuracy target cannot be met.

    Cost is bounded before anything is allocated (``InputError``, a ``ValueError``,
    naming the setting and the fix): ``shape`` whole numbers >= 2; at most
    ``MAX_WAVELENGTHS`` (1024) wavelengths; at most ``MAX_EDGES`` (1024) edges per
    outline (polygon vertices, blades, vanes; the closed form only up to
    ``MAX_EXACT_EDGES``, 256, above which the pupil is sampled); and the memory the plan
    needs (:func:`psf_bytes`) within ``DIFSTAR_MEMORY_LIMIT`` or the device's or the
    machine's memory."""
    _check_shape(shape)
    n_lam = _check_counts(pupil, wavelength)
    return _plan(pupil, wavelength=wavelength, z_image=z_image, defocus=defocus,
                 pixel_pitch=pixel_pitch, shape=shape, sampling=sampling, accuracy=accuracy,
                 wavefront=wavefront, scaling=scaling, method=method, max_radius=max_radius,
                 n_eval=n_lam)


def _plan(pupil, *, wavelength, z_image, defocus, pixel_pitch, shape, sampling, accuracy,
          wavefront, scaling, method, max_radius, n_eval: int,
          period: float | None = None) -> PSFPlan:
    """:func:`plan_psf` for ``n_eval`` wavelengths evaluated per call (its memory
    estimate), after the counts were checked (``choose_grid`` plans one engine grid for
    every channel's wavelengths, each channel a call of its own; ``period``: its grid's,
    where ``n`` or ``padding`` set it)."""
    check_pupil_cost(pupil, "difstar.psf: pupil")
    n_lam = int(n_eval)
    if scaling not in SCALINGS:
        raise ValueError(f"scaling must be one of {SCALINGS}; got {scaling!r}.")
    if sampling not in SAMPLINGS:
        raise ValueError(f"difstar.psf: sampling must be one of {SAMPLINGS}; got {sampling!r}.")
    acc = DEFAULT_ACCURACY if accuracy is None else float(accuracy)
    if not (math.isfinite(acc) and 1e-7 <= acc < 1):
        raise ValueError(
            f"difstar.psf: accuracy must be a relative RMS error in [1e-7, 1); got {accuracy!r}.")
    h, w = _check_shape(shape)
    edges = _check_output_memory(pupil, (h, w), n_lam)
    vals = _concrete_all(pupil.max_radius() if max_radius is None else max_radius,
                         wavelength, z_image, defocus, pixel_pitch)
    if vals is None:
        raise ValueError(
            "difstar.psf: the pupil's size, the wavelength, z_image, defocus or the pitch is "
            "traced (inside jit or grad), so the sampling cannot be planned there: make the "
            "plan outside with plan = difstar.plan_psf(pupil, ...) (concrete values, "
            "max_radius= a bound if the pupil's size varies) and pass psf(..., plan=plan).")
    r, lams, z_r, dz, p = vals
    _check_inputs(pupil, lams=lams, z_r=z_r, p=p, r=float(r), dz=dz)
    r, z_r, dz, p = float(r), float(z_r), float(dz), float(p)
    slope = _wavefront_slope(wavefront, r)
    if slope is None:
        raise ValueError("difstar.psf: the wavefront is traced; pass plan=difstar.plan_psf(...) "
                         "made with concrete coefficients of about the same size.")
    exact_ok = isinstance(pupil, (Polygon, RegularPolygon)) and wavefront is None
    if exact_ok and edges > MAX_EXACT_EDGES:  # the closed form's cost grows with them
        if method == "exact":
            raise InputError(
                f"difstar.psf: method='exact' with {edges} edges; the closed form takes at "
                f"most {MAX_EXACT_EDGES} (its compile time and memory grow with each edge); "
                "leave method unset or use method='mft' (a sampled pupil).")
        exact_ok = False
    plan = plan_window(pupil_radius=r, wavelengths=lams.ravel(), z_image=z_r, defocus=dz,
                       pixel_pitch=p, shape=(h, w), sampling=sampling, accuracy=acc,
                       exact_ok=exact_ok, wavefront_slope=slope, scaling=scaling,
                       method=method, period=period)
    _check_cost(plan, (h, w), acc, p)
    check_memory_of(plan, (h, w), n_lam, edges, p)
    return plan


def _check_shape(shape) -> tuple[int, int]:
    """(H, W) whole numbers >= 2 (8.5 is refused, not truncated), naming ``shape``."""
    return check_shape(shape, "difstar.psf: shape", least=2)


def _check_counts(pupil, wavelength) -> int:
    """The wavelengths' count (static: works on tracers), refused above
    ``MAX_WAVELENGTHS``, and the pupil's outlines' edges, above ``MAX_EDGES``."""
    n_lam = math.prod(np.shape(wavelength))
    check_wavelength_count(n_lam, "difstar.psf: wavelength")
    check_pupil_cost(pupil, "difstar.psf: pupil")
    return n_lam


def _bytes(real: bool = True) -> int:
    """Bytes of one real (or complex) element in the precision JAX computes in."""
    item = 8 if jax.config.jax_enable_x64 else 4
    return item if real else 2 * item


def _edges(pupil) -> int:
    """Straight edges of a polygonal pupil (the closed form's per-edge planes); 0 else."""
    if isinstance(pupil, RegularPolygon):
        return int(pupil.n)
    if isinstance(pupil, Polygon):
        return int(np.shape(pupil.vertices)[0])
    return 0


def _check_output_memory(pupil, shape, n_lam) -> int:
    """Before planning: the windows alone (one per wavelength, stacked) must fit."""
    h, w = shape
    need = (n_lam + 1) * h * w * _bytes()
    check_memory(need, where="difstar.psf",
                 what=f"the {h} x {w} px window alone ({n_lam} wavelength(s))",
                 fix="use a much smaller shape" + (" or fewer wavelengths." if n_lam > 1
                                                    else "."))
    return _edges(pupil)


def psf_bytes(plan: PSFPlan, shape, n_wavelengths: int, edges: int, pixel_pitch: float,
              pupils: int = 1) -> int:
    """Lower estimate of the bytes :func:`psf` holds at once for this plan: the stacked
    windows of every wavelength, and one wavelength's working arrays: the closed form's
    plane pair per vertex (``_mft._edge_sum`` holds them together), or the sampled
    pupil (× its sub-cells; ``pupils`` of them at once, :func:`psf_each`) and the
    transform's matrices or FFT passes."""
    r, c = _bytes(), _bytes(real=False)
    h, w = shape
    nodes = plan.nodes
    pts = h * w * nodes**2
    need = n_wavelengths * h * w * r + 2 * pts * r
    if plan.method == "exact":
        return need + pts * r * 2 * max(int(edges), 3)
    m = plan.pupil_window
    need += pupils * ((m * plan.subcells) ** 2 * (3 * r + c) + m * m * c)
    if plan.method == "mft":
        return need + pts * c + m * (h + w) * nodes * c + m * min(h, w) * nodes * c
    n = max(1, round(plan.period / pixel_pitch))
    # the first pass holds every column node's (m, n) transform, the second one row
    # node's over every column node (W, n)
    return need + nodes * m * n * c + nodes * m * w * c + nodes * w * n * c + pts * r


def check_memory_of(plan: PSFPlan, shape, n_wavelengths: int, edges: int,
                    pixel_pitch: float, pupils: int = 1) -> None:
    """:class:`~difstar._validate.InputError` when :func:`psf_bytes` exceeds the memory
    budget (``DIFSTAR_MEMORY_LIMIT``, else the device's or the machine's memory)."""
    need = psf_bytes(plan, shape, n_wavelengths, edges, pixel_pitch, pupils)
    budget = memory_budget()
    if need <= budget:
        return
    h, w = shape
    scale = math.sqrt(budget / need)
    fit_h, fit_w = max(2, int(h * scale)), max(2, int(w * scale))
    how = (f"the closed form, {edges} edges" if plan.method == "exact" else
           f"{plan.method}, a {plan.pupil_window} x {plan.pupil_window} pupil grid"
           + (f" x {plan.subcells}² sub-cells" if plan.subcells > 1 else ""))
    fixes = [f"use a smaller shape (about {fit_h} x {fit_w} px may fit)"]
    if plan.nodes > 1:
        fixes.append(f"sampling='point' (this plan integrates each pixel on {plan.nodes}² "
                     "nodes)")
    if n_wavelengths > 1:
        fixes.append("fewer wavelengths")
    if plan.method != "exact":
        fixes.append("a larger accuracy")
    check_memory(need, where="difstar.psf",
                 what=f"the {h} x {w} px window ({how}, {n_wavelengths} wavelength(s))",
                 fix=", ".join(fixes) + ".")


def _check_inputs(pupil, *, lams, z_r, p, r, dz):
    check_psf_inputs(wavelength=lams, z_image=z_r, pixel_pitch=p, defocus=dz)
    check_pupil(pupil)
    if not (math.isfinite(r) and r > 0):
        raise ValueError(f"difstar.psf: the pupil's max_radius must be finite and > 0; got {r}.")


#: Largest number of complex samples one window may hold (about 2.4 GB in complex128).
_MAX_SAMPLES = 1.5e8


def _check_cost(plan: PSFPlan, shape, accuracy, pixel_pitch):
    if plan.method == "exact":
        return
    h, w = shape
    pupil = (plan.pupil_window * plan.subcells) ** 2
    out = h * w * plan.nodes**2
    if plan.method == "fft":  # the first pass holds the pupil's rows × the period
        n = round(plan.period / pixel_pitch)
        out = max(out, plan.pupil_window * n * plan.nodes)
    if max(pupil, out) > _MAX_SAMPLES:
        raise SamplingError(
            f"difstar.psf: the accuracy target {accuracy:g} needs a pupil of "
            f"{plan.pupil_window} x {plan.pupil_window} samples with {plan.subcells}² sub-cells "
            f"and {plan.nodes}² nodes per pixel on {h} x {w} pixels, over the memory limit; "
            f"use a larger accuracy (e.g. {min(0.5, accuracy * 10):g}), a smaller window, or "
            f"sampling='point'.")


def psf(
    pupil: AbstractPupil,
    *,
    wavelength,
    z_image,
    defocus=0.0,
    pixel_pitch: float,
    shape: Any,  # (H, W) whole numbers: _check_shape refuses the rest, naming it
    sampling: str = "pixel",
    accuracy: float | None = None,
    wavefront=None,
    weights=None,
    scaling: str = "fresnel",
    method: str | None = None,
    plan: PSFPlan | None = None,
    oversample: int | None = None,
    check: bool = True,
) -> Float[Array, "h w"]:
    """The PSF on an (H, W) pixel window: each value the fraction of the power through
    the pupil that lands on that pixel. Summed over the infinite plane it is 1; over a
    window it is ≤ 1 (the light beyond the window is not folded in).

    The window is centred on the optical axis at pixel (H//2, W//2); rows run down the
    image and y points up: row k is at y = −(k − H//2)·p, column k at x = (k − W//2)·p.
    Pupil vertices are counter-clockwise with y up, a rotation is counter-clockwise.

    Its cost is checked before anything is allocated or compiled, as :func:`plan_psf`
    says (the shape, the wavelengths' count, the pupil's edges, the memory against
    ``DIFSTAR_MEMORY_LIMIT`` or the machine's): an ``InputError`` (a ``ValueError``)
    names the setting and the fix. The checks use static shapes, so they also run
    under jit and grad.

    Args:
        pupil: exit-pupil shape (metres).
        wavelength: metres; an array with ``weights`` gives the weighted sum (weights
            normalised to 1) of the monochromatic PSFs on the same pixels.
        z_image: exit pupil to sensor, z_R (metres).
        defocus: Δz, sensor minus in-focus image plane (metres); the in-focus image is at
            z_i = z_R − Δz.
        pixel_pitch: p, metres.
        shape: (H, W) pixels.
        sampling: "pixel" (default): the intensity integrated over each pixel's square
            (fill factor 1), by a Gauss–Legendre rule whose error is bounded below the
            target (the intensity is band-limited); "point": the intensity at the pixel's
            centre × the pixel's area.
        accuracy: relative RMS error over the window the engine must meet (default
            1e-3); the method and its sampling are chosen for it (``plan_psf``).
        wavefront: an optical path difference added to the pupil, e.g.
            :class:`difstar.Zernike` (anything with ``opd(x, y)`` in metres).
        scaling: "fresnel" (default) or "paper" (the paper's Eq. 2–4, pupil scaled by λ z_i).
        method: None (chosen), "exact" (in-focus polygons, closed form) or "mft"
            (sampled pupil, matrix DFT to the window).
        plan: a :class:`PSFPlan` from :func:`plan_psf`, needed where the pupil's size,
            the wavelength or Δz are traced (inside jit or grad).
        oversample: ignored (pixel integration no longer needs it); kept so that older
            calls run.
        check: kept for older calls; the plan always meets the accuracy or raises
            :class:`SamplingError`.
    """
    del check
    if not isinstance(pupil, AbstractPupil):
        raise TypeError(f"difstar.psf: pupil must be a difstar pupil (e.g. "
                        f"difstar.RegularPolygon(7, 1e-3), difstar.Circle(1e-3), "
                        f"difstar.Polygon(vertices), or a builder of difstar.pupils); got "
                        f"{type(pupil).__name__}.")
    if oversample is not None and not (isinstance(oversample, (int, np.integer))
                                       and oversample >= 1):
        raise ValueError(f"oversample must be an integer >= 1; got {oversample!r}.")
    h, w = _check_shape(shape)
    n_lam = _check_counts(pupil, wavelength)
    if plan is None:
        # a plain call with concrete values: the plan and the compiled program are made
        # once and reused by every later call that needs the same (see _plain_call)
        key = _plain_key(pupil, wavelength, weights, z_image, defocus, pixel_pitch,
                         wavefront, (h, w), sampling, accuracy, scaling, method)
        if key is not None:
            return _plain_call(key, pupil, wavelength=wavelength, weights=weights,
                               z_image=z_image, defocus=defocus, pixel_pitch=pixel_pitch,
                               shape=(h, w), sampling=sampling, accuracy=accuracy,
                               wavefront=wavefront, scaling=scaling, method=method)
        plan = plan_psf(pupil, wavelength=wavelength, z_image=z_image, defocus=defocus,
                        pixel_pitch=pixel_pitch, shape=(h, w), sampling=sampling,
                        accuracy=accuracy, wavefront=wavefront, scaling=scaling,
                        method=method)
    else:
        _check_given_plan(plan, pupil, (h, w), n_lam, pixel_pitch, z_image, defocus)
    lam, wts = _wavelengths_and_weights(wavelength, weights)
    return _evaluate_all(pupil, lam, wts, z_image, defocus, wavefront, plan=plan,
                         shape=(h, w), pixel_pitch=float(pixel_pitch), scaling=scaling)


def _check_given_plan(plan, pupil, shape, n_lam: int, pixel_pitch, z_image, defocus,
                      pupils: int = 1) -> None:
    """A plan given to :func:`psf` (or :func:`psf_each`, ``pupils`` sampled at once),
    made for another window or wavelengths: its type, and its cost and period here,
    before any work."""
    if not isinstance(plan, PSFPlan):
        raise TypeError(f"difstar.psf: plan must be a PSFPlan from difstar.plan_psf; got "
                        f"{type(plan).__name__}.")
    edges = _check_output_memory(pupil, shape, n_lam)
    if plan.method == "exact" and edges > MAX_EXACT_EDGES:
        raise InputError(
            f"difstar.psf: plan.method 'exact' with {edges} edges; the closed form takes "
            f"at most {MAX_EXACT_EDGES}; make the plan with difstar.plan_psf for this "
            "pupil (it samples the pupil instead).")
    check_memory_of(plan, shape, n_lam, edges, float(pixel_pitch), pupils)
    _check_plan_period(plan, pupil, shape, float(pixel_pitch), z_image, defocus)


def psf_each(pupil: AbstractPupil, wavelengths, *, z_image, defocus=0.0, pixel_pitch,
             shape, plan: PSFPlan, wavefront=None, scaling: str = "fresnel"):
    """The window of each wavelength of ``wavelengths`` (C,), (C, h, w): each the window
    ``psf(pupil, wavelength=wavelengths[c], ..., plan=plan)`` gives, not weighted
    together. The pupil's coverage of every wavelength's grid is made at once (its
    raster's many small operations traced and compiled once, not C times: the
    simulation's colour channels, a fit's Jacobian), then each wavelength's phases and
    transform. ``plan`` is required and checked as :func:`psf` checks a given plan."""
    h, w = _check_shape(shape)
    lam = jnp.asarray(wavelengths, dtype=jax.dtypes.canonicalize_dtype(np.float64))
    if lam.ndim != 1 or lam.size < 1:
        raise ValueError(f"psf_each: wavelengths must be a 1-D array; got shape "
                         f"{lam.shape}.")
    n = int(lam.size)
    _check_given_plan(plan, pupil, (h, w), n, pixel_pitch, z_image, defocus, pupils=n)
    return evaluate_each(pupil, lam, z_image=z_image, defocus=defocus,
                         pixel_pitch=float(pixel_pitch), shape=(h, w), scaling=scaling,
                         wavefront=wavefront, plan=plan)


def _check_plan_period(plan: PSFPlan, pupil, shape, pixel_pitch: float, z_image,
                       defocus) -> None:
    """A plan given to :func:`psf` whose period is shorter than the window plus the
    defocus blur (where the pupil's size, z_image and Δz are concrete) refused: the
    field is periodic with the plan's period, so a wider window (or blur) wraps onto
    itself, silently. The plan's own rule adds a guard band on top (a plan made for a
    smaller window may still fall short of the accuracy it was made for)."""
    if plan.method == "exact":
        return
    extent = max(shape) * pixel_pitch
    vals = _concrete_all(pupil.max_radius(), z_image, defocus)
    blur = 0.0
    if vals is not None and plan.use_defocus:
        r, z_r = float(np.max(vals[0])), float(np.min(vals[1]))
        blur = max(defocus_blur(r, z_r, float(d)) for d in vals[2].ravel())  # the widest
    if plan.period < (extent + blur) * (1 - 1e-9):
        raise InputError(
            f"difstar.psf: the plan's period ({plan.period:.4g} m) is shorter than this "
            f"window ({max(shape)} px of {pixel_pitch:.4g} m = {extent:.4g} m)"
            + (f" and its defocus blur ({blur:.4g} m)" if blur else "")
            + ": the PSF would wrap onto itself. Make the plan for this window: "
            f"difstar.plan_psf(..., shape={tuple(shape)}, pixel_pitch={pixel_pitch:.4g}).")


def _wavelengths_and_weights(wavelength, weights, xp=jnp):
    """(λ as an array, normalised weights or None for one wavelength), checked; ``xp``
    NumPy for concrete inputs (a plain call: no eager JAX operation to dispatch)."""
    dtype = jax.dtypes.canonicalize_dtype(np.float64)
    lam = xp.asarray(wavelength, dtype=dtype)
    if lam.ndim == 0:
        if weights is not None:
            raise ValueError("difstar.psf: weights need an array of wavelengths.")
        return lam, None
    if lam.ndim != 1 or lam.size < 1:
        raise ValueError(f"difstar.psf: wavelength must be a number or a 1-D array; got "
                         f"shape {lam.shape}.")
    wts = xp.ones_like(lam) if weights is None else xp.asarray(weights, dtype=dtype)
    if wts.shape != lam.shape:
        raise ValueError(f"difstar.psf: weights must have the wavelengths' shape {lam.shape}; "
                         f"got {wts.shape}.")
    wv = _concrete_all(wts)
    if wv is not None and (not np.all(np.isfinite(wv[0])) or np.any(wv[0] < 0)
                           or not np.sum(wv[0]) > 0):
        raise ValueError("difstar.psf: weights must be finite, >= 0 and not all 0.")
    return lam, wts / xp.sum(wts)


def _evaluate_all(pupil, lam, wts, z_image, defocus, wavefront, *, plan, shape,
                  pixel_pitch: float, scaling):
    """The window for λ (a number, or an array weighted by ``wts``) by ``plan``."""

    def one(lam1):
        return evaluate(pupil, lam1, z_image=z_image, defocus=defocus,
                        pixel_pitch=pixel_pitch, shape=shape, scaling=scaling,
                        wavefront=wavefront, plan=plan)

    if wts is None:
        return one(lam)
    # one wavelength at a time (lax.map): the memory of one, whatever their number
    return jnp.einsum("l,lhw->hw", wts, jax.lax.map(one, lam))


# --- plain calls: the plan and the compiled program made once --------------------------

#: the plans of the latest plain calls, by their concrete inputs (least recently used
#: dropped first); the compiled programs are equinox's, by the plan and the inputs' shapes
_PLANS: collections.OrderedDict = collections.OrderedDict()
_PLANS_KEPT = 64


def _leaf_key(x):
    """A hashable stand-in for one concrete leaf, or None (a tracer, or unknown)."""
    if isinstance(x, jax.core.Tracer):
        return None
    if isinstance(x, (bool, int, float, complex, str, type(None), np.generic)):
        return (type(x).__name__, x)
    if isinstance(x, (np.ndarray, jax.Array)):
        a = np.asarray(x)
        return (a.dtype.str, a.shape, a.tobytes())
    return None


def _plain_key(pupil, wavelength, weights, z_image, defocus, pixel_pitch, wavefront,
               *static):
    """The key of a plain call's plan: every input's concrete value and the pytrees'
    structure; None when anything is traced (inside jit, grad or vmap: the caller passes
    a plan there) or cannot be keyed."""
    try:
        leaves, treedef = jax.tree_util.tree_flatten(
            (pupil, wavelength, weights, z_image, defocus, pixel_pitch, wavefront))
        keys = tuple(_leaf_key(x) for x in leaves)
        if any(k is None for k in keys):
            return None
        key = (treedef, keys, static, jax.config.jax_enable_x64)
        hash(key)
    except (TypeError, ValueError):
        return None
    return key


@eqx.filter_jit
def _compiled(pupil, lam, wts, z_image, defocus, wavefront, *, plan, shape, pixel_pitch,
              scaling):
    return _evaluate_all(pupil, lam, wts, z_image, defocus, wavefront, plan=plan,
                         shape=shape, pixel_pitch=pixel_pitch, scaling=scaling)


def _plain_call(key, pupil, *, wavelength, weights, z_image, defocus, pixel_pitch, shape,
                sampling, accuracy, wavefront, scaling, method):
    """:func:`psf` with concrete inputs: the plan from the cache (or made and kept), then
    one compiled program for the whole window (compiled once per plan and shapes)."""
    plan = _PLANS.get(key)
    if plan is None:
        plan = plan_psf(pupil, wavelength=wavelength, z_image=z_image, defocus=defocus,
                        pixel_pitch=pixel_pitch, shape=shape, sampling=sampling,
                        accuracy=accuracy, wavefront=wavefront, scaling=scaling,
                        method=method)
        _PLANS[key] = plan
        while len(_PLANS) > _PLANS_KEPT:
            _PLANS.popitem(last=False)
    else:
        _PLANS.move_to_end(key)
    # NumPy for the concrete numbers: the compiled program takes them as they are (an
    # eager jnp conversion is a dispatched operation each, about 0.2 ms)
    lam, wts = _wavelengths_and_weights(wavelength, weights, xp=np)
    dtype = lam.dtype
    return _compiled(pupil, lam, wts, np.asarray(z_image, dtype),
                     np.asarray(defocus, dtype), wavefront, plan=plan, shape=tuple(shape),
                     pixel_pitch=float(pixel_pitch), scaling=scaling)
