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
``difstar.simulate`` and nothing lower. Captures of one configuration (one focus
setting: an exposure bracket) share one PSF: ``simulate`` is vmapped over the exposure
time only, and JAX keeps the PSF computation unbatched. Configurations on one grid are
one ``lax.map`` (:func:`jointly`), each linearised inside it: the chain is traced and
compiled once for all of them.

The parameters, their shapes and units: :mod:`difstar._fit_params`.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._batch import device_mesh
from ._chain import Camera, Grid, Lens, Scene, Sensor, geometry_of, read_out, simulate
from ._detector import Blur, Halo
from ._fit_params import IRIS_ONLY as IRIS_ONLY
from ._fit_params import UNITS as UNITS
from ._fit_params import base_name as base_name
from ._fit_params import blur_layers, blur_reach
from ._fit_params import builder_parameters as builder_parameters
from ._fit_params import param_shape as param_shape
from ._fit_params import unit_of as unit_of
from ._fit_params import zernike_index as zernike_index
from ._image import DiscSource
from ._lm import LMStepper, SolveResult, normal_covariance, with_batched_jacobian
from ._param import ForwardModel, Param
from ._pupil import Polygon, RegularPolygon
from ._pupil_curved import CurvedIris
from ._sensor import Response
from ._xla import solver_jit_options
from ._zernike import Zernike

SHARED = ("circumradius", "curvature", "rotation", "vertex_radial", "vertex_angular",
          "source_radius", "phi0", "toe", "knee", "background")
@dataclasses.dataclass(frozen=True)
class CameraConstants:
    """What the fit takes as known. Lengths in metres."""

    focal_length: float
    principal_separation: float
    pupil_magnification: float
    pixel_pitch: float
    pattern: str
    #: one per channel (trichromatic), or 3 tuples of K with ``spectral_weights`` (3 × K,
    #: a spectral sensor: :class:`difstar.Sensor`'s)
    wavelengths: tuple
    n_blades: int
    white_balance: tuple[float, float, float] = (2.0, 1.0, 2.0)
    colour_matrix: tuple | None = None
    zernike_radius: float | None = None  # m; the Zernike terms' circle (None: no terms)
    #: the exit pupil as a :class:`difstar.PupilBuilder` of named parameters (e.g.
    #: :func:`difstar.obstructed_circle_pupil` for a mirror lens), rotated by
    #: ``rotation``; ``n_blades`` is then only the period 2π/n of the rotation. None:
    #: the ``n_blades`` iris of ``circumradius`` (and ``curvature``, vertex deviations).
    pupil: Any = None
    #: the detector's halos (:class:`difstar.Halo`): each one's parameters ``<name>`` and
    #: ``<name>_width`` may be fitted (a halo is on where its fraction is a parameter)
    halos: tuple = (Halo(),)
    spectral_weights: tuple | None = None


@dataclasses.dataclass(frozen=True)
class ConfigSpec:
    """One lens setting (focus) and object distance; its captures share the PSF."""

    name: str
    focus_distance: float
    object_distance: float
    grid: Grid


def joint_grid(grids) -> tuple[int, int] | None:
    """The period n (pixels) and oversampling q on which configurations' engine grids
    could be one (:func:`merged_grid`): the largest of each; None where they cannot
    (another method, other crops)."""
    if any(g.method != "engine" or g.psf_plan.method == "exact" for g in grids):
        return None
    if len({(g.crop, g.scaling, g.raw_only, g.psf_plan.method) for g in grids}) != 1:
        return None
    return max(g.n for g in grids), max(g.oversample for g in grids)


def merged_grid(grids) -> Grid | None:
    """One grid that holds what each of ``grids`` holds (planned on one period): the
    largest windows, sub-cells and nodes of any; None where their periods or shapes
    differ."""
    g0 = grids[0]
    if len({(g.n, g.oversample, g.crop, g.scaling, g.raw_only, g.method, g.psf_plan.method,
             g.psf_plan.period) for g in grids}) != 1:
        return None
    plans = [g.psf_plan for g in grids]
    plan = dataclasses.replace(
        plans[0], nodes=max(p.nodes for p in plans),
        pupil_window=max(p.pupil_window for p in plans),
        subcells=max(p.subcells for p in plans),
        use_defocus=any(p.use_defocus for p in plans))
    return dataclasses.replace(
        g0, use_defocus=any(g.use_defocus for g in grids), psf_plan=plan,
        source_window=max(g.source_window for g in grids),
        blur_reach=max(g.blur_reach for g in grids))


@dataclasses.dataclass(frozen=True)
class CaptureSpec:
    """One capture: its configuration, nominal exposure time (s) and the rough source
    position relative to its region's centre pixel (h//2, w//2), in pixels (row, col)."""

    name: str
    config: str
    exposure_time: float
    base_offset: tuple[float, float]


@dataclasses.dataclass(frozen=True)
class FitModel(ForwardModel):
    """The RAW fit's :class:`ForwardModel`: camera, configurations, captures, params."""

    camera: CameraConstants
    configs: tuple[ConfigSpec, ...]
    captures: tuple[CaptureSpec, ...]
    params: dict[str, Param]  # name → Param (a number or an array of param_shape)

    def __post_init__(self):
        object.__setattr__(self, "params", dict(self.params))
        for name, p in self.params.items():
            if not isinstance(p, Param):
                raise ValueError(f"parameter {name}: expected a difstar Param; got "
                                 f"{type(p).__name__}")
            want = param_shape(name, self.camera.n_blades, self.camera.pupil,
                               self.camera.halos)
            if p.shape != want:
                raise ValueError(f"parameter {name}: shape {p.shape}, expected {want}")
            if p.free and p.bounds is None:
                raise ValueError(f"parameter {name}: a free parameter of a RAW fit needs "
                                 "bounds (lo, hi)")
        cfg = {c.name for c in self.configs}
        for c in self.captures:
            if c.config not in cfg:
                raise ValueError(f"capture {c.name}: unknown configuration {c.config!r}")
        need = ("rotation", "source_radius", "phi0", "toe", "knee")
        for req in need if self.camera.pupil is not None else ("circumradius", *need):
            if req not in self.params:
                raise ValueError(f"fit model lacks parameter {req!r}")

    @property
    def n_free(self) -> int:
        return sum(self.params[k].size for k in self.free)

    def captures_of(self, config: str) -> tuple[CaptureSpec, ...]:
        return tuple(c for c in self.captures if c.config == config)

    def unit(self, name: str) -> str:
        return unit_of(name, self.camera.halos)

    def with_values(self, values, free=None) -> FitModel:
        """A copy with ``values`` as the starts (bounds kept) and, given ``free``, only
        those of the free parameters left free."""
        ps = {k: p.with_value(np.asarray(values[k], float)) if k in values else p
              for k, p in self.params.items()}
        if free is not None:
            ps = {k: dataclasses.replace(p, free=p.free and k in free) for k, p in ps.items()}
        return dataclasses.replace(self, params=ps)

    def fixed_at(self, values) -> FitModel:
        """A copy with every parameter fixed at ``values`` (default: its start)."""
        ps = {k: Param(np.asarray(values.get(k, p.value), float))
              for k, p in self.params.items()}
        return dataclasses.replace(self, params=ps)


# ---------------------------------------------------------------- parameter transforms

#: How far inside its bounds a start is moved, as a fraction of the range. The RAW fit's
#: bounds often span decades (φ0 in [1e-4, 1e4]), where the image fit's
#: :data:`difstar._param.START_MARGIN` (1e-4 of the range, here 1.0) would move a start
#: of 0.26 up to 1: only starts within 1e-9 of the range of a bound are moved.
RAW_START_MARGIN = 1e-9


def to_unconstrained(model: FitModel, values: dict | None = None) -> jax.Array:
    """Flat u for the free parameters' ``values`` (default: their starts), by the one
    bound map (:class:`difstar._param.Param`), starts moved inside by
    :data:`RAW_START_MARGIN` at most."""
    parts = [np.ravel(model.params[k].to_unconstrained(
        None if values is None else np.asarray(values[k], float), margin=RAW_START_MARGIN))
             for k in model.free]
    return jnp.asarray(np.concatenate(parts)) if parts else jnp.zeros((0,))


def from_unconstrained(model: FitModel, u: jax.Array) -> dict[str, jax.Array]:
    """Physical values of every parameter (free from ``u``, fixed from their starts)."""
    out = {}
    i = 0
    for k, p in model.params.items():
        if p.free:
            out[k] = p.from_unconstrained(u[i : i + p.size].reshape(p.shape))
            i += p.size
        else:
            out[k] = jnp.asarray(p.value)
    return out


def free_parts(model: FitModel, u) -> dict[str, np.ndarray]:
    """The solver's vector ``u`` (unconstrained values) split by free parameter."""
    ends = np.cumsum([model.params[k].size for k in model.free])
    return dict(zip(model.free, np.split(np.asarray(u), ends[:-1])))


def pupil_of(model: FitModel, x: dict):
    builder = model.camera.pupil
    if builder is not None:  # named parameters from x, the others at their defaults
        values = {k: x.get(k, v) for k, v in builder_parameters(builder).items()}
        return builder.build(values).transformed(x["rotation"])
    n = model.camera.n_blades
    r, rot = x["circumradius"], x["rotation"]
    dr = x.get("vertex_radial")
    da = x.get("vertex_angular")
    curv = x.get("curvature")
    if dr is None and da is None and curv is None:
        return RegularPolygon(n, r, rot)
    dr = jnp.zeros(n) if dr is None else dr - jnp.mean(dr)
    da = jnp.zeros(n) if da is None else da - jnp.mean(da)
    if curv is not None:
        return CurvedIris(n, r, curv, radial=dr, angular=da, rotation=rot)
    theta = rot + 2 * math.pi * jnp.arange(n) / n + da
    rad = r * (1.0 + dr)
    return Polygon(jnp.stack([rad * jnp.cos(theta), rad * jnp.sin(theta)], axis=-1))


def wavefront_of(model: FitModel, x: dict):
    """The Zernike wavefront of the ``z<j>`` parameters (nm RMS), or None."""
    terms = {zernike_index(k): 1e-9 * v for k, v in x.items() if zernike_index(k) is not None}
    if not terms:
        return None
    if model.camera.zernike_radius is None:
        raise ValueError("Zernike parameters (z<j>) need camera.zernike_radius, the circle "
                         "(metres in the exit pupil) the terms are normalised over.")
    return Zernike(terms, radius=model.camera.zernike_radius)


def sensor_of(model: FitModel, x: dict) -> Sensor:
    """The camera's sensor with the exposure scale φ0, response curves and detector blur
    (:func:`difstar._fit_params.blur_layers`) of ``x``."""
    cc = model.camera
    layers = blur_layers(model.params, cc.halos)
    blur = None
    if layers:
        names = [k for layer in layers for k in layer.parameters]
        blur = Blur(layers, {k: x[k] for k in names if k in x},
                    reach=blur_reach(model.params, layers))
    return Sensor(
        pixel_pitch=cc.pixel_pitch, pattern=cc.pattern, wavelengths=cc.wavelengths,
        phi0=x["phi0"], response=Response(toe=x["toe"], knee=x["knee"]),
        white_balance=cc.white_balance, colour_matrix=cc.colour_matrix, blur=blur,
        spectral_weights=cc.spectral_weights,
    )


def exposure_times(model: FitModel, x: dict, config: str):
    """The exposure times (K,) in seconds of ``config``'s captures: nominal × their
    ``exposure_scale/<capture>`` (1 where absent)."""
    return jnp.stack([
        c.exposure_time * x.get(f"exposure_scale/{c.name}", jnp.asarray(1.0))
        for c in model.captures_of(config)
    ])


def camera_scene(model: FitModel, x: dict, config: str):
    """From physical parameter values ``x``: the camera and scene of ``config`` (its
    first capture) and, for all its captures, the exposure times (K,) in seconds and
    the source positions (K, 2) in the object plane (metres, x right, y up)."""
    cc = model.camera
    cfg = next(c for c in model.configs if c.name == config)
    lens = Lens(
        pupil_of(model, x), focal_length=cc.focal_length, focus_distance=cfg.focus_distance,
        principal_separation=cc.principal_separation,
        pupil_magnification=cc.pupil_magnification, defocus=x.get(f"defocus/{config}"),
        wavefront=wavefront_of(model, x),
    )
    camera = Camera(lens, sensor_of(model, x))
    caps = model.captures_of(config)
    ts = exposure_times(model, x, config)
    bg = x.get("background", jnp.zeros(3))
    scene = Scene(object_distance=cfg.object_distance,
                  sources=(DiscSource(x["source_radius"]),), exposure_time=ts[0], background=bg)
    # pixel offsets (row, col) on the sensor → object-plane positions; the image of
    # (x, y) is M (x, y) and rows grow downwards
    m = geometry_of(camera, scene).magnification
    off = x.get(f"source_offset/{config}", jnp.zeros(2))
    rc = jnp.asarray([c.base_offset for c in caps]) + off[None, :]
    pos = jnp.stack([rc[:, 1] * cc.pixel_pitch / m, -rc[:, 0] * cc.pixel_pitch / m], axis=-1)
    scene = eqx.tree_at(lambda s: s.sources, scene, (DiscSource(x["source_radius"], pos[0]),))
    return camera, scene, ts, pos


def predict(model: FitModel, x: dict, *, full: bool = False) -> dict:
    """RAW mosaics ζ (K_c, h, w) per configuration (``full``: whole Predictions). The
    captures of a configuration are one vmap over exposure time (and source position,
    when the captures' rough positions differ); the PSF depends on neither, so JAX
    computes it once per configuration, and with a shared position the image too.
    Configurations on one grid with as many captures each (:func:`jointly`) are one
    ``lax.map`` over them: the chain traced and compiled once, not once per
    configuration."""
    if jointly(model):
        outs = jax.lax.map(lambda i: predict_config(model, x, i, full=full),
                           jnp.arange(len(model.configs)))
        return {cfg.name: jax.tree.map(lambda a, i=i: a[i], outs)
                for i, cfg in enumerate(model.configs)}
    return {cfg.name: _bracket(camera_scene(model, x, cfg.name), cfg.grid, full,
                               _one_position(model.captures_of(cfg.name)))
            for cfg in model.configs}


def predict_config(model: FitModel, x: dict, i, *, full: bool = False):
    """The RAW mosaics ζ (K, h, w) of configuration ``i`` (a traced index) of a model
    whose configurations are on one grid (:func:`jointly`)."""
    each = [camera_scene(model, x, cfg.name) for cfg in model.configs]
    stacked = jax.tree.map(lambda *a: jnp.stack(a), *each)
    return _bracket(jax.tree.map(lambda a: a[i], stacked), model.configs[0].grid, full,
                    all(_one_position(model.captures_of(c.name)) for c in model.configs))


def _one_position(captures) -> bool:
    return len({c.base_offset for c in captures}) == 1


def _bracket(camera_scene_of, grid: Grid, full: bool, one_position: bool):
    # one configuration's captures (camera_scene's output), one vmap over exposure time
    # and, unless they share one rough position, over the source position
    camera, scene, ts, pos = camera_scene_of

    def one(t, p):
        s = eqx.tree_at(lambda s: (s.exposure_time, s.sources[0].position), scene, (t, p))
        pr = simulate(camera, s, grid)
        return pr if full else pr.cfa

    if one_position:
        return jax.vmap(one, in_axes=(0, None))(ts, pos[0])
    return jax.vmap(one)(ts, pos)


def jointly(model: FitModel) -> bool:
    """Whether :func:`predict` maps over the configurations: more than one, all on one
    grid, with as many captures each."""
    cfgs = model.configs
    return (len(cfgs) > 1 and all(c.grid == cfgs[0].grid for c in cfgs)
            and len({len(model.captures_of(c.name)) for c in cfgs}) == 1)


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

        def item(u, args, i):
            obs = jnp.stack([args["data"][k][0] for k in names])[i]
            weight = jnp.stack([args["data"][k][1] for k in names])[i]
            return (predict_config(model, physical(u, args), i) - obs) * weight

        stacked = with_batched_jacobian(item, batch=jac_batch, mesh=mesh, items=len(names))

        def fn(u, args):
            r = stacked(u, args)
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
        # would cost a compile of the chain for nothing
        self._predict_full = eqx.filter_jit(
            lambda u: predict(model, from_unconstrained(model, u), full=True))
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
