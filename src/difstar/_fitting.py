"""Fitting a PSF model to an intensity image (a star, a measured PSF): the public API.

A model is assembled from parts with named parameters, each a :class:`Param` that is
fixed or free (with bounds):

- pupil: a *builder*, a function of the named parameters returning a difstar pupil
  (:func:`jwst_pupil`: 18 hexagonal segments, three struts, an obstruction;
  :func:`obstructed_circle_pupil`: a circular primary, obstruction and struts, e.g.
  Spitzer); the whole pupil is rotated by ``rotation`` (degrees, counter-clockwise);
- wavefront: Zernike terms by Noll index (parameters ``z4`` … in nm RMS over the
  pupil's circumscribed circle);
- light: one wavelength or a band (:class:`Light`, Gauss–Legendre nodes of a flat or
  blackbody spectrum over the band);
- source: a point at a sub-pixel position ``x0`` (columns, +right) and ``y0`` (rows,
  +down) in data pixels from the window's centre pixel (H//2, W//2), total ``flux``
  (the PSF's integral over the whole plane); the shift is a wavefront tilt, exact in
  Fraunhofer optics;
- detector: pixel integration at the data's pitch (``pixel_scale``, arcsec per data
  pixel; any z_image / pitch with the same angle), a native pixel for drizzled or
  oversampled data (a box ``native_pixel`` data pixels wide), a Gaussian blur ``jitter``
  (σ in data pixels: pointing jitter, charge diffusion, resampling) and a constant
  ``background``;
- data (:class:`FitData`): an image, per-pixel σ (given or from a noise model: read
  noise, Poisson with a gain, a relative floor), a mask of invalid pixels and a region of
  interest.

:func:`fit` runs optimistix's Levenberg–Marquardt on the free parameters mapped to O(1)
numbers (a logistic map into the bounds), stage by stage (coarse to fine: a small
central window and a few parameters first), optionally from several starts, and returns
a :class:`FitResult` (values, Gauss–Newton standard errors, χ²/dof, the residual image,
status and warnings about unconstrained parameters). The PSF's plan is made once,
outside jit, with bounds on the pupil radius and on the wavefront's slope.
"""

from __future__ import annotations

import contextlib
import dataclasses
import gc
import math
import re
import sys
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._psf import plan_psf, psf
from ._pupil import Circle, Obstructed, Struts, distorted, hex_segments
from ._sensor import response_curve
from ._validate import MAX_WAVELENGTHS
from ._zernike import Zernike

ARCSEC = math.pi / (180 * 3600)
PERTURB = 0.2  # rough starts: each free parameter within ± 20 % (perturbed_starts)
_PITCH = 1e-5  # metres: the detector pitch the model uses (only pitch / z_image matters)


class FitInputError(ValueError):
    """A fitting input that cannot be right (a unit, a bound, NaN data, nothing free)."""


# --- parameters -----------------------------------------------------------------------


@dataclasses.dataclass
class Param:
    """One named parameter: ``value`` (the start when free), ``free``, ``bounds``
    (lo, hi) for a free parameter (a logistic map keeps it inside), ``scale`` (the
    step of O(1) in the fitted variable for an unbounded parameter; default 10 % of
    |value| or 1e-3)."""

    value: Any
    free: Any = False
    bounds: Any = None
    scale: Any = None

    def __post_init__(self):
        self.value = float(self.value)
        if not math.isfinite(self.value):
            raise FitInputError(f"Param value must be finite; got {self.value}.")
        if self.bounds is not None:
            lo, hi = (float(b) for b in self.bounds)
            if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                raise FitInputError(f"Param bounds must be finite with lo < hi; got {self.bounds}.")
            self.bounds = (lo, hi)
            if self.free and not lo <= self.value <= hi:
                raise FitInputError(f"Param start {self.value} lies outside its bounds "
                                    f"{self.bounds}.")


def _as_param(p: Any) -> Param:
    if isinstance(p, Param):
        return dataclasses.replace(p)
    if isinstance(p, Mapping):
        return Param(p["value"], bool(p.get("free", False)),
                     None if p.get("bounds") is None else tuple(p["bounds"]), p.get("scale"))
    return Param(float(p))


# --- pupil builders ---------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class PupilBuilder:
    """A pupil as a function of named parameters. ``build(values)`` returns the pupil
    before the overall rotation; ``defaults`` name its parameters and their defaults (SI
    units, angles in degrees); ``max_radius`` bounds its radius over the fit (metres).

    A segmented pupil may also give ``segment(values)``, one of its segments centred on
    the origin (same orientation), and ``segment_radius``, that segment's outermost
    radius: the model then has the parameter ``incoherent``, the fraction of the light
    that falls as the segments' own diffraction patterns added incoherently (see
    :class:`ImageModel`)."""

    name: str
    build: Callable[[Mapping[str, Any]], Any]
    defaults: Mapping[str, float]
    max_radius: float
    segment: Callable[[Mapping[str, Any]], Any] | None = None
    segment_radius: float | None = None


def jwst_pupil(flat_to_flat: float = 1.32, gap: float = 0.007) -> PupilBuilder:
    """JWST-like: 18 hexagonal segments (two rings, no centre; flat top and bottom at
    rotation 0, so the six big spikes are at 90° ± k 60°), a circular central
    obstruction and three struts from the centre at 90° (up) and 270° ± ``strut_spread``
    (30° by default: their spikes lie on the hexagons' at 30° and 150°).
    Parameters: ``flat_to_flat``, ``gap``, ``obstruction`` (radius), ``strut_width``
    (metres), ``strut_spread`` and ``strut_tilt`` (the upper strut's angle from 90°),
    degrees."""

    def build(v):
        segs = hex_segments(2, v["flat_to_flat"], v["gap"])
        s = jnp.deg2rad(v["strut_spread"])
        up = 0.5 * math.pi + jnp.deg2rad(v["strut_tilt"])
        angles = jnp.stack([up, 1.5 * math.pi - s, 1.5 * math.pi + s])
        struts = Struts(angles, v["strut_width"])
        return Obstructed(segs, Circle(v["obstruction"]), struts)

    def segment(v):
        return hex_segments(0, v["flat_to_flat"], v["gap"], include_centre=True)

    r = 2 * (flat_to_flat + gap) + flat_to_flat / math.sqrt(3)  # outermost vertex
    return PupilBuilder("jwst", build, {"flat_to_flat": flat_to_flat, "gap": gap,
                                        "obstruction": 0.37, "strut_width": 0.1,
                                        "strut_spread": 30.0, "strut_tilt": 0.0,
                                        "incoherent": 0.0},
                        max_radius=1.05 * r, segment=segment,
                        segment_radius=1.05 * flat_to_flat / math.sqrt(3))


def obstructed_circle_pupil(radius: float = 0.425) -> PupilBuilder:
    """A circular primary of ``radius`` with a circular obstruction (``obstruction``,
    radius in metres) and three struts at 90° + k·120° + ``strut_offsets`` (degrees),
    ``strut_width`` metres wide (Spitzer-like)."""

    def build(v):
        angles = jnp.deg2rad(jnp.asarray([90.0, 210.0, 330.0]))
        struts = Struts(angles, v["strut_width"])
        return Obstructed(Circle(v["radius"]), Circle(v["obstruction"]), struts)

    return PupilBuilder("circle", build, {"radius": radius, "obstruction": 0.16,
                                          "strut_width": 0.03}, max_radius=1.1 * radius)


def iris_pupil(blades: int = 7, radius: float = 1.2e-3) -> PupilBuilder:
    """A camera's iris: ``blades`` blades with circular-arc edges (a regular polygon when
    ``curvature`` is 0; difstar's ``CurvedIris``), its first vertex on +x at rotation 0.
    Parameters: ``iris_radius`` (circumradius, metres; the aperture's radius is focal
    length / (2 N)) and ``curvature`` (each edge's relative curvature, R·κ: 0 straight,
    1 an arc of the circle through the vertices)."""
    from ._pupil_curved import CurvedIris

    if not isinstance(blades, (int, np.integer)) or blades < 3:
        raise FitInputError(f"iris_pupil: blades must be an integer >= 3; got {blades!r}.")

    def build(v):
        return CurvedIris(int(blades), v["iris_radius"], v["curvature"])

    return PupilBuilder("iris", build, {"iris_radius": radius, "curvature": 0.0},
                        max_radius=1.2 * radius)


BUILDERS = {"jwst": jwst_pupil, "circle": obstructed_circle_pupil, "iris": iris_pupil}


# --- light, detector, data -----------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Light:
    """Wavelengths (metres) and weights (summing to 1)."""

    wavelengths: Any
    weights: Any

    def __post_init__(self):
        lam = np.asarray(self.wavelengths, float)
        if lam.ndim != 1 or lam.size < 1 or not np.all(np.isfinite(lam)):
            raise FitInputError(f"Light: wavelengths must be finite numbers; got {lam}.")
        if lam.size > MAX_WAVELENGTHS:
            raise FitInputError(f"Light: {lam.size} wavelengths, each a PSF per model image; "
                                f"at most {MAX_WAVELENGTHS}: sample the band with fewer "
                                "(Light.band's Gauss–Legendre nodes need few).")
        if np.any(lam > 100e-6) or np.any(lam < 10e-9):
            raise FitInputError(
                f"Light: wavelengths {lam.tolist()} are not in metres (a wavelength above "
                "100 µm or below 10 nm): give e.g. 0.9e-6 for 0.9 µm.")
        w = np.asarray(self.weights, float)
        if w.shape != lam.shape or not np.all(np.isfinite(w)) or np.any(w < 0) \
                or not w.sum() > 0:
            raise FitInputError(f"Light: weights must be one finite number >= 0 per "
                                f"wavelength, not all 0; got {w.tolist()}.")

    @staticmethod
    def monochromatic(wavelength: Any) -> Light:
        return Light((float(wavelength),), (1.0,))

    @staticmethod
    def band(lo: Any, hi: Any, n: Any = 4, source: Any = "flat") -> Light:
        """``n`` Gauss–Legendre nodes over [lo, hi] (metres), weighted by a flat
        photon spectrum (``"flat"``) or a blackbody of temperature ``source`` kelvin
        (photon counts)."""
        if not (lo < hi):
            raise FitInputError(f"Light.band: need lo < hi; got {lo}, {hi}.")
        Light((lo, hi), (0.5, 0.5))  # unit check
        try:
            whole = (isinstance(n, (int, float, np.integer, np.floating))
                     and not isinstance(n, bool) and float(n) == int(n))
        except (TypeError, ValueError, OverflowError):
            whole = False
        if not (whole and 1 <= int(n) <= MAX_WAVELENGTHS):
            raise FitInputError(f"Light.band: n must be a whole number from 1 to "
                                f"{MAX_WAVELENGTHS}; got {n!r}.")
        if source != "flat" and not (isinstance(source, (int, float))
                                     and not isinstance(source, bool)
                                     and math.isfinite(source) and source > 0):
            raise FitInputError(f"Light.band: source must be 'flat' or a blackbody "
                                f"temperature in kelvin > 0; got {source!r}.")
        x, w = np.polynomial.legendre.leggauss(int(n))
        lam = 0.5 * (lo + hi) + 0.5 * (hi - lo) * x
        if source != "flat":
            t = float(source)
            h, c, k = 6.62607015e-34, 2.99792458e8, 1.380649e-23
            with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
                w = w * lam ** -4 / np.expm1(h * c / (lam * k * t))  # photons ∝ B_λ λ
            if not (np.all(np.isfinite(w)) and w.sum() > 0):
                raise FitInputError(f"Light.band: source: a blackbody of {t:g} K gives no "
                                    f"light over the band [{lo}, {hi}] m (the weights "
                                    "underflow); give a temperature in kelvin (e.g. 5000) "
                                    "or 'flat'.")
        w = w / w.sum()
        return Light(tuple(lam.tolist()), tuple(w.tolist()))


@dataclasses.dataclass(frozen=True)
class Noise:
    """σ² = read² + max(I, 0) / gain + (floor · I)² per pixel (I the data, same units).
    ``read=None``: estimated from the border of the image (median absolute deviation)."""

    read: float | None = None
    gain: float = 1.0
    floor: float = 0.0


@dataclasses.dataclass
class FitData:
    """An image to fit: ``image`` (H, W), ``sigma`` (per pixel, or from ``noise``),
    ``mask`` (True = use), cut to ``roi`` = (row0, row1, col0, col1) if given.

    ``exposure``: this capture's relative exposure (time × gain; 1 by default); the
    model's ``flux`` is multiplied by it, so the captures of an exposure bracket can
    share one flux (leave ``flux`` out of ``per_capture``). ``saturation``: pixels at or
    above this level are not used (the sensor clipped them). ``light``: this capture's
    :class:`Light` where it differs from the model's (the R, G and B photosites of one
    RAW fitted together, each in its own band)."""

    image: np.ndarray
    sigma: np.ndarray
    mask: np.ndarray
    pixel_scale: float | None = None
    path: str | None = None
    exposure: float = 1.0
    light: Any = None

    @staticmethod
    def from_array(image, *, sigma=None, noise: Noise | None = None, mask=None, roi=None,
                   pixel_scale=None, path=None, exposure=1.0, saturation=None,
                   light=None) -> FitData:
        exposure = float(exposure)
        if not (math.isfinite(exposure) and exposure > 0):
            raise FitInputError(f"FitData: exposure must be a finite number > 0 (a relative "
                                f"exposure time); got {exposure}.")
        img = np.asarray(image, dtype=float)
        if img.ndim != 2 or min(img.shape) < 4:
            raise FitInputError(f"FitData: the image must be 2-D, at least 4 × 4; got shape "
                                f"{img.shape}.")
        m = np.isfinite(img) if mask is None else (np.asarray(mask, bool) & np.isfinite(img))
        if saturation is not None:
            if not math.isfinite(float(saturation)):
                raise FitInputError(f"FitData: saturation must be a finite level; got "
                                    f"{saturation}.")
            m = m & ~(np.where(np.isfinite(img), img, 0.0) >= float(saturation))
        if roi is not None:
            r0, r1, c0, c1 = (int(v) for v in roi)
            img, m = img[r0:r1, c0:c1], m[r0:r1, c0:c1]
            if sigma is not None and np.ndim(sigma) == 2:
                sigma = np.asarray(sigma)[r0:r1, c0:c1]
        if not m.any():
            raise FitInputError("FitData: no valid pixel (all NaN, infinite or masked).")
        if np.count_nonzero(~np.isfinite(img) & m):
            raise FitInputError("FitData: NaN or infinite values in unmasked pixels.")
        img = np.where(m, img, 0.0)
        if sigma is None:
            noise = noise or Noise()
            read = noise.read
            if read is None:
                b = max(2, min(img.shape) // 10)
                border = np.concatenate([img[:b].ravel(), img[-b:].ravel(),
                                         img[:, :b].ravel(), img[:, -b:].ravel()])
                bm = np.concatenate([m[:b].ravel(), m[-b:].ravel(), m[:, :b].ravel(),
                                     m[:, -b:].ravel()])
                v = border[bm]
                read = 1.4826 * np.median(np.abs(v - np.median(v)))
                if not read > 0:
                    read = 1e-3 * np.max(np.abs(img[m]))
            if not (noise.gain > 0):
                raise FitInputError(f"Noise.gain must be > 0; got {noise.gain}.")
            var = read**2 + np.maximum(img, 0) / noise.gain + (noise.floor * img) ** 2
            sigma = np.sqrt(var)
        sigma = np.broadcast_to(np.asarray(sigma, float), img.shape).copy()
        if np.any(~np.isfinite(sigma[m])) or np.any(sigma[m] <= 0):
            raise FitInputError("FitData: sigma must be finite and > 0 on every used pixel.")
        sigma[~m] = 1.0
        if light is not None and not isinstance(light, Light):
            raise FitInputError("FitData: light must be a difstar Light (Light.monochromatic or "
                                f"Light.band); got {type(light).__name__}.")
        return FitData(img, sigma, m, pixel_scale, path, exposure, light)

    @staticmethod
    def from_file(path, **kw) -> FitData:
        from .io._images import read_image

        im = read_image(path)
        kw.setdefault("pixel_scale", im.pixel_scale)
        mask = im.valid if kw.get("mask") is None else (im.valid & kw.pop("mask"))
        kw.pop("mask", None)
        return FitData.from_array(im.data, mask=mask, path=str(path), **kw)

    @staticmethod
    def from_raw(raw, *, channel="G", gain_e_per_dn, read_noise_dn, roi=None,
                 pixel_scale=None, exposure=1.0, light=None) -> FitData:
        """The pixels of one colour of a Bayer RAW mosaic as data for the image fit.

        ``raw``: a path (read by :func:`difstar.io.read_raw`: any Bayer layout LibRaw
        decodes, colour matrix or not; X-Trans, Foveon and monochrome sensors are
        refused there) or a :class:`difstar.io.RawCapture`. The image is the whole
        mosaic ζ = (raw − black)/(white − black) on its own pixel grid, so the model is
        integrated over each photosite at the sensor's pitch; the mask keeps only the
        photosites of ``channel`` ("R", "G" or "B", as the file's pattern places them)
        that are not saturated. σ² = read_noise_dn² + (raw − black)/gain_e_per_dn (DN²;
        Poisson in electrons), divided by (white − black)². ``roi`` = (row0, row1, col0,
        col1) cuts a window around the source (keep row0 and col0 even to keep the
        pattern's phase — any offset works, the mask follows the photosites).
        ``pixel_scale``: arcsec per pixel (pitch / focal length). ``exposure`` and
        ``light``: as for :meth:`from_array` (the channel's band)."""
        from ._cfa import channel_index
        from .io._raw import RawCapture, read_raw

        cap = raw if isinstance(raw, RawCapture) else read_raw(raw)
        if channel not in ("R", "G", "B"):
            raise FitInputError(f"FitData.from_raw: channel must be 'R', 'G' or 'B'; got "
                                f"{channel!r}.")
        if not (gain_e_per_dn > 0 and read_noise_dn >= 0):
            raise FitInputError("FitData.from_raw: gain_e_per_dn must be > 0 and "
                                f"read_noise_dn >= 0; got {gain_e_per_dn}, {read_noise_dn}.")
        colour = channel_index(cap.shape, cap.pattern)  # 0 R, 1 G, 2 B
        scale = cap.white_level - cap.black_level_tile.mean()
        signal_dn = np.maximum(cap.cfa * scale, 0.0)
        sigma = np.sqrt(read_noise_dn**2 + signal_dn / gain_e_per_dn) / scale
        mask = (colour == "RGB".index(channel)) & ~cap.saturated
        return FitData.from_array(cap.cfa, sigma=sigma, mask=mask, roi=roi,
                                  pixel_scale=pixel_scale, path=str(cap.path),
                                  exposure=exposure, light=light)

    def annulus(self, r_min: float, r_max: float) -> FitData:
        """Only the pixels between ``r_min`` and ``r_max`` pixels of the centre pixel
        (e.g. the spikes, without the core)."""
        h, w = self.image.shape
        r, _ = _polar((h, w), (w // 2, h // 2))
        return dataclasses.replace(self, mask=self.mask & (r >= r_min) & (r <= r_max))

    def cropped(self, half: int) -> FitData:
        """The central (2 half + 1)² window (around the data's centre pixel)."""
        h, w = self.image.shape
        r0, c0 = max(0, h // 2 - half), max(0, w // 2 - half)
        r1, c1 = min(h, h // 2 + half + 1), min(w, w // 2 + half + 1)
        return dataclasses.replace(self, image=self.image[r0:r1, c0:c1],
                                   sigma=self.sigma[r0:r1, c0:c1], mask=self.mask[r0:r1, c0:c1])


def data_intensity(data: FitData, background) -> np.ndarray:
    """The data's own intensity above ``background``: each pixel's 3 × 3 mean over the
    used pixels (masked ones left out), clipped at 0. The I of σ with
    ``noise_from_residuals(..., intensity="data")``."""
    from scipy.ndimage import uniform_filter

    used = data.mask.astype(float)
    mean = (uniform_filter(np.where(data.mask, data.image, 0.0), 3, mode="constant")
            / np.maximum(uniform_filter(used, 3, mode="constant"), 1e-12))
    return np.maximum(mean - background, 0.0)


def noise_from_residuals(data: FitData, model_image, background, *, floor=0.0, faint=0.01,
                         bins=12, intensity="model", relative=None) -> tuple[Noise, FitData]:
    """Read noise and gain estimated from a fit's residual, and the data with σ from them.

    The residual (data − model) is high-passed — each pixel minus the mean of its four
    neighbours, divided by √1.25 so white noise keeps its variance — so that the model's
    smooth mismatch drops out. Its robust variance (MAD²) in ``bins`` logarithmic bins of
    the model's intensity I (above ``background``), over pixels fainter than ``faint`` × the
    peak (wings and spikes, where noise rather than mismatch dominates), is fitted by
    var = read² + I / gain (non-negative least squares). The new σ² = read² + I/gain +
    (``floor`` · I)², with I from the model (not the data: no bias toward pixels that
    fluctuated low); ``floor`` is the model's relative mismatch. For data whose units
    are not electrons (a gain of 1 then weights the spikes far too little).

    ``intensity="data"``: I in σ is the data's own (its 3 × 3 mean over the used pixels,
    above ``background``) instead of the model's. σ then no longer depends on where the
    fit is, so the χ² of different minima — a hop's alternatives, the ends of fits from
    different starts — are measured with one yardstick; with the model's I, σ carries
    each minimum's own image (the floor and the Poisson term), and each minimum's own σ
    can favour another one. The 3 × 3 mean keeps the bias toward pixels that fluctuated
    low small where the noise matters (read and Poisson); the floor dominates the core.

    ``relative`` (a fraction of the peak, e.g. 3e-4): σ² = (``relative`` · P)² +
    (``floor`` · I)², P the brightest I: weights that scale with the star, the same for
    a bright or a faint star of the same kind. For a model whose mismatch, not the
    noise, dominates the residual (χ²/dof well above 1): the mismatch scales with the
    star, so these are its σ, and the compromise such a model settles at (its geometry:
    the rotation) is then the same for every star, where the noise's own weights move it
    with the star's brightness. Choose ``relative`` at least the noise of the faintest
    star meant (read and Poisson over its peak). The read noise and gain are still
    estimated and returned (for the log and for fainter copies)."""
    if intensity not in ("model", "data"):
        raise FitInputError(f"noise_from_residuals: intensity must be 'model' or 'data'; "
                            f"got {intensity!r}.")
    if relative is not None and not (isinstance(relative, (int, float))
                                     and not isinstance(relative, bool)
                                     and math.isfinite(relative) and 0 < relative < 1):
        raise FitInputError(f"noise_from_residuals: relative must be a fraction of the peak "
                            f"(0 < relative < 1); got {relative!r}.")
    from scipy.optimize import nnls

    m = np.asarray(model_image, float)
    inten = np.maximum(m - background, 0.0)
    r = np.where(data.mask, data.image - m, 0.0)
    ok = data.mask.copy()
    hp = np.zeros_like(r)
    hp[1:-1, 1:-1] = (r[1:-1, 1:-1] - 0.25 * (r[:-2, 1:-1] + r[2:, 1:-1] + r[1:-1, :-2]
                                                + r[1:-1, 2:])) / math.sqrt(1.25)
    ok[0, :] = ok[-1, :] = ok[:, 0] = ok[:, -1] = False
    ok[1:-1, 1:-1] &= (data.mask[:-2, 1:-1] & data.mask[2:, 1:-1] & data.mask[1:-1, :-2]
                       & data.mask[1:-1, 2:])
    sel = ok & (inten < faint * inten[ok].max())
    if sel.sum() < 10 * bins:
        raise FitInputError("noise from residuals: too few faint pixels to estimate the "
                            "noise; give Noise(read, gain) instead.")
    lo = max(np.quantile(inten[sel], 0.05), 1e-12 * inten[sel].max())
    edges = np.concatenate([[0.0], np.geomspace(lo, inten[sel].max(), bins)])
    xs, vs = [], []
    for lo, hi in zip(edges[:-1], edges[1:]):
        b = sel & (inten >= lo) & (inten <= hi)
        if b.sum() < 8:
            continue
        h = hp[b]
        xs.append(np.mean(inten[b]))
        vs.append((1.4826 * np.median(np.abs(h - np.median(h)))) ** 2)
    a = np.stack([np.ones(len(xs)), np.asarray(xs)], axis=1)
    (read2, inv_gain), _ = nnls(a / np.asarray(vs)[:, None], np.ones(len(xs)))
    read = math.sqrt(max(read2, 1e-300))
    gain = 1.0 / inv_gain if inv_gain > 0 else float("inf")
    if intensity == "data":
        inten = data_intensity(data, background)
    if relative is None:
        var = read2 + inten * inv_gain + (floor * inten) ** 2
    else:
        var = (relative * inten[data.mask].max()) ** 2 + (floor * inten) ** 2
    sigma = np.where(data.mask, np.sqrt(np.maximum(var, 1e-300)), 1.0)
    return Noise(read, gain, floor), dataclasses.replace(data, sigma=sigma)


def reject_outliers(data: FitData, model_image, background, centre, *, above=20.0,
                    r_min=0.0, grow=1, relative=None) -> tuple[FitData, int, float]:
    """The data with the pixels no model of the star is meant to explain masked: a
    neighbouring star, a cosmic ray, a hot or dead pixel. A pixel goes where
    |data − model| > ``above`` · σ and it lies at least ``r_min`` pixels from ``centre``
    (x, y in pixels from the top-left pixel's centre, rows down), then each such pixel's
    square of ± ``grow`` pixels goes with it (the wings of a neighbour or a charge
    spill), still only at ``r_min`` and beyond: the star's core, where the model's own
    mismatch is largest, is always kept. Returns (the data, the number of pixels newly
    masked, the largest |data − model| / σ left at ``r_min`` and beyond). σ is the
    data's own: choose ``above`` well over the largest |residual| / σ the model leaves
    on a clean star (that last number, on a clean star).

    ``relative`` (a fraction of the peak, e.g. 3e-4): σ is at least ``relative`` · P, P
    the brightest of the data's own intensity above ``background`` (as in
    :func:`noise_from_residuals`): the model's mismatch scales with the star, so on the
    star's own noise a brighter star would have its spikes' mismatch masked; with this
    floor the same pixels go for a bright or a faint star of one kind."""
    from scipy.ndimage import binary_dilation

    def number(x, lo):
        return (not isinstance(x, bool) and isinstance(x, (int, float))
                and math.isfinite(x) and x >= lo)

    if not (number(above, 0) and above > 0 and number(r_min, 0)
            and isinstance(grow, int) and not isinstance(grow, bool) and grow >= 0
            and (relative is None or number(relative, 0) and 0 < relative < 1)):
        raise FitInputError(f"reject: needs above > 0 (in σ), r_min >= 0 (pixels), grow "
                            f"a whole number >= 0 (pixels) and relative, if given, a "
                            f"fraction of the peak (0 < relative < 1); got above={above!r}, "
                            f"r_min={r_min!r}, grow={grow!r}, relative={relative!r}.")
    m = np.asarray(model_image, float)
    if m.shape != data.image.shape:
        raise FitInputError(f"reject: the model image's shape {m.shape} is not the data's "
                            f"{data.image.shape}.")
    sigma = data.sigma
    if relative is not None:
        sigma = np.maximum(sigma, relative * data_intensity(data, background)[data.mask].max())
    z = np.where(data.mask, np.abs(data.image - m) / sigma, 0.0)
    r, _ = _polar(data.image.shape, centre)
    bad = z > above
    if grow:
        bad = binary_dilation(bad, structure=np.ones((2 * grow + 1,) * 2, bool))
    bad &= data.mask & (r >= r_min)
    if bad.all(where=data.mask):
        raise FitInputError(f"reject: every used pixel is more than {above:g} σ from the "
                            "model; the model is far from the data (reject later in the "
                            "stages) or σ is too small.")
    kept = data.mask & ~bad & (r >= r_min)
    largest = float(z[kept].max()) if kept.any() else 0.0
    return dataclasses.replace(data, mask=data.mask & ~bad), int(bad.sum()), largest


def fainter_copy(data: FitData, model_image, background, factor, noise: Noise, *,
                 seed=0) -> FitData:
    """The data as a star ``factor`` times fainter would give them: (data − background)
    / factor + background, plus Gaussian noise that brings each pixel's variance up to
    that of the fainter star under ``noise`` (read² + I/gain, I from ``model_image``),
    σ from the same model. A stand-in for other stars of the same kind: a fit of the
    copy should give the same geometry (rotation) as the fit of the original."""
    if not factor >= 1:
        raise FitInputError(f"fainter_copy: factor must be >= 1; got {factor}.")
    inten = np.maximum(np.asarray(model_image, float) - background, 0.0)
    f = float(factor)
    extra = noise.read**2 * (1 - 1 / f**2) + inten * (1 / f - 1 / f**2) / noise.gain
    rng = np.random.default_rng(seed)
    img = background + (data.image - background) / f + rng.normal(0, 1, inten.shape) * np.sqrt(
        np.maximum(extra, 0.0))
    sigma = np.sqrt(noise.read**2 + inten / f / noise.gain)
    return dataclasses.replace(data, image=np.where(data.mask, img, 0.0),
                               sigma=np.where(data.mask, sigma, 1.0))


# --- the model --------------------------------------------------------------------------


class _Shifted(eqx.Module):
    """A wavefront tilt (tx, ty) plus Zernike terms: OPD = tx x + ty y + Σ c_j Z_j."""

    zernike: Zernike | None
    tx: Any
    ty: Any

    def opd(self, x, y):
        w = self.tx * x + self.ty * y
        return w if self.zernike is None else w + self.zernike.opd(x, y)


#: Parameters every model has, with defaults (SI units except where noted).
COMMON = {"rotation": 0.0, "x0": 0.0, "y0": 0.0, "flux": 1.0, "background": 0.0,
          "pixel_scale": 0.03, "jitter": 0.0, "halo": 0.0, "halo_width": 4.0,
          "halo2": 0.0, "halo2_width": 1.5,
          "shear": 0.0, "aspect": 0.0}


#: The disc source's parameter: its radius in data pixels.
SOURCE_DISC = {"source_radius": 1.0}
#: The detector's response curve (:func:`difstar._sensor.response_curve`): the image is
#: ``white`` · Z(I / ``white``; ``toe``, ``knee``) + background, I the linear image.
RESPONSE = {"white": 1.0, "toe": 0.0, "knee": 60.0}


def _source_kind(source):
    """"point", "disc" or a user image (a 2-D array of non-negative finite values with a
    positive sum; its centre pixel (shape // 2) is the star's position)."""
    if isinstance(source, str):
        if source not in ("point", "disc"):
            raise FitInputError(f"ImageModel: source must be 'point', 'disc' or an image "
                                f"(2-D array); got {source!r}.")
        return source
    a = np.asarray(source, dtype=float)
    if a.ndim != 2 or not np.all(np.isfinite(a)) or np.any(a < 0) or not a.sum() > 0:
        raise FitInputError("ImageModel: a source image must be a 2-D array of finite, "
                            "non-negative values with a positive sum.")
    return a.copy()


def disc_transform(x):
    """2 J1(x) / x, the Fourier transform of a uniform disc of unit area at
    x = 2π f R (f cycles per pixel, R the radius in pixels); 1 at x = 0. J1 by the
    rational and asymptotic approximations of Hart (Numerical Recipes' bessj1), to
    about 1e-8, smooth in x for gradients."""
    x = jnp.abs(jnp.asarray(x, float))
    y = x * x
    p = 72362614232.0 + y * (-7895059235.0 + y * (242396853.1 + y * (
        -2972611.439 + y * (15704.48260 + y * (-30.16036606)))))
    q = 144725228442.0 + y * (2300535178.0 + y * (18583304.74 + y * (
        99447.43394 + y * (376.9991397 + y))))
    small = 2.0 * p / q  # 2 J1(x)/x for x < 8 (J1 = x p/q)
    xb = jnp.maximum(x, 8.0)
    z = 8.0 / xb
    y2 = z * z
    xx = xb - 2.356194491
    a1 = 1.0 + y2 * (0.183105e-2 + y2 * (-0.3516396496e-4 + y2 * (
        0.2457520174e-5 + y2 * (-0.240337019e-6))))
    a2 = 0.04687499995 + y2 * (-0.2002690873e-3 + y2 * (0.8449199096e-5 + y2 * (
        -0.88228987e-6 + y2 * 0.105787412e-6)))
    big = 2.0 * jnp.sqrt(0.636619772 / xb) * (jnp.cos(xx) * a1 - z * jnp.sin(xx) * a2) / xb
    return jnp.where(x < 8.0, small, big)


def _resampling_order(resampling) -> int:
    """``None`` (no resampling modelled) → 0; ``"lanczos<a>"`` (a = 2 … 5) → a."""
    if resampling is None:
        return 0
    m = re.fullmatch(r"lanczos([2-5])", str(resampling).lower())
    if m is None:
        raise FitInputError(f"ImageModel: resampling must be null or 'lanczos2' … "
                            f"'lanczos5' (the kernel that resampled the data, e.g. SWarp's "
                            f"RESAMPT1 = LANCZOS3); got {resampling!r}.")
    return int(m.group(1))


def lanczos_kernel(x, a: int):
    """The Lanczos-``a`` interpolation kernel sinc(x)·sinc(x/a) for |x| < a, else 0."""
    x = np.asarray(x, float)
    return np.where(np.abs(x) < a, np.sinc(x) * np.sinc(x / a), 0.0)


def lanczos_transfer(f, a: int, n: int = 4001):
    """The transfer function (Fourier transform, unit at f = 0) of the continuous
    Lanczos-``a`` kernel at frequencies ``f`` (cycles per data pixel).

    Why a resampled image sees it: a frame sampled at an offset u and interpolated
    onto the output grid with kernel L gives out(x) = Σ_k g(k + u) L(x − k − u); averaged
    over offsets u spread evenly over a pixel this is ∫ g(t) L(x − t) dt, the
    convolution of the pixel-integrated PSF g with L. A co-add of many frames at
    random sub-pixel offsets (SWarp's RESAMPT = LANCZOS3, combined by mean or median)
    is blurred by L on average; the separable 2-D kernel is L(x) L(y).
    Composite Simpson's rule over [−a, a] with ``n`` (odd) nodes: the kernel is smooth
    and compact, so 4001 nodes give the transfer to about 1e-12."""
    x = np.linspace(-a, a, n)
    w = np.ones(n)
    w[1:-1:2], w[2:-1:2] = 4.0, 2.0
    w *= (x[1] - x[0]) / 3.0
    k = lanczos_kernel(x, a) * w
    f = np.asarray(f, float)
    h = np.cos(2 * np.pi * f[..., None] * x) @ k
    return h / k.sum()


def image_distortion(shear, aspect):
    """The image-plane linear map D = [[1, 0], [shear, 1 + aspect]] (x right, y up): the
    data's y axis keeps its direction (so ``rotation`` is read against it), a direction
    at angle θ tilts by about shear·cos²θ, and y is stretched by 1 + aspect. A resampled
    (drizzled) or distorted detector grid has such a map; it moves the spikes of a rigid
    pupil off their 60° spacing."""
    return jnp.array([[1.0, 0.0], [shear, 1.0 + aspect]])


class ImageModel:
    """A star image: pupil builder, wavefront (Zernike Noll indices), light, detector.

    ``params``: name → :class:`Param` (or a number, or a dict with value/free/bounds/
    scale) for the common parameters (``rotation`` deg, ``x0``, ``y0`` data pixels,
    ``flux``, ``background``, ``pixel_scale`` arcsec per data pixel, ``jitter`` σ in data
    pixels, ``halo`` fraction and ``halo_width`` σ in data pixels: a broad scattered-light
    Gaussian; ``halo2``, ``halo2_width``: a second one, applied after the first (each
    moves a fraction of the light into a Gaussian: a segmented mirror's phasing errors
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

    ``source``: "point" (default); "disc", a uniform disc of radius ``source_radius``
    (data pixels; its transform 2 J1(x)/x multiplies the image's spectrum, like the
    blurs); or a 2-D array, the source as the data's pixels would see it (any size up to
    the padded window, its centre pixel shape // 2 at the star's position). ``response``:
    the detector's response curve, the image becomes ``white`` · Z(I / ``white``) +
    background with the toe and knee of :func:`difstar._sensor.response_curve` (the
    camera fitter's curve) — for images that saturate softly; hard-clipped pixels are
    better masked (``FitData.from_array(..., saturation=level)``)."""

    def __init__(self, pupil: PupilBuilder, params: Mapping[str, Any], *, light: Light,
                 zernike: Sequence[int] = (), oversample: float = 1.0, pad: int = 8,
                 accuracy: float = 1e-2, max_shift: float = 4.0, source: Any = "point",
                 response: bool = False, resampling: str | None = None):
        self.pupil = pupil
        self.resampling = _resampling_order(resampling)
        self.source = _source_kind(source)
        self.response = bool(response)
        self.light = light
        self.zernike = tuple(int(j) for j in zernike)
        if any(j < 2 for j in self.zernike):
            raise FitInputError("ImageModel: Zernike Noll indices must be >= 2 (1 is piston).")
        self.oversample = float(oversample)
        self.pad = int(pad)
        self.accuracy = float(accuracy)
        self.max_shift = float(max_shift)
        defaults = dict(COMMON) | dict(pupil.defaults) | {f"z{j}": 0.0 for j in self.zernike}
        if isinstance(self.source, str) and self.source == "disc":
            defaults |= SOURCE_DISC
        if self.response:
            defaults |= RESPONSE
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
                      ("toe", 0.0)):
            p = self.params.get(k)
            if p is not None and min([p.value, *(p.bounds or ())]) < lo:
                raise FitInputError(f"ImageModel: {k} = {p.value} (bounds {p.bounds}) must be "
                                    f"{'>= 0' if lo == 0 else '> 0'}.")
        p = self.params.get("incoherent")
        if p is not None and not 0 <= min([p.value, *(p.bounds or ())]) <= max(
                [p.value, *(p.bounds or ())]) <= 1:
            raise FitInputError(f"ImageModel: incoherent = {p.value} (bounds {p.bounds}) is "
                                "a fraction of the light: keep it and its bounds in [0, 1].")
        for j in self.zernike:
            p = self.params[f"z{j}"]
            if max([abs(p.value), *(abs(b) for b in (p.bounds or ()))]) > 1e4:
                raise FitInputError(f"ImageModel: z{j} = {p.value} (bounds {p.bounds}) is "
                                    "not in nm RMS (over 10 µm).")
        self._plans = {}
        self._source_ft = {}
        self.per_capture: tuple[str, ...] = ()

    def for_captures(self, per_capture: Sequence[str], n: int) -> ImageModel:
        """A copy for ``n`` captures fitted together: each name in ``per_capture`` (e.g.
        ``x0``, ``y0``, ``flux``, ``background``) gets one parameter per capture,
        ``name@i`` (a copy of the original's value, bounds and free flag); every other
        parameter (pupil, rotation, wavefront, detector) is shared by all captures."""
        unknown = set(per_capture) - set(self.params)
        if unknown:
            raise FitInputError(f"per_capture: unknown parameters {sorted(unknown)}.")
        m = object.__new__(ImageModel)
        m.__dict__ = dict(self.__dict__)
        m.params = {}
        for k, p in self.params.items():
            if k in per_capture:
                m.params[k] = dataclasses.replace(p, free=False)
                for i in range(n):
                    m.params[f"{k}@{i}"] = dataclasses.replace(p)
            else:
                m.params[k] = dataclasses.replace(p)
        m.per_capture = tuple(per_capture)
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

    @property
    def free(self) -> list[str]:
        return [k for k, p in self.params.items() if p.free]

    def values(self) -> dict[str, float]:
        return {k: p.value for k, p in self.params.items()}

    def with_values(self, values: Mapping[str, float], free: Sequence[str] | None = None):
        """A copy with new values (and, if given, only ``free`` left free)."""
        m = object.__new__(ImageModel)
        m.__dict__ = dict(self.__dict__)
        m.params = {}
        for k, p in self.params.items():
            q = dataclasses.replace(p, value=float(values.get(k, p.value)))
            if free is not None:
                q.free = k in free and p.free
            if q.bounds is not None:
                q.value = min(max(q.value, q.bounds[0]), q.bounds[1])
            m.params[k] = q
        return m

    def with_resampling(self, resampling: str | None) -> ImageModel:
        """A copy whose detector models a co-add resampled with ``resampling`` (null or
        'lanczos2' … 'lanczos5', as the constructor takes it); every parameter and plan
        kept (the kernel does not change the PSF's plan)."""
        m = object.__new__(ImageModel)
        m.__dict__ = dict(self.__dict__)
        m.resampling = _resampling_order(resampling)
        return m

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

    def plan(self, shape, light: Light | None = None, *, segment: bool = False):
        """The PSF plan for an output window ``shape`` (data pixels, padding included) and
        ``light`` (default: the model's), made once with the largest angular scale and
        wavefront slope the bounds allow. ``segment``: the plan of one segment's pattern
        (the incoherent part; tilt only, no Zernike terms), which the whole pupil's plan
        makes and caches as well, so that :meth:`image` finds it inside a trace."""
        light = self.light if light is None else light
        key = (tuple(shape), tuple(light.wavelengths), segment)
        if key in self._plans:
            return self._plans[key]
        if not segment and self.has_incoherent:
            self.plan(shape, light, segment=True)
        ang = self._bound("pixel_scale", min) * ARCSEC
        z = _PITCH / ang
        v = self.values()
        if segment:
            pupil, r = self._oriented(self.pupil.segment(v), v), float(self.pupil.segment_radius)
        else:
            pupil, r = self._pupil_at(v), float(self.pupil.max_radius)
        # the widest shift of the star any value or bound allows (x0@i: each capture's)
        shift = max([self.max_shift] + [abs(b) for k, p in self.params.items()
                                         if k.split("@")[0] in ("x0", "y0")
                                         for b in [p.value, *(p.bounds or ())]])
        tilt = shift * self._bound("pixel_scale", max) * ARCSEC
        # the largest Zernike terms any value or bound allows (the whole pupil's only)
        coeffs = {} if segment else {
            j: 1e-9 * max(abs(c) for c in [self.params[f"z{j}"].value,
                                           *(self.params[f"z{j}"].bounds or ())])
            for j in self.zernike}
        coeffs = {j: c for j, c in coeffs.items() if c > 0}
        wf = _Shifted(Zernike(coeffs, r) if coeffs else None, tilt, tilt)
        plan = plan_psf(pupil,
                        wavelength=np.asarray(light.wavelengths),
                        z_image=z, pixel_pitch=_PITCH, shape=tuple(shape), sampling="pixel",
                        accuracy=self.accuracy, wavefront=wf, max_radius=r)
        self._plans[key] = plan
        return plan

    def _pupil_at(self, v):
        return self._oriented(self.pupil.build(v), v)

    def _oriented(self, pup, v):
        """``pup`` rotated by ``rotation`` and distorted by ``shear``, ``aspect``."""
        pup = pup.transformed(jnp.deg2rad(v["rotation"]))
        if any(self.params[k].free or self.params[k].value != 0 for k in ("shear", "aspect")):
            d = image_distortion(v["shear"], v["aspect"])
            pup = distorted(pup, jnp.linalg.inv(d).T)  # the pupil map for image map D
        return pup

    def image(self, v: Mapping[str, Any], shape: tuple[int, int], plan=None,
              exposure: float = 1.0, light: Light | None = None):
        """The model image (H, W) in data pixels for parameter values ``v`` (a dict of
        scalars, traceable), for a capture of relative ``exposure`` in ``light`` (default:
        the model's)."""
        light = self.light if light is None else light
        h, w = shape
        o = self.oversample
        pad = self.pad
        hp, wp = h + 2 * pad, w + 2 * pad
        plan = self.plan((hp, wp), light) if plan is None else plan
        ang = v["pixel_scale"] * ARCSEC  # radians per data pixel
        z = _PITCH / ang * 1.0
        zern = None
        if self.zernike:
            r = float(self.pupil.max_radius)
            zern = Zernike({j: 1e-9 * v[f"z{j}"] for j in self.zernike}, r)
        # a shift by (x0 columns right, y0 rows down) data pixels is a tilt of the
        # wavefront: the field's phase exp(i k W) with W = −θ·x moves the image by +θ
        tx = -v["x0"] * ang
        ty = v["y0"] * ang
        wf = _Shifted(zern, tx, ty)
        pupil = self._pupil_at(v)
        lam = np.asarray(light.wavelengths)
        wts = np.asarray(light.weights)
        img = psf(pupil, wavelength=lam, weights=wts, z_image=z, pixel_pitch=_PITCH,
                  shape=(hp, wp), plan=plan, wavefront=wf)
        if self.has_incoherent:
            # random phasing errors of RMS φ between segments: the mean image is
            # e^(−φ²) × the whole pupil's + (1 − e^(−φ²)) × the sum of the segments' own
            # patterns, each the one segment's shifted in the pupil (the same image)
            seg = psf(self._oriented(self.pupil.segment(v), v), wavelength=lam,
                      weights=wts, z_image=z, pixel_pitch=_PITCH, shape=(hp, wp),
                      plan=self.plan((hp, wp), light, segment=True),
                      wavefront=_Shifted(None, tx, ty))
            img = (1.0 - v["incoherent"]) * img + v["incoherent"] * seg
        # detector: native pixel box (oversampled data) and Gaussian blur, by FFT
        fy = np.fft.fftfreq(hp)[:, None]
        fx = np.fft.rfftfreq(wp)[None, :]
        f2 = fx**2 + fy**2
        kern = jnp.exp(-2 * math.pi**2 * v["jitter"] ** 2 * f2)
        for frac, width in (("halo", "halo_width"), ("halo2", "halo2_width")):
            kern = kern * ((1.0 - v[frac])
                           + v[frac] * jnp.exp(-2 * math.pi**2 * v[width] ** 2 * f2))
        if o != 1.0:
            kern = kern * jnp.asarray(np.sinc(o * fx) * np.sinc(o * fy))
        if self.resampling:
            a = self.resampling
            kern = kern * jnp.asarray(lanczos_transfer(fx, a) * lanczos_transfer(fy, a))
        if isinstance(self.source, str) and self.source == "disc":
            kern = kern * disc_transform(2 * math.pi * np.sqrt(f2) * v["source_radius"])
        elif not isinstance(self.source, str):
            kern = kern * self._source_spectrum((hp, wp))
        img = jnp.fft.irfft2(jnp.fft.rfft2(img) * kern, s=(hp, wp))
        img = v["flux"] * exposure * img[pad:pad + h, pad:pad + w]
        if self.response:
            img = v["white"] * response_curve(img / v["white"], v["toe"], v["knee"])
        return img + v["background"]

    def _source_spectrum(self, shape):
        """The half spectrum of the user's source image (unit sum, its centre pixel at
        the origin) on the padded window ``shape``."""
        if shape not in self._source_ft:
            src = self.source
            sh, sw = src.shape
            if sh > shape[0] or sw > shape[1]:
                raise FitInputError(f"ImageModel: the source image ({sh} × {sw}) is larger "
                                    f"than the padded window {shape}; crop it or raise pad.")
            big = np.zeros(shape)
            big[:sh, :sw] = src / src.sum()
            big = np.roll(big, (-(sh // 2), -(sw // 2)), axis=(0, 1))
            self._source_ft[shape] = np.fft.rfft2(big)  # NumPy: a constant in any trace
        return self._source_ft[shape]

    def __call__(self, shape, values=None):
        """Concrete model image at ``values`` (default: the current values)."""
        v = self.values() if values is None else {**self.values(), **values}
        v = {k: jnp.asarray(x, float) for k, x in v.items()}
        return np.asarray(self.image(v, tuple(shape)))


# --- parametrisation --------------------------------------------------------------------


def _to_u(p: Param) -> float:
    if p.bounds is not None:
        lo, hi = p.bounds
        t = min(max((p.value - lo) / (hi - lo), 1e-4), 1 - 1e-4)
        return math.log(t / (1 - t))
    return 0.0


def _from_u(p: Param, u):
    if p.bounds is not None:
        lo, hi = p.bounds
        return lo + (hi - lo) * jax.nn.sigmoid(u)
    s = p.scale if p.scale else max(0.1 * abs(p.value), 1e-3)
    return p.value + s * u


# --- results --------------------------------------------------------------------------


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


# --- fitting ----------------------------------------------------------------------------


def _polar(shape, centre, period=180.0):
    """(r, θ) of every pixel of a window ``shape`` about ``centre`` (x, y in pixels from
    the top-left pixel's centre, rows down): r in pixels, θ in degrees counter-clockwise
    from +x with y up, modulo ``period`` (180: a spike and its opposite are one)."""
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w]
    dx, dy = xx - centre[0], -(yy - centre[1])
    return np.hypot(dx, dy), np.degrees(np.arctan2(dy, dx)) % period


def _angle_from(th, phi):
    """Signed angle (degrees, in [−90, 90)) from direction ``phi`` to ``th``, mod 180."""
    return (th - phi + 90.0) % 180.0 - 90.0


class _PixelTarget:
    """The residuals (model − data)/σ on the data's used pixels."""

    kind = "pixels"

    def __init__(self, data: FitData):
        self.data = data
        self.img = jnp.asarray(data.image)
        self.wgt = jnp.asarray(np.where(data.mask, 1.0 / data.sigma, 0.0))
        self.n = int(data.mask.sum())

    def __call__(self, model_image, v):
        return ((model_image - self.img) * self.wgt).ravel()


class SpikeProfiles:
    """The residuals of the spikes' angular profiles: around each spike direction
    (``directions``, degrees, [0, 180), from the data), the mean of r²(I − background)
    over the pixels between ``r_min`` and ``r_max`` data pixels of the star, in bins of
    ``bin_width`` degrees within ± ``half_width`` (a spike and its opposite one share
    bins), each window normalised to unit sum, for data and model alike; weighted by the
    data's σ propagated through the same sums. The same pixels and bins serve both, so
    the binning's own bias cancels and only the spikes' positions and shapes count, not
    their brightness: a stage on these residuals fits the rotation and the distortion of
    the pupil from the spikes' directions alone. ``centre`` (x, y data pixels from the
    top-left pixel's centre, y down) and ``background`` are held (from earlier stages)."""

    kind = "spikes"

    def __init__(self, data: FitData, centre, background, directions, *, r_min=12.0,
                 r_max=45.0, half_width=4.0, bin_width=0.25):
        h, w = data.image.shape
        r, th = _polar((h, w), (float(centre[0]), float(centre[1])))
        use = data.mask & (r >= r_min) & (r <= r_max)
        nb = int(round(2 * half_width / bin_width))
        rows, cols, vals, window = [], [], [], []
        b = 0
        for k, phi in enumerate(directions):
            off = _angle_from(th, phi)
            j = np.floor((off + half_width) / bin_width).astype(int)
            for jb in range(nb):
                sel = np.flatnonzero((use & (j == jb)).ravel())
                if sel.size == 0:
                    continue
                rows += [b] * sel.size
                cols += sel.tolist()
                vals += (r.ravel()[sel] ** 2 / sel.size).tolist()
                window.append(k)
                b += 1
        if b == 0 or len(set(window)) < len(directions):
            raise FitInputError("spike profiles: no pixel near a spike direction between "
                                f"r = {r_min} and {r_max} px; check the annulus.")
        mat = np.zeros((b, h * w))
        mat[rows, cols] = vals
        self.window = np.asarray(window)
        self.n_windows = len(directions)
        self.mat = jnp.asarray(mat)
        self.background = float(background)
        pd = mat @ (data.image - self.background).ravel()
        sums = np.bincount(self.window, pd, minlength=self.n_windows)
        if np.any(sums <= 0):
            raise FitInputError("spike profiles: a spike window has no positive signal; "
                                "check the directions and the annulus.")
        self.profile = pd / sums[self.window]
        sig = np.sqrt((mat**2) @ (data.sigma**2).ravel()) / sums[self.window]
        self.wgt = jnp.asarray(1.0 / np.maximum(sig, 1e-12 * sig.max()))
        self.data_profile = jnp.asarray(self.profile)
        self.n = b
        self.directions = [float(d) for d in directions]

    def __call__(self, model_image, v):
        pm = self.mat @ (model_image - v["background"]).ravel()
        sums = jax.ops.segment_sum(pm, jnp.asarray(self.window), self.n_windows)
        return (pm / sums[self.window] - self.data_profile) * self.wgt


def _residual_fn(model: ImageModel, data, target):
    """values → (residual vector, [model image of each capture]) for ``model`` on each
    of ``data``'s windows (a FitData or a list of them, one ``target`` each)."""
    datas, targets = _as_list(data), _as_list(target)
    plans = [model.plan((d.image.shape[0] + 2 * model.pad, d.image.shape[1] + 2 * model.pad),
                        d.light) for d in datas]

    def res(v):
        rs, ms = [], []
        for i, (d, t, plan) in enumerate(zip(datas, targets, plans)):
            vi = model.capture_values(v, i)
            m = model.image(vi, d.image.shape, plan, exposure=d.exposure, light=d.light)
            rs.append(t(m, vi))
            ms.append(m)
        return (rs[0] if len(rs) == 1 else jnp.concatenate(rs)), ms

    return res


def model_images(model: ImageModel, values: Mapping[str, float], data) -> list:
    """The model image of each capture's window at ``values`` (a fit's values, or a
    result.json's), as a list of arrays; ``data``: a :class:`FitData` or a list of them.
    Not jitted: for one-off images (a stage's σ or spike directions, a figure)."""
    datas = _as_list(data)
    v = {k: jnp.asarray(x, float) for k, x in values.items()}
    return [np.asarray(m) for m in _residual_fn(model.with_values(values), datas,
                                                [_PixelTarget(d) for d in datas])(v)[1]]


def values_of_capture(values: Mapping[str, Any], i: int) -> dict:
    """The values capture ``i`` of a fit saw: ``name@i`` read as ``name`` (a fit's
    result, or a result.json's values, for any per-capture names)."""
    tag = f"@{i}"
    return {**values, **{k[:-len(tag)]: x for k, x in values.items() if k.endswith(tag)}}


def _release_compiled() -> None:
    """Drop JAX's compiled programs and traces once a stage is done. Each stage (and each
    re-run of one in a hop) traces new closures over the data and the model's plans;
    JAX's caches keep their programs, and the constants they hold, after the closures are
    gone: about 0.4 GB per stage on the JWST star, so a fit and its rough starts ran out
    of 24 GB. A stage never reuses another's programs, so nothing is compiled twice
    because of this (other jitted functions of the process compile again on their next
    call)."""
    jax.clear_caches()
    gc.collect()


def _as_list(x):
    return list(x) if isinstance(x, (list, tuple)) else [x]


def _one_fit(model: ImageModel, data, target, *, max_steps: int, rtol: float,
             atol: float, ftol: float = 1e-6, label: str | None = None):
    """One Levenberg–Marquardt solve of ``model``'s free parameters; with ``label``, a
    progress bar (tqdm, on stderr) of its steps and χ²."""
    from ._lm import LMStepper

    free = model.free
    if not free:
        raise FitInputError("fit: no free parameter (set free=true on at least one).")
    fixed = {k: jnp.asarray(p.value, float) for k, p in model.params.items() if not p.free}
    params = [model.params[k] for k in free]
    res = _residual_fn(model, data, target)

    def values_of(u):
        v = dict(fixed)
        for i, (k, p) in enumerate(zip(free, params)):
            v[k] = _from_u(p, u[i])
        return v

    def residuals(u, _):
        return res(values_of(u))[0]

    residuals = jax.jit(residuals)  # one compile, shared by the check and the solver
    u0 = jnp.asarray([_to_u(p) for p in params], float)
    r0 = residuals(u0, None)
    if not bool(jnp.all(jnp.isfinite(r0))):
        raise FitInputError("fit: the model is not finite at the start; check the units "
                            "(wavelength in metres, pixel_scale in arcsec, Zernike in nm).")
    with _progress_bar(label, max_steps) as progress:
        sol = LMStepper(residuals, rtol=rtol, atol=atol).solve(
            u0, None, max_steps=max_steps, ftol=ftol, progress=progress)
    ok = sol.result == "converged"
    status = {"converged": "converged", "failed": "not converged: the solver failed",
              "max_steps": f"not converged: reached max_steps={max_steps}"}[sol.result]
    vals = {k: float(x) for k, x in values_of(sol.u).items()}
    return vals, status, ok, sol.steps


@contextlib.contextmanager
def _progress_bar(label: str | None, max_steps: int):
    """A ``progress(k, loss, step_size, done)`` for :meth:`LMStepper.solve`: a tqdm bar
    on stderr named ``label`` (None: no bar), closed when the solve ends."""
    if label is None:
        yield None
        return
    from tqdm.auto import tqdm

    bar = tqdm(total=max_steps, desc=label, unit="step", leave=False, file=sys.stderr,
               dynamic_ncols=True)

    def progress(k, loss, size, done):
        bar.update(1)
        bar.set_postfix_str(f"χ² {2 * loss:.6g}", refresh=False)

    try:
        yield progress
    finally:
        bar.close()


def _jacobian(model: ImageModel, data, values: Mapping[str, float], target, *,
              residual: bool = True):
    """The residual's Jacobian over the free parameters (physical units) at ``values``;
    with ``residual``, also the residual and the model images (one more compile)."""
    free = model.free
    base = {k: jnp.asarray(v, float) for k, v in values.items()}
    resv = _residual_fn(model, data, target)

    def res(x):
        v = dict(base)
        for i, k in enumerate(free):
            v[k] = x[i]
        return resv(v)

    x0 = jnp.asarray([values[k] for k in free], float)
    jac = np.asarray(jax.jit(jax.jacfwd(lambda x: res(x)[0]))(x0))
    if not residual:
        return jac
    r, m = jax.jit(res)(x0)
    return jac, np.asarray(r), [np.asarray(mi) for mi in m]


def _covariance(jac):
    """(JᵀJ)⁻¹ by a pseudo-inverse of the column-scaled normal matrix, and the columns'
    norms (0: a parameter the model does not depend on)."""
    jtj = jac.T @ jac
    colnorm = np.sqrt(np.diag(jtj))
    dscale = np.where(colnorm > 0, 1.0 / np.where(colnorm > 0, colnorm, 1.0), 0.0)
    cov = dscale[:, None] * np.linalg.pinv(dscale[:, None] * jtj * dscale[None, :],
                                           rcond=1e-12) * dscale[None, :]
    return cov, colnorm


def _errors(model: ImageModel, data, values: Mapping[str, float], target=None):
    """Gauss–Newton covariance in the physical parameters at ``values``, scaled by
    χ²/dof when that exceeds 1 (always, for spike profiles: their σ are relative)."""
    if target is None:
        target = [_PixelTarget(d) for d in _as_list(data)]
    free = model.free
    jac, r, m = _jacobian(model, data, values, target)
    chi2 = float(r @ r)
    dof = sum(t.n for t in _as_list(target)) - len(free)
    kinds = {t.kind for t in _as_list(target)}
    cov, colnorm = _covariance(jac)
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
        cov, colnorm = _covariance(jac / np.where(data.mask, sig, 1.0).reshape(-1, 1))
        err = np.sqrt(np.maximum(np.diag(cov), 0.0))
        out.append({k: float(e) if c > 0 else float("inf")
                    for k, e, c in zip(free, err, colnorm)})
    return out


def fit(model: ImageModel, data, *, stages: Sequence[Mapping] | None = None,
        starts: Mapping[str, Sequence[float]] | None = None, max_steps: int = 100,
        rtol: float = 1e-6, atol: float = 1e-8, verbose: bool = False,
        per_capture: Sequence[str] | None = None) -> FitResult:
    """Fit ``model`` to ``data`` by Levenberg–Marquardt.

    ``data``: a :class:`FitData`, or a list of them (captures of the same star:
    exposures, dithers, frames) fitted together; then each name in ``per_capture``
    (default ``x0``, ``y0``, ``flux``, ``background``) has one value per capture,
    ``name@i`` in the result, and every other parameter is shared.

    ``stages``: coarse to fine, each a dict with

    - ``free`` (names, or "all": the model's free parameters), ``fix`` (names held);
    - ``set`` (name → value): before the stage, put those parameters at those values
      (kept inside their bounds), whatever the start or the earlier stages gave them:
      coarse to fine, e.g. the wavefront at zero until the geometry is found, so that
      a rough start's wavefront cannot steer the coarse stages into another basin;
    - ``half`` (fit the central (2 half + 1)² pixels; None: the whole image) and
      ``annulus`` ([r_min, r_max] pixels: only those radii);
    - ``spikes``: fit the spikes instead of all pixels, around the directions
      :func:`spike_angles` measures in the data, about the star's centre and background
      reached so far (options of :func:`spike_target`: ``r_min``, ``r_max``,
      ``half_width``, ``n_spikes``, ``directions`` "data" or "model"; ``profiles``
      true: their angular profiles, :class:`SpikeProfiles`; false: the pixels within
      ± ``half_width`` degrees): the stage for the rotation;
    - ``noise_from_residuals`` (options of :func:`noise_from_residuals`, e.g.
      ``{"floor": 0.03}``): before the stage, σ from read noise and gain estimated from
      the residual at the values reached, for this and later stages and the errors;
    - ``reject`` (options of :func:`reject_outliers`, e.g. ``{"above": 20, "r_min": 12,
      "grow": 2, "relative": 3e-4}``): before the stage (after ``noise_from_residuals``),
      mask the pixels more than ``above`` σ from the model at the values reached, away
      from the core (a neighbouring star, a cosmic ray, a hot pixel), for this and later
      stages; the number masked and the largest |residual| / σ kept are logged;
    - ``scan`` (``{"name": "rotation", "half_range": 5, "step": 0.2}``): first move that
      parameter to the lowest χ² on a grid, then solve;
    - ``max_steps``, ``rtol``: the solver's limits (default: the arguments);
    - a stage that is only ``hop`` (``{"name": "rotation", "offsets": [-0.5, 0.5],
      "stages": 2}``): re-run the ``stages`` solving stages before it with that
      parameter moved by each offset and keep the lowest χ² on all pixels: a way out of
      a neighbouring basin that the other parameters' adaptation makes self-consistent;
      ``{"flip": ["z6"], "stages": 2}`` negates each named parameter in turn instead
      (an entry that is a list of names negates those together: ``{"flip": [["z4",
      "z5", "z6", "z11"]]}`` is the whole twin of the even terms) —
      for the sign ambiguities of even wavefront terms in an in-focus image (the
      "twin" of phase retrieval: W(x, y) and −W(−x, −y) give the same image for a
      centrally symmetric pupil, so an almost symmetric one has a near-twin minimum);
      ``{"set": {"z4": 0, "z5": 0}, "stages": 3}`` puts the named parameters at those
      values, all at once (a second start for the wavefront from zero: a rough start's
      wavefront can settle in a neighbouring minimum);
    - a stage that is only ``repeat`` (``{"until": {"rotation": 0.002}, "stages": 2,
      "max_rounds": 6}``): re-run the ``stages`` solving stages before it, round after
      round (σ as it is), until each parameter named in ``until`` moves by less than its
      tolerance over a round: the fixed point of stages that fit different parameters
      in turn (the rotation on the spikes, then the rest on all pixels), which a single
      pass leaves wherever its start put it along a long, flat valley. Not settled after
      ``max_rounds``: a warning in the result.

    A stage with a key or an option not listed here is refused before any fitting.
    Each stage starts from the last one's values. Standard errors are computed at the
    end for every free parameter on the pixels; those of parameters last fitted in a
    spikes stage come from that stage. Default: one stage, all free, whole image.
    ``starts``: name → start values tried in the first stage (multi-start; the lowest χ²
    goes on). Raises :class:`FitInputError` for inputs that cannot be right. For several
    captures the result's images (``model_image``, ``residual``, ``data``, ``mask``)
    are lists, one per capture.
    """
    t0 = time.perf_counter()
    datas = _as_list(data)
    n_cap = len(datas)
    if n_cap == 0:
        raise FitInputError("fit: no data (an empty list of captures).")
    for i, d in enumerate(datas):
        if d.image.shape[0] < 4 or d.image.shape[1] < 4:
            raise FitInputError(f"fit: capture {i}'s window is smaller than 4 × 4 pixels.")
    if n_cap > 1 or per_capture:
        per = ("x0", "y0", "flux", "background") if per_capture is None else tuple(per_capture)
        model = model.for_captures(per, n_cap)
    if not model.free:
        raise FitInputError("fit: no free parameter (set free=true on at least one).")
    stages = list(stages or [{"free": "all", "half": None}])
    values = model.values()
    log = []
    last_stage = {}
    spike_errors = {}
    notes = []  # the procedure's own warnings (e.g. a repeat that did not settle)
    status, ok, steps = "converged", True, 0

    def run_stage(si, st, values, datas):
        """One stage from ``values``: returns (values, status, ok, steps, datas)."""
        datas = list(datas)
        names = (model.free if st.get("free", "all") == "all"
                 else model.expand(st["free"], n_cap))
        fix = set(model.expand(st.get("fix", ()), n_cap))
        names = [k for k in names if k not in fix]
        bad = set(names) - set(model.free)
        if bad:
            raise FitInputError(f"fit: stage {si} frees {sorted(bad)}, which are not free "
                                "parameters of the model.")
        if st.get("set") is not None:
            put = st["set"]
            if isinstance(put, Mapping):  # a per-capture name: every capture's own
                put = {q2: x for q, x in put.items() for q2 in model.expand([q], n_cap)}
            values = {**values, **_put(model, put, f"fit: stage {si}: set")}
            log.append({"stage": si, "set": dict(st["set"])})
        if st.get("noise_from_residuals") is not None:
            mimgs = model_images(model, values, datas)
            noises = []
            for i, mi in enumerate(mimgs):
                bg = model.capture_values(values, i)["background"]
                nz, datas[i] = noise_from_residuals(datas[i], np.asarray(mi), bg,
                                                    **dict(st["noise_from_residuals"]))
                noises.append({"read": nz.read, "gain": nz.gain, "floor": nz.floor})
            log.append({"stage": si, "noise": noises[0] if n_cap == 1 else noises})
            if verbose:
                for nz in noises:
                    print(f"stage {si}: noise from the residuals: read {nz['read']:.4g}, "
                          f"gain {nz['gain']:.4g}, floor {nz['floor']:g}", flush=True)
        if st.get("reject") is not None:
            mimgs = model_images(model, values, datas)
            counts, largest = [], []
            for i, mi in enumerate(mimgs):
                h, w = datas[i].image.shape
                cv = model.capture_values(values, i)
                datas[i], n, z = reject_outliers(datas[i], np.asarray(mi), cv["background"],
                                                 (w // 2 + cv["x0"], h // 2 + cv["y0"]),
                                                 **dict(st["reject"]))
                counts.append(n)
                largest.append(z)
            log.append({"stage": si, "rejected": counts[0] if n_cap == 1 else counts,
                        "largest_kept": largest[0] if n_cap == 1 else largest})
            if verbose:
                print(f"stage {si}: rejected {counts[0] if n_cap == 1 else counts} pixels "
                      f"more than {st['reject'].get('above', 20.0):g} σ from the model; "
                      f"the largest kept: {max(largest):.3g} σ", flush=True)
        half = st.get("half")
        ds = [d if half is None else d.cropped(int(half)) for d in datas]
        if st.get("annulus") is not None:
            ds = [d.annulus(*(float(r) for r in st["annulus"])) for d in ds]
        if st.get("spikes") is not None:
            mimgs = [None] * len(ds)
            if st["spikes"].get("directions") == "model":
                mimgs = model_images(model, values, ds)
            targets = [spike_target(d, model.capture_values(values, i), model_image=mi,
                                    **dict(st["spikes"]))
                       for i, (d, mi) in enumerate(zip(ds, mimgs))]
        else:
            targets = [_PixelTarget(d) for d in ds]
        kind = targets[0].kind
        if st.get("scan") is not None:
            values = _scan(model, ds, targets, values, **dict(st["scan"]))
            log.append({"stage": si, "scan": dict(st["scan"]),
                        "best": values[st["scan"]["name"]]})
            if verbose:
                print(f"stage {si}: scan of {st['scan']['name']}: best "
                      f"{values[st['scan']['name']]:.4g}", flush=True)
        tries = [{}]
        if si == 0 and starts:
            tries = [{}]
            for k, vs in starts.items():
                tries = [dict(t, **{k: float(x)}) for t in tries for x in vs]
        best = None
        for tr in tries:
            m = model.with_values({**values, **tr}, free=names)
            ts = time.perf_counter()
            vals, status, ok, n = _one_fit(m, ds, targets, max_steps=int(
                st.get("max_steps", max_steps)), rtol=float(st.get("rtol", rtol)), atol=atol,
                label=f"stage {si}" if verbose else None)
            chi2 = chi2_at(m, ds, vals, targets)
            entry = {"stage": si, "start": tr, "free": names, "half": half, "chi2": chi2,
                     "kind": kind, "status": status, "steps": n,
                     "seconds": time.perf_counter() - ts}
            log.append(entry)
            if verbose:
                print(f"stage {si} ({kind}) start {tr}: chi2 {chi2:.6g} {status} "
                      f"{n} steps {time.perf_counter() - ts:.1f} s", flush=True)
            if best is None or chi2 < best[0]:
                best = (chi2, vals, status, ok, n, m, entry)
        _, values, status, ok, steps, m, entry = best
        for k in names:
            last_stage[k] = si
        if kind != "pixels":
            errs = _errors(m, ds, values, targets)[0]
            entry["errors"] = errs
            entry["directions"] = [t.directions for t in targets] if n_cap > 1 \
                else targets[0].directions
            spike_errors[si] = errs
        _release_compiled()
        return values, status, ok, steps, datas

    def solving_before(si):
        """The solving stages before stage ``si`` (hop and repeat stages passed over)."""
        return [sj for sj in range(si)
                if stages[sj].get("hop") is None and stages[sj].get("repeat") is None]

    def rerun(which, v, datas):
        """Re-run the stages ``which`` from ``v`` with σ and the pixels as they are
        (their own noise_from_residuals and reject left out, so that what is compared
        has one yardstick): (values, (status, ok, steps), datas)."""
        ds = list(datas)
        st_j, ok_j, n_j = status, ok, steps
        for sj in which:
            again = {q: x for q, x in stages[sj].items()
                     if q not in ("noise_from_residuals", "reject")}
            v, st_j, ok_j, n_j, ds = run_stage(sj, again, v, ds)
        return v, (st_j, ok_j, n_j), ds

    def repeat(si, st, values, datas):
        """Re-run the ``stages`` solving stages before this one, round after round, until
        every parameter named in ``until`` moves by less than its tolerance over a round
        (or ``max_rounds``): the fixed point of stages that fit different parameters in
        turn (e.g. the rotation on the spikes, then the rest on all pixels), which one
        pass leaves wherever its start put it in a long, flat valley."""
        nonlocal status, ok, steps
        k, until, max_rounds = repeats[si]
        solving = solving_before(si)
        names = {q2: tol for q, tol in until.items() for q2 in model.expand([q], n_cap)}
        rounds = []
        settled = False
        for _ in range(max_rounds):
            before = {q: values[q] for q in names}
            values, (status, ok, steps), datas = rerun(solving[-k:], values, datas)
            moved = {q: values[q] - before[q] for q in names}
            rounds.append({"values": {q: values[q] for q in names}, "moved": moved,
                           "chi2": chi2_at(model, datas, values)})
            if verbose:
                print(f"stage {si}: repeat round {len(rounds)}: " + ", ".join(
                    f"{q} {values[q]:.6g} (moved {moved[q]:+.3g})" for q in names)
                    + f", chi2 {rounds[-1]['chi2']:.6g}", flush=True)
            if all(abs(moved[q]) < names[q] for q in names):
                settled = True
                break
        log.append({"stage": si, "repeat": dict(st["repeat"]), "rounds": rounds,
                    "settled": settled})
        if not settled:
            notes.append(f"repeat (stage {si}): {', '.join(names)} still moved by more than "
                         f"the tolerance after {max_rounds} rounds: raise max_rounds or "
                         "the tolerance.")
        return values, datas

    def hop(si, st, values, datas):
        """Re-run the ``stages`` solving stages before this one (hop stages are passed
        over) from ``values`` changed in each way the hop names: ``name`` moved by each
        of ``offsets``, each name in ``flip`` negated, or the parameters of ``set`` put
        at its values, all at once (σ as before the hop: they do not re-estimate the
        noise); keep whichever ends at the lowest χ² on all pixels, the unchanged
        result included."""
        nonlocal status, ok, steps, spike_errors
        h = dict(st["hop"])
        k = int(h.get("stages", 2))
        solving = solving_before(si)
        # each entry of flip: one name, or a list of names negated together (the twin)
        flips = [(q,) if isinstance(q, str) else tuple(q) for q in h.get("flip", ())]
        name = h.get("name")
        put = dict(h.get("set", {}))
        named = [q for g in flips for q in g] + list(put) + ([name] if name is not None else [])
        bad = [q for q in named if not isinstance(q, str) or q not in model.params]
        if any(not g for g in flips):
            bad.append("[] (an empty group)")
        kinds = (name is not None) + bool(flips) + bool(put)
        if (bad or not 1 <= k <= len(solving) or kinds != 1
                or (name is not None and not h.get("offsets"))):
            raise FitInputError(f"fit: stage {si}: hop needs one of: a parameter of the model "
                                "with offsets ({'name': ..., 'offsets': [...]}), a list of "
                                "parameters to negate, each a name or a list of names "
                                "negated together ({'flip': ['z6', ['z4', 'z11']]}), or "
                                "values to put "
                                "({'set': {name: value}}); and 1 <= stages <= "
                                f"{len(solving)} earlier solving stages; got {h}"
                                + (f" (unknown: {bad})" if bad else "") + ".")
        ref = list(datas)

        def chi2_of(v):
            return chi2_at(model, ref, v)

        put_at = _put(model, put, f"fit: stage {si}: hop set") if put else {}
        best = (chi2_of(values), values, datas, (status, ok, steps), dict(spike_errors))
        tried = [{"change": "none", "chi2": best[0]}]
        moves = ([(f"{name} {float(off):+g}", {name: values[name] + float(off)})
                  for off in h.get("offsets", ()) if name is not None]
                 + [(", ".join(g) + " negated", {q: -values[q] for q in g}) for g in flips]
                 + ([("set " + ", ".join(f"{q}={x:g}" for q, x in put.items()), put_at)]
                    if put else []))
        for label, change in moves:
            v = dict(values)
            for q, x in change.items():
                p = model.params[q]
                v[q] = x if p.bounds is None else min(max(x, p.bounds[0]), p.bounds[1])
            v, (st_j, ok_j, n_j), ds = rerun(solving[-k:], v, ref)
            c = chi2_of(v)
            tried.append({"change": label, "chi2": c,
                          "ends_at": {q: v[q] for q in change}})
            if verbose:
                print(f"stage {si}: hop {label}: ends at "
                      f"{ {q: round(v[q], 4) for q in change} }, chi2 {c:.6g} "
                      f"(best so far {best[0]:.6g})", flush=True)
            if c < best[0]:
                best = (c, v, ds, (st_j, ok_j, n_j), dict(spike_errors))
        log.append({"stage": si, "hop": h, "tried": tried})
        _, values, datas, (status, ok, steps), spike_errors = best
        return values, datas

    # every stage's mistakes (keys, names, windows, limits, scans, hops, repeats) and the
    # starts' are found before any fitting; a repeat's (stages, until, max_rounds) kept
    repeats = _check_fit_inputs(model, datas, stages, starts=starts, max_steps=max_steps,
                                rtol=rtol)
    for si, st in enumerate(stages):
        if st.get("hop") is not None:
            values, datas = hop(si, st, values, datas)
            continue
        if st.get("repeat") is not None:
            values, datas = repeat(si, st, values, datas)
            continue
        values, status, ok, steps, datas = run_stage(si, st, values, datas)

    final = model.with_values(values)
    errors, cov, chi2, dof, mimgs, msgs = _errors(final, datas, values)
    for k in errors:
        if last_stage.get(k) in spike_errors:
            errors[k] = spike_errors[last_stage[k]][k]
    resids = [np.where(d.mask, d.image - mi, 0.0) for d, mi in zip(datas, mimgs)]

    def one(xs):
        return xs[0] if n_cap == 1 else xs

    return FitResult(values=values, errors=errors, free=final.free, covariance=cov, chi2=chi2,
                     dof=dof, status=status, converged=ok, steps=steps,
                     model_image=one(mimgs), residual=one(resids),
                     data=one([d.image for d in datas]), mask=one([d.mask for d in datas]),
                     warnings=notes + msgs, wall_time=time.perf_counter() - t0, stages=log)


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


def _check_repeat(model: ImageModel, si: int, r: Any, n_solving: int) -> tuple:
    """A ``repeat`` stage's (stages, until, max_rounds), its defaults filled in; refuses
    one that cannot be right, naming what to fix (a per-capture name stands for every
    capture's own)."""
    given, r = r, (r if isinstance(r, Mapping) else {})
    k, until, max_rounds = r.get("stages", 2), r.get("until"), r.get("max_rounds", 6)
    bad = [] if isinstance(until, Mapping) and until else ["until (missing or empty)"]
    if isinstance(until, Mapping):
        bad += [f"until.{q}" for q, tol in until.items()
                if q not in model.params and q not in model.per_capture
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
    return k, dict(until), max_rounds


#: the most grid points a stage's ``scan`` may try (each one a model image: a scan step
#: of 1e-7 ran for minutes)
MAX_SCAN_POINTS = 1000
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


def _whole(x) -> bool:
    """A whole number (an int, or a float such as JSON's 2.0), not a bool."""
    if isinstance(x, (bool, np.bool_)):
        return False
    if isinstance(x, (int, np.integer)):
        return True
    return isinstance(x, (float, np.floating)) and math.isfinite(x) and float(x).is_integer()


def _finite(x) -> bool:
    """A finite real number, not a bool."""
    return (isinstance(x, (int, float, np.integer, np.floating))
            and not isinstance(x, (bool, np.bool_)) and math.isfinite(x))


def _scan_problem(model: ImageModel, name, half_range, step) -> str | None:
    """Why a scan of ``name`` over ± ``half_range`` by ``step`` cannot run, or None."""
    if not isinstance(name, str) or name not in model.params:
        return (f"name {name!r} is not a parameter of the model; known: "
                f"{sorted(model.params)}")
    for q, x in (("half_range", half_range), ("step", step)):
        if not (_finite(x) and x > 0):
            return f"{q} must be a finite number > 0 (in {name}'s units); got {x!r}"
    if step > 2 * half_range:
        return (f"step {step:g} is wider than the range (2 × half_range = "
                f"{2 * half_range:g}): give step <= 2 half_range")
    ratio = 2 * half_range / step
    if not ratio < MAX_SCAN_POINTS:  # (a ratio of inf: the same)
        return (f"half_range {half_range:g} / step {step:g} makes {ratio:.3g} grid points, "
                f"each a model image; at most {MAX_SCAN_POINTS}: raise step or lower "
                "half_range")
    return None


def _check_hop(model: ImageModel, si: int, h: Any, n_solving: int) -> None:
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
                      *, starts=None, max_steps=100, rtol=1e-6) -> dict:
    """Every mistake in a fit's stages and starts that can be found before any fitting
    (:func:`fit` and :func:`load_manifest` call it; ``model`` already made for the
    captures): returns the repeat stages' (stages, until, max_rounds) by index. Raises
    :class:`FitInputError` (an :class:`_InputAt` naming the stage and key)."""
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
    repeats = {}
    n_solving = 0
    for si, st in enumerate(stages):
        try:
            _check_stage_keys(si, st)
            if st.get("repeat") is not None:
                repeats[si] = _check_repeat(model, si, st["repeat"], n_solving)
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
    if not isinstance(model.source, str):  # a source image: inside every padded window
        sh, sw = model.source.shape
        for si, st in enumerate(stages):
            half = st.get("half") if st.get("hop") is None and st.get("repeat") is None \
                else None
            for d in datas:
                h, w = d.image.shape if half is None else d.cropped(int(half)).image.shape
                hp, wp = h + 2 * model.pad, w + 2 * model.pad
                if sh > hp or sw > wp:
                    raise _InputAt(("source", "image"), f"the source image ({sh} × {sw}) is "
                                   f"larger than stage {si}'s padded window ({hp} × {wp}); "
                                   "crop it or raise detector pad.")
    _check_fit_memory(model, datas)
    return repeats


#: the fitted Jacobian's memory over :func:`~difstar._psf.psf_bytes` per free parameter
#: (jacfwd carries every intermediate once per parameter, and XLA keeps more): calibrated
#: on the Spitzer campaign (fit/spitzer-irac: 81² pixels, 17 free, measured peak 9.4 GB
#: against psf_bytes × 19 = 0.47 GB), rounded down so that the estimate stays a lower one
_JACOBIAN_FACTOR = 8


def _check_fit_memory(model: ImageModel, datas: Sequence[FitData]) -> None:
    """Refuse (before any compile) a fit whose Jacobian cannot fit in memory: the
    largest capture's padded window, its plan, the free parameters; the estimate is a
    lower one, so a refused fit would certainly not have fitted."""
    from ._psf import _edges, psf_bytes
    from ._validate import fmt_bytes, memory_budget

    h, w = max((d.image.shape for d in datas), key=lambda s: s[0] * s[1])
    shape = (h + 2 * model.pad, w + 2 * model.pad)
    try:
        plan = model.plan(shape)
        one = psf_bytes(plan, shape, 1, _edges(model._pupil_at(model.values())), _PITCH)
    except (ValueError, TypeError):  # the fit's own first step reports these, named
        return
    k = len(model.free)
    need = _JACOBIAN_FACTOR * (k + 2) * one * (2 if model.has_incoherent else 1)
    budget = memory_budget()
    if need > budget:
        side = max(8, int(min(h, w) * math.sqrt(budget / need)))
        raise _InputAt(
            ("data",), f"fitting {k} free parameters on the {h} × {w} pixel window (padded to "
            f"{shape[0]} × {shape[1]}) needs at least {fmt_bytes(need)} of memory, more than "
            f"the {fmt_bytes(budget)} available (DIFSTAR_MEMORY_LIMIT overrides); give a "
            f"smaller roi (about {side} × {side} may fit), fewer free parameters, or a "
            "larger accuracy.", f"fit: the Jacobian needs at least {fmt_bytes(need)}, more "
            f"than the {fmt_bytes(budget)} available; fit a smaller window (roi) or fewer "
            "free parameters.")


def _put(model: ImageModel, put: Mapping[str, Any], where: str) -> dict[str, float]:
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
        out[q] = float(x) if p.bounds is None else min(max(float(x), p.bounds[0]),
                                                        p.bounds[1])
    return out


def _scan(model: ImageModel, data, target, values, *, name: str, half_range,
          step) -> dict:
    """``values`` with ``name`` moved to the lowest χ² of ``target`` on a grid of
    ``step`` over ± ``half_range`` about its value (inside its bounds): a coarse search
    that puts the local solver in the right basin when the objective has several (the
    rotation, against spikes whose fine structure repeats every fraction of a degree).
    The grid is the whole multiples of ``step`` in that range, not the value plus
    multiples: starts that differ by less than a step search the same points, so the
    basin chosen does not depend on where inside a step the start happened to be."""
    why = _scan_problem(model, name, half_range, step)
    if why:
        raise FitInputError(f"scan: {why}.")
    p = model.params[name]
    v = float(values[name])
    grid = step * np.arange(math.ceil((v - half_range) / step - 1e-9),
                            math.floor((v + half_range) / step + 1e-9) + 1)
    if p.bounds is not None:
        grid = grid[(grid > p.bounds[0]) & (grid < p.bounds[1])]
    if grid.size == 0:  # no grid point inside the bounds: nothing better to move to
        return dict(values)
    cost = chi2_slice(model, data, values, name, grid, target=target)
    return {**values, name: float(grid[int(np.argmin(cost))])}


def chi2_slice(model: ImageModel, data, values: Mapping[str, float], name: str, grid,
               *, target=None) -> np.ndarray:
    """χ² of ``model`` on ``data`` (a FitData or a list of captures; on all their used
    pixels unless ``target`` says otherwise) with ``name`` at each value of ``grid`` and
    every other parameter held at ``values``: a slice through the objective, to see
    whether it has one minimum along that parameter or several (the rotation of a
    pupil whose spikes the model matches only in part). One compile, then one model
    image per grid value. Raises :class:`FitInputError` for a name the model lacks or a
    grid that is empty or not finite."""
    if name not in model.params:
        raise FitInputError(f"chi2_slice: {name!r} is not a parameter of the model; known: "
                            f"{sorted(model.params)}.")
    g = np.asarray(grid, float).ravel()
    if g.size == 0 or not np.all(np.isfinite(g)):
        raise FitInputError(f"chi2_slice: grid must be a non-empty list of finite values; "
                            f"got {grid!r}.")
    datas = _as_list(data)
    targets = [_PixelTarget(d) for d in datas] if target is None else _as_list(target)
    res = _residual_fn(model, datas, targets)
    base = {k: jnp.asarray(x, float) for k, x in values.items()}
    chi2 = jax.jit(lambda x: jnp.sum(res({**base, name: x})[0] ** 2))
    return np.array([float(chi2(jnp.asarray(x, float))) for x in g])


def spike_target(data: FitData, values: Mapping[str, float], *, n_spikes=8, r_min=12.0,
                 r_max=45.0, half_width=4.0, bin_width=0.25, profiles=True,
                 directions="data", model_image=None):
    """The residuals of the spikes about the star at the model's ``values`` (x0, y0 from
    the window's centre pixel; background), around the directions :func:`spike_angles`
    measures in the data (``directions="data"``) or in ``model_image``, the model at the
    values reached (``"model"``: noise-free, so a faint star's noise cannot put a window
    where there is no spike): their angular profiles (:class:`SpikeProfiles`), or with
    ``profiles=False`` the pixels themselves within ± ``half_width`` degrees of each
    direction and between ``r_min`` and ``r_max`` pixels."""
    h, w = data.image.shape
    centre = (w // 2 + values["x0"], h // 2 + values["y0"])
    if directions == "data":
        img = np.where(data.mask, data.image - values["background"], np.nan)
    elif directions == "model" and model_image is not None:
        img = np.asarray(model_image, float) - values["background"]
    else:
        raise FitInputError(f"spikes: directions must be 'data' or 'model' (with the model "
                            f"image); got {directions!r}.")
    dirs = spike_angles(img, centre, r_min=r_min, r_max=r_max, n_spikes=n_spikes)
    if profiles:
        return SpikeProfiles(data, centre, values["background"], dirs, r_min=r_min,
                             r_max=r_max, half_width=half_width, bin_width=bin_width)
    r, th = _polar((h, w), centre)
    near = np.zeros((h, w), bool)
    for phi in dirs:
        near |= np.abs(_angle_from(th, phi)) <= half_width
    t = _PixelTarget(dataclasses.replace(data, mask=data.mask & near & (r >= r_min)
                                         & (r <= r_max)))
    t.kind = "spike pixels"
    t.directions = [float(d) for d in dirs]
    return t


def perturbed_starts(model: ImageModel, n, *, rel=PERTURB, seed=0) -> list[dict[str, float]]:
    """``n`` rough starts: every free parameter's start moved by a uniform random
    fraction within ± ``rel`` of its value (of half its bounds' width, or of its
    ``scale``, where the start is 0), kept inside its bounds. For checking that a fit
    converges to the same answer from anywhere near (the issue's ±20 %)."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(int(n)):
        start = {}
        for k in model.free:
            p = model.params[k]
            size = abs(p.value)
            if size == 0:
                size = (0.5 * (p.bounds[1] - p.bounds[0]) if p.bounds is not None
                        else (p.scale or 1e-3))
            v = p.value + rel * size * rng.uniform(-1, 1)
            if p.bounds is not None:
                lo, hi = p.bounds
                v = min(max(v, lo + 1e-3 * (hi - lo)), hi - 1e-3 * (hi - lo))
            start[k] = float(v)
        out.append(start)
    return out


def chi2_at(model: ImageModel, data, values: Mapping[str, float], target=None) -> float:
    """χ² = Σ ((data − model) / σ)² over the used pixels of ``data`` (a :class:`FitData`
    or a list of them) at ``values``; ``model`` as the fit had it (its own values are
    replaced by ``values``). ``target``: a spike stage's target instead of the pixels."""
    model = model.with_values(values)
    if target is None:
        target = [_PixelTarget(d) for d in _as_list(data)]
    v = {k: jnp.asarray(x, float) for k, x in values.items()}
    r = np.asarray(_residual_fn(model, data, target)(v)[0])
    return float(np.sum(r**2))


# --- spike angles measured from an image ---------------------------------------------------


def spike_angles(image, centre=None, *, r_min=15.0, r_max=40.0, n_spikes=6, bins=720,
                 symmetric=True, near=None, window=8.0):
    """Angles (degrees, counter-clockwise from +x, y up, in [0, 180) when ``symmetric``)
    of the ``n_spikes`` brightest spikes of an image, from the azimuthal profile of
    r² I between ``r_min`` and ``r_max`` pixels of ``centre`` (x, y in pixel units from
    the top-left pixel's centre; default: the intensity-weighted centre of the brightest
    3 × 3 pixels). Each peak is refined by a parabola through its three bins. With
    ``symmetric`` the profile is folded (θ and θ + 180° are one spike).

    ``near`` (angles in degrees): instead, for each of them the brightest peak within
    ± ``window`` degrees, in the same order (NaN where the profile there has no peak,
    only a slope: its maximum at the window's edge). This measures a second image's
    spikes where the first image's are, e.g. a model's where the data's were found."""
    img = np.asarray(image, float)
    h, w = img.shape
    if centre is None:
        r, c = np.unravel_index(np.nanargmax(img), img.shape)
        sub = img[r - 1:r + 2, c - 1:c + 2]
        yy, xx = np.mgrid[r - 1:r + 2, c - 1:c + 2]
        centre = (float((sub * xx).sum() / sub.sum()), float((sub * yy).sum() / sub.sum()))
    period = 180.0 if symmetric else 360.0
    rr, th = _polar((h, w), centre, period)
    sel = (rr >= r_min) & (rr <= r_max) & np.isfinite(img)
    nb = bins // 2 if symmetric else bins
    edges = np.linspace(0, period, nb + 1)
    idx = np.clip(np.digitize(th[sel], edges) - 1, 0, nb - 1)
    prof = np.bincount(idx, weights=(rr[sel] ** 2 * img[sel]), minlength=nb)
    cnt = np.bincount(idx, minlength=nb)
    prof = np.where(cnt > 0, prof / np.maximum(cnt, 1), 0)
    # smooth a little (circularly)
    k = np.array([1, 2, 3, 2, 1], float)
    k /= k.sum()
    prof = np.convolve(np.concatenate([prof[-2:], prof, prof[:2]]), k, "valid")
    width = period / nb

    def refined(i):
        a, b, c = prof[i - 1], prof[i], prof[(i + 1) % nb]
        den = a - 2 * b + c
        off = 0.5 * (a - c) / den if den != 0 else 0.0
        return ((i + 0.5 + off) * width) % period

    if near is not None:
        near = np.asarray(near, float).ravel()
        if not (np.all(np.isfinite(near)) and 2 * width < window < period / 2):
            raise FitInputError(f"spike_angles: near must be finite angles and window between "
                                f"{2 * width:g} and {period / 2:g} degrees; got {near}, {window}.")
        centres = (np.arange(nb) + 0.5) * width
        out = []
        for t in near:
            gap = np.abs((centres - t + period / 2) % period - period / 2)
            inside = np.flatnonzero(gap <= window)
            i = int(inside[np.argmax(prof[inside])])
            edge = gap[i] > window - width
            out.append(float("nan") if edge else refined(i))
        return out
    peaks = []
    p = prof.copy()
    for _ in range(n_spikes // (2 if symmetric else 1)):
        i = int(np.argmax(p))
        peaks.append(refined(i))
        lo, hi = i - int(8 / width), i + int(8 / width)
        for j in range(lo, hi + 1):
            p[j % nb] = -np.inf
    return sorted(peaks)


def model_spike_angles(values: Mapping[str, float], builder: str = "jwst") -> dict:
    """The spike directions (degrees, [0, 180), counter-clockwise from +x in the image,
    y up) a fitted model implies: perpendicular to the hexagons' edges and to the struts,
    then through the image distortion (``shear``, ``aspect``). For the ``jwst``
    builder: the six hexagon spikes (three directions) at 90° + rotation + k·60° and the
    strut spikes."""
    rot = values.get("rotation", 0.0)
    d = np.array([[1.0, 0.0], [values.get("shear", 0.0), 1.0 + values.get("aspect", 0.0)]])

    def seen(angles):
        a = np.deg2rad(np.asarray(angles, float) + rot)
        u = d @ np.stack([np.cos(a), np.sin(a)])
        return sorted(float(t) for t in np.degrees(np.arctan2(u[1], u[0])) % 180.0)

    out = {}
    if builder == "jwst":
        out["hexagon"] = seen([90.0 + 60 * k for k in range(3)])
        sp = values.get("strut_spread", 30.0)
        up = 90.0 + values.get("strut_tilt", 0.0)
        out["struts"] = seen([a + 90.0 for a in (up, 270 - sp, 270 + sp)])
    else:
        out["struts"] = seen([a + 90.0 for a in (90.0, 210.0, 330.0)])
    return out


def _nowarn():
    warnings.simplefilter("ignore")


# --- manifests ----------------------------------------------------------------------------


def resolve_data_path(path: str, manifest_dir, *, field: str | None = None,
                      source: str = "manifest") -> str:
    """A data path from a manifest: absolute, or relative to the manifest's folder, the
    current folder or the repository root (the folder above ``fit/``), whichever exists.
    ``field``: the manifest's field that gave it (named in the error)."""
    import os
    from pathlib import Path

    p = Path(path)
    if p.is_absolute():
        cands = [p]
    else:
        md = Path(manifest_dir).resolve()
        cands = [md / p, Path.cwd() / p] + [a / p for a in md.parents if (a / "fit").is_dir()]
    for c in cands:
        try:
            found = c.exists()
        except (OSError, ValueError):  # a name the system cannot hold
            found = False
        if found:
            return os.path.abspath(c)  # ".." folded: the path the output policy compares
    where = f"{source}: field {field}" if field else source
    raise FitInputError(f"{where}: data file {path!r} not found (looked in "
                        f"{', '.join(str(c.parent) for c in cands[:3])}); give a path "
                        "relative to the manifest's folder, or an absolute one.")


def _read_at(file: str, field: str, source: str):
    """:func:`difstar.io.read_image` of ``file``, its errors naming the manifest's field."""
    from .io._images import read_image

    try:
        return read_image(file)
    except (ValueError, OSError) as e:
        raise FitInputError(f"{source}: field {field}: {e}") from None


def _load_capture(d: Mapping, where, manifest_dir, *, source: str = "manifest",
                  inputs: list | None = None) -> FitData:
    """One capture of a manifest's ``data``: its file, window, σ (a number, a σ map file or
    the noise model), exposure and saturation level, checked against the image (the ROI
    inside it, a σ map of its shape, some signal) with errors naming ``where`` (the
    capture's JSON path). The files read are appended to ``inputs``. Pixels that are NaN
    or infinite (a FITS border) are left out of the fit, with a warning."""
    if not isinstance(d, Mapping) or "path" not in d:
        raise FitInputError(f"{source}: field {where}: needs a 'path' (the image file).")
    inputs = [] if inputs is None else inputs
    file = resolve_data_path(d["path"], manifest_dir, field=f"{where}/path", source=source)
    inputs.append(file)
    im = _read_at(file, f"{where}/path", source)
    h, w = im.shape
    roi = d.get("roi")
    win = np.s_[:, :]
    if roi is not None:
        r0, r1, c0, c1 = (int(v) for v in roi)
        if not (0 <= r0 < r1 <= h and 0 <= c0 < c1 <= w and r1 - r0 >= 4 and c1 - c0 >= 4):
            raise FitInputError(
                f"{source}: field {where}/roi: {list(roi)} is not a window of the image "
                f"({h} × {w} pixels): give [row0, row1, col0, col1] with 0 <= row0 < row1 <= "
                f"{h}, 0 <= col0 < col1 <= {w}, at least 4 × 4 pixels.")
        win = np.s_[r0:r1, c0:c1]
    mask = np.array(im.valid)
    sigma = d.get("sigma")
    if isinstance(sigma, str):  # a σ map: an image of the data's shape
        sfile = resolve_data_path(sigma, manifest_dir, field=f"{where}/sigma", source=source)
        inputs.append(sfile)
        sm = _read_at(sfile, f"{where}/sigma", source)
        if sm.shape != im.shape:
            raise FitInputError(
                f"{source}: field {where}/sigma: the σ map is {sm.shape[0]} × {sm.shape[1]} "
                f"pixels, the image {h} × {w}: give a σ map of the image's shape (before "
                "roi).")
        mask &= sm.valid
        sigma = np.where(sm.valid, sm.data, 1.0)
        bad = int(np.count_nonzero(mask[win] & (sigma[win] <= 0)))
        if bad:
            raise FitInputError(f"{source}: field {where}/sigma: the σ map holds {bad} values "
                                "<= 0 on pixels of the window; σ must be > 0 (NaN where a "
                                "pixel is not to be used).")
    n_bad = int(np.count_nonzero(~mask[win]))
    used = im.data[win][mask[win]]
    if used.size == 0:
        raise FitInputError(f"{source}: field {where}: no pixel of the window holds a finite "
                            "value; check the file and the roi.")
    if not np.ptp(used) > 0:
        raise FitInputError(f"{source}: field {where}: the data has no signal above the "
                            f"background (every used pixel is {used[0]:g}); check the file "
                            "and the roi.")
    noise = d.get("noise") or {}
    try:
        fd = FitData.from_array(
            im.data, sigma=sigma, mask=mask, roi=roi, pixel_scale=im.pixel_scale, path=file,
            noise=Noise(None if noise.get("read") is None else float(noise["read"]),
                        float(noise.get("gain", 1.0)), float(noise.get("floor", 0.0))),
            exposure=float(d.get("exposure", 1.0)), saturation=d.get("saturation"))
    except FitInputError as e:
        raise FitInputError(f"{source}: field {where}: "
                            f"{str(e).removeprefix('FitData: ')}") from None
    big = float(np.max(np.abs(fd.image[fd.mask])))
    if not 1.0 / MAX_DATA_MAGNITUDE <= big <= MAX_DATA_MAGNITUDE:
        raise FitInputError(f"{source}: field {where}: values up to {big:.3g} (outside "
                            f"{1 / MAX_DATA_MAGNITUDE:g} to {MAX_DATA_MAGNITUDE:g}, where the "
                            "χ² overflows or underflows); rescale the data (and its σ) to "
                            "counts or another unit near 1.")
    bg = _border_background(fd)
    amp = float(np.max(fd.image[fd.mask])) - bg
    spread = _border_spread(fd, bg)
    if not (amp > 5.0 * spread and amp > 1e-6 * abs(bg)):
        raise FitInputError(f"{source}: field {where}: the data has no signal above the "
                            f"background ({bg:g}, the border's median; the brightest pixel "
                            f"is {amp:.3g} above it, the border's scatter {spread:.3g}); check "
                            "the file, its sign, the roi and the saturation level.")
    if n_bad:
        warnings.warn(f"{source}: field {where}/path: {n_bad} of {used.size + n_bad} pixels "
                      "of the window are NaN or infinite (e.g. a border of the image); they "
                      "are left out of the fit.", stacklevel=3)
    return fd


def _load_source(src, manifest_dir, *, source: str = "manifest",
                 inputs: list | None = None):
    """The manifest's ``source``: "point", "disc" or {"image": path} (FITS, TIFF, PNG or
    .npy: the source as the data's pixels see it; finite, non-negative, a positive sum).
    The file read is appended to ``inputs``."""
    if isinstance(src, Mapping):
        if set(src) != {"image"} or not isinstance(src["image"], str):
            raise FitInputError(f"{source}: field source: must be 'point', 'disc' or "
                                f"{{'image': path}}; got {dict(src)}.")
        file = resolve_data_path(src["image"], manifest_dir, field="source/image",
                                 source=source)
        if inputs is not None:
            inputs.append(file)
        im = _read_at(file, "source/image", source)
        a = np.where(im.valid, im.data, 0.0)
        if not (np.all(a >= 0) and a.sum() > 0):
            raise FitInputError(f"{source}: field source/image: a source image must be "
                                "non-negative with a positive sum (the source's light as "
                                "the data's pixels see it).")
        return a
    return src


def _border_background(data: FitData) -> float:
    """The median of the used pixels in the border of the window (a tenth of its size, at
    least 2 pixels): the ``"auto"`` background. Where that border holds no used pixel (a
    border of NaN in the file), the border of the box of the used pixels instead."""
    m = data.mask
    box = np.s_[:, :]
    if not _edge(m.shape)[m].any():
        rows, cols = np.flatnonzero(m.any(axis=1)), np.flatnonzero(m.any(axis=0))
        box = np.s_[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1]
    img, m = data.image[box], m[box]
    return float(np.median(img[_edge(m.shape) & m]))


#: the largest |value| a fitted image may hold, and 1 / it the least largest one: its
#: squares (χ²) stay finite and normal in float64
MAX_DATA_MAGNITUDE = 1e100


def _border_spread(data: FitData, background: float) -> float:
    """The scatter of the border's used pixels about ``background`` (1.4826 × their
    median absolute deviation: σ for Gaussian noise)."""
    m = data.mask & _edge(data.mask.shape)
    if not m.any():
        return 0.0
    return 1.4826 * float(np.median(np.abs(data.image[m] - background)))


def _edge(shape) -> np.ndarray:
    b = max(2, min(shape) // 10)
    edge = np.ones(shape, bool)
    edge[b:-b, b:-b] = False
    return edge


def _brightest_offset(data: FitData, background: float) -> tuple[float, float]:
    """(x, y) of the star from the window's centre pixel (columns right, rows down): the
    centroid of (data − ``background``) over the 3 × 3 pixels about the brightest used
    pixel. The ``"auto"`` start of ``x0`` and ``y0`` for a star anywhere in its window."""
    img = np.where(data.mask, data.image - background, -np.inf)
    r, c = np.unravel_index(int(np.argmax(img)), img.shape)
    h, w = img.shape
    r0, r1, c0, c1 = max(r - 1, 0), min(r + 2, h), max(c - 1, 0), min(c + 2, w)
    sub = np.maximum(np.where(np.isfinite(img[r0:r1, c0:c1]), img[r0:r1, c0:c1], 0.0), 0.0)
    yy, xx = np.mgrid[r0:r1, c0:c1]
    tot = sub.sum()
    if not tot > 0:
        return float(c - w // 2), float(r - h // 2)
    return (float((sub * xx).sum() / tot - w // 2), float((sub * yy).sum() / tot - h // 2))


def _manifest_shape(man: Any, src: str) -> None:
    """The mistakes the schema would name less plainly, named first: not an object, an
    empty list of captures, a capture without its file, a pupil without its builder,
    light with neither or both of wavelength and band, unknown keys (with the known
    ones)."""
    if not isinstance(man, Mapping):
        raise FitInputError(f"{src}: field (top level): a manifest is a JSON object with "
                            f"data, pupil, light and params; got {type(man).__name__}.")
    data = man.get("data")
    if isinstance(data, list) and not data:
        raise FitInputError(f"{src}: field data: an empty list; give one capture or more "
                            "({'path': 'star.fits'}).")
    for i, d in enumerate(data if isinstance(data, list) else [data]):
        if isinstance(d, Mapping) and "path" not in d:
            where = f"data/{i}: capture data[{i}]" if isinstance(data, list) else "data: it"
            raise FitInputError(f"{src}: field {where} needs a 'path' (the image file).")
    pu = man.get("pupil")
    if isinstance(pu, Mapping) and "builder" not in pu:
        raise FitInputError(f"{src}: field pupil: needs a 'builder', one of "
                            f"{sorted(BUILDERS)}.")
    li = man.get("light")
    if isinstance(li, Mapping) and ("wavelength" in li) == ("band" in li):
        raise FitInputError(f"{src}: field light: give exactly one of wavelength (metres, "
                            "e.g. 9e-07) or band ([lo, hi] in metres); got "
                            f"{'both' if 'band' in li else 'neither'}.")
    if isinstance(li, Mapping) and "wavelength" in li:
        for q in ("n", "source"):
            if q in li:
                raise FitInputError(f"{src}: field light/{q}: goes with band (the "
                                    "wavelengths over it and their spectrum); with one "
                                    "wavelength leave it out.")
    _known_keys(man, src)


def _known_keys(man: Mapping, src: str) -> None:
    """A key the manifest's schema does not know, in an object with a fixed set of keys
    (a typo would otherwise be refused by the schema without the keys it knows, or passed
    over): refused naming its field and the known keys."""
    from .io._json import load_schema

    schema = load_schema("image_fit_manifest")
    props, defs = schema["properties"], schema["$defs"]

    def check(obj, allowed, where, what=""):
        if isinstance(obj, Mapping):
            bad = sorted(str(q) for q in set(obj) - set(allowed))
            if bad:
                raise FitInputError(f"{src}: field {where}: unknown key{'s' * (len(bad) > 1)} "
                                    f"{', '.join(map(repr, bad))}{what}; known: "
                                    f"{', '.join(sorted(allowed))}.")

    check(man, props, "(top level)")
    data = man.get("data")
    for i, d in enumerate(data if isinstance(data, list) else [data]):
        where = f"data/{i}" if isinstance(data, list) else "data"
        check(d, defs["capture"]["properties"], where)
        if isinstance(d, Mapping):
            check(d.get("noise"), defs["capture"]["properties"]["noise"]["properties"],
                  f"{where}/noise")
    for k in ("detector", "light", "spikes"):
        check(man.get(k), props[k]["properties"], k)
    pu = man.get("pupil")
    if isinstance(pu, Mapping):
        for branch in props["pupil"]["oneOf"]:
            if branch["properties"]["builder"]["const"] == pu.get("builder"):
                check(pu, branch["properties"], "pupil", f" for builder {pu['builder']!r}")
    params = man.get("params")
    if isinstance(params, Mapping):
        for k, spec in params.items():
            check(spec, defs["param_spec"]["properties"], f"params/{k}")
    if isinstance(man.get("source"), Mapping):
        check(man["source"], {"image"}, "source")
    stage = props["stages"]["items"]["properties"]
    stages = man.get("stages")
    for si, st in enumerate(stages if isinstance(stages, list) else ()):
        check(st, stage, f"stages/{si}", " (a stage that is only 'hop' or only 'repeat' "
              "takes no other key)")
        if isinstance(st, Mapping):
            for k in ("scan", "hop", "noise_from_residuals", "reject", "spikes", "repeat"):
                check(st.get(k), stage[k]["properties"], f"stages/{si}/{k}")


def _range_of(p: Param) -> tuple[float, float]:
    """The lowest and highest values a parameter takes in a fit: its value, and its
    bounds when free."""
    vals = [p.value, *(p.bounds if p.free and p.bounds else ())]
    return min(vals), max(vals)


def _check_geometry(kind: str, model: ImageModel, src: str) -> None:
    """An obstruction that covers the whole pupil (all its light blocked: the model is
    not finite) is refused, naming the field, before any model is computed."""
    p = model.params
    if kind == "circle":
        outer, what = _range_of(p["radius"])[0], "the pupil's radius"
    elif kind == "jwst":
        f2f, gap = _range_of(p["flat_to_flat"])[0], _range_of(p["gap"])[0]
        outer = 2 * (f2f + gap) + f2f / math.sqrt(3)
        what = "the outermost segment's corner"
    else:
        return
    obs = _range_of(p["obstruction"])[1]
    if not obs < outer:
        raise FitInputError(f"{src}: field params/obstruction: an obstruction of radius "
                            f"{obs:g} m (its value or bound) covers the whole pupil ({what} "
                            f"at {outer:g} m): give an obstruction (and bounds) below "
                            f"{outer:g} m.")


def _params_of(man: Mapping, kind: str, builder: PupilBuilder, auto: Mapping,
               src: str) -> dict:
    """The manifest's ``params``, each checked and turned into a :class:`Param` (the
    ``"auto"`` and ``"header"`` values and their relative bounds filled in), with errors
    naming the parameter's field."""
    known = (set(COMMON) | set(builder.defaults)
             | {f"z{j}" for j in man.get("zernike", ())}
             | (set(SOURCE_DISC) if man.get("source") == "disc" else set())
             | (set(RESPONSE) if man.get("detector", {}).get("response") else set()))
    out = {}
    for k, spec in man["params"].items():
        at = f"{src}: field params/{k}"
        if k not in known:
            raise FitInputError(f"{at}: not a parameter of this model (pupil {kind!r}, its "
                                f"zernike terms, source and detector); known: {sorted(known)}.")
        spec = dict(spec) if isinstance(spec, Mapping) else spec
        if isinstance(spec, dict):
            rel = [q for q in ("bounds", "bounds_relative", "bounds_about") if q in spec]
            if len(rel) > 1:
                raise FitInputError(f"{at}: give one of {rel}, not several.")
            if spec["value"] in ("header", "auto"):
                if auto.get(k) is None:
                    raise FitInputError(f"{at}/value: {spec['value']!r} but it cannot be found "
                                        "from the data (give a number).")
                spec["value"] = auto[k]
                if "bounds_relative" in spec:
                    lo, hi = spec.pop("bounds_relative")
                    spec["bounds"] = sorted([auto[k] * lo, auto[k] * hi])
                if "bounds_about" in spec:
                    lo, hi = spec.pop("bounds_about")
                    spec["bounds"] = [auto[k] + lo, auto[k] + hi]
            elif rel and rel[0] != "bounds":
                raise FitInputError(f"{at}/{rel[0]}: applies only with value 'auto' or "
                                    "'header' (bounds about the value found from the data); "
                                    "give bounds [lo, hi] instead.")
        try:
            out[k] = _as_param(spec)
        except FitInputError as e:
            raise FitInputError(f"{at}: {str(e).removeprefix('Param ')}") from None
        vals = [out[k].value, *(out[k].bounds or ())]
        if k == "pixel_scale" and not all(1e-4 < v < 100 for v in vals):
            raise FitInputError(f"{at}: {vals} is not in arcsec per data pixel (expected "
                                "1e-4 … 100).")
        if re.fullmatch(r"z\d+", k) and max(map(abs, vals)) > 1e4:
            raise FitInputError(f"{at}: {vals} is not in nm RMS (over 10 µm).")
    return out


def _stage_field(e: FitInputError, src: str) -> FitInputError:
    """A fit's refusal as the manifest's field (``stages/1/half``, ``starts/x0``)."""
    if isinstance(e, _InputAt):
        return FitInputError(f"{src}: field {e.field}: {e.detail}")
    return FitInputError(f"{src}: field stages: {e}")


def load_manifest(path):
    """(model, data, options) from an image-fit manifest (JSON; see
    data_schemas/image_fit_manifest.schema.json). ``data`` is a FitData, or a list of
    them when the manifest's ``data`` is a list of captures (exposures, dithers, an
    exposure bracket); then ``options["per_capture"]`` names the parameters each capture
    has its own of. ``options``: stages, starts, max_steps, per_capture, builder, the raw
    manifest, and ``inputs``: every file the manifest made difstar read (each capture's
    image and σ map, the source image).

    The manifest is read strictly (no NaN or Infinity, no key given twice), checked
    against its schema, then against its data and model (an ROI inside the image, some
    signal, the obstruction inside the pupil, the parameters the model has, every stage
    with a window that holds pixels and something free): every mistake raises
    :class:`FitInputError` or :class:`difstar.io._scene.SceneError` (both ValueError)
    naming the manifest and the field, before anything is computed."""
    from pathlib import Path

    from .io._json import SceneError, read_json, validate

    path = Path(path)
    src = str(path)
    try:  # one kind of error for a manifest's every mistake (the command line's prefix)
        man = read_json(path, what="manifest")
        _manifest_shape(man, src)
        validate(man, "image_fit_manifest", source=src)
    except SceneError as e:
        raise FitInputError(str(e)) from None
    several = isinstance(man["data"], list)
    caps = man["data"] if several else [man["data"]]
    inputs: list[str] = []
    fds = [_load_capture(d, f"data/{i}" if several else "data", path.parent, source=src,
                         inputs=inputs)
           for i, d in enumerate(caps)]
    fd = fds[0]
    pu = dict(man["pupil"])
    kind = pu.pop("builder")
    pu = {k: int(v) if k == "blades" else float(v) for k, v in pu.items()}
    try:
        builder = BUILDERS[kind](**pu)
    except FitInputError as e:
        raise FitInputError(f"{src}: field pupil: {e}") from None
    li = man["light"]
    at = "light/band" if "band" in li else "light/wavelength"
    try:
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            if "band" in li:
                light = Light.band(*li["band"], n=int(li.get("n", 4)),
                                   source=li.get("source", "flat"))
            else:
                light = Light.monochromatic(li["wavelength"])
    except FitInputError as e:
        if str(e).startswith("Light.band: source"):
            at = "light/source"
        raise FitInputError(f"{src}: field {at}: {e}") from None
    det = man.get("detector", {})
    bg = _border_background(fd)
    x0, y0 = _brightest_offset(fd, bg)
    auto = {"pixel_scale": fd.pixel_scale, "background": bg,
            "flux": float(np.sum(fd.image[fd.mask] - bg)) / fd.exposure, "x0": x0, "y0": y0}
    params = _params_of(man, kind, builder, auto, src)
    try:
        model = ImageModel(builder, params, light=light, zernike=man.get("zernike", ()),
                           oversample=float(det.get("oversample", 1.0)),
                           pad=int(det.get("pad", 8)),
                           accuracy=float(man.get("accuracy", 1e-2)),
                           source=_load_source(man.get("source", "point"), path.parent,
                                               source=src, inputs=inputs),
                           response=bool(det.get("response", False)),
                           resampling=det.get("resampling"))
    except FitInputError as e:  # the parameter it names, where it names one
        msg = str(e).removeprefix("ImageModel: ")
        m = re.match(r"(\w+) = ", msg)
        field = f"params/{m.group(1)}" if m and m.group(1) in params else "(top level)"
        raise FitInputError(f"{src}: field {field}: {msg}") from None
    _check_geometry(kind, model, src)
    opts = {"stages": man.get("stages"), "starts": man.get("starts"),
            "max_steps": int(man.get("max_steps", 100)), "manifest": man,
            "builder": kind, "per_capture": man.get("per_capture"), "inputs": inputs}
    # the stages, starts and per-capture names, as fit() will check them: refused here,
    # naming the manifest's field, before anything is computed
    checked = model
    if several or opts["per_capture"]:
        per = (("x0", "y0", "flux", "background") if opts["per_capture"] is None
               else tuple(opts["per_capture"]))
        try:
            checked = model.for_captures(per, len(fds))
        except FitInputError as e:
            raise FitInputError(f"{src}: field per_capture: "
                                f"{str(e).removeprefix('per_capture: ')}") from None
    try:
        _check_fit_inputs(checked, fds, list(opts["stages"] or [{"free": "all"}]),
                          starts=opts["starts"], max_steps=opts["max_steps"])
    except FitInputError as e:
        raise _stage_field(e, src) from None
    return model, (fds if several else fd), opts
