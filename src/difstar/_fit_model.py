"""The RAW fit's model: what is fixed (the camera's known values, the configurations'
geometry and grids, the captures' exposure times and regions), every parameter as a
:class:`difstar.Param`, the one bound map between the solver's vector ``u`` and the
physical values, and the prediction of every capture's RAW mosaic through
``difstar.simulate`` and nothing lower.

Captures of one configuration (one focus setting: an exposure bracket) share one PSF:
``simulate`` is vmapped over the exposure time only, and JAX keeps the PSF computation
unbatched. Configurations on one grid are one ``lax.map`` (:func:`jointly`): the chain
is traced and compiled once for all of them (:func:`merged_grid` makes that grid). The
residuals, their Jacobian and the solver: :mod:`difstar._fit`.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._chain import Camera, Grid, Lens, Scene, Sensor, geometry_of, simulate
from ._detector import Blur, Halo
from ._fit_params import (
    blur_layers,
    blur_reach,
    builder_parameters,
    param_shape,
    unit_of,
    zernike_index,
)
from ._image import DiscSource
from ._param import ForwardModel, Param
from ._pupil import Polygon, RegularPolygon
from ._pupil_curved import CurvedIris
from ._sensor import Response
from ._zernike import Zernike


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
    grid, with as many captures each (:func:`equal_brackets`)."""
    cfgs = model.configs
    return (len(cfgs) > 1 and all(c.grid == cfgs[0].grid for c in cfgs)
            and equal_brackets(model.captures, [c.name for c in cfgs]))


def equal_brackets(captures, names) -> bool:
    """Whether the configurations ``names`` have as many of ``captures`` each."""
    return len({sum(c.config == k for c in captures) for k in names}) == 1
