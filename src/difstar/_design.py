"""Aperture design: image-space objectives, constraints and an optimiser loop.

A design study is four things:

1. **parameters** — any PyTree of arrays (an equinox Module); for irises,
   :class:`IrisParams` (blade curvature and per-vertex deviations) with the static
   :class:`IrisFamily` (blade count, open area) that turns them into a pupil;
2. an **objective** — a function of the parameters that builds the pupil, predicts the
   image with :func:`difstar.psf` (or :func:`difstar.simulate`) and scores it with the
   image-space measures of :mod:`difstar._design_measures` (:func:`spike_energy`,
   :func:`core_energy`, :func:`spike_length`, :func:`angular_profile`,
   :func:`bokeh_nonuniformity`, :func:`image_mismatch`);
3. **constraints** — reparametrisations, not penalties: a fixed open area by setting the
   circumradius analytically (:func:`difstar.curved_iris_from_area`), bounds (convexity,
   blade curvature) by a smooth map from unconstrained values (:class:`Box`), the blade
   count static;
4. an **optimiser** — an optax gradient transformation (default Adam) on the
   unconstrained values, an optimistix minimiser, or the bound-constrained quasi-Newton
   :class:`LBFGSB` (``optimiser="lbfgsb"``) on the bounded parameters themselves, run by
   :func:`design`, which returns the history. (Image angles, radii: see the measures.)
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._custom_types import Array, Float
from ._design_measures import Real
from ._psf import plan_psf, psf
from .pupils import AbstractPupil, CurvedIris, curved_iris_from_area

# --- PSFs for a design ---------------------------------------------------------------------


class PSFSetup(eqx.Module):
    """How a design's PSFs are predicted (monochromatic, through :func:`difstar.psf`).

    wavelength: metres. z_focus: exit pupil to the in-focus image, metres (the focal
    length for a lens focused at infinity with pupil magnification 1). pixel_pitch:
    metres. shape: (H, W) pixels. oversample: no longer used (pixels are integrated
    exactly). defocus: Δz of the defocused-highlight (bokeh) PSF, metres; defocus_shape:
    its (H, W) (the geometric blur must fit inside). max_radius: a bound on the design's
    pupil radius (metres), which plans the PSF for traced pupils (e.g.
    ``IrisFamily.radius_bound()``). accuracy: the PSF's target (default
    :data:`difstar.psf`'s).
    All static: they fix shapes or are plain numbers of the study.
    """

    wavelength: Real = eqx.field(static=True)
    z_focus: Real = eqx.field(static=True)
    pixel_pitch: Real = eqx.field(static=True)
    shape: tuple[int, int] = eqx.field(static=True)
    oversample: int = eqx.field(static=True, default=1)
    defocus: Real = eqx.field(static=True, default=0.0)
    defocus_shape: tuple[int, int] | None = eqx.field(static=True, default=None)
    max_radius: Real | None = eqx.field(static=True, default=None)
    accuracy: Real | None = eqx.field(static=True, default=None)

    def _psf(self, pupil, *, z_image, defocus, shape):
        """:func:`difstar.psf` planned for a pupil up to ``max_radius`` (metres: the
        design's pupils are traced, so the plan needs a concrete bound on their size)."""
        kw = dict(wavelength=self.wavelength, z_image=z_image, defocus=defocus,
                  pixel_pitch=self.pixel_pitch, shape=shape, accuracy=self.accuracy)
        plan = None
        if self.max_radius is not None:
            plan = plan_psf(pupil, max_radius=self.max_radius, **kw)
        return psf(pupil, plan=plan, **kw)

    def focused(self, pupil: AbstractPupil) -> Float[Array, "h w"]:
        """The in-focus PSF (fraction of the pupil's power per pixel)."""
        return self._psf(pupil, z_image=self.z_focus, defocus=0.0, shape=self.shape)

    def defocused(self, pupil: AbstractPupil) -> Float[Array, "h w"]:
        """The PSF with the sensor ``defocus`` behind the in-focus image (unit sum)."""
        if self.defocus == 0:
            raise ValueError("PSFSetup.defocus is 0; give a defocus (metres) for bokeh.")
        return self._psf(pupil, z_image=self.z_focus + self.defocus, defocus=self.defocus,
                         shape=self.defocus_shape or self.shape)

    def blur_radius(self, area: Real) -> float:
        """Geometric blur radius (pixels) of a pupil of open ``area`` (m²), taken as the
        area-equivalent disc: r_eq Δz / z_focus / pixel_pitch."""
        return math.sqrt(area / math.pi) * abs(self.defocus) / self.z_focus / self.pixel_pitch

    def airy_scale(self, area: Real) -> float:
        """λ N in pixels for the area-equivalent f-number N = z_focus / (2 r_eq)."""
        n_w = self.z_focus / (2 * math.sqrt(area / math.pi))
        return self.wavelength * n_w / self.pixel_pitch


# --- iris parameters and constraints -------------------------------------------------------


class IrisParams(eqx.Module):
    """What a curved-iris design varies: one blade curvature (all blades are cut alike),
    and each vertex's relative radial and angular (radians) deviation."""

    curvature: Float[Array, ""]
    radial: Float[Array, " blades"]
    angular: Float[Array, " blades"]


class IrisFamily(eqx.Module):
    """The fixed part of an iris design: blade count ``n``, open ``area`` (m², the fixed
    exposure), ``rotation`` (radians) and arc ``segments``. :meth:`pupil` builds a
    :class:`CurvedIris` whose circumradius gives exactly this area."""

    n: int = eqx.field(static=True)
    area: Real = eqx.field(static=True)
    rotation: Real = eqx.field(static=True, default=0.0)
    segments: int = eqx.field(static=True, default=16)

    def __check_init__(self):
        from ._validate import MAX_BLADES, check_number

        check_number(self.n, "IrisFamily.n", integer=True, ge=3, le=MAX_BLADES,
                     fix="the blade count")
        check_number(self.area, "IrisFamily.area", gt=0, unit="m²",
                     fix="the open area, e.g. π (f / 2N)²")
        check_number(self.rotation, "IrisFamily.rotation", unit="rad")
        check_number(self.segments, "IrisFamily.segments", integer=True, ge=1,
                     fix="chords per blade arc")

    def radius_bound(self, margin: float = 1.25) -> float:
        """A bound (metres) on the circumradius of this family's irises: ``margin`` times
        that of the regular n-gon of the family's area (curvature only shrinks it; the
        margin covers radial deviations up to 20 %)."""
        n = self.n
        r_ngon = math.sqrt(2 * self.area / (n * math.sin(2 * math.pi / n)))
        return margin * r_ngon

    def params(self, curvature=0.0, radial=0.0, angular=0.0) -> IrisParams:
        dt = jnp.result_type(float)
        return IrisParams(
            jnp.asarray(curvature, dt),
            jnp.broadcast_to(jnp.asarray(radial, dt), (self.n,)),
            jnp.broadcast_to(jnp.asarray(angular, dt), (self.n,)),
        )

    def pupil(self, p: IrisParams) -> CurvedIris:
        return curved_iris_from_area(
            self.n, self.area, p.curvature, radial=p.radial, angular=p.angular,
            rotation=self.rotation, segments=self.segments,
        )

    def bounds(
        self, *, curvature: tuple[Real, Real] = (0.0, 0.0), radial: Real = 0.0,
        angular: Real = 0.0, convex: bool = True,
    ) -> Box:
        """A :class:`Box`: curvature in [lo, hi], |radial| ≤ ``radial``, |angular| ≤
        ``angular`` (radians). A range of zero width fixes that parameter.

        ``convex=True`` checks that every iris inside the box is convex, with the
        conservative bound of :func:`convexity_bound`, and raises if not.
        """
        lo_c, hi_c = (float(c) for c in curvature)
        if convex:
            if lo_c < 0:
                raise ValueError("IrisFamily.bounds: negative curvature (concave blades) "
                                 "is not convex; use curvature >= 0 or convex=False.")
            m = convexity_bound(self.n, max_curvature=hi_c, max_radial=radial,
                                max_angular=angular)
            if m < 0:
                raise ValueError(
                    f"IrisFamily.bounds: these bounds allow non-convex irises (worst-case "
                    f"turning {m:.3g} rad < 0); reduce the curvature or vertex bounds, or "
                    "pass convex=False."
                )
        return Box(self.params(lo_c, -radial, -angular), self.params(hi_c, radial, angular))


def convexity_bound(n: int, *, max_curvature: Real, max_radial: Real,
                    max_angular: Real) -> float:
    """A lower bound (radians) on :meth:`CurvedIris.convexity_margin` over all irises
    with curvature in [0, max_curvature], |radial| ≤ max_radial, |angular| ≤ max_angular.

    Each vertex moves at most ε R from its regular place, ε = ρ + 2 sin(δ/2)(1 + ρ); a
    chord of nominal length L₀ = 2R sin(π/n) then turns at most asin(2ε R / L₀) and
    lengthens to at most L₀ + 2ε R, so the turning at a vertex is at least
    2π/n − 2 asin(ε / sin(π/n)) − 2 asin(c (sin(π/n) + ε)).
    """
    s = math.sin(math.pi / n)
    eps = max_radial + 2 * math.sin(max_angular / 2) * (1 + max_radial)
    if eps >= s or max_curvature * (s + eps) >= 1:
        return -math.inf
    return 2 * math.pi / n - 2 * math.asin(eps / s) - 2 * math.asin(max_curvature * (s + eps))


class Box(eqx.Module):
    """Bounds as a reparametrisation: params = lower + (upper − lower) σ(u), u free.

    ``lower`` and ``upper`` are PyTrees shaped like the parameters. Where they are equal
    the parameter is fixed (its gradient is zero). Starting values on a bound are moved
    inside by ``margin`` × the range (a logistic map cannot reach its ends).
    """

    lower: Any
    upper: Any
    margin: Real = eqx.field(static=True, default=1e-3)

    def constrain(self, u):
        return jax.tree.map(lambda lo, hi, x: lo + (hi - lo) * jax.nn.sigmoid(x),
                            self.lower, self.upper, u)

    def unconstrain(self, params):
        def inv(lo, hi, p):
            span = hi - lo
            fixed = span == 0
            t = (p - lo) / jnp.where(fixed, 1.0, span)
            t = jnp.clip(t, self.margin, 1 - self.margin)
            return jnp.where(fixed, 0.0, jnp.log(t) - jnp.log1p(-t))

        return jax.tree.map(inv, self.lower, self.upper, params)


# --- the optimiser loop ---------------------------------------------------------------------


class LBFGSB(eqx.Module):
    """Bound-constrained quasi-Newton (L-BFGS-B, ``jaxopt.LBFGSB``) for :func:`design`,
    working in the bounded parameters themselves (each as its fraction of its range, an
    affine rescaling): no sigmoid map, so a parameter can sit exactly on its bound
    (where the optimum of a bounded design often is) and every iterate stays inside the
    :class:`Box` (each step ends on the segment from the iterate to a point of the box;
    rounding is clipped off).

    history: correction pairs kept (the memory of the Hessian approximation).
    tol: stop once the projected gradient's largest component is at most ``tol`` (in
        the objective's units per parameter range); 0 (the default) runs every step,
        but a line search that cannot lower the objective twice running (the second
        time from the projected gradient, the memory dropped) also stops it.
    max_linesearch: objective evaluations per line search at most.
    first_step: the first step's largest move, as a fraction of that parameter's range
        (the quasi-Newton matrix starts as a multiple of the identity, so the objective's
        units would set it otherwise); later steps are scaled by the curvature seen.

    Each iteration is one line search (usually one objective-and-gradient evaluation
    and, in jaxopt, one value-only evaluation at its start; more when the step has to be
    shortened). Compiling the step takes several times as long as an Adam step (jaxopt's
    line search holds the objective in several branches): it pays on longer runs and on
    optima on the bounds (BENCHMARKS.md, "Design optimisers"). jaxopt is no longer
    maintained (its authors point to optax, which has no bound-constrained L-BFGS); its
    import-time DeprecationWarning is silenced where it is imported, in :meth:`solver`.
    """

    history: int = eqx.field(static=True, default=10)
    tol: Real = eqx.field(static=True, default=0.0)
    max_linesearch: int = eqx.field(static=True, default=30)
    first_step: Real = eqx.field(static=True, default=0.1)

    def __check_init__(self):
        from ._validate import check_number

        check_number(self.history, "LBFGSB.history", integer=True, ge=1, le=1000,
                     fix="correction pairs kept, e.g. 10")
        check_number(self.tol, "LBFGSB.tol", ge=0,
                     fix="a projected-gradient tolerance, or 0 to run every step")
        check_number(self.max_linesearch, "LBFGSB.max_linesearch", integer=True, ge=1,
                     le=1000, fix="objective evaluations per line search, e.g. 30")
        check_number(self.first_step, "LBFGSB.first_step", gt=0, le=1,
                     fix="a fraction of the parameters' ranges, e.g. 0.1")

    def solver(self, loss: Callable):
        """The ``jaxopt.LBFGSB`` minimising ``loss(params) -> (value, aux)``."""
        import warnings

        with warnings.catch_warnings():  # "JAXopt is no longer maintained" (0.8.5)
            warnings.filterwarnings("ignore", category=DeprecationWarning,
                                    module="jaxopt")
            warnings.filterwarnings("ignore", message=".*JAXopt.*",
                                    category=DeprecationWarning)
            import jaxopt

        # max_stepsize 1: a step never goes past the projected quasi-Newton point, which
        # lies in the box, so the iterates stay feasible
        return jaxopt.LBFGSB(fun=loss, has_aux=True, tol=self.tol,
                             history_size=self.history, maxls=self.max_linesearch,
                             max_stepsize=1.0)


#: the optimisers :func:`design` knows by name, each with its defaults
OPTIMISERS = {"adam": "optax.adam(0.1) on the sigmoid-unconstrained values of the Box",
              "lbfgsb": "LBFGSB(): bound-constrained quasi-Newton in the parameters"}


def optimiser_kind(optimiser) -> tuple[str, Any]:
    """The one place that decides how :func:`design` runs an optimiser: returns
    (``"optax"`` | ``"optimistix"`` | ``"lbfgsb"``, the optimiser object), turning the
    names of :data:`OPTIMISERS` (and None, Adam) into their default objects. Anything
    else is refused with the accepted forms."""
    from ._validate import InputError

    if optimiser is None or (isinstance(optimiser, str) and optimiser == "adam"):
        import optax

        return "optax", optax.adam(0.1)
    if isinstance(optimiser, str):
        if optimiser == "lbfgsb":
            return "lbfgsb", LBFGSB()
        raise InputError(f"optimiser: {optimiser!r} is not a known optimiser; give one of "
                         f"{', '.join(map(repr, OPTIMISERS))}, an optax "
                         "GradientTransformation, an optimistix minimiser or "
                         "difstar._design.LBFGSB(...).")
    if isinstance(optimiser, LBFGSB):
        return "lbfgsb", optimiser
    import optimistix as optx

    if isinstance(optimiser, optx.AbstractMinimiser):
        return "optimistix", optimiser
    if callable(getattr(optimiser, "init", None)) and callable(
            getattr(optimiser, "update", None)):
        return "optax", optimiser
    raise InputError(f"optimiser: a {type(optimiser).__name__} is not an optimiser; give "
                     f"one of {', '.join(map(repr, OPTIMISERS))}, an optax "
                     "GradientTransformation, an optimistix minimiser or "
                     "difstar._design.LBFGSB(...).")



class DesignResult(eqx.Module):
    """What :func:`design` returns.

    params: the final parameters; best_params / best_value: the best seen;
    history: ``{"value": (steps + 1,), "aux": {name: (steps + 1,)}, "params": [PyTree],
    "evaluations": (steps + 1,)}`` — entry i is at the parameters after i steps (for
    optimistix and L-BFGS-B, the i-th iterate; fewer entries when they stop early);
    ``evaluations[i]``: the objective-and-gradient evaluations the optimiser had made
    when entry i's value was known (Adam and optimistix: one per step; L-BFGS-B: its
    line searches' count). Evaluations made only to record the history are not counted.
    """

    params: Any
    best_params: Any
    best_value: Float[Array, ""]
    history: dict


def _split_objective(objective):
    def fn(params):
        out = objective(params)
        if isinstance(out, tuple):
            val, aux = out
        else:
            val, aux = out, {}
        return val, aux

    return fn


def design(
    objective: Callable,
    params0,
    *,
    constraints: Any = None,
    optimiser=None,
    steps: int = 100,
    callback: Callable | None = None,
) -> DesignResult:
    """Minimise ``objective(params)`` from ``params0``.

    objective: params → scalar, or → (scalar, dict of scalars to record).
    constraints: a :class:`Box` (or any object with ``constrain``/``unconstrain``); the
        optimiser then works on the unconstrained values and the objective always sees
        feasible parameters. Fixed area is not a bound: build the pupil with
        :meth:`IrisFamily.pupil` inside the objective.
    optimiser: an ``optax.GradientTransformation`` (default ``optax.adam(0.1)``, suited
        to the unconstrained values of a Box), an optimistix minimiser (e.g.
        ``optx.BFGS(rtol=1e-6, atol=1e-8)``), both stepped one iteration at a time on
        the unconstrained values, or :class:`LBFGSB` (``"lbfgsb"`` for its defaults),
        which works on the parameters themselves within the Box's bounds. Names:
        :data:`OPTIMISERS` (``"adam"``, ``"lbfgsb"``); :func:`optimiser_kind` decides.
    steps: iterations. callback(step, params, value, aux): called after every step with
        concrete values; returning True stops early.

    The step is compiled once (``eqx.filter_jit``); objectives must be jittable.
    """
    from ._validate import check_number

    steps = check_number(steps, "steps", integer=True, ge=0,
                         fix="the optimiser iterations")
    kind, optimiser = optimiser_kind(optimiser)
    fn = _split_objective(objective)
    values, auxes, plist, evals = [], [], [], []

    if kind == "lbfgsb":
        bounds = _box_bounds(constraints)

        def record(p_, val, aux, n_eval):
            values.append(float(val))
            auxes.append({k: float(v) for k, v in aux.items()})
            plist.append(jax.device_get(p_))
            evals.append(int(n_eval))

        _run_lbfgsb(fn, params0, bounds, optimiser, steps, record, callback)
    else:
        box = constraints

        def loss(u):
            p = box.constrain(u) if box is not None else u
            return fn(p)

        to_params = (lambda u: box.constrain(u)) if box is not None else (lambda u: u)
        u = box.unconstrain(params0) if box is not None else params0

        def record(u_, val, aux):
            values.append(float(val))
            auxes.append({k: float(v) for k, v in aux.items()})
            plist.append(jax.device_get(to_params(u_)))
            evals.append(len(values))  # one evaluation per step (see DesignResult)

        run = _run_optimistix if kind == "optimistix" else _run_optax
        run(loss, u, optimiser, steps, record, callback, to_params)
    vals = np.asarray(values)
    best = int(np.nanargmin(vals))
    keys = auxes[0].keys() if auxes else ()
    history = {
        "value": vals,
        "aux": {k: np.asarray([a[k] for a in auxes]) for k in keys},
        "params": plist,
        "evaluations": np.asarray(evals),
    }
    return DesignResult(plist[-1], plist[best], jnp.asarray(vals[best]), history)


def _box_bounds(constraints):
    """(lower, upper) of the constraints for :class:`LBFGSB` (None: unbounded)."""
    from ._validate import InputError

    if constraints is None:
        return None
    if not isinstance(constraints, Box):
        raise InputError(f"constraints: L-BFGS-B needs the bounds themselves, a Box; got a "
                         f"{type(constraints).__name__}. Give a Box (e.g. "
                         "IrisFamily.bounds(...)), or an optax optimiser for other "
                         "reparametrisations.")
    return constraints.lower, constraints.upper


def _unit_box(bounds):
    """(to_params, to_unit, unit bounds) for :class:`LBFGSB`: each bounded parameter as
    its fraction t ∈ [0, 1] of its range, p = lower + (upper − lower) t — an affine
    rescaling (a diagonal preconditioner), not a reparametrisation: p is exactly
    ``lower`` at t = 0 and exactly ``upper`` at t = 1 (rounding is clipped off), and
    dp/dt = upper − lower everywhere, bounds included. Fixed parameters (a range of zero
    width) stay at their value. Unbounded (None): the parameters themselves."""
    if bounds is None:
        return (lambda t: t), (lambda p: p), None
    lower, upper = bounds

    def up(lo, hi, t):
        span = hi - lo
        affine = lo + span * t
        exact = jnp.where(t >= 1, hi, jnp.where(t <= 0, lo, jnp.clip(affine, lo, hi)))
        return affine + jax.lax.stop_gradient(exact - affine)

    def down(lo, hi, p):
        span = hi - lo
        free = span > 0
        t = jnp.clip((p - lo) / jnp.where(free, span, 1.0), 0.0, 1.0)
        return jnp.where(free, t, 0.0)

    unit = (jax.tree.map(jnp.zeros_like, lower),
            jax.tree.map(lambda lo, hi: jnp.where(hi > lo, 1.0, 0.0).astype(lo.dtype),
                         lower, upper))
    return (lambda t: jax.tree.map(up, lower, upper, t),
            lambda p: jax.tree.map(down, lower, upper, p), unit)


def _run_lbfgsb(fn, params0, bounds, optimiser: LBFGSB, steps, record, callback):
    """L-BFGS-B from ``params0`` (projected into the bounds: a copy, the input is not
    touched), one compiled iteration at a time (an attempt whose line search fails
    counts as one), on the parameters as fractions of their ranges (:func:`_unit_box`)
    and on the objective scaled so that its start's largest gradient component there
    is ``optimiser.first_step``: the first step (a projected gradient step: the
    quasi-Newton matrix starts as the identity) then moves that parameter by that
    fraction of its range, not by a length set by the objective's units. Stops after
    ``steps`` iterations, when the projected gradient is within ``optimiser.tol`` (in
    the objective's own units per range), when a line search fails right after a
    restart from the projected gradient (no lower value along either step) or when
    ``callback`` returns True."""
    to_params, to_unit, unit = _unit_box(bounds)

    def scaled(t, scale):
        val, aux = fn(to_params(t))
        return val * scale, aux

    solver = optimiser.solver(scaled)
    t = to_unit(jax.tree.map(jnp.asarray, params0))
    g0 = eqx.filter_jit(jax.grad(lambda t_: fn(to_params(t_))[0]))(t)
    g_max = max((float(jnp.max(jnp.abs(g))) for g in jax.tree.leaves(g0)), default=0.0)
    scale = jnp.asarray(optimiser.first_step / g_max if g_max > 0 else 1.0)
    state = eqx.filter_jit(solver.init_state)(t, unit, scale)
    extra = 1  # the gradient that set the scale

    def report(t_, st):
        p_ = to_params(t_)
        record(p_, st.value / scale, st.aux, st.num_fun_eval + extra)
        return p_

    p = report(t, state)

    @eqx.filter_jit
    def step(t_, st):
        return solver.update(t_, st, unit, scale)

    def restart(st, counts):
        """The state with the curvature memory dropped (the next step is a projected
        gradient step again), keeping the evaluation counts of ``counts``."""
        zeros = jax.tree.map(jnp.zeros_like, (st.s_history, st.y_history))
        return st._replace(s_history=zeros[0], y_history=zeros[1],
                           num_updates=jnp.zeros_like(st.num_updates),
                           theta=jnp.ones_like(st.theta),
                           stepsize=jnp.ones_like(st.stepsize),
                           num_fun_eval=counts.num_fun_eval,
                           num_grad_eval=counts.num_grad_eval)

    restarted = False
    for i in range(steps):
        t_new, new = step(t, state)
        if bool(new.failed_linesearch) and not float(new.value) < float(state.value):
            # no lower value along the quasi-Newton direction: once, drop the memory
            # and try the projected gradient; twice in a row, stop
            if restarted:
                break
            state, restarted = restart(state, new), True
            continue
        t, state, restarted = t_new, new, False
        p = report(t, state)
        if callback is not None and callback(i, p, float(state.value / scale), state.aux):
            break
        if float(state.error) / float(scale) <= optimiser.tol:
            break
    return p


def _run_optax(loss, u, optimiser, steps, record, callback, to_params):
    import optax

    opt_state = optimiser.init(eqx.filter(u, eqx.is_inexact_array))

    @eqx.filter_jit
    def step(u_, state):
        (val, aux), g = eqx.filter_value_and_grad(loss, has_aux=True)(u_)
        updates, state = optimiser.update(g, state, u_)
        return optax.apply_updates(u_, updates), state, val, aux

    evaluate = eqx.filter_jit(loss)
    for i in range(steps):
        u_new, opt_state, val, aux = step(u, opt_state)
        record(u, val, aux)
        if callback is not None and callback(i, to_params(u), float(val), aux):
            u = u_new
            break
        u = u_new
    val, aux = evaluate(u)
    record(u, val, aux)
    return u


def _run_optimistix(loss, u, solver, steps, record, callback, to_params):
    def fn(y, args):
        val, aux = loss(y)
        return val, (val, aux)

    f_struct, aux_struct = jax.eval_shape(fn, u, None)
    tags = frozenset()
    state = eqx.filter_jit(solver.init)(fn, u, None, {}, f_struct, aux_struct, tags)
    evaluate = eqx.filter_jit(loss)
    val, aux = evaluate(u)
    record(u, val, aux)

    @eqx.filter_jit
    def step(y, st):
        y, st, _ = solver.step(fn, y, None, {}, st, tags)
        done, _ = solver.terminate(fn, y, None, {}, st, tags)
        return y, st, done

    for i in range(steps):
        u, state, done = step(u, state)
        val, aux = evaluate(u)
        record(u, val, aux)
        if callback is not None and callback(i, to_params(u), float(val), aux):
            break
        if bool(done):
            break
    return u


__all__ = [
    "PSFSetup", "IrisParams", "IrisFamily", "Box", "DesignResult", "design", "LBFGSB",
    "OPTIMISERS", "optimiser_kind", "convexity_bound",
]

