"""Inverse characterization: fit optics, exposure and response curves to RAW mosaics.

Pure layer under ``difstar fit``: no files, no printing. A :class:`FitModel` holds what
is fixed (the camera's known values, the configurations' geometry and grids, the
captures' exposure times and regions) and, for every parameter, a
:class:`difstar.Param` (whether it is free, its start and its bounds). Free parameters
live in one flat unconstrained vector ``u``; each element maps to its physical value by
the one bound map, ``lo + (hi − lo)·sigmoid(u)`` (:mod:`difstar._param`), so every
value the solver tries is inside its bounds and all ``u`` are O(1) (the Levenberg–
Marquardt damping is isotropic in ``u``, so this also balances the parameters' scales).

The residuals are the RAW mosaic itself, ``(ζ_pred − ζ_obs) / σ`` with σ from a
Poisson–Gaussian noise model and weight 0 on saturated pixels; the prediction is
``difstar.simulate`` and nothing lower (:mod:`difstar._fit_model`: the model, its
parameters' bound map and the prediction, re-exported here). Configurations on one grid
are one ``lax.map`` (:func:`jointly`), each linearised inside it: the chain is traced
and compiled once for all of them.

The parameters, their shapes and units: :mod:`difstar._fit_params`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._batch import device_mesh
from ._chain import read_out
from ._fit_model import RAW_START_MARGIN as RAW_START_MARGIN
from ._fit_model import CameraConstants as CameraConstants
from ._fit_model import CaptureSpec as CaptureSpec
from ._fit_model import ConfigSpec as ConfigSpec
from ._fit_model import FitModel as FitModel
from ._fit_model import camera_scene as camera_scene
from ._fit_model import equal_brackets as equal_brackets
from ._fit_model import exposure_times as exposure_times
from ._fit_model import free_parts as free_parts
from ._fit_model import from_unconstrained as from_unconstrained
from ._fit_model import joint_grid as joint_grid
from ._fit_model import jointly as jointly
from ._fit_model import merged_grid as merged_grid
from ._fit_model import predict as predict
from ._fit_model import predict_config as predict_config
from ._fit_model import pupil_of as pupil_of
from ._fit_model import sensor_of as sensor_of
from ._fit_model import to_unconstrained as to_unconstrained
from ._fit_model import wavefront_of as wavefront_of
from ._fit_params import IRIS_ONLY as IRIS_ONLY
from ._fit_params import UNITS as UNITS
from ._fit_params import base_name as base_name
from ._fit_params import builder_parameters as builder_parameters
from ._fit_params import param_shape as param_shape
from ._fit_params import unit_of as unit_of
from ._fit_params import zernike_index as zernike_index
from ._lm import LMStepper, SolveResult, with_batched_jacobian
from ._normal_equations import normal_covariance
from ._param import Param as Param
from ._xla import solver_jit_options

# ----------------------------------------------------------------------- residuals

def noise_sigma(zeta, *, gain_e_per_dn, read_noise_dn, full_scale_dn, xp=jnp):
    """σ of normalised ζ under the Poisson–Gaussian model: var = ζ/(g·S) + (r/S)²,
    with S = white − black in DN and g electrons per DN. ``xp``: NumPy for the data's
    own σ at a fit's set-up (no eager JAX operation, each compiled once per process)."""
    z = xp.maximum(zeta, 0.0)
    return xp.sqrt(z / (gain_e_per_dn * full_scale_dn) + (read_noise_dn / full_scale_dn) ** 2)


def make_residual_fn(model: FitModel, *, jac_batch: int | None = None, mesh=None) -> Callable:
    """``fn(u, args) -> residuals`` per configuration, (K_c, h, w).

    ``args = {"data": {config: (ζ_obs, weight)}, "active": (P,), "u_ref": (P,)}``: only
    the active elements of ``u`` move the model (the others stay at ``u_ref``), so a
    solve can hold some parameters (e.g. the response curves, at first) without
    recompiling; their Jacobian columns are zero and the damped step leaves them.

    The Jacobian is materialised ``jac_batch`` columns at a time (default
    :data:`difstar._lm.JAC_BATCH`), and with ``mesh`` (a one-axis
    :func:`difstar._batch.device_mesh`) its columns are shared out over the devices:
    :func:`difstar._lm.with_batched_jacobian`, the one Jacobian rule of every difstar fit.
    """

    def physical(u, args):
        return from_unconstrained(model, args["u_ref"] + args["active"] * (u - args["u_ref"]))

    if jointly(model):  # the configurations one lax.map, each linearised inside it
        names = [cfg.name for cfg in model.configs]

        def item(u, args, i):  # args["data"]: (ζ_obs, weight), each stacked
            obs, weight = (a[i] for a in args["data"])
            return (predict_config(model, physical(u, args), i) - obs) * weight

        stacked = with_batched_jacobian(item, batch=jac_batch, mesh=mesh, items=len(names))

        def fn(u, args):
            # the configurations' data stacked once, outside the map's body
            data = tuple(jnp.stack([args["data"][k][j] for k in names]) for j in (0, 1))
            r = stacked(u, {**args, "data": data})
            return {k: r[i] for i, k in enumerate(names)}
    else:
        def raw(u, args):
            pred = predict(model, physical(u, args))
            return {k: (pred[k] - args["data"][k][0]) * args["data"][k][1] for k in pred}

        fn = with_batched_jacobian(raw, batch=jac_batch, mesh=mesh)

    # jitted, so that the solver's init, its step, the residuals and the Jacobian reuse
    # one trace of the chain instead of tracing it again each (half the compile time)
    return jax.jit(fn)


#: The sensor's parameters (one per channel): they act after the optics, on the linear
#: image, each only on its channel's pixels.
SENSOR_PARAMS = ("phi0", "toe", "knee")


def sensor_index(model: FitModel, channel: int) -> np.ndarray:
    """The places in the solver's vector ``u`` of channel ``channel``'s free
    :data:`SENSOR_PARAMS`."""
    out, i = [], 0
    for k in model.free:
        n = model.params[k].size
        if base_name(k) in SENSOR_PARAMS:
            out.append(i + channel)
        i += n
    return np.asarray(out, dtype=np.int32)


def make_sensor_residual_fn(model: FitModel) -> Callable:
    """``fn(v, args) -> residuals`` as :func:`make_residual_fn`'s, of the sensor's
    parameters alone with the optics held: ``v`` replaces ``args["u_ref"]`` at
    ``args["index"]`` (:func:`sensor_index`), and ``args["image"]`` = {config: linear
    images (K_c, 3, h, w)}, as ``predict(..., full=True)`` gives them at ``u_ref``, go
    through the sensor alone (:func:`difstar._chain.read_out`). A step costs the
    sensor's arithmetic for a few columns, not the PSF; the residuals equal the whole
    chain's wherever the optics are at ``u_ref``."""

    def raw(v, args):
        x = from_unconstrained(model, args["u_ref"].at[args["index"]].set(v))
        sen = sensor_of(model, x)
        out = {}
        for cfg in model.configs:
            ts = exposure_times(model, x, cfg.name)
            cfa = jax.vmap(lambda im, t: read_out(im, t, sen)[1])(args["image"][cfg.name], ts)
            obs, w = args["data"][cfg.name]
            out[cfg.name] = (cfa - obs) * w
        return out

    return jax.jit(raw)


def make_args(model: FitModel, data: dict, u_ref=None, *, hold: tuple[str, ...] = ()) -> dict:
    """Solver ``args`` from ``data`` = {config: (ζ_obs, weight)}, holding the parameter
    blocks named in ``hold`` (base names or full names) at ``u_ref``."""
    active = []
    for k in model.free:
        on = k not in hold and base_name(k) not in hold
        active.append(np.full(model.params[k].size, 1.0 if on else 0.0))
    active = jnp.asarray(np.concatenate(active)) if active else jnp.zeros((0,))
    if u_ref is None:
        u_ref = to_unconstrained(model)
    return {"data": data, "active": active, "u_ref": jnp.asarray(u_ref)}


def weights(sigma, saturated, xp=jnp):
    """1/σ, 0 on the ``saturated`` (masked) pixels."""
    return xp.where(saturated, 0.0, 1.0 / sigma)


# ------------------------------------------------------------------------- solving

class Fitter:
    """Compiled least-squares machinery for one :class:`FitModel`: the solver step, the
    residuals and their Jacobian, compiled once and reused for any start ``u0`` and any
    data ``args`` of the same shapes (so a recovery study compiles once).

    ``args`` comes from :func:`make_args`: per configuration ``(ζ_obs, weight)``, both
    (K_c, h, w); the residual is ``(ζ_pred − ζ_obs)·weight`` with weight = 1/σ, 0 on
    saturated pixels.

    ``devices`` (a count, as ``--devices``; default one device): the Jacobian's columns
    are shared out over that many devices (see :func:`make_residual_fn`); a Fitter on
    several devices is for one fit at a time (many fits: :func:`difstar._batch_fits.solve_many`
    with a one-device Fitter).
    """

    def __init__(self, model: FitModel, *, method: str = "lm", rtol: float = 1e-6,
                 atol: float = 1e-6, devices=None):
        self.model = model
        mesh = None
        if devices is not None:
            mesh = device_mesh(devices)
            mesh = mesh if mesh.size > 1 else None
        #: the mesh the Jacobian's columns are shared out over (None: one device)
        self.mesh = mesh
        fn = make_residual_fn(model, mesh=mesh)
        self._fn = fn
        self._lm = LMStepper(fn, method=method, rtol=rtol, atol=atol)
        self._init, self._step = self._lm._init, self._lm._step  # for batched solves
        self.method = method

        def flat(u, a):
            r = fn(u, a)
            return jnp.concatenate([v.ravel() for v in jax.tree_util.tree_leaves(r)])

        self._flat = eqx.filter_jit(flat)
        self._jac = eqx.filter_jit(jax.jacfwd(flat), **solver_jit_options())
        # one compiled prediction (the photometric start, the reweighting's σ, the
        # restarts and the outputs all read it): a second program for the mosaics alone
        # would cost a compile of the chain for nothing. It compiles during the solver's
        # step (compiled ahead, on the other core), so with the solver's options: a
        # shorter compile (1.4–1.9 s against 2.1–2.6 s on the 2-core machine) leaves
        # more of the processor to the step's, and the first step came about 0.5 s
        # sooner; it runs a few times a fit, where its speed does not show
        self._predict_full = eqx.filter_jit(
            lambda u: predict(model, from_unconstrained(model, u), full=True),
            **solver_jit_options())
        # the physical values as one compiled program (a fit's set-up and outputs read
        # them; eagerly, each bound map's operations compile one by one)
        self._values = eqx.filter_jit(lambda u: from_unconstrained(model, u))
        self._sensor_fn = make_sensor_residual_fn(model)
        self._sensor_lm = LMStepper(self._sensor_fn, method=method, rtol=rtol, atol=atol)

    def values(self, u) -> dict[str, np.ndarray]:
        """Every parameter's physical value at ``u`` (:func:`from_unconstrained`)."""
        return {k: np.asarray(v) for k, v in self._values(jnp.asarray(u)).items()}

    def residuals(self, u, args) -> np.ndarray:
        return np.asarray(self._flat(u, args))

    def loss(self, u, args) -> float:
        r = self.residuals(u, args)
        return float(0.5 * r @ r)

    def predict(self, u, *, full: bool = False) -> dict:
        """{config: the RAW mosaics ζ (K_c, h, w)} at ``u`` (``full``: the whole
        Predictions)."""
        out = self._predict_full(u)
        return out if full else {k: p.cfa for k, p in out.items()}

    def solve(self, u0, args, *, max_steps: int = 100, ftol: float = 1e-6,
              progress: Callable[[int, float, float, bool, np.ndarray], None] | None = None
              ) -> SolveResult:
        """See :meth:`difstar._lm.LMStepper.solve` (the stopping rule)."""
        return self._lm.solve(u0, args, max_steps=max_steps, ftol=ftol, progress=progress)

    def compile_ahead(self, u0, args) -> None:
        """Start compiling the solver's step for ``u0``, ``args``'s shapes on a
        background thread (:meth:`difstar._lm.LMStepper.compile_ahead`), to be used by
        the next :meth:`solve` of those shapes."""
        self._lm.compile_ahead(jnp.asarray(u0), args)

    def linear_images(self, u) -> dict:
        """{config: the linear images (K_c, 3, h, w) at ``u``}, for :meth:`sensor_args`."""
        return {k: p.image for k, p in self.predict(u, full=True).items()}

    def sensor_args(self, u, data: dict, channel: int, images: dict) -> dict:
        """``args`` for :meth:`solve_sensor` and :meth:`sensor_loss`: channel
        ``channel``'s sensor parameters free, all else held at ``u``, where ``images``
        (:meth:`linear_images`) were predicted."""
        return {"data": data, "image": images, "u_ref": jnp.asarray(u),
                "index": jnp.asarray(sensor_index(self.model, channel))}

    @staticmethod
    def _sensor_start(u, args) -> np.ndarray:
        # NumPy: an eager gather would compile an operation of its own
        return np.asarray(u)[np.asarray(args["index"])]

    def sensor_loss(self, u, args) -> float:
        """The loss at ``u`` with the optics held (``args`` from :meth:`sensor_args`)."""
        r = jax.tree_util.tree_leaves(self._sensor_fn(self._sensor_start(u, args), args))
        return float(sum(0.5 * np.sum(np.square(np.asarray(v))) for v in r))

    def solve_sensor(self, u0, args, *, max_steps: int = 100, ftol: float = 1e-6
                     ) -> SolveResult:
        """Solve for one channel's sensor parameters alone from ``u0``, the optics held
        (``args`` from :meth:`sensor_args`); each step costs the sensor, not the PSF.
        The result's ``u`` is the whole vector."""
        res = self._sensor_lm.solve(self._sensor_start(u0, args), args,
                                    max_steps=max_steps, ftol=ftol)
        u = np.array(args["u_ref"])
        u[np.asarray(args["index"])] = np.asarray(res.u)
        return dataclasses.replace(res, u=jnp.asarray(u), state=None)

    def covariance(self, u, args, solved: SolveResult | None = None):
        """Gauss–Newton covariance of the free parameters at ``u``.

        Cov_u = (JᵀJ)⁺ (pseudo-inverse: the vertex deviations' mean-free gauge leaves
        null directions) with J the Jacobian of the σ-weighted residuals, mapped to
        physical units through the diagonal Jacobian of the bounds transform. Returns the
        covariance (physical units, flattened free parameters), standard errors per
        parameter and diagnostics (χ², degrees of freedom, reduced χ², condition number
        of JᵀJ). ``solved``: the solve (of this Fitter, on ``args``)
        that ended at ``u``: its last linearisation gives the Jacobian, so nothing more
        is compiled or evaluated (without it, the Jacobian is computed anew)."""
        if solved is not None and solved.state is not None and np.array_equal(
                np.asarray(solved.u), np.asarray(u)):
            j, r = self._lm.linearisation(solved)
        else:
            j, r = np.asarray(self._jac(u, args)), self.residuals(u, args)
        return _covariance(self.model, j, r, u)


# --------------------------------------------------------------------- uncertainty

def _covariance(model: FitModel, j: np.ndarray, r: np.ndarray, u):
    jtj = j.T @ j
    cov_u = normal_covariance(j)[0]

    def xflat(u_):
        x = from_unconstrained(model, u_)
        return jnp.concatenate([x[k].ravel() for k in model.free])

    dxdu = np.asarray(jax.jit(jax.jacfwd(xflat))(u))  # one program, not many eager ones
    cov = dxdu @ cov_u @ dxdu.T
    se = np.sqrt(np.clip(np.diag(cov), 0, None))
    out = {}
    i = 0
    for k in model.free:
        p = model.params[k]
        out[k] = se[i : i + p.size].reshape(p.shape)
        i += p.size
    n_used = int(np.count_nonzero(r))
    w = np.linalg.eigvalsh(jtj) if jtj.size else np.array([1.0])
    dof = max(n_used - model.n_free, 1)
    diag = {
        "chi2": float(r @ r), "n_residuals": n_used, "n_free": model.n_free, "dof": dof,
        "reduced_chi2": float(r @ r) / dof,
        "jtj_condition": float(w.max() / max(w.min(), 1e-300)),
    }
    return cov, out, diag


__all__ = ["CameraConstants", "ConfigSpec", "CaptureSpec", "FitModel", "SolveResult",
           "to_unconstrained", "from_unconstrained", "camera_scene", "predict", "noise_sigma",
           "make_residual_fn", "make_args", "weights", "Fitter", "pupil_of", "sensor_of",
           "make_sensor_residual_fn", "sensor_index", "exposure_times"]
