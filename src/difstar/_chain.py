"""The whole chain in one pure function: camera + scene → PSFs, RAW mosaic, sRGB.

``simulate`` is what jit and grad see whole; fitting and design call it and nothing
lower. What fixes array shapes (grid size, oversampling, crop, Bayer layout, whether the
defocus phase is computed at all, whether to demosaic) is static and lives in ``Grid``
and in the static fields of ``Sensor``.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _pruned
from ._atf import SCALINGS, atf
from ._cfa import mosaic
from ._colour import render_srgb
from ._custom_types import Array, Float
from ._geometry import Geometry, camera_geometry, check_geometry
from ._image import DiscSource, convolve, geometric_image, image_spectrum
from ._otf import otf
from ._psf import (
    SamplingError,
    _concrete,
    intensity_from_atf,
    sampling_report,
)
from ._psf_engine import PSFPlan
from ._pupil import AbstractPupil
from ._sensor import Response, sensor
from ._xla import stored

PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")
METHODS = ("fft", "exact", "engine")


class Lens(eqx.Module):
    """A prime lens focused by extension (paper Fig. 3, Eq. 6). Lengths in metres.

    pupil: the exit-pupil shape (its size is the exit pupil's, not the stop's).
    focal_length: f (the paper's Nikkor: 51.5 mm).
    focus_distance: r_f, from the sensor to the plane of best focus (``inf`` allowed).
    principal_separation: z_p, front to rear principal plane (paper: about −3 mm).
    pupil_magnification: m_p, exit over entrance pupil diameter; puts the exit pupil
        f·m_p in front of the sensor at infinity focus.
    defocus: Δz override (metres). ``None`` derives Δz from the geometry; a value makes
        Δz a parameter of its own (for fitting).
    wavefront: the lens's wavefront error on the exit pupil, e.g. :class:`difstar.Zernike`
        (anything with ``opd(x, y)`` in metres); ``None`` for a perfect lens.
    """

    pupil: AbstractPupil
    focal_length: Float[Array, ""]
    focus_distance: Float[Array, ""]
    principal_separation: Float[Array, ""]
    pupil_magnification: Float[Array, ""]
    defocus: Float[Array, ""] | None
    wavefront: eqx.Module | None

    def __init__(
        self,
        pupil: AbstractPupil,
        *,
        focal_length,
        focus_distance,
        principal_separation=0.0,
        pupil_magnification=1.0,
        defocus=None,
        wavefront=None,
    ):
        if not isinstance(pupil, AbstractPupil):
            raise TypeError(
                f"Lens.pupil must be a difstar pupil (RegularPolygon, Polygon, Circle, "
                f"CurvedIris, Obstructed, Mask); got {type(pupil).__name__}."
            )
        self.pupil = pupil
        self.focal_length = jnp.asarray(focal_length, dtype=float)
        self.focus_distance = jnp.asarray(focus_distance, dtype=float)
        self.principal_separation = jnp.asarray(principal_separation, dtype=float)
        self.pupil_magnification = jnp.asarray(pupil_magnification, dtype=float)
        self.defocus = None if defocus is None else jnp.asarray(defocus, dtype=float)
        if wavefront is not None and not callable(getattr(wavefront, "opd", None)):
            raise TypeError("Lens.wavefront must have an opd(x, y) method (metres), e.g. "
                            f"difstar.Zernike; got {type(wavefront).__name__}.")
        self.wavefront = wavefront


class Sensor(eqx.Module):
    """Sensor, colour filter and rendering.

    pixel_pitch: metres (static). pattern: Bayer layout (static).
    wavelengths: (3,) metres, one per channel R, G, B (trichromatic model), or (3, K) for
        the spectral model: K wavelengths per channel with ``spectral_weights``.
    spectral_weights: (3, K) each channel's weight of each wavelength (the source's
        spectrum × the channel's sensitivity × the quadrature weight, e.g. from
        :func:`difstar.choose_wavelengths`); normalised per channel, so φ0 and the
        response curves keep their per-channel meaning. ``None`` for trichromatic.
    phi0: (3,) reference exposure per channel, seconds.
    response: response-curve parameters. white_balance: (3,) gains R, G, B.
    colour_matrix: (3, 3) camera RGB → linear sRGB.
    """

    pixel_pitch: float = eqx.field(static=True)
    pattern: str = eqx.field(static=True)
    wavelengths: Float[Array, "3"] | Float[Array, "3 k"]
    spectral_weights: Float[Array, "3 k"] | None
    phi0: Float[Array, "3"]
    response: Response
    white_balance: Float[Array, "3"]
    colour_matrix: Float[Array, "3 3"]

    def __init__(
        self,
        *,
        pixel_pitch: float,
        pattern: str = "RGGB",
        wavelengths=(600e-9, 530e-9, 450e-9),
        phi0=(0.1, 0.1, 0.1),
        response: Response | None = None,
        white_balance=(2.0, 1.0, 2.0),
        colour_matrix=None,
        spectral_weights=None,
    ):
        if pattern not in PATTERNS:
            raise ValueError(f"Sensor.pattern must be one of {PATTERNS}; got {pattern!r}.")
        p = float(pixel_pitch)
        if not p > 0:
            raise ValueError(f"Sensor.pixel_pitch must be > 0 metres; got {p}.")
        self.pixel_pitch = p
        self.pattern = pattern
        self.wavelengths = jnp.asarray(wavelengths, dtype=float)
        self.spectral_weights = None
        if self.wavelengths.ndim == 2 or spectral_weights is not None:
            wts = (jnp.ones_like(self.wavelengths) if spectral_weights is None
                   else jnp.asarray(spectral_weights, dtype=float))
            if self.wavelengths.ndim != 2 or self.wavelengths.shape[0] != 3 or \
                    wts.shape != self.wavelengths.shape:
                raise ValueError(
                    "Sensor: spectral mode needs wavelengths of shape (3, K) and "
                    f"spectral_weights of the same shape; got {self.wavelengths.shape} and "
                    f"{wts.shape}.")
            self.spectral_weights = wts / jnp.sum(wts, axis=1, keepdims=True)
        self.phi0 = jnp.asarray(phi0, dtype=float)
        self.response = Response() if response is None else response
        self.white_balance = jnp.asarray(white_balance, dtype=float)
        self.colour_matrix = (
            jnp.eye(3) if colour_matrix is None else jnp.asarray(colour_matrix, dtype=float)
        )
        for name, v in (("wavelengths", self.wavelengths[:, 0] if self.wavelengths.ndim == 2
                         else self.wavelengths), ("phi0", self.phi0),
                        ("white_balance", self.white_balance)):
            if v.shape != (3,):
                raise ValueError(f"Sensor.{name} must have 3 values (R, G, B); got shape {v.shape}.")
        if self.colour_matrix.shape != (3, 3):
            raise ValueError(
                f"Sensor.colour_matrix must be 3 x 3; got shape {self.colour_matrix.shape}."
            )


class Camera(eqx.Module):
    lens: Lens
    sensor: Sensor


class Scene(eqx.Module):
    """What is photographed and for how long.

    object_distance: sensor to object plane, metres. sources: discs in the object plane.
    exposure_time: t, seconds. background: (3,) uniform light added to the image, in
    the sources' relative radiance units.
    """

    object_distance: Float[Array, ""]
    sources: tuple[DiscSource, ...]
    exposure_time: Float[Array, ""]
    background: Float[Array, "3"]

    def __init__(self, *, object_distance, sources, exposure_time, background=(0.0, 0.0, 0.0)):
        self.object_distance = jnp.asarray(object_distance, dtype=float)
        self.sources = tuple(sources)
        if not self.sources:
            raise ValueError("Scene.sources is empty; give at least one DiscSource.")
        self.exposure_time = jnp.asarray(exposure_time, dtype=float)
        self.background = jnp.broadcast_to(jnp.asarray(background, dtype=float), (3,))


class Grid(eqx.Module):
    """Static sampling: an n × n pixel simulation grid, q sub-samples per pixel, an output
    crop (rows, cols) centred on the grid, whether the defocus phase is computed, and
    whether to render sRGB (``raw_only`` stops after the CFA).

    ``method="fft"`` is the paper's double transform on the n × n grid. ``method="exact"``
    (in focus, polygonal pupils only) evaluates the PSF in closed form (Lee & Mittra) on
    exactly the offsets the crop needs and convolves it linearly with the geometric image
    on a ``source_window`` × ``source_window`` window: no grid, no aliasing, no wrap.

    On the FFT path a non-zero ``source_window`` (odd, pixels) computes the geometric
    image only on that centred window, and ``pupil_window`` (even, samples of the n·q
    frequency grid) computes the pupil's ATF only on that centred window; both must hold
    what they hold (``simulate`` checks, ``choose_grid`` sizes them). 0 = the whole grid.
    """

    n: int = eqx.field(static=True)
    oversample: int = eqx.field(static=True, default=1)
    crop: tuple[int, int] = eqx.field(static=True, default=(256, 256))
    use_defocus: bool = eqx.field(static=True, default=True)
    raw_only: bool = eqx.field(static=True, default=False)
    scaling: str = eqx.field(static=True, default="fresnel")
    method: str = eqx.field(static=True, default="fft")
    source_window: int = eqx.field(static=True, default=0)
    pupil_window: int = eqx.field(static=True, default=0)
    psf_plan: PSFPlan | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        if self.method not in METHODS:
            raise ValueError(f"Grid.method must be one of {METHODS}; got {self.method!r}.")
        if self.method == "engine" and (self.psf_plan is None or self.source_window < 1
                                         or self.source_window % 2 == 0):
            raise ValueError("Grid.method='engine' needs a psf_plan and an odd source_window "
                             "(difstar.choose_grid sets them).")
        if self.method == "exact" and (self.source_window < 1 or self.source_window % 2 == 0):
            raise ValueError(
                "Grid.source_window must be an odd number of pixels holding the sources "
                f"for method='exact'; got {self.source_window} (difstar.choose_grid sets it)."
            )
        if self.method == "fft" and self.source_window and (
            self.source_window % 2 == 0 or self.source_window > self.n
        ):
            raise ValueError(
                f"Grid.source_window must be 0 (the whole grid) or an odd number of pixels "
                f"<= n = {self.n}; got {self.source_window}."
            )
        if self.pupil_window and (self.pupil_window % 2 or self.pupil_window < 2):
            raise ValueError(
                f"Grid.pupil_window must be 0 (the whole grid) or an even number of samples; "
                f"got {self.pupil_window}."
            )
        if self.n < 8:
            raise ValueError(f"Grid.n must be >= 8 pixels; got {self.n}.")
        if self.oversample < 1:
            raise ValueError(f"Grid.oversample must be >= 1; got {self.oversample}.")
        if self.crop[0] > self.n or self.crop[1] > self.n:
            raise ValueError(f"Grid.crop {self.crop} is larger than the grid n = {self.n}.")
        if self.crop[0] % 2 or self.crop[1] % 2:
            raise ValueError(f"Grid.crop {self.crop} must be even (whole Bayer quads).")
        if self.scaling not in SCALINGS:
            raise ValueError(f"Grid.scaling must be one of {SCALINGS}; got {self.scaling!r}.")


class Prediction(eqx.Module):
    """Everything ``simulate`` returns; images are cropped to ``grid.crop``.

    psf: (3, h, w) per-channel PSF on the crop, normalised so that it sums to 1 over
        the whole plane (Parseval: by the pupil's area, not by the grid's sum, so the
        normalisation does not depend on the grid).
    image: (3, h, w) C, the linear image of the normalised object.
    zeta: (3, h, w) normalised pixel values per channel before the CFA.
    cfa: (h, w) the RAW mosaic ζ in [0, 1].
    srgb: (3, h, w) the rendered sRGB image in [0, 1] (None when ``raw_only``).
    geometry: the derived geometry (Δz, magnification, exit-pupil distance...).
    """

    psf: Float[Array, "3 h w"]
    image: Float[Array, "3 h w"]
    zeta: Float[Array, "3 h w"]
    cfa: Float[Array, "h w"]
    srgb: Float[Array, "3 h w"] | None
    geometry: Geometry


def geometry_of(camera: Camera, scene: Scene) -> Geometry:
    """The camera's geometry for this scene, with the lens's Δz override applied."""
    lens = camera.lens
    g = camera_geometry(
        focal_length=lens.focal_length,
        object_distance=scene.object_distance,
        focus_distance=lens.focus_distance,
        principal_separation=lens.principal_separation,
        pupil_magnification=lens.pupil_magnification,
        pupil_radius=lens.pupil.max_radius(),
    )
    if lens.defocus is not None:
        z_i = g.z_exit_pupil - lens.defocus
        scale = g.z_exit_pupil / z_i
        m = -(g.s_image / g.s_object) * scale
        g = eqx.tree_at(lambda t: (t.defocus, t.z_in_focus, t.magnification), g,
                        (lens.defocus, z_i, m))
    return g


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


def simulate(camera: Camera, scene: Scene, grid: Grid) -> Prediction:
    """Predict the PSFs, the linear image, the RAW mosaic and the sRGB image.

    The sensor integrates the optical image over each pixel exactly once: the geometric
    image is each source's area coverage of the pixels (the object integrated over each
    pixel's square), convolved with the PSF sampled at the pixel centres (as
    ``difstar.psf(..., sampling="point")``: fraction of power per pixel).

    Pure and jittable (``jax.jit(simulate)``, with ``grid`` static through equinox's
    filtering, e.g. ``eqx.filter_jit``); differentiable with respect to every array in
    ``camera`` and ``scene``. When called with concrete values it first checks the
    sampling rules and raises :class:`SamplingError` naming the rule and the fix.
    """
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
        bw = geometric_image(scene.sources, magnification=g.magnification,
                             pixel_pitch=sen.pixel_pitch, shape=(w, w))
        if _pruned.applies(grid):  # only the work the crop needs; equal to the below
            psfs, image = _pruned.image(camera.lens.pupil, sen.wavelengths, g, bw,
                                        pixel_pitch=sen.pixel_pitch, grid=grid)
            return _finish(camera, scene, grid, g, psfs, image)
        b = jax.lax.dynamic_update_slice(jnp.zeros((3, n, n), bw.dtype), bw,
                                         (0, n // 2 - w // 2, n // 2 - w // 2))
    else:
        b = geometric_image(scene.sources, magnification=g.magnification,
                            pixel_pitch=sen.pixel_pitch, shape=(n, n))
    b_ft = image_spectrum(b)  # once, shared by the three channels' convolutions

    def one(wavelength, b_ft_c):
        p = channel_psf(camera.lens.pupil, wavelength, g, pixel_pitch=sen.pixel_pitch, grid=grid)
        c = convolve(b_ft_c, otf(p), (n, n))
        return _crop(p, grid.crop), _crop(c, grid.crop)

    psfs, image = jax.vmap(one)(sen.wavelengths, b_ft)
    return _finish(camera, scene, grid, g, psfs, image)


def _exact_image(camera: Camera, scene: Scene, grid: Grid, g: Geometry):
    from ._mft import focused_image
    from ._pupil import Polygon, RegularPolygon

    pupil = camera.lens.pupil
    if not isinstance(pupil, (Polygon, RegularPolygon)):
        raise ValueError(
            f"Grid.method='exact' needs a Polygon or RegularPolygon pupil; got "
            f"{type(pupil).__name__}. Use method='fft'."
        )
    w = grid.source_window
    b = geometric_image(scene.sources, magnification=g.magnification,
                        pixel_pitch=camera.sensor.pixel_pitch, shape=(w, w))
    return focused_image(pupil.vertices, b, camera.sensor.wavelengths, z_image=g.z_exit_pupil,
                         pixel_pitch=camera.sensor.pixel_pitch, crop=grid.crop,
                         oversample=1)  # at the pixel centres (see simulate)


def engine_psf_shape(crop: tuple[int, int], source_window: int) -> tuple[int, int]:
    """The PSF offsets a crop needs from a centred source window: (h + s − 1, w + s − 1)."""
    return crop[0] + source_window - 1, crop[1] + source_window - 1


def _engine_image(camera: Camera, scene: Scene, grid: Grid, g: Geometry):
    """Linear image and PSFs through :func:`difstar.psf`'s engine: each channel's PSF at
    the pixel centres on exactly the offsets the crop needs (nothing folded in), weighted
    over the channel's wavelengths in the spectral model, with the lens's wavefront, and
    convolved linearly with the sources' window."""
    from ._mft import _conv_offsets, polygon_intensities, window_rfft2
    from ._psf import psf
    from ._sampling import fast_length

    sen = camera.sensor
    w = grid.source_window
    h, wc = grid.crop
    kh, kw = engine_psf_shape(grid.crop, w)
    b = geometric_image(scene.sources, magnification=g.magnification,
                        pixel_pitch=sen.pixel_pitch, shape=(w, w))
    nh, nw = fast_length(kh + w - 1), fast_length(kw + w - 1)
    _, _, r0, c0 = _conv_offsets(grid.crop, (w, w))
    b_ft = window_rfft2(b, (nh, nw))
    psfs, imgs = [], []
    for c in range(3):
        lam = sen.wavelengths[c]
        wts = None if sen.spectral_weights is None else sen.spectral_weights[c]
        if grid.psf_plan.method == "exact" and grid.psf_plan.nodes == 1:
            # the closed form's fast form (half-plane, hand-written gradient) for all of
            # the channel's wavelengths at once
            lams = lam.reshape(-1)
            inten, scale = polygon_intensities(camera.lens.pupil.vertices, list(lams),
                                               z_image=g.z_exit_pupil,
                                               pixel_pitch=sen.pixel_pitch, shape=(kh, kw))
            wv = jnp.ones_like(lams) if wts is None else wts.reshape(-1)
            p = jnp.einsum("l,lhw->hw", wv * scale / jnp.sum(wv), inten)
        else:
            p = psf(camera.lens.pupil, wavelength=lam, weights=wts, z_image=g.z_exit_pupil,
                    defocus=g.defocus, pixel_pitch=sen.pixel_pitch, shape=(kh, kw),
                    wavefront=camera.lens.wavefront, scaling=grid.scaling, plan=grid.psf_plan)
        full = jnp.fft.irfft2(jnp.fft.rfft2(p, s=(nh, nw)) * b_ft[c], s=(nh, nw))
        imgs.append(full[r0 : r0 + h, c0 : c0 + wc])
        i0, j0 = kh // 2 - h // 2, kw // 2 - wc // 2
        psfs.append(p[i0 : i0 + h, j0 : j0 + wc])
    return jnp.stack(psfs), jnp.stack(imgs)


def _finish(camera: Camera, scene: Scene, grid: Grid, g: Geometry, psfs, image) -> Prediction:
    sen = camera.sensor
    image = image + scene.background[:, None, None]
    # stored apart (see _xla.stored): ζ is an output and the mosaic's input; otherwise the
    # mosaic re-evaluates it and its square roots and exponentials are stored as arrays
    zeta = stored(lambda a: sensor(a[0], exposure_time=a[1], phi0=a[2], response=a[3]),
                  (image, scene.exposure_time, sen.phi0, sen.response), sen.phi0[0])
    cfa = mosaic(zeta, sen.pattern)
    srgb = None
    if not grid.raw_only:
        srgb = render_srgb(
            cfa, sen.pattern, white_balance=sen.white_balance, matrix=sen.colour_matrix
        )
    return Prediction(psfs, image, zeta, cfa, srgb, g)


def check_sampling(camera: Camera, scene: Scene, grid: Grid) -> None:
    """Raise SamplingError when the grid breaks a sampling rule (concrete inputs only)."""
    lens = camera.lens
    r_f = _concrete(lens.focus_distance)
    r_o = _concrete(scene.object_distance)
    f = _concrete(lens.focal_length)
    if f is None or r_o is None or r_f is None:
        return
    check_geometry(
        focal_length=f, object_distance=r_o, focus_distance=r_f,
        principal_separation=float(lens.principal_separation),
    )
    g = geometry_of(camera, scene)
    vals = [_concrete(v) for v in (lens.pupil.max_radius(), g.z_exit_pupil, g.defocus)]
    lams = [_concrete(v) for v in np.ravel(camera.sensor.wavelengths)]
    if any(v is None for v in vals + lams):
        return
    r, z_r, dz = vals
    fails = []
    for lam in sorted(set(lams)):
        fails += [
            f"[λ = {lam * 1e9:.4g} nm] {m}"
            for m in sampling_report(
                pupil_radius=r, wavelength=lam, z_image=z_r, defocus=dz,
                pixel_pitch=camera.sensor.pixel_pitch, oversample=grid.oversample,
                n=grid.n * grid.oversample, scaling=grid.scaling,
            )
            # the exact path has no grid (the closed form at the pixel centres)
            if grid.method == "fft"
        ]
    if grid.method == "fft" and grid.pupil_window:
        need = max(pupil_window_for(r, lam, z_r, camera.sensor.pixel_pitch, grid.n)
                   for lam in lams)
        if need > grid.pupil_window:
            fails.append(
                f"Grid.pupil_window = {grid.pupil_window} samples cannot hold the pupil "
                f"({r * 1e3:.4g} mm radius spans {need} samples at the shortest wavelength); "
                f"use pupil_window >= {need}, or 0 for the whole grid."
            )
    if grid.method == "fft" and 0 < grid.source_window < grid.n:
        from ._sampling import scene_extent

        need_w = source_window_for(scene_extent(camera, scene)["object_radius_px"])
        if need_w > grid.source_window:
            fails.append(
                f"Grid.source_window = {grid.source_window} px cannot hold the sources' "
                f"image; use source_window >= {need_w} (odd), or 0 for the whole grid."
            )
    if grid.method == "exact" and abs(dz) > 0:
        peak = math.pi * r * r * abs(dz) / (min(lams) * z_r * (z_r - dz))
        if peak > 1e-2:
            fails.append(
                f"Grid.method='exact' is for in-focus scenes, but Δz = {dz * 1e3:.4g} mm "
                f"gives {peak:.3g} rad of defocus phase; use method='fft'."
            )
    if grid.method == "fft" and not grid.use_defocus and abs(dz) > 0:
        # Without the phase the model is wrong by the defocus's peak phase; allow only
        # a negligible amount (< 0.01 rad at the pupil edge).
        peak = math.pi * r * r * abs(dz) / (min(lams) * z_r * (z_r - dz))
        if peak > 1e-2:
            fails.append(
                f"Grid.use_defocus is False but Δz = {dz * 1e3:.4g} mm gives "
                f"{peak:.3g} rad of defocus phase; set use_defocus=True."
            )
    if fails:
        raise SamplingError("difstar.simulate: " + " ".join(fails))


def pupil_window_for(pupil_radius: float, wavelength: float, z_image: float,
                     pixel_pitch: float, n: int) -> int:
    """Even number of frequency samples (a side, of the n·q grid) holding a pupil of this
    radius, with 2 samples to spare each side: 2 r n p / (λ z_R) + 4."""
    span = 2 * pupil_radius * n * pixel_pitch / (wavelength * z_image)
    m = math.ceil(span) + 4
    return m + m % 2


def source_window_for(object_radius_px: float) -> int:
    """Odd number of pixels holding the sources' image (its radius plus one pixel)."""
    return 2 * math.ceil(object_radius_px + 1) + 1


def needs_defocus(camera: Camera, scene: Scene, *, tolerance: float = 1e-2) -> bool:
    """Whether the defocus phase is worth computing (peak phase above ``tolerance`` rad)."""
    g = geometry_of(camera, scene)
    r = float(camera.lens.pupil.max_radius())
    dz = float(g.defocus)
    z_r = float(g.z_exit_pupil)
    lam = float(jnp.min(camera.sensor.wavelengths))
    return math.pi * r * r * abs(dz) / (lam * z_r * (z_r - dz)) > tolerance


__all__ = [
    "Camera", "Lens", "Sensor", "Scene", "Grid", "Prediction", "DiscSource",
    "simulate", "geometry_of", "check_sampling", "needs_defocus", "SamplingError",
]
