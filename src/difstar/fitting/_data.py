"""Data: an intensity image with its σ, mask and pixel scale (:class:`FitData`,
:class:`Noise`), and what is estimated from data and a model image (noise, outliers,
fainter copies)."""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from .._cfa import channel_index
from ..io._images import read_image
from ..io._raw import RawCapture, read_raw
from ._params import FitInputError
from ._parts import Light


@dataclasses.dataclass(frozen=True)
class Noise:
    """σ² = read² + max(I, 0) / gain + (floor · I)² per pixel (I the data, same units).
    ``read=None``: estimated from the border of the image (median absolute deviation)."""

    read: float | None = None
    gain: float = 1.0
    floor: float = 0.0

    def __post_init__(self):
        if self.read is not None:
            _number(self.read, "Noise.read", ">= 0", lambda x: x >= 0)
        # inf: no shot noise (as noise_from_residuals may find)
        _number(self.gain, "Noise.gain", "> 0 (inf: no shot noise)", lambda x: x > 0,
                finite=False)
        _number(self.floor, "Noise.floor", ">= 0", lambda x: x >= 0)


def _number(value, field: str, need: str, ok=lambda x: True, *, finite=True) -> float:
    """``value`` as a float (``finite``: a finite one; never NaN) for which ``ok`` holds,
    else a :class:`FitInputError` naming ``field`` and what it needs (``need``)."""
    try:
        x = float(value)
    except (TypeError, ValueError):
        x = math.nan
    if math.isnan(x) or (finite and not math.isfinite(x)) or not ok(x):
        raise FitInputError(f"{field} must be a {'finite ' if finite else ''}number {need}; "
                            f"got {value!r}.")
    return x


def _image(image) -> np.ndarray:
    """The image as a 2-D float array of at least 4 × 4 real numbers, else an error
    saying what it is (text, complex values, a mask, a ragged list, a cube)."""
    try:
        a = np.asarray(image)
    except ValueError:  # a ragged list
        raise FitInputError("FitData: the image must be a 2-D array of numbers; got a "
                            "ragged list (rows of different lengths).") from None
    if a.dtype.kind not in "iuf":
        what = {"b": "True/False values (a mask? give it as mask=)",
                "c": "complex numbers (give the intensity, e.g. abs(field)**2)"}.get(
                    a.dtype.kind, f"values of type {a.dtype}")
        raise FitInputError(f"FitData: the image must be real numbers; got {what}.")
    if a.ndim != 2 or min(a.shape) < 4:
        raise FitInputError(f"FitData: the image must be 2-D, at least 4 × 4; got shape "
                            f"{a.shape}.")
    return a.astype(float)


def _like_image(value, img: np.ndarray, field: str, dtype) -> np.ndarray:
    """``value`` as an array of the image's shape (before any roi), else an error
    naming ``field``."""
    try:
        a = np.asarray(value, dtype)
    except (TypeError, ValueError):
        raise FitInputError(f"FitData: {field} must be an array of numbers shaped like "
                            f"the image {img.shape}.") from None
    if a.shape != img.shape:
        raise FitInputError(f"FitData: {field} has shape {a.shape}; give one of the "
                            f"image's shape {img.shape} (before any roi).")
    return a


def _roi(roi, shape) -> tuple[int, int, int, int]:
    """``roi`` = (row0, row1, col0, col1): whole numbers inside ``shape`` with at least
    4 × 4 pixels between them, else an error saying which."""
    try:
        vals = [float(v) for v in roi]
    except (TypeError, ValueError):
        vals = []
    h, w = shape
    if len(vals) != 4 or not all(math.isfinite(v) and v == int(v) for v in vals):
        raise FitInputError(f"FitData: roi must be 4 whole numbers (row0, row1, col0, "
                            f"col1); got {roi!r}.")
    r0, r1, c0, c1 = (int(v) for v in vals)
    if not (0 <= r0 and r0 + 4 <= r1 <= h and 0 <= c0 and c0 + 4 <= c1 <= w):
        raise FitInputError(f"FitData: roi {(r0, r1, c0, c1)} must lie inside the "
                            f"{h} × {w} image, at least 4 × 4: 0 ≤ row0, row0 + 4 ≤ row1 ≤ "
                            f"{h}, 0 ≤ col0, col0 + 4 ≤ col1 ≤ {w}.")
    return r0, r1, c0, c1


#: the largest |value| a fitted image may hold, and 1 / it the least largest one: its
#: squares (χ², and the noise model's variance) stay finite and normal in float64
MAX_DATA_MAGNITUDE = 1e100


@dataclasses.dataclass
class FitData:
    """An image to fit: ``image`` (H, W), ``sigma`` (per pixel, or from ``noise``),
    ``mask`` (True = use), cut to ``roi`` = (row0, row1, col0, col1) if given.

    ``exposure``: this capture's relative exposure (time × gain; 1 by default); the
    model's ``flux`` is multiplied by it, so the captures of an exposure bracket can
    share one flux (leave ``flux`` out of ``per_capture``). ``saturation``: pixels at or
    above this level are not used (the sensor clipped them). ``light``: this capture's
    :class:`Light` where it differs from the model's (the R, G and B photosites of one
    RAW fitted together, each in its own band). ``noise``: the :class:`Noise` σ was
    made from (None where σ was given)."""

    image: np.ndarray
    sigma: np.ndarray
    mask: np.ndarray
    pixel_scale: float | None = None
    path: str | None = None
    exposure: float = 1.0
    light: Any = None
    noise: Noise | None = None

    @staticmethod
    def from_array(image, *, sigma=None, noise: Noise | None = None, mask=None, roi=None,
                   pixel_scale=None, path=None, exposure=1.0, saturation=None,
                   light=None) -> FitData:
        exposure = _number(exposure, "FitData: exposure", "> 0 (a relative exposure time)",
                           lambda x: x > 0)
        img = _image(image)
        m = np.isfinite(img) if mask is None else (_like_image(mask, img, "mask", bool)
                                                   & np.isfinite(img))
        if saturation is not None:
            level = _number(saturation, "FitData: saturation", "(the level the sensor clips at)")
            m = m & ~(np.where(np.isfinite(img), img, 0.0) >= level)
        if pixel_scale is not None:
            pixel_scale = _number(pixel_scale, "FitData: pixel_scale", "> 0 (arcsec per pixel)",
                                  lambda x: x > 0)
        if sigma is not None and np.ndim(sigma) != 0:
            sigma = _like_image(sigma, img, "sigma", float)
        if roi is not None:
            r0, r1, c0, c1 = _roi(roi, img.shape)
            img, m = img[r0:r1, c0:c1], m[r0:r1, c0:c1]
            if sigma is not None and np.ndim(sigma) == 2:
                sigma = sigma[r0:r1, c0:c1]
        if not m.any():
            raise FitInputError("FitData: no valid pixel (all NaN, infinite or masked).")
        if np.count_nonzero(~np.isfinite(img) & m):
            raise FitInputError("FitData: NaN or infinite values in unmasked pixels.")
        img = np.where(m, img, 0.0)
        big = float(np.max(np.abs(img[m])))  # before the noise model squares them
        if big == 0:
            raise FitInputError("FitData: the image is 0 on every used pixel: nothing to "
                                "fit (check the file, the mask, the roi and the saturation).")
        if not 1.0 / MAX_DATA_MAGNITUDE <= big <= MAX_DATA_MAGNITUDE:
            raise FitInputError(f"FitData: values up to {big:.3g} (outside "
                                f"{1 / MAX_DATA_MAGNITUDE:g} to {MAX_DATA_MAGNITUDE:g}, where "
                                "the χ² overflows or underflows); rescale the data (and its "
                                "σ) to counts or another unit near 1.")
        given = sigma is not None
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
            var = read**2 + np.maximum(img, 0) / noise.gain + (noise.floor * img) ** 2
            sigma = np.sqrt(var)
        sigma = np.broadcast_to(np.asarray(sigma, float), img.shape).copy()
        if np.any(~np.isfinite(sigma[m])) or np.any(sigma[m] <= 0):
            raise FitInputError("FitData: sigma must be finite and > 0 on every used pixel.")
        sigma[~m] = 1.0
        if light is not None and not isinstance(light, Light):
            raise FitInputError("FitData: light must be a difstar Light (Light.monochromatic or "
                                f"Light.band); got {type(light).__name__}.")
        return FitData(img, sigma, m, pixel_scale, path, exposure, light,
                       None if given else noise)

    @staticmethod
    def from_file(path, **kw) -> FitData:
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
