"""The whole chain in one pure function: camera + scene → PSFs, RAW mosaic, sRGB.

``simulate`` is what jit and grad see whole; fitting and design call it and nothing
lower. The model's types live in :mod:`._model`, the sampling rules in
:mod:`._sampling_rules`, the grid chooser in :mod:`._sampling`; they are re-exported here.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ._atf import atf
from ._cfa import mosaic
from ._colour import render_srgb
from ._custom_types import Array
from ._fft_size import fast_length
from ._geometry import Geometry
from ._grid_psf import bin_pixels, intensity_from_atf
from ._image import DiscSource as DiscSource
from ._image import PointSource as PointSource
from ._image import convolve, geometric_image, image_spectrum
from ._mft import _conv_offsets, focused_image, polygon_intensities, window_rfft2
from ._model import (
    METHODS as METHODS,
)
from ._model import (
    PATTERNS as PATTERNS,
)
from ._model import (
    Camera as Camera,
)
from ._model import (
    Grid as Grid,
)
from ._model import (
    Lens as Lens,
)
from ._model import (
    Prediction as Prediction,
)
from ._model import (
    Scene as Scene,
)
from ._model import (
    Sensor as Sensor,
)
from ._model import (
    geometry_of as geometry_of,
)
from ._otf import otf
from ._psf import psf, psf_each
from ._psf_engine import SamplingError as SamplingError
from ._pupil import Polygon, RegularPolygon
from ._radiometry import radiometry
from ._sampling_rules import (
    check_sampling as check_sampling,
)
from ._sampling_rules import (
    engine_crop,
    engine_fine_crop,
    engine_psf_shape,
)
from ._sampling_rules import (
    needs_defocus as needs_defocus,
)
from ._sampling_rules import (
    pupil_window_for as pupil_window_for,
)
from ._sampling_rules import (
    source_window_for as source_window_for,
)
from ._sensor import sensor
from ._xla import stored


def _crop(a: Array, crop: tuple[int, int]) -> Array:
    n0, n1 = a.shape[-2:]
    r0 = n0 // 2 - crop[0] // 2
    c0 = n1 // 2 - crop[1] // 2
    return a[..., r0 : r0 + crop[0], c0 : c0 + crop[1]]


def channel_psf(pupil, wavelength, geometry: Geometry, *, pixel_pitch: float, grid: Grid):
    """One channel's PSF on the full n × n grid, sampled at the pixel centres: the fraction
    of the pupil's power per pixel (the intensity at the centre × the pixel's area),
    normalised by the pupil's energy (Parseval) so that its sum over the infinite plane
    is 1. The pixels integrate the image once, through the geometric image's area
    coverage (see :func:`simulate`); the PSF itself is not integrated again."""
    n, q = grid.n, grid.oversample
    h_atf, energy = atf(
        pupil, wavelength=wavelength, z_image=geometry.z_exit_pupil,
        defocus=geometry.defocus, dx=pixel_pitch / q, shape=(n * q, n * q),
        scaling=grid.scaling, use_defocus=grid.use_defocus,
        cell_average=pupil.area_coverage, window=grid.pupil_window, with_energy=True,
    )
    fine = intensity_from_atf(h_atf, correct_cell=pupil.area_coverage)
    # fine sample (n q)//2 is the axis (n even) and pixel k's centre is fine sample k q
    return pixel_centres(fine, n, q) * ((n * q) ** 2 * q * q / energy)


def pixel_centres(fine, n: int, q: int):
    """The samples of a centred (n q)² fine grid at the centres of a centred n² pixel grid."""
    if q == 1:
        return fine
    off = (n * q) // 2 - (n // 2) * q
    return fine[..., off::q, off::q][..., :n, :n]


def sources_image(camera: Camera, scene: Scene, g: Geometry, shape, *,
                  pixel_pitch: float | None = None) -> Array:
    """The geometric image of the scene's sources on a centred ``shape`` pixel window,
    with the light the pupil passes (:func:`difstar.radiometry`): the one place where
    the sources become image irradiance. ``pixel_pitch``: a finer sampling of the same
    irradiance (default: the sensor's pitch)."""
    rad = radiometry(camera, scene, g)
    pitch = camera.sensor.pixel_pitch if pixel_pitch is None else pixel_pitch
    return geometric_image(scene.sources, magnification=g.magnification,
                           pixel_pitch=pitch, shape=shape,
                           extended_scale=rad.extended_scale, point_scale=rad.point_scale)


def simulate(camera: Camera, scene: Scene, grid: Grid) -> Prediction:
    """Predict the PSFs, the linear image, the RAW mosaic and the sRGB image.

    Radiometry: a disc of radiance L gives the image irradiance L · A_exit / z_R² (the
    exit pupil's open area over its distance to the sensor squared), a point source of
    intensity I the power I · A_entrance / r_ent²; the linear image is that over the
    reference pupil's solid angle (circular f/22), and the sensor sees it × t / φ0. So
    opening from f/22 to f/8 at the same exposure time multiplies the unsaturated image
    by (22/8)², and focusing closer dims it as (z_∞ / z_R)².

    The sensor integrates the optical image over each pixel exactly once: the geometric
    image is each source's area coverage of the pixels (the object integrated over each
    pixel's square), convolved with the PSF sampled at the pixel centres (as
    ``difstar.psf(..., sampling="point")``: fraction of power per pixel). That sum is the
    pixel integral of the source convolved with the PSF only where the PSF is sampled
    finely enough: where its bandwidth 2r·p/(λ z_R) exceeds half a cycle per pixel
    (e.g. f/11 with 3.9 µm pixels in blue), ``choose_grid`` gives the engine's grid an
    odd ``oversample`` q and both are sampled at p/q, each pixel the mean of its q × q
    samples (``benchmarks/independent_camera.py``).

    Pure and jittable (``jax.jit(simulate)``, with ``grid`` static through equinox's
    filtering, e.g. ``eqx.filter_jit``); differentiable with respect to every array in
    ``camera`` and ``scene``. When called with concrete values it first checks the
    sampling rules and raises :class:`SamplingError` naming the rule and the fix.

    A plain call runs JAX operation by operation: compile it with
    ``eqx.filter_jit(difstar.simulate)`` (as the README does). On the paper's focused
    camera with a 256² crop, on 2 CPU cores, a plain call took 6.2 s the first time and
    1.15 s again; compiled, 1.45 s the first time (the compile) and 0.018 s again, with
    the same image.
    """
    if grid.method != "engine" and (camera.lens.wavefront is not None
                                    or camera.sensor.spectral_weights is not None
                                    or camera.sensor.blur is not None):
        # the other paths model one wavelength per channel, no wavefront and no blur:
        # refuse rather than silently drop them (structure, not values: at trace time)
        raise ValueError(
            f"simulate: Grid.method={grid.method!r} models one wavelength per channel, no "
            "wavefront error and no detector blur, but this camera has a lens wavefront, a "
            "spectral sensor or a Sensor.blur; use difstar.choose_grid(camera, scene, "
            "crop=...) (it picks method='engine') or Grid(method='engine', psf_plan=..., "
            "source_window=...).")
    check_sampling(camera, scene, grid)
    g = geometry_of(camera, scene)
    sen = camera.sensor
    if grid.method == "exact":
        psfs, image = _exact_image(camera, scene, grid, g)
        return _finish(camera, scene, grid, g, psfs, image)
    if grid.method == "engine":
        psfs, image = _engine_image(camera, scene, grid, g)
        return _finish(camera, scene, grid, g, psfs, image)
    n = grid.n
    w = grid.source_window
    if 0 < w < n:  # the sources' image on its window
        bw = sources_image(camera, scene, g, (w, w))
        b = jax.lax.dynamic_update_slice(jnp.zeros((3, n, n), bw.dtype), bw,
                                         (0, n // 2 - w // 2, n // 2 - w // 2))
    else:
        b = sources_image(camera, scene, g, (n, n))
    b_ft = image_spectrum(b)  # once, shared by the three channels' convolutions

    def one(wavelength, b_ft_c):
        p = channel_psf(camera.lens.pupil, wavelength, g, pixel_pitch=sen.pixel_pitch, grid=grid)
        c = convolve(b_ft_c, otf(p), (n, n))
        return _crop(p, grid.crop), _crop(c, grid.crop)

    psfs, image = jax.vmap(one)(sen.wavelengths, b_ft)
    return _finish(camera, scene, grid, g, psfs, image)


def _exact_image(camera: Camera, scene: Scene, grid: Grid, g: Geometry):
    pupil = camera.lens.pupil
    if not isinstance(pupil, (Polygon, RegularPolygon)):
        raise ValueError(
            f"Grid.method='exact' needs a Polygon or RegularPolygon pupil; got "
            f"{type(pupil).__name__}. Use method='fft'."
        )
    w = grid.source_window
    b = sources_image(camera, scene, g, (w, w))
    return focused_image(pupil.vertices, b, camera.sensor.wavelengths, z_image=g.z_exit_pupil,
                         pixel_pitch=camera.sensor.pixel_pitch, crop=grid.crop,
                         oversample=1)  # at the pixel centres (see simulate)


def _channel_psf(camera: Camera, g: Geometry, grid: Grid, c: int, pitch, shape):
    """Channel ``c``'s PSF on ``shape`` at ``pitch``: weighted over its wavelengths in the
    spectral model; the closed form's fast form where the plan is exact at the pixel
    centres."""
    sen = camera.sensor
    lam = sen.wavelengths[c]
    wts = None if sen.spectral_weights is None else sen.spectral_weights[c]
    if grid.psf_plan.method == "exact" and grid.psf_plan.nodes == 1:
        # the closed form's fast form (half-plane, hand-written gradient) for all of
        # the channel's wavelengths at once
        lams = lam.reshape(-1)
        inten, scale = polygon_intensities(camera.lens.pupil.vertices, list(lams),
                                           z_image=g.z_exit_pupil, pixel_pitch=pitch,
                                           shape=shape)
        wv = jnp.ones_like(lams) if wts is None else wts.reshape(-1)
        return jnp.einsum("l,lhw->hw", wv * scale / jnp.sum(wv), inten)
    return psf(camera.lens.pupil, wavelength=lam, weights=wts, z_image=g.z_exit_pupil,
               defocus=g.defocus, pixel_pitch=pitch, shape=shape,
               wavefront=camera.lens.wavefront, scaling=grid.scaling, plan=grid.psf_plan)


def _engine_image(camera: Camera, scene: Scene, grid: Grid, g: Geometry):
    """Linear image and PSFs through :func:`difstar.psf`'s engine: each channel's PSF at
    the sample centres on exactly the offsets the crop needs (nothing folded in), weighted
    over the channel's wavelengths in the spectral model, with the lens's wavefront, and
    convolved linearly with the sources' window.

    With ``grid.oversample`` q > 1 (odd; :func:`difstar.choose_grid` sets it where the
    PSF is undersampled at the pixels) both are sampled at pitch p/q, the q × q samples
    of each pixel centred on it, and the image is their mean (the pixel's integral), the
    PSF their sum: the sum over a pixel grid alone is not the pixel integral of the
    source convolved with an undersampled PSF (``benchmarks/independent_camera.py``).

    The sensor's ``blur`` (:class:`difstar.Blur`) multiplies the image's spectrum by its
    transfer; the image is computed ``grid.blur_reach`` pixels beyond the crop on every
    side (:func:`engine_crop`; at least the blur's reach), so that the light it moves into
    the crop is there."""
    sen = camera.sensor
    if sen.blur is not None and sen.blur.reach > grid.blur_reach:
        raise ValueError(
            f"simulate: the sensor's blur reaches {sen.blur.reach} px, but the grid computes "
            f"{grid.blur_reach} px beyond the crop (Grid.blur_reach): plan the grid with "
            "this camera (difstar.choose_grid(camera, scene, crop=...)).")
    q = grid.oversample
    pitch = sen.pixel_pitch / q
    w = grid.source_window * q
    h, wc = grid.crop
    reach = grid.blur_reach * q  # fine samples
    fh, fw = engine_fine_crop(engine_crop(grid.crop, grid.blur_reach), q)
    kh, kw = engine_psf_shape((fh, fw), w)
    b = sources_image(camera, scene, g, (w, w), pixel_pitch=pitch)
    nh, nw = fast_length(kh + w - 1), fast_length(kw + w - 1)
    _, _, r0, c0 = _conv_offsets((fh, fw), (w, w))
    r0, c0 = r0 + reach, c0 + reach  # the crop within the computed image
    b_ft = window_rfft2(b, (nh, nw))
    if sen.blur is not None:  # cycles per pixel at the FFT's frequencies
        fy = jnp.fft.fftfreq(nh)[:, None] * q
        fx = jnp.fft.rfftfreq(nw)[None, :] * q
        b_ft = b_ft * sen.blur.transfer(fx, fy)[None]
    fh0, fw0 = engine_fine_crop(grid.crop, q)
    i0, j0 = kh // 2 - fh0 // 2, kw // 2 - fw0 // 2  # the crop within the PSF's offsets
    if grid.psf_plan.method != "exact" and sen.spectral_weights is None:
        # one wavelength a channel: the pupil's coverage of the three grids made at once
        ps = psf_each(camera.lens.pupil, sen.wavelengths, z_image=g.z_exit_pupil,
                      defocus=g.defocus, pixel_pitch=pitch, shape=(kh, kw),
                      wavefront=camera.lens.wavefront, scaling=grid.scaling,
                      plan=grid.psf_plan)
    else:
        ps = [_channel_psf(camera, g, grid, c, pitch, (kh, kw)) for c in range(3)]
    psfs, imgs = [], []
    for c in range(3):
        p = ps[c]
        full = jnp.fft.irfft2(jnp.fft.rfft2(p, s=(nh, nw)) * b_ft[c], s=(nh, nw))
        imgs.append(bin_pixels(full[r0 : r0 + h * q, c0 : c0 + wc * q], q) / (q * q))
        psfs.append(bin_pixels(p[i0 : i0 + h * q, j0 : j0 + wc * q], q))
    return jnp.stack(psfs), jnp.stack(imgs)


def read_out(image, exposure_time, sen: Sensor):
    """(ζ, RAW mosaic) of the linear image ``image`` (3, h, w) exposed for
    ``exposure_time`` by the sensor ``sen``: the one place where light becomes pixel
    values (``simulate``, and fits that move only the sensor's parameters)."""
    # stored apart (see _xla.stored): ζ is an output and the mosaic's input; otherwise the
    # mosaic re-evaluates it and its square roots and exponentials are stored as arrays
    zeta = stored(lambda a: sensor(a[0], exposure_time=a[1], phi0=a[2], response=a[3]),
                  (image, exposure_time, sen.phi0, sen.response), sen.phi0[0])
    return zeta, mosaic(zeta, sen.pattern)


def _finish(camera: Camera, scene: Scene, grid: Grid, g: Geometry, psfs, image) -> Prediction:
    sen = camera.sensor
    # a uniform radiance through the pupil (the PSF sums to 1: it stays uniform)
    image = image + radiometry(camera, scene, g).extended_scale * scene.background[:, None, None]
    zeta, cfa = read_out(image, scene.exposure_time, sen)
    srgb = None
    if not grid.raw_only:
        srgb = render_srgb(
            cfa, sen.pattern, white_balance=sen.white_balance, matrix=sen.colour_matrix
        )
    return Prediction(psfs, image, zeta, cfa, srgb, g)


__all__ = [
    "Camera", "Lens", "Sensor", "Scene", "Grid", "Prediction", "DiscSource",
    "PointSource", "sources_image", "read_out",
    "simulate", "geometry_of", "check_sampling", "needs_defocus", "SamplingError",
]
