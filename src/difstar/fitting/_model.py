"""The forward model: :class:`ImageModel` predicts the data's image from named values
(source, detector effects: shifts, distortion, resampling kernels)."""

from __future__ import annotations

import copy
import dataclasses
import functools
import re
from collections.abc import Mapping, Sequence
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._custom_types import ScalarLike
from .._param import ForwardModel
from .._psf import plan_psf, psf
from .._pupil import distorted
from .._sensor import response_curve
from .._zernike import Zernike
from ._centred import fine_factor, image_from_psf
from ._detector import (
    DiscSource,
    Halo,
    Jitter,
    NativePixel,
    Resampling,
    SourceImage,
    halos_of,
    source_of,
)
from ._params import _PITCH, ARCSEC, FitInputError, _as_param
from ._parts import Light, PupilBuilder
from ._plans import PLAN_HEADROOM, PLAN_MARGIN, Shifted, as_fine

#: Parameters every model has, with defaults (SI units except where noted).
#: The detector's layers add theirs (:mod:`._detector`: ``jitter``, each halo's).
COMMON = {"rotation": 0.0, "x0": 0.0, "y0": 0.0, "flux": 1.0, "background": 0.0,
          "pixel_scale": 0.03, "shear": 0.0, "aspect": 0.0}

#: the image distortion's parameters (:func:`image_distortion`)
DISTORTION = ("shear", "aspect")

#: The detector's response curve (:func:`difstar._sensor.response_curve`): the image is
#: ``white`` · Z(I / ``white``; ``toe``, ``knee``) + background, I the linear image.
RESPONSE = {"white": 1.0, "toe": 0.0, "knee": 60.0}

#: The unit of every parameter a model can have besides its detector layers' (theirs:
#: :attr:`ImageModel.units`; result.json's "units", the FITS keywords' comments);
#: ``z<j>`` are nm RMS (:func:`parameter_unit`). "1": a pure number.
UNITS = {"rotation": "deg, counter-clockwise", "x0": "data px right of centre",
         "y0": "data px down from centre", "pixel_scale": "arcsec per data px",
         "flux": "data units x exposure", "background": "data units",
         "shear": "1", "aspect": "1",
         "white": "data units", "toe": "1, of I / white",
         "knee": "1", "flat_to_flat": "m", "gap": "m", "obstruction": "m, radius",
         "strut_width": "m", "strut_spread": "deg", "strut_tilt": "deg, from 90",
         "incoherent": "1, fraction of the light", "radius": "m",
         "iris_radius": "m, circumradius", "curvature": "1, R x curvature"}


#: the detector layers every model has (its halos: one, ``halo``, unless it is given others)
DEFAULT_LAYERS = (Jitter(), Halo())


def parameter_unit(name: str, model: ImageModel | None = None) -> str:
    """The unit of parameter ``name`` (a per-capture copy "x0@1" has x0's): from
    ``model``'s detector layers (default: a model's default layers), :data:`UNITS`, "nm
    RMS" for a Zernike term ``z<j>``."""
    base = name.split("@")[0]
    layers = DEFAULT_LAYERS if model is None else model.layers
    for layer in layers:
        if base in layer.units:
            return layer.units[base]
    if re.fullmatch(r"z\d+", base):
        return "nm RMS"
    if base not in UNITS:
        raise KeyError(f"parameter_unit: no unit for {name!r}; add it to fitting._model.UNITS.")
    return UNITS[base]


def parameter_defaults(pupil: PupilBuilder, *, zernike: Sequence[int] = (),
                       source: Any = "point", response: bool = False,
                       halos: Sequence[Halo] = (Halo(),)) -> dict[str, float]:
    """Every parameter a model of these parts has, with its default: the common ones,
    the detector layers' (the jitter, each halo's), the pupil builder's, ``z<j>`` for
    each Zernike term, a disc source's radius and the response curve's. The one list
    :class:`ImageModel` and a manifest's ``params`` are checked against."""
    zern = {f"z{int(j)}": 0.0 for j in zernike}
    # a halo may take no name another part has, whether this model has that part or not
    taken = (set(COMMON) | set(pupil.defaults) | set(zern) | set(Jitter().parameters)
             | set(DiscSource().parameters) | set(RESPONSE))
    # the detector's after the pixel scale, before the distortion: the order of the
    # solver's vector (which a long, flat valley's end can depend on) as it always was
    out = {k: v for k, v in COMMON.items() if k not in DISTORTION} | Jitter().parameters
    for halo in halos:
        clash = sorted(set(halo.parameters) & (taken | set(out)))
        if clash:
            raise FitInputError(f"halos: the halo {halo.name!r} has the parameters "
                                f"{sorted(halo.parameters)}: the names {clash} are taken "
                                "with other parameters of the model; name the halo otherwise.")
        out |= halo.parameters
    out |= {k: COMMON[k] for k in DISTORTION} | dict(pupil.defaults) | zern
    layer = source_of(source)
    if layer is not None:
        out |= layer.parameters
    if response:
        out |= RESPONSE
    return out

def _resampling_order(resampling) -> int:
    """``None`` (no resampling modelled) → 0; ``"lanczos<a>"`` (a = 2 … 5) or
    :class:`Resampling` (a) → a."""
    if resampling is None:
        return 0
    if isinstance(resampling, Resampling):
        return resampling.order
    m = re.fullmatch(r"lanczos([2-5])", str(resampling).lower())
    if m is None:
        raise FitInputError(f"ImageModel: resampling must be null or 'lanczos2' … "
                            f"'lanczos5' (the kernel that resampled the data, e.g. SWarp's "
                            f"RESAMPT1 = LANCZOS3); got {resampling!r}.")
    return int(m.group(1))

def image_distortion(shear, aspect):
    """The image-plane linear map D = [[1, 0], [shear, 1 + aspect]] (x right, y up): the
    data's y axis keeps its direction (so ``rotation`` is read against it), a direction
    at angle θ tilts by about shear·cos²θ, and y is stretched by 1 + aspect. A resampled
    (drizzled) or distorted detector grid has such a map; it moves the spikes of a rigid
    pupil off their 60° spacing."""
    return jnp.array([[1.0, 0.0], [shear, 1.0 + aspect]])

def _oriented(pup, v, has_distortion: bool):
    """``pup`` rotated by ``rotation`` and, with ``has_distortion``, distorted by
    ``shear``, ``aspect``."""
    pup = pup.transformed(jnp.deg2rad(v["rotation"]))
    if has_distortion:
        d = image_distortion(v["shear"], v["aspect"])
        pup = distorted(pup, jnp.linalg.inv(d).T)  # the pupil map for image map D
    return pup


@functools.lru_cache(maxsize=32)
def _compiled_build(build, has_distortion: bool):
    """A pupil builder's ``build`` (or ``segment``) and the orientation as one compiled
    function of the values (:meth:`ImageModel.concrete_pupil`)."""
    return eqx.filter_jit(lambda v: _oriented(build(v), v, has_distortion))


class ImageModel(ForwardModel):
    """A star image (the image fit's :class:`ForwardModel`): pupil builder, wavefront
    (Zernike Noll indices), light, detector.

    ``params``: name → :class:`Param` (or a number, or a dict with value/free/bounds/
    scale) for the common parameters (``rotation`` deg, ``x0``, ``y0`` data pixels,
    ``flux``, ``background``, ``pixel_scale`` arcsec per data pixel, ``jitter`` σ in data
    pixels; for each of ``halos`` (:class:`Halo`, default one named ``halo``) its
    fraction ``<name>`` and σ ``<name>_width`` in data pixels (each moves a fraction of
    the light into a Gaussian: scattered light; a segmented mirror's phasing errors
    scatter light into a halo about one segment's diffraction pattern wide, a co-add's
    misregistration and a detector's charge diffusion spread the core); ``shear`` and
    ``aspect``: the image-plane distortion of :func:`image_distortion`), the pupil
    builder's and ``z<j>`` (nm RMS) for each Noll index in ``zernike``. A segmented
    builder (one with a ``segment``, :func:`jwst_pupil`) adds ``incoherent``, a fraction
    f in [0, 1]: the image is (1 − f) × the whole pupil's + f × one segment's own pattern
    (same orientation and shift), which is the mean image for random phasing errors of
    RMS φ between the segments with f = 1 − e^(−φ²) (the cross terms between segments
    average out; the segments' patterns differ only in phase, so their sum is the one
    segment's; struts and obstruction crossing a segment are left out of it). ``oversample``:
    data pixels per native detector pixel (drizzled or oversampled data: the PSF is
    integrated over the data's fine pixels, then convolved with a native pixel's box);
    ``pad``: extra data pixels computed around the window so the blur does not wrap.
    ``accuracy``: the PSF engine's target.

    ``source``: "point" (default); "disc" (:class:`DiscSource`), a uniform disc of radius
    ``source_radius`` (data pixels; its transform 2 J1(x)/x multiplies the image's
    spectrum, like the blurs); or a 2-D array (:class:`SourceImage`), the source as the
    data's pixels would see it (any size up to the padded window, its centre pixel
    shape // 2 at the star's position). ``response``:
    the detector's response curve, the image becomes ``white`` · Z(I / ``white``) +
    background with the toe and knee of :func:`difstar._sensor.response_curve` (the
    camera fitter's curve) — for images that saturate softly; hard-clipped pixels are
    better masked (``FitData.from_array(..., saturation=level)``)."""

    def __init__(self, pupil: PupilBuilder, params: Mapping[str, Any], *, light: Light,
                 zernike: Sequence[int] = (), oversample: float = 1.0, pad: int = 8,
                 accuracy: float = 1e-2, max_shift: float = 4.0, source: Any = "point",
                 response: bool = False, resampling: str | Resampling | None = None,
                 halos: Sequence[Halo | str | Mapping] | None = None):
        self.pupil = pupil
        self.resampling = _resampling_order(resampling)
        #: the source's layer: None (a point), :class:`DiscSource` or :class:`SourceImage`
        self.source = source_of(source)
        self.response = bool(response)
        self.light = light
        self.zernike = tuple(int(j) for j in zernike)
        if any(j < 2 for j in self.zernike):
            raise FitInputError("ImageModel: Zernike Noll indices must be >= 2 (1 is piston).")
        self.oversample = float(oversample)
        self.pad = int(pad)
        self.accuracy = float(accuracy)
        self.max_shift = float(max_shift)
        #: the halos (:class:`Halo`), each a fraction of the light in a Gaussian
        self.halos = halos_of(halos)
        defaults = parameter_defaults(pupil, zernike=self.zernike, source=self.source,
                                      response=self.response, halos=self.halos)
        unknown = set(params) - set(defaults)
        if unknown:
            raise FitInputError(f"ImageModel: unknown parameters {sorted(unknown)}; known: "
                                f"{sorted(defaults)}.")
        self.params = {k: _as_param(params.get(k, v)) for k, v in defaults.items()}
        ps = self.params["pixel_scale"]
        for v in [ps.value, *(ps.bounds or ())]:
            if not 1e-4 < v < 100:
                raise FitInputError(f"ImageModel: pixel_scale {v} is not in arcsec per pixel "
                                    "(expected 1e-4 … 100).")
        for k, lo in (("source_radius", 0.0), ("white", 1e-300), ("knee", 1e-300),
                      ("toe", 0.0), *((f"{h.name}_width", 0.0) for h in self.halos)):
            p = self.params.get(k)
            if p is not None and min([p.value, *(p.bounds or ())]) < lo:
                raise FitInputError(f"ImageModel: {k} = {p.value} (bounds {p.bounds}) must be "
                                    f"{'>= 0' if lo == 0 else '> 0'}.")
        for k in ("incoherent", *(h.name for h in self.halos)):
            p = self.params.get(k)
            if p is not None and not 0 <= min([p.value, *(p.bounds or ())]) <= max(
                    [p.value, *(p.bounds or ())]) <= 1:
                raise FitInputError(f"ImageModel: {k} = {p.value} (bounds {p.bounds}) is "
                                    "a fraction of the light: keep it and its bounds in [0, 1].")
        for j in self.zernike:
            p = self.params[f"z{j}"]
            if max([abs(p.value), *(abs(b) for b in (p.bounds or ()))]) > 1e4:
                raise FitInputError(f"ImageModel: z{j} = {p.value} (bounds {p.bounds}) is "
                                    "not in nm RMS (over 10 µm).")
        self._plans = {}
        self.per_capture: tuple[str, ...] = ()

    def for_captures(self, per_capture: Sequence[str], n: int) -> ImageModel:
        """A copy for ``n`` captures fitted together: each name in ``per_capture`` (e.g.
        ``x0``, ``y0``, ``flux``, ``background``) gets one parameter per capture,
        ``name@i`` (a copy of the original's value, bounds and free flag); every other
        parameter (pupil, rotation, wavefront, detector) is shared by all captures."""
        unknown = set(per_capture) - set(self.params)
        if unknown:
            raise FitInputError(f"per_capture: unknown parameters {sorted(unknown)}.")
        params = {}
        for k, p in self.params.items():
            if k in per_capture:
                params[k] = dataclasses.replace(p, free=False)
                for i in range(n):
                    params[f"{k}@{i}"] = dataclasses.replace(p)
            else:
                params[k] = dataclasses.replace(p)
        return self._copy(params=params, per_capture=tuple(per_capture))

    def _copy(self, **changes) -> ImageModel:
        """A copy with ``changes`` (attribute → value) set; its PSF plans and source
        layer are shared with this model's (they depend on neither the values nor which
        parameters are free)."""
        m = copy.copy(self)
        m.__dict__.update(changes)
        return m

    def capture_values(self, v: Mapping[str, Any], i: int) -> dict:
        """The values capture ``i`` sees: its own ``name@i`` for the per-capture names."""
        if not self.per_capture:
            return dict(v)
        return {**v, **{k: v[f"{k}@{i}"] for k in self.per_capture}}

    def expand(self, names: Sequence[str], n: int) -> list[str]:
        """Stage names with each per-capture name replaced by its ``name@i``."""
        out = []
        for k in names:
            out += [f"{k}@{i}" for i in range(n)] if k in self.per_capture else [k]
        return out

    # names
    @property
    def names(self) -> list[str]:
        return list(self.params)

    def with_values(self, values: Mapping[str, float], free: Sequence[str] | None = None):
        """A copy with new values (and, if given, only ``free`` left free)."""
        params = {}
        for k, p in self.params.items():
            q = dataclasses.replace(p, value=float(values.get(k, p.value)))
            if free is not None:
                q.free = k in free and p.free
            if q.bounds is not None:
                q.value = min(max(q.value, q.bounds[0]), q.bounds[1])
            params[k] = q
        return self._copy(params=params)

    def with_resampling(self, resampling: str | Resampling | None) -> ImageModel:
        """A copy whose detector models a co-add resampled with ``resampling`` (null or
        'lanczos2' … 'lanczos5', as the constructor takes it); every parameter and plan
        kept (the kernel does not change the PSF's plan)."""
        return self._copy(resampling=_resampling_order(resampling))

    def _bound(self, name, pick):
        p = self.params[name]
        vals = [p.value] + (list(p.bounds) if (p.free and p.bounds) else [])
        return pick(vals)

    @property
    def has_incoherent(self) -> bool:
        """Whether the image has the segments' incoherent part (``incoherent`` free or
        not 0; only for a pupil builder with a ``segment``)."""
        p = self.params.get("incoherent")
        return (self.pupil.segment is not None and p is not None
                and (p.free or p.value != 0))

    @property
    def has_distortion(self) -> bool:
        """Whether the pupil is distorted (``shear`` or ``aspect`` free or not 0)."""
        return any(self.params[k].free or self.params[k].value != 0
                   for k in ("shear", "aspect"))

    @property
    def plan_cache(self) -> dict:
        """The PSF plans this model made (:meth:`plan`), shared by every copy
        :meth:`with_values`, :meth:`for_captures` and :meth:`with_resampling` make: it
        stands for the model's construction (pupil builder, light, Zernike terms,
        detector options, source) in :meth:`trace_key`."""
        return self._plans

    def trace_key(self) -> tuple:
        """What a trace of :meth:`image` depends on besides the values: the model's
        construction (by its :attr:`plan_cache`, which a caller keeps alive while it
        uses the key), the resampling, the parameters' names, the per-capture names, and
        which optional parts are on (the segments' incoherent part, the distortion)."""
        return (id(self._plans), self.resampling, tuple(self.params), self.per_capture,
                self.has_incoherent, self.has_distortion)

    def padded_shape(self, shape) -> tuple[int, int]:
        """The window the PSF is computed on for a data window ``shape``: ``pad`` data
        pixels more on every side (light from outside the window that falls into it)."""
        return (int(shape[0]) + 2 * self.pad, int(shape[1]) + 2 * self.pad)

    def plan(self, shape, light: Light | None = None, *, segment: bool = False,
             margin: float = PLAN_MARGIN, headroom: float = PLAN_HEADROOM,
             reuse: bool = True):
        """The PSF plan for an output window ``shape`` (data pixels, padding included) and
        ``light`` (default: the model's), made once (cached) with the largest angular
        scale and star shift the bounds allow and the Zernike terms at ``margin`` × the
        model's values, a free term at least at ``headroom`` × its bounds' reach (a fit
        checks with :meth:`plan_holds` that its answer stays within them). ``segment``:
        the plan of one segment's pattern (the incoherent part; tilt only, no Zernike
        terms), which the whole pupil's plan makes and caches as well, so that
        :meth:`image` finds it inside a trace.

        ``reuse``: a plan made before for this window and light serves instead wherever
        it is fine enough for these values (the plan of ``margin`` 1, with the
        ``headroom``): a later stage then runs the programs an earlier one compiled,
        where the values grew a little, rather than a plan of its own (the automatic
        Spitzer fit's last whole-image stage compiled its solver again for one more
        sub-cell). A stage's answer is checked by :meth:`plan_holds` either way."""
        light = self.light if light is None else light
        key = self._plan_key(shape, light, segment, margin, headroom)
        if not reuse:
            if key not in self._plans:
                self._plans[key] = self._make_plan(shape, light, segment, dict(key[3]))
            return self._plans[key]
        in_use = ("in use",) + key
        if in_use not in self._plans:
            need = self.plan(shape, light, segment=segment, margin=1.0, headroom=headroom,
                             reuse=False)
            made = self._plans.setdefault(("made",) + key[:3], [])
            plan = next((old for old in reversed(made) if as_fine(old, need)), None)
            if plan is None:
                plan = self.plan(shape, light, segment=segment, margin=margin,
                                 headroom=headroom, reuse=False)
                made.append(plan)
            self._plans[in_use] = plan
        return self._plans[in_use]

    def _plan_key(self, shape, light, segment, margin, headroom) -> tuple:
        # the Zernike terms (the whole pupil's only) at margin × their values: their
        # slope sets the pupil's sub-cells, whose number grows with it (planning for the
        # bounds' extremes made the Spitzer fit's pupil 5× finer than its answer needs)
        coeffs = {} if segment else {
            j: 1e-9 * margin * self._planned_size(f"z{j}", headroom) for j in self.zernike}
        coeffs = {j: c for j, c in coeffs.items() if c > 0}
        return (tuple(shape), tuple(light.wavelengths), segment, tuple(sorted(coeffs.items())))

    def _make_plan(self, shape, light, segment, coeffs):
        """A new plan for ``shape``, ``light`` and the Zernike ``coeffs`` (m RMS by Noll
        index; :meth:`_plan_key`'s last part)."""
        if not segment and self.has_incoherent:
            self.plan(shape, light, segment=True)
        ang = self._bound("pixel_scale", min) * ARCSEC
        z = _PITCH / ang
        pupil = self.concrete_pupil(segment=segment)
        r = float(self.pupil.segment_radius if segment else self.pupil.max_radius)
        # the widest shift of the star any value or bound allows (x0@i: each capture's)
        shift = max([self.max_shift] + [abs(b) for k, p in self.params.items()
                                         if k.split("@")[0] in ("x0", "y0")
                                         for b in [p.value, *(p.bounds or ())]])
        tilt = shift * self._bound("pixel_scale", max) * ARCSEC
        wf = Shifted(Zernike(coeffs, r) if coeffs else None, tilt, tilt)
        # where the data's pixels undersample the intensity, point samples q times finer
        # (the pixels and the blurs then act exactly: :meth:`image`)
        q = fine_factor(self, light)
        plan = plan_psf(pupil,
                        wavelength=np.asarray(light.wavelengths), z_image=z,
                        pixel_pitch=_PITCH / q, shape=(shape[0] * q, shape[1] * q),
                        sampling="point" if q > 1 else "pixel",
                        accuracy=self.accuracy, wavefront=wf, max_radius=r)
        return plan

    def _planned_size(self, name: str, headroom: float) -> float:
        """|value| of a Zernike term, or for a free one at least ``headroom`` × the
        largest |bound| (nm)."""
        p = self.params[name]
        size = abs(float(p.value))
        if p.free and p.bounds is not None and headroom > 0:
            size = max(size, headroom * max(abs(float(b)) for b in p.bounds))
        return size

    def plan_holds(self, values: Mapping[str, float], shape,
                   light: Light | None = None) -> bool:
        """Whether the plan this model made for ``shape`` and ``light`` (:meth:`plan`, at
        its own values) is fine enough for ``values`` too: the plan ``values`` need
        (margin 1, no headroom) asks no more sub-cells of the pupil and is otherwise the same."""
        used = self.plan(shape, light)
        need = self.with_values(values).plan(shape, light, margin=1.0, headroom=0.0,
                                             reuse=False)
        return as_fine(used, need)

    def _pupil_at(self, v):
        return self._oriented(self.pupil.build(v), v)

    def _oriented(self, pup, v):
        """``pup`` rotated by ``rotation`` and distorted by ``shear``, ``aspect``."""
        return _oriented(pup, v, self.has_distortion)

    def concrete_pupil(self, values: Mapping[str, Any] | None = None, *,
                       segment: bool = False):
        """The oriented pupil (or with ``segment`` its one segment) at concrete
        ``values`` (default: the model's own), built by one compiled program, kept by the
        builder: what a plan or a memory check looks at. Built eagerly, JAX would run, and
        on a first run compile, each of the builder's operations one at a time (2 s for
        the JWST pupil's 18 segments)."""
        v = self.values() if values is None else values
        build = self.pupil.segment if segment else self.pupil.build
        return _compiled_build(build, self.has_distortion)(
            {k: jnp.asarray(x, float) for k, x in v.items()})

    def image(self, v: Mapping[str, Any], shape: tuple[int, int], plan=None,
              exposure: ScalarLike = 1.0, light: Light | None = None):
        """The model image (H, W) in data pixels at values ``v`` (scalars, traceable) of
        a capture of relative ``exposure`` in ``light`` (default: the model's)."""
        img, q = self.window_psf(v, shape, plan, light)
        return image_from_psf(self, img, v, shape, q, exposure)

    def window_psf(self, v: Mapping[str, Any], shape: tuple[int, int], plan=None,
                   light: Light | None = None, *, shift: bool = True):
        """(the PSF, q): :meth:`optics` on a ``shape`` capture's padded window, q samples
        a data pixel a side, by the window's plans (``plan``: the whole pupil's); ``shift``
        False: at the window's centre, for ``image_from_psf(move=True)`` to move."""
        light = self.light if light is None else light
        (hp, wp), q = self.padded_shape(shape), fine_factor(self, light)
        plan = self.plan((hp, wp), light) if plan is None else plan
        seg = self.plan((hp, wp), light, segment=True) if self.has_incoherent else None
        return self.optics(v, light, (hp * q, wp * q), q, plans=(plan, seg), shift=shift), q

    def _wavefront_and_grid(self, v, light: Light, fine_shape, q: int):
        """The Zernike wavefront at values ``v`` (None without terms) and the window's
        grid for :func:`difstar.psf`, as :meth:`optics` and :meth:`point_plans` use them."""
        ang = v["pixel_scale"] * ARCSEC  # radians per data pixel
        zern = None
        if self.zernike:
            zern = Zernike({j: 1e-9 * v[f"z{j}"] for j in self.zernike},
                           float(self.pupil.max_radius))
        grid = dict(wavelength=np.asarray(light.wavelengths), z_image=_PITCH / ang,
                    pixel_pitch=_PITCH / q, shape=tuple(fine_shape))
        return zern, grid

    def point_plans(self, v: Mapping[str, Any], light: Light, fine_shape, q: int):
        """(whole pupil's plan, one segment's or None) of :meth:`optics` without a shift,
        as :func:`difstar.psf` plans point samples at the concrete values ``v`` (the
        Zernike terms at their values, the model's accuracy)."""
        zern, grid = self._wavefront_and_grid(v, light, fine_shape, q)
        grid.update(sampling="point", accuracy=self.accuracy)
        whole = plan_psf(self.concrete_pupil(v), wavefront=zern, **grid)
        seg = (plan_psf(self.concrete_pupil(v, segment=True), **grid)
               if self.has_incoherent else None)
        return whole, seg

    def optics(self, v: Mapping[str, Any], light: Light, fine_shape: tuple[int, int], q: int,
               *, plans, shift: bool = True):
        """The star's PSF on the ``fine_shape`` window sampled ``q`` times a data pixel a
        side (fraction of the power per sample), for the optics at values ``v``, the
        segments' incoherent part mixed in: the one place the model's pupil, wavefront
        and light become a PSF (:meth:`image`, and the centred PSF of a stage that holds
        the optics). ``plans``: (the whole pupil's, one segment's or None), as
        :meth:`plan` or :meth:`point_plans` make them. ``shift``: moved by (``x0``,
        ``y0``) as a wavefront tilt."""
        zern, grid = self._wavefront_and_grid(v, light, fine_shape, q)
        grid["weights"] = np.asarray(light.weights)
        whole_wf, seg_wf = zern, None
        if shift:
            # a shift by (x0 columns right, y0 rows down) data pixels is a tilt of the
            # wavefront: the field's phase exp(i k W) with W = −θ·x moves the image by +θ
            ang = v["pixel_scale"] * ARCSEC
            tx, ty = -v["x0"] * ang, v["y0"] * ang
            whole_wf, seg_wf = Shifted(zern, tx, ty), Shifted(None, tx, ty)
        img = psf(self._pupil_at(v), plan=plans[0], wavefront=whole_wf, **grid)
        if self.has_incoherent:
            # random phasing errors of RMS φ between segments: the mean image is
            # e^(−φ²) × the whole pupil's + (1 − e^(−φ²)) × the sum of the segments' own
            # patterns, each the one segment's shifted in the pupil (the same image)
            seg = psf(self._oriented(self.pupil.segment(v), v), plan=plans[1],
                      wavefront=seg_wf, **grid)
            img = (1.0 - v["incoherent"]) * img + v["incoherent"] * seg
        return img

    def detector_kernel(self, v: Mapping[str, Any], padded: tuple[int, int], q: int = 1,
                        *, data_grid: bool = True):
        """The transfer function of what acts on the image after the optics, on the
        half spectrum (``rfft2``) of the ``padded`` window sampled ``q`` times a data
        pixel a side: the jitter's and the halos' Gaussians, a native pixel's box
        (oversampled data), the source's disc, and with ``data_grid`` what is defined
        on the data's pixels (the co-add's resampling kernel, a source image; q = 1
        only)."""
        hp, wp = padded
        fy = np.fft.fftfreq(hp * q)[:, None] * q  # cycles per data pixel
        fx = np.fft.rfftfreq(wp * q)[None, :] * q
        kern = 1.0
        for layer in self.layers:
            kern = kern * layer.transfer(v, fx, fy)
        if data_grid and self.has_data_grid_kernel:
            if q != 1:
                raise ValueError("detector_kernel: the resampling kernel and a source image "
                                 "are defined on the data's pixels (q = 1 only).")
            kern = kern * self.data_grid_kernel((hp, wp))
        return kern

    @property
    def layers(self) -> tuple:
        """The layers after the optics that act on any grid (:mod:`._detector`): the
        jitter, each halo, a native pixel's box for oversampled data, a disc source.
        (Those on the data's pixels, a co-add's :class:`Resampling` and a
        :class:`SourceImage`: :attr:`data_grid_layers`.)"""
        native = (NativePixel(self.oversample),) if self.oversample != 1.0 else ()
        disc = (self.source,) if isinstance(self.source, DiscSource) else ()
        return (Jitter(), *self.halos, *native, *disc)

    @property
    def data_grid_layers(self) -> tuple:
        """The layers that act on the data's pixels themselves, after they sample the
        image: a co-add's :class:`Resampling`, a :class:`SourceImage`."""
        resampled = (Resampling(self.resampling),) if self.resampling else ()
        image = (self.source,) if isinstance(self.source, SourceImage) else ()
        return (*resampled, *image)

    def unit(self, name: str) -> str:
        """The unit of parameter ``name`` (:func:`parameter_unit`)."""
        return parameter_unit(name, self)

    @property
    def has_data_grid_kernel(self) -> bool:
        """Whether something acts on the data's pixels themselves after they sample the
        image: the co-add's resampling kernel, or a source image."""
        return bool(self.data_grid_layers)

    def data_grid_kernel(self, padded: tuple[int, int]):
        """The transfer function, on the half spectrum of the ``padded`` window of data
        pixels, of what acts on those pixels themselves: the co-add's resampling kernel
        and a source image (1 where neither is modelled)."""
        hp, wp = padded
        fy = np.fft.fftfreq(hp)[:, None]
        fx = np.fft.rfftfreq(wp)[None, :]
        if isinstance(self.source, SourceImage) and (
                self.source.shape[0] > hp or self.source.shape[1] > wp):
            sh, sw = self.source.shape
            raise FitInputError(f"ImageModel: the source image ({sh} × {sw}) is larger "
                                f"than the padded window {(hp, wp)}; crop it or raise pad.")
        kern = np.ones((hp, wp // 2 + 1))
        for layer in self.data_grid_layers:
            kern = kern * layer.transfer({}, fx, fy)
        return jnp.asarray(kern)

    def read_out(self, img, v: Mapping[str, Any], shape, exposure: ScalarLike = 1.0):
        """The data window (``shape``) of the padded image ``img`` (the PSF after the
        detector's blurs, unit flux) times flux and exposure, through the response
        curve, plus the background."""
        h, w = shape
        pad = self.pad
        img = v["flux"] * exposure * img[pad:pad + h, pad:pad + w]
        if self.response:
            img = v["white"] * response_curve(img / v["white"], v["toe"], v["knee"])
        return img + v["background"]

    def __call__(self, shape, values=None):
        """Concrete model image at ``values`` (default: the current values)."""
        v = self.values() if values is None else {**self.values(), **values}
        v = {k: jnp.asarray(x, float) for k, x in v.items()}
        return np.asarray(self.image(v, tuple(shape)))
