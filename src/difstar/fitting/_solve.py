"""One solve and its errors: the Levenberg–Marquardt solve from one start (its residuals
from :mod:`._residuals`), the Jacobian, covariance and standard errors,
and :class:`FitResult`."""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._ahead import Ahead
from .._lm import JAC_BATCH, LMStepper, with_batched_jacobian
from .._normal_equations import (
    BlockColumns,
    block_normal_equations,
    direction_seeds,
    normal_covariance,
    normal_covariance_of,
)
from .._param import bound_map_slope, step_map
from .._progress import moved_most, step_bar
from .._xla import solver_jit_options
from ._centred import centred_psf, optics_fixed
from ._data import FitData
from ._model import ImageModel
from ._params import FitInputError, _from_u, _to_u
from ._programs import _light_key, program, trace_key
from ._residuals import (
    _as_list,
    _PixelTarget,
    _residual_fn,
    column_blocks,
    projected,
)


@dataclasses.dataclass
class FitResult:
    """What :func:`fit` found. ``values``: every parameter (fixed ones at their value);
    ``errors``: standard errors of the free ones, from the Gauss–Newton covariance
    (JᵀJ)⁻¹ at the optimum, scaled by √(χ²/dof) when that exceeds 1 (``covariance`` is
    the scaled matrix in the order of ``free``); ``status``: "converged" or why not;
    ``warnings``: parameters at a bound, unconstrained (zero Jacobian column or a
    standard error wider than the bounds); ``residual``: data − model (unmasked
    pixels; 0 elsewhere)."""

    values: dict
    errors: dict
    free: list
    covariance: np.ndarray
    chi2: float
    dof: int
    status: str
    converged: bool
    steps: int
    model_image: np.ndarray | list
    residual: np.ndarray | list
    data: np.ndarray | list
    mask: np.ndarray | list
    warnings: list
    wall_time: float
    stages: list

    @property
    def chi2_dof(self) -> float:
        return self.chi2 / max(self.dof, 1)

    @property
    def residual_rms_peak(self) -> float:
        """RMS of the residual over the used pixels relative to the data's peak (for
        several captures: the largest of theirs)."""
        if isinstance(self.residual, list):
            return max(_rms_peak(r, d, m) for r, d, m in zip(self.residual, self.data,
                                                             self.mask))
        return _rms_peak(self.residual, self.data, self.mask)

    def summary(self) -> str:
        lines = [f"status: {self.status} ({self.steps} steps, {self.wall_time:.1f} s)",
                 f"chi2/dof: {self.chi2_dof:.4g} (dof {self.dof}); residual RMS / peak: "
                 f"{100 * self.residual_rms_peak:.3f} %"]
        for k in self.free:
            lines.append(f"  {k:14s} = {self.values[k]:.6g} ± {self.errors[k]:.3g}")
        lines += [f"warning: {w}" for w in self.warnings]
        return "\n".join(lines)

def _rms_peak(residual, data, mask) -> float:
    r = residual[mask]
    return float(np.sqrt(np.mean(r**2)) / np.max(data[mask]))

def model_images(model: ImageModel, values: Mapping[str, float], data) -> list:
    """The model image of each capture's window at ``values`` (a fit's values, or a
    result.json's), as a list of arrays; ``data``: a :class:`FitData` or a list of them.
    One program (the values and the data its arguments, as in the solver), so that a
    repeat's or a hop's re-runs of a stage find it in JAX's compilation cache."""
    datas = _as_list(data)
    targets = [_PixelTarget(d) for d in datas]
    v = {k: jnp.asarray(x, float) for k, x in values.items()}
    model = model.with_values(values)
    key, keep = trace_key(model, datas, targets)

    def make():
        res = _residual_fn(model, datas, targets)
        return jax.jit(lambda v_, arrays: res(v_, arrays)[1])

    images = program(("images", key), make, keep)
    return [np.asarray(m) for m in images(v, [t.arrays for t in targets])]

def values_of_capture(values: Mapping[str, Any], i: int) -> dict:
    """The values capture ``i`` of a fit saw: ``name@i`` read as ``name`` (a fit's
    result, or a result.json's values, for any per-capture names)."""
    tag = f"@{i}"
    return {**values, **{k[:-len(tag)]: x for k, x in values.items() if k.endswith(tag)}}

#: How many times a solve starts again from its answer with a finer PSF plan (the plan
#: follows the Zernike terms' values: :meth:`ImageModel.plan_holds`).
MAX_REPLANS = 3

def _one_fit(model: ImageModel, data, target, *, max_steps: int, rtol: float,
             atol: float, ftol: float = 1e-6, label: str | None = None):
    """Levenberg–Marquardt solves of ``model``'s free parameters: the PSF planned for the
    start's values, and again from the answer wherever that needs a finer plan (at most
    :data:`MAX_REPLANS` times); with ``label``, a progress bar (tqdm, on stderr) of its
    steps and χ². Returns (values, status, converged, steps, the model at the values, the
    χ² of ``target`` at the values on the plan they were solved on: the solver's own,
    and a function giving the Jacobian and residuals there from the solver's last
    linearisation, or None: :func:`_linearised`)."""
    if not model.free:
        raise FitInputError("fit: no free parameter (set free=true on at least one).")
    shapes = [(model.padded_shape(d.image.shape), d.light) for d in _as_list(data)]
    steps = 0
    for k in range(MAX_REPLANS + 1):
        vals, status, ok, n, chi2, lin = _solve_once(
            model, data, target, max_steps=max_steps, rtol=rtol, atol=atol, ftol=ftol,
            label=None if label is None else label + (f" (plan {k + 1})" if k else ""))
        steps += n
        holds = all(model.plan_holds(vals, s, li) for s, li in shapes)
        model = model.with_values(vals)
        if holds:
            break
    else:  # the wavefront kept growing: the answer stands on the last plan, said so
        warnings.warn(f"fit: the answer's Zernike terms still need a finer PSF plan after "
                      f"{MAX_REPLANS + 1} solves; its values were computed on a plan made "
                      "for smaller terms. Check the Zernike bounds, or start nearer the "
                      "answer.", RuntimeWarning, stacklevel=2)
    return vals, status, ok, steps, model, chi2, lin

#: the parameters that enter a capture's image linearly (image = flux · exposure · PSF +
#: background, without a response curve): a solve takes them in closed form
LINEAR = ("flux", "background")

def linear_names(model: ImageModel, free: Sequence[str]) -> list[str]:
    """Those of ``free`` that enter the image linearly: each capture's flux and
    background without bounds, where the image has no response curve."""
    if model.response:
        return []
    return [k for k in free if k.split("@")[0] in LINEAR and model.params[k].bounds is None]

def projected_names(model: ImageModel, free: Sequence[str], target) -> list[str]:
    """The free parameters a solve of ``free`` on ``target`` takes in closed form at every
    step (variable projection): :func:`linear_names`, where the residuals are pixels
    (not spike profiles) and something else is free for the solver to move."""
    if not all(isinstance(t, _PixelTarget) for t in _as_list(target)):
        return []
    lin = linear_names(model, free)
    return lin if len(lin) < len(free) else []

def _solve_once(model: ImageModel, data, target, *, max_steps: int, rtol: float,
                atol: float, ftol: float, label: str | None):
    """One Levenberg–Marquardt solve of ``model``'s free parameters on its PSF plan; the
    flux and background of :func:`projected_names` in closed form at every step."""
    lin = projected_names(model, model.free, target)
    free = [k for k in model.free if k not in lin]
    fixed = {k: jnp.asarray(p.value, float) for k, p in model.params.items() if not p.free}
    params = [model.params[k] for k in free]

    # an unbounded parameter's start and step (start + step·u) vary from stage to stage
    steps = {k: (jnp.asarray(p.value, float), jnp.asarray(p.step_scale(), float))
             for k, p in zip(free, params) if p.bounds is None}

    def values_of(u, fixed, steps):
        v = dict(fixed)
        for i, (k, p) in enumerate(zip(free, params)):
            v[k] = step_map(u[i], *steps[k]) if k in steps else _from_u(p, u[i])
        return v

    def make():
        res = _residual_fn(model, data, target)

        def residuals_and_linear(u, args):
            fixed, steps, arrays, psfs = args
            v = values_of(u, fixed, steps)
            if not lin:
                return res(v, arrays, psfs)[0], jnp.zeros(0)
            v1 = {**v, **{q: jnp.asarray(1.0 if q.split("@")[0] == "flux" else 0.0)
                          for q in lin}}
            return projected(model, lin, res(v1, arrays, psfs)[1], v1, arrays)

        # the Jacobian a few columns at a time (bounded memory); one trace, shared by
        # the solver's init and step; the closed-form values ride along as the
        # residuals' aux: the solver's state holds them at its answer, so no other
        # program computes them
        # a star's own parameters (of a field's several) in directions shared with the
        # other stars' (column_blocks): the Jacobian's cost grows with the stars, not
        # with their square
        # (and their normal equations then from those directions: BlockColumns)
        blocks = column_blocks(model, free, target, lin)
        residuals = jax.jit(with_batched_jacobian(residuals_and_linear, has_aux=True,
                                                  blocks=blocks))
        # tolerances: each solve's own
        return LMStepper(residuals, has_aux=True, structure=BlockColumns.of(blocks))

    # the fixed values, the unbounded parameters' starts and the data are the solver's
    # arguments, not constants of its program: the same stage run again (a repeat's
    # rounds, a hop's tries, another star's window of the same size) is then the same
    # program, kept in :mod:`._programs` (and, across processes, in JAX's compilation
    # cache); what else its trace depends on is the key
    # where the optics are held, one PSF at the star's centre serves every step
    # (:mod:`._centred`): computed here, an argument of the program
    datas = _as_list(data)
    psfs = None
    if optics_fixed(model, model.free):
        at = model.values()
        # one PSF for the captures whose own values all act after the optics and whose
        # windows and light are one (the stars of a field)
        shared = optics_fixed(model, model.per_capture)
        psfs, made = [], {}
        for i, d in enumerate(datas):
            key = (d.image.shape, _light_key(d.light)) if shared else i
            if key not in made:
                made[key] = jnp.asarray(centred_psf(model, model.capture_values(at, i),
                                                    d.image.shape, d.light))
            psfs.append(made[key])
    args = (fixed, steps, [t.arrays for t in _as_list(target)], psfs)
    key, keep = trace_key(model, datas, _as_list(target))
    stepper = program(("solve", key, tuple(free), tuple(p.bounds for p in params),
                       tuple(lin), psfs is not None), make, keep)
    u0 = np.asarray([_to_u(p) for p in params], float)  # NumPy: no eager operation
    with step_bar(label, max_steps) as progress:
        last = [np.asarray(u0)]

        def checked(k, loss, size, done, u):
            # the solver's first step only evaluates the start: its loss is the start's
            if k == 1 and not math.isfinite(loss):
                raise FitInputError("fit: the model is not finite at the start; check the "
                                    "units (wavelength in metres, pixel_scale in arcsec, "
                                    "Zernike in nm).")
            if progress is not None:
                name, _ = moved_most(dict(zip(free, last[0])), dict(zip(free, u)))
                last[0] = u
                progress(f"χ² {2 * loss:.6g}, moved most: {name or '-'}")

        sol = stepper.solve(u0, args, max_steps=max_steps, ftol=ftol, progress=checked,
                            rtol=rtol, atol=atol)
    ok = sol.result == "converged"
    status = {"converged": "converged", "failed": "not converged: the solver failed",
              "max_steps": f"not converged: reached max_steps={max_steps}"}[sol.result]
    vals = {k: float(x) for k, x in values_of(sol.u, fixed, steps).items()}
    vals |= {k: float(x) for k, x in zip(lin, np.asarray(sol.aux))}  # at the answer
    # each value's slope in the solver's own number at the answer: the maps of
    # :func:`values_of`, differentiated in NumPy
    slope = np.asarray([float(steps[k][1]) if k in steps
                        else bound_map_slope(u, *map(float, p.bounds))
                        for k, p, u in zip(free, params, np.asarray(sol.u))])
    return vals, status, ok, sol.steps, 2.0 * sol.loss, _linearised(stepper, sol, lin,
                                                                    slope)


def _linearised(stepper, sol, lin, slope):
    """A function giving (J, r) at the answer in physical units from the solver's last
    linearisation (no Jacobian program compiled or run), where it holds every free
    parameter's column: not where flux and background were taken in closed form, nor
    where a bounded parameter ended on its bound (its map's slope 0 there); else None.
    ``slope``: each free value's derivative in the solver's number at the answer."""
    if lin:
        return None
    if not np.all(np.abs(slope) > 1e-12):
        return None

    def jac_r():
        j, r = stepper.linearisation(sol)
        return j / np.asarray(slope)[None, :], r

    return jac_r


def _jacobian_program(model: ImageModel, data, values: Mapping[str, float], target,
                      residual: bool, *, normal: bool = False):
    """(program, x, args) of :func:`_jacobian` (``normal``: of :func:`_normal_matrix`'s
    block structure): the kept program (an :class:`Ahead`, which may have been compiled
    ahead) and its arguments at ``values``."""
    free = model.free
    base = {k: jnp.asarray(v, float) for k, v in values.items()}

    def make():
        resv = _residual_fn(model, data, target)

        def res(x, args):  # the values and data as arguments (see _solve_once)
            base, arrays = args
            v = dict(base)
            for i, k in enumerate(free):
                v[k] = x[i]
            return resv(v, arrays)

        if not residual:
            batched = with_batched_jacobian(lambda x, a: res(x, a)[0],
                                            blocks=column_blocks(model, free, target))
            return Ahead(jax.jit(jax.jacfwd(batched), **solver_jit_options()))
        if normal:
            # the stars of a field: their normal matrix from the Jacobian along its
            # compressed directions, a few at a time (pixels × directions², not the
            # dense pixels × parameters matrix and its pixels × parameters² product)
            structure = BlockColumns.of(column_blocks(model, free, target))
            seeds = jnp.asarray(direction_seeds(structure.colour))

            def normal_matrix(x, a):
                (r, m), lin = jax.linearize(lambda x_: res(x_, a), x)
                jc = jax.lax.map(lambda d: lin(d)[0], seeds, batch_size=JAC_BATCH)
                return block_normal_equations(jc, r, structure)[0], (r, m)

            return Ahead(jax.jit(normal_matrix, **solver_jit_options()))
        # (residual, model images), one linearisation
        both = with_batched_jacobian(res, blocks=column_blocks(model, free, target,
                                                               outputs=True))

        def with_values(x, a):  # the residual differentiated, both returned as they are
            out = both(x, a)
            return out[0], out

        return Ahead(jax.jit(jax.jacfwd(with_values, has_aux=True), **solver_jit_options()))

    key, keep = trace_key(model, _as_list(data), _as_list(target))
    jacobian = program(("jacobian", key, tuple(free), residual, normal), make, keep)
    x0 = np.asarray([values[k] for k in free], float)
    return jacobian, x0, (base, [t.arrays for t in _as_list(target)])


def _jacobian(model: ImageModel, data, values: Mapping[str, float], target, *,
              residual: bool = True):
    """The residual's Jacobian over the free parameters (physical units) at ``values``,
    a few columns at a time (:func:`difstar._lm.with_batched_jacobian`); with
    ``residual``, also the residual and the model images (from the same program: the
    linearisation's primal values)."""
    jacobian, x0, args = _jacobian_program(model, data, values, target, residual)
    if not residual:
        return np.asarray(jacobian(x0, args))
    jac, (r, m) = jacobian(x0, args)
    return np.asarray(jac), np.asarray(r), [np.asarray(mi) for mi in m]


def _by_blocks(model: ImageModel, target) -> bool:
    """Whether the errors' normal matrix comes from the Jacobian's block structure
    (the stars of a field: :class:`difstar._normal_equations.BlockColumns`)."""
    return BlockColumns.of(column_blocks(model, model.free, target)) is not None


def _normal_matrix(model: ImageModel, data, values: Mapping[str, float], target):
    """(JᵀJ, residual, model images) at ``values``: for the stars of a field from the
    Jacobian along its compressed directions (pixels × directions² operations, no
    dense pixels × parameters matrix), else from :func:`_jacobian`'s."""
    if not _by_blocks(model, target):
        jac, r, m = _jacobian(model, data, values, target)
        return jac.T @ jac, r, m
    normal, x0, args = _jacobian_program(model, data, values, target, True, normal=True)
    jtj, (r, m) = normal(x0, args)
    return np.asarray(jtj), np.asarray(r), [np.asarray(mi) for mi in m]


def compile_errors_ahead(model: ImageModel, data, values: Mapping[str, float]) -> None:
    """Compile, on the background thread (:mod:`difstar._ahead`), the Jacobian that
    :func:`_errors` of ``model`` on all pixels of ``data`` will run at values and σ of
    these shapes: a fit's standard errors at its end then wait for no compile (3–4 s on
    the automatic Spitzer fit) where its last stages gave the compile the time."""
    target = [_PixelTarget(d) for d in _as_list(data)]
    jacobian, x0, args = _jacobian_program(model, data, values, target, True,
                                           normal=_by_blocks(model, target))
    jacobian.compile_ahead(x0, args)

def _errors(model: ImageModel, data, values: Mapping[str, float], target=None, *,
            linearised=None):
    """Gauss–Newton covariance in the physical parameters at ``values``, scaled by
    χ²/dof when that exceeds 1 (always, for spike profiles: their σ are relative).
    ``linearised``: the solve's (:func:`_one_fit`), whose Jacobian then serves (the
    model images are then None)."""
    if target is None:
        target = [_PixelTarget(d) for d in _as_list(data)]
    free = model.free
    if linearised is not None:
        (jac, r), m = linearised(), None
        jtj = jac.T @ jac
    else:
        jtj, r, m = _normal_matrix(model, data, values, target)
    if not (np.all(np.isfinite(jtj)) and np.all(np.isfinite(r))):
        raise FitInputError("fit: the model or its derivatives are not finite at the "
                            "answer; check the units (wavelength in metres, pixel_scale "
                            "in arcsec, Zernike in nm) and the bounds.")
    chi2 = float(r @ r)
    dof = sum(t.n for t in _as_list(target)) - len(free)
    kinds = {t.kind for t in _as_list(target)}
    cov, colnorm = normal_covariance_of(jtj)
    msgs = []
    for k, c in zip(free, colnorm):
        if not c > 1e-12 * max(colnorm.max(), 1e-300):
            msgs.append(f"{k}: unconstrained (the model does not depend on it: zero "
                        "Jacobian column); fix it.")
    red = chi2 / max(dof, 1)
    cov = cov * (max(red, 1.0) if kinds == {"pixels"} else red)
    err = np.sqrt(np.maximum(np.diag(cov), 0))
    errors = {}
    for i, k in enumerate(free):
        errors[k] = float(err[i]) if colnorm[i] > 0 else float("inf")
        p = model.params[k]
        if p.bounds is not None:
            lo, hi = p.bounds
            if errors[k] > (hi - lo):
                msgs.append(f"{k}: poorly constrained (standard error {errors[k]:.3g} is "
                            f"wider than its bounds {p.bounds}).")
            if min(values[k] - lo, hi - values[k]) < 1e-3 * (hi - lo):
                msgs.append(f"{k} = {values[k]:.6g} is at a bound {p.bounds}: widen it or "
                            "check the start.")
    return errors, cov, chi2, dof, m, msgs

def noise_limited_errors(model: ImageModel, data: FitData, values: Mapping[str, float],
                         sigmas: Sequence[Any]) -> list[dict[str, float]]:
    """The Cramér–Rao standard errors of ``model``'s free parameters at ``values``, one
    dict for each per-pixel σ in ``sigmas`` (arrays shaped like ``data.image``, finite and
    > 0 on its used pixels): √diag((Jᵀ Σ⁻¹ J)⁻¹), J the model image's Jacobian over the
    used pixels. The least standard error any unbiased fit of these pixels can have, if
    the model were exact and the noise Gaussian with that σ: noise alone, no mismatch,
    not scaled by χ²/dof. The Jacobian is computed once; each σ costs a p × p inverse.
    For a star ``f`` times fainter in the same units, σ² = (f · read)² + f · I / gain
    (the fainter star's noise scaled back up to this star's brightness)."""
    if isinstance(data, list):
        raise FitInputError("noise_limited_errors: one FitData (one capture), not a list.")
    free = model.free
    if not free:
        raise FitInputError("noise_limited_errors: the model has no free parameter.")
    unit = dataclasses.replace(data, sigma=np.ones_like(data.image))
    jac = _jacobian(model, unit, values, [_PixelTarget(unit)], residual=False)
    out = []
    for i, sig in enumerate(sigmas):
        sig = np.asarray(sig, float)
        if sig.shape != data.image.shape:
            raise FitInputError(f"noise_limited_errors: sigmas[{i}] has shape {sig.shape}; "
                                f"the data's is {data.image.shape}.")
        used = sig[data.mask]
        if not np.all(np.isfinite(used) & (used > 0)):
            raise FitInputError(f"noise_limited_errors: sigmas[{i}] must be finite and > 0 "
                                "on every used pixel.")
        cov, colnorm = normal_covariance(jac / np.where(data.mask, sig, 1.0).reshape(-1, 1))
        err = np.sqrt(np.maximum(np.diag(cov), 0.0))
        out.append({k: float(e) if c > 0 else float("inf")
                    for k, e, c in zip(free, err, colnorm)})
    return out
