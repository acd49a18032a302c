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
   blade curvature) by the one bound map from unconstrained values (a
   :class:`difstar.Param` with bounds, e.g. from :meth:`IrisFamily.bounds`), the blade
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
from ._design_optimisers import (
    LBFGSB,
    OPTIMISERS,
    optimiser_kind,
    run_lbfgsb,
    run_optax,
    run_optimistix,
)
from ._param import Param
from ._progress import step_bar, ticking
from ._psf import plan_psf, psf
from ._validate import MAX_BLADES, InputError, check_number
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
    ) -> tuple[IrisParams, IrisParams]:
        """The bounds ``(lower, upper)`` for :func:`design` (or a :class:`difstar.Param`):
        curvature in [lo, hi], |radial| ≤ ``radial``, |angular| ≤ ``angular`` (radians).
        A range of zero width fixes that parameter.

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
        return self.params(lo_c, -radial, -angular), self.params(hi_c, radial, angular)


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


#: A design's start on a bound is moved this fraction of the range inside it before the
#: sigmoid map (Adam's first steps from a deeper saturation would barely move it).
START_MARGIN = 1e-3


def _constraints(params0, constraints):
    """A :class:`difstar.Param` holding the start and its bounds (None: unbounded), or
    the user's own reparametrisation object (``constrain``/``unconstrain``)."""
    if isinstance(params0, Param):
        if constraints is not None:
            raise InputError("constraints: the start is a Param, which carries its own "
                             "bounds; give the bounds once (in the Param, or as "
                             "constraints=(lower, upper) with a plain start).")
        return params0
    if constraints is None:
        return None
    if hasattr(constraints, "constrain") and hasattr(constraints, "unconstrain"):
        return constraints
    if isinstance(constraints, tuple) and len(constraints) == 2:
        return Param(params0, True, constraints)
    raise InputError(f"constraints: expected the bounds (lower, upper), each shaped like "
                     f"the parameters (e.g. IrisFamily.bounds(...)), or an object with "
                     f"constrain/unconstrain; got a {type(constraints).__name__}.")


# --- the optimiser loop ---------------------------------------------------------------------


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
    progress: str | None = None,
) -> DesignResult:
    """Minimise ``objective(params)`` from ``params0``.

    objective: params → scalar, or → (scalar, dict of scalars to record).
    params0: the start, a PyTree of arrays, or a :class:`difstar.Param` carrying the start
        and its bounds (then leave ``constraints`` out).
    constraints: the bounds ``(lower, upper)``, PyTrees like the parameters (e.g.
        :meth:`IrisFamily.bounds`; equal bounds fix an element), mapped by the one bound
        map of :class:`difstar.Param`; or any object with ``constrain``/``unconstrain``.
        The optimiser then works on the unconstrained values and the objective always
        sees feasible parameters. Fixed area is not a bound: build the pupil with
        :meth:`IrisFamily.pupil` inside the objective.
    optimiser: an ``optax.GradientTransformation`` (default ``optax.adam(0.1)``, suited
        to the unconstrained values of bounded parameters), an optimistix minimiser (e.g.
        ``optx.BFGS(rtol=1e-6, atol=1e-8)``), both stepped one iteration at a time on
        the unconstrained values, or :class:`LBFGSB` (``"lbfgsb"`` for its defaults),
        which works on the parameters themselves within the bounds. Names:
        :data:`OPTIMISERS` (``"adam"``, ``"lbfgsb"``); :func:`optimiser_kind` decides.
    steps: iterations. callback(step, params, value, aux): called after every step with
        concrete values; returning True stops early.
    progress: a label: a bar on stderr ticking once a step, with the objective, the
        parameter that moved most and the time left (None: quiet).

    The step is compiled once (``eqx.filter_jit``); objectives must be jittable.
    """
    steps = check_number(steps, "steps", integer=True, ge=0,
                         fix="the optimiser iterations")
    kind, optimiser = optimiser_kind(optimiser)
    box = _constraints(params0, constraints)
    if isinstance(params0, Param):
        params0 = params0.value
    fn = _split_objective(objective)
    values, auxes, plist, evals = [], [], [], []

    with step_bar(progress, steps) as tick:
        if tick is not None:
            callback = ticking(callback, tick, params0)
        if kind == "lbfgsb":
            bounds = _box_bounds(box)

            def record(p_, val, aux, n_eval):
                values.append(float(val))
                auxes.append({k: float(v) for k, v in aux.items()})
                plist.append(jax.device_get(p_))
                evals.append(int(n_eval))

            run_lbfgsb(fn, params0, bounds, optimiser, steps, record, callback)
        else:
            if box is None:
                to_params, u = (lambda u_: u_), params0
            elif isinstance(box, Param):
                to_params = box.from_unconstrained
                u = jax.tree.map(jnp.asarray, box.to_unconstrained(margin=START_MARGIN))
            else:
                to_params, u = box.constrain, box.unconstrain(params0)

            def loss(u_):
                return fn(to_params(u_))

            def record(u_, val, aux):
                values.append(float(val))
                auxes.append({k: float(v) for k, v in aux.items()})
                plist.append(jax.device_get(to_params(u_)))
                evals.append(len(values))  # one evaluation per step (see DesignResult)

            run = run_optimistix if kind == "optimistix" else run_optax
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
    if constraints is None:
        return None
    if not isinstance(constraints, Param):
        raise InputError(f"constraints: L-BFGS-B needs the bounds themselves, (lower, "
                         f"upper); got a {type(constraints).__name__}. Give the bounds "
                         "(e.g. IrisFamily.bounds(...)), or an optax optimiser for other "
                         "reparametrisations.")
    return constraints.bounds



__all__ = [
    "PSFSetup", "IrisParams", "IrisFamily", "DesignResult", "design", "LBFGSB",
    "OPTIMISERS", "optimiser_kind", "convexity_bound",
]

