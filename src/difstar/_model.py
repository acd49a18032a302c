"""The model's types: what a camera, a scene and a grid are (equinox Modules), what
``simulate`` returns, and the camera's geometry for a scene.

What fixes array shapes (grid size, oversampling, crop, Bayer layout, the method) is
static and lives in ``Grid`` and in the static fields of ``Sensor``.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ._atf import SCALINGS
from ._custom_types import Array, Float
from ._detector import Blur
from ._geometry import Geometry, camera_geometry
from ._image import SOURCE_TYPES, DiscSource, PointSource
from ._psf_engine import PSFPlan
from ._pupil import AbstractPupil
from ._sensor import Response

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
    phi0: (3,) reference exposure per channel: the exposure time, in seconds, at which a
        source of unit radiance seen through the reference pupil (a circular f/22
        focused at infinity, solid angle π/(4·22²) sr) reaches the response curve's
        knee; equivalently the knee's radiant exposure divided by that solid angle. It
        is the camera's, and holds at every aperture, focus and exposure time: the
        image scales with the exit pupil's area over its distance squared (see
        :func:`difstar.irradiance_scale`, :func:`difstar.phi0_from_configuration` to
        convert a φ0 characterised at one configuration).
    response: response-curve parameters. white_balance: (3,) gains R, G, B.
    colour_matrix: (3, 3) camera RGB → linear sRGB.
    blur: the detector's blur of the linear image (a :class:`difstar.Blur` of
        :class:`~difstar.fitting.Jitter` and :class:`~difstar.fitting.Halo` layers,
        widths in pixels), applied to each channel before the read-out; ``None``: none.
    """

    pixel_pitch: float = eqx.field(static=True)
    pattern: str = eqx.field(static=True)
    wavelengths: Float[Array, 3] | Float[Array, "3 k"]
    spectral_weights: Float[Array, "3 k"] | None
    phi0: Float[Array, 3]
    response: Response
    white_balance: Float[Array, 3]
    colour_matrix: Float[Array, "3 3"]
    blur: Blur | None

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
        blur=None,
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
        if blur is not None and not isinstance(blur, Blur):
            raise ValueError(f"Sensor.blur must be a difstar.Blur or None; got {blur!r}.")
        self.blur = blur
        for name, v in (("wavelengths", self.wavelengths[:, 0] if self.wavelengths.ndim == 2
                         else self.wavelengths), ("phi0", self.phi0),
                        ("white_balance", self.white_balance)):
            if v.shape != (3,):
                raise ValueError(f"Sensor.{name} must have 3 values (R, G, B); got shape "
                                 f"{v.shape}.")
        if self.colour_matrix.shape != (3, 3):
            raise ValueError(
                f"Sensor.colour_matrix must be 3 x 3; got shape {self.colour_matrix.shape}."
            )


class Camera(eqx.Module):
    lens: Lens
    sensor: Sensor


class Scene(eqx.Module):
    """What is photographed and for how long.

    object_distance: sensor to object plane, metres. sources: :class:`DiscSource` and
    :class:`PointSource` in the object plane, in any mix. exposure_time: t, seconds.
    background: (3,) a uniform radiance filling the field (the discs' radiance unit),
    imaged through the pupil like them.
    """

    object_distance: Float[Array, ""]
    sources: tuple[DiscSource | PointSource, ...]
    exposure_time: Float[Array, ""]
    background: Float[Array, 3]

    def __init__(self, *, object_distance, sources, exposure_time, background=(0.0, 0.0, 0.0)):
        self.object_distance = jnp.asarray(object_distance, dtype=float)
        self.sources = tuple(sources)
        if not self.sources:
            raise ValueError("Scene.sources is empty; give at least one DiscSource or "
                             "PointSource.")
        for i, src in enumerate(self.sources):
            if not isinstance(src, SOURCE_TYPES):
                raise TypeError(f"Scene.sources[{i}] must be a DiscSource or a PointSource; "
                                f"got {type(src).__name__}.")
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
    ``method="engine"`` (what ``choose_grid`` picks for every sampled pupil) does the same
    with :func:`difstar.psf`'s engine and its ``psf_plan``; ``n`` is then the field's
    period in pixels where ``choose_grid``'s ``n`` or ``padding`` set it (else the crop's
    side), and ``oversample`` the odd number of samples a side that integrate each pixel.

    ``blur_reach`` (engine): the pixels computed beyond the crop on every side for the
    sensor's blur (:class:`difstar.Blur`; ``choose_grid`` sets it to the blur's reach),
    so that the light it moves into the crop is there.

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
    blur_reach: int = eqx.field(static=True, default=0)

    def __check_init__(self):
        if self.method not in METHODS:
            raise ValueError(f"Grid.method must be one of {METHODS}; got {self.method!r}.")
        if self.method == "engine" and (self.psf_plan is None or self.source_window < 1
                                         or self.source_window % 2 == 0):
            raise ValueError("Grid.method='engine' needs a psf_plan and an odd source_window "
                             "(difstar.choose_grid sets them).")
        if self.method == "engine" and (self.oversample < 1 or self.oversample % 2 == 0):
            raise ValueError(f"Grid.oversample must be odd for method='engine' (each pixel's "
                             f"sub-samples centred on it); got {self.oversample}.")
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
        if not isinstance(self.blur_reach, int) or self.blur_reach < 0:
            raise ValueError(f"Grid.blur_reach must be a whole number of pixels >= 0; got "
                             f"{self.blur_reach!r}.")
        if self.oversample < 1:
            raise ValueError(f"Grid.oversample must be >= 1; got {self.oversample}.")
        if self.crop[0] > self.n or self.crop[1] > self.n:
            raise ValueError(f"Grid.crop {self.crop} is larger than the grid n = {self.n}.")
        if self.crop[0] % 2 or self.crop[1] % 2:
            raise ValueError(f"Grid.crop {self.crop} must be even (whole Bayer quads).")
        if self.scaling not in SCALINGS:
            raise ValueError(f"Grid.scaling must be one of {SCALINGS}; got {self.scaling!r}.")

    def describe(self) -> str:
        """One line for logs: the path and what sizes it (``n``: the FFT grid's side on
        the fft path, the field's period on the engine's where ``choose_grid``'s ``n``
        or ``padding`` set it)."""
        if self.method == "exact":
            return (f"exact in-focus path (closed-form PSF, no grid), crop = {self.crop}, "
                    f"source window {self.source_window} px")
        defocus = "on" if self.use_defocus else "off (Δz negligible)"
        if self.method == "engine":
            q = self.oversample
            # n beyond the crop: the field's period the caller set (n or padding)
            period = f", period n = {self.n} px" if self.n > max(self.crop) else ""
            return (f"PSF engine ({self.psf_plan.method}{period}), {q} × {q} samples per "
                    f"pixel, crop = {self.crop}, defocus phase {defocus}")
        return (f"FFT grid n = {self.n}, oversample = {self.oversample}, crop = {self.crop}, "
                f"defocus phase {defocus}")


class Prediction(eqx.Module):
    """Everything ``simulate`` returns; images are cropped to ``grid.crop``.

    psf: (3, h, w) per-channel PSF on the crop, normalised so that it sums to 1 over
        the whole plane (Parseval: by the pupil's area, not by the grid's sum, so the
        normalisation does not depend on the grid).
    image: (3, h, w) C, the linear image: the pixels' mean irradiance over the reference
        pupil's solid angle, in the sources' radiance unit (the sensor sees C t / φ0).
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
    return _lens_geometry(lens.focal_length, scene.object_distance, lens.focus_distance,
                          lens.principal_separation, lens.pupil_magnification,
                          lens.pupil.max_radius(), lens.defocus)


@jax.jit
def _lens_geometry(focal_length, object_distance, focus_distance, principal_separation,
                   pupil_magnification, pupil_radius, defocus) -> Geometry:
    """:func:`geometry_of`'s numbers as one compiled program: a plan's concrete geometry
    costs one compile per process, not one per eager operation (a dozen, 25 ms each on 2
    cores); inside a trace it is inlined. ``focus_distance`` and ``defocus`` may be None."""
    g = camera_geometry(
        focal_length=focal_length,
        object_distance=object_distance,
        focus_distance=focus_distance,
        principal_separation=principal_separation,
        pupil_magnification=pupil_magnification,
        pupil_radius=pupil_radius,
    )
    if defocus is not None:
        z_i = g.z_exit_pupil - defocus
        scale = g.z_exit_pupil / z_i
        m = -(g.s_image / g.s_object) * scale
        g = eqx.tree_at(lambda t: (t.defocus, t.z_in_focus, t.magnification), g,
                        (defocus, z_i, m))
    return g
