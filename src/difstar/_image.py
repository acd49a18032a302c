"""The geometric image of the object and its convolution with the PSF.

The object is a set of uniform discs (the paper's source is a 10.5 mm diffuser disc)
and point sources (stars, distant lamps), or a pixel array already in sensor
coordinates. The geometric image B is the object scaled by the magnification M
(negative: inverted) and rasterised on the pixel grid: discs by area coverage, points by
bilinear weights, so it is differentiable with respect to the sources' size and
position. The predicted image is C = IFFT(OTF · FFT(B)) (circular convolution on the
grid). How much light each source sends through the pupil is :mod:`._radiometry`'s.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ._atf import centred_coordinates
from ._custom_types import Array, Complex, Float
from ._pupil import disc_coverage


class DiscSource(eqx.Module):
    """A uniform disc in the object plane.

    radius: metres (object plane). position: (x, y) of its centre from the optical axis,
    metres, x right, y up. radiance: (3,) radiance per channel (R, G, B), in the unit
    the sensor's φ0 is stated in (the paper's examples: 1 = their source); the image
    irradiance is radiance × the exit pupil's solid angle (see
    :func:`difstar.irradiance_scale`).
    """

    radius: Float[Array, ""]
    position: Float[Array, "2"]
    radiance: Float[Array, "3"]

    def __init__(self, radius, position=(0.0, 0.0), radiance=(1.0, 1.0, 1.0)):
        self.radius = jnp.asarray(radius, dtype=float)
        self.position = jnp.asarray(position, dtype=float)
        self.radiance = jnp.asarray(radiance, dtype=float)


class PointSource(eqx.Module):
    """A point in the object plane: a star, a distant lamp, anything the camera does not
    resolve.

    position: (x, y) from the optical axis, metres (object plane), x right, y up.
    intensity: (3,) radiant intensity per channel (R, G, B), in the unit of a
    :class:`DiscSource`'s radiance × m² (W sr⁻¹ for radiance in W m⁻² sr⁻¹): a disc of
    radiance L and radius r seen face on has I = π r² L. The power through the pupil is
    I · A_entrance / r_ent² (see :func:`difstar.radiometry`), spread by the PSF.
    """

    position: Float[Array, "2"]
    intensity: Float[Array, "3"]

    def __init__(self, position=(0.0, 0.0), intensity=(1.0, 1.0, 1.0)):
        self.position = jnp.asarray(position, dtype=float)
        self.intensity = jnp.asarray(intensity, dtype=float)

    @property
    def radius(self) -> Float[Array, ""]:
        """0: a point has no extent (the sampling rules size the windows from it)."""
        return jnp.zeros((), dtype=self.position.dtype)


SOURCE_TYPES = (DiscSource, PointSource)


def geometric_image(
    sources: tuple[DiscSource | PointSource, ...],
    *,
    magnification,
    pixel_pitch: float,
    shape: tuple[int, int],
    extended_scale=1.0,
    point_scale=1.0,
) -> Float[Array, "3 h w"]:
    """B: per-channel geometric image on a centred (H, W) pixel grid.

    A source at object position (x, y) images at M (x, y) on the sensor (y up, so the
    row coordinate is −y); a disc's radius is |M| r. Each pixel is split into 4 × 4
    sub-cells for the disc's coverage, so even a disc a few pixels across has its area
    right to ~1e-4; a disc adds radiance × coverage × ``extended_scale``. A point adds
    intensity × ``point_scale`` / pixel_pitch² spread over the four nearest pixels with
    bilinear weights (they sum to 1, and move smoothly with the position), so the
    image's sum is the power through the pupil over the pixel's area. Sources may mix
    both kinds in any order (the sum does not depend on it).
    """
    h, w = shape
    x = centred_coordinates(w, pixel_pitch)[None, :]
    y = -centred_coordinates(h, pixel_pitch)[:, None]
    for i, s in enumerate(sources):
        if not isinstance(s, SOURCE_TYPES):
            raise TypeError(f"scene.sources[{i}] must be a DiscSource or a PointSource; "
                            f"got {type(s).__name__}.")
    discs = [s for s in sources if isinstance(s, DiscSource)]
    points = [s for s in sources if isinstance(s, PointSource)]

    def add_disc(out, s):
        radius, position, radiance = s
        cov = disc_coverage(
            jnp.abs(magnification) * radius,
            magnification * position[0],
            magnification * position[1],
            x, y, pixel_pitch, subsamples=4,
        )
        return out + radiance[:, None, None] * cov[None], None

    def add_point(out, s):
        position, intensity = s
        wx = jnp.maximum(0.0, 1.0 - jnp.abs(x - magnification * position[0]) / pixel_pitch)
        wy = jnp.maximum(0.0, 1.0 - jnp.abs(y - magnification * position[1]) / pixel_pitch)
        return out + intensity[:, None, None] * (wy * wx)[None], None

    out = jnp.zeros((3, h, w))
    # one source at a time (lax.scan), one scan per kind: traced and compiled once
    # whatever their number, with the memory of one coverage map
    if discs:
        stacked = (jnp.stack([jnp.asarray(s.radius, float) for s in discs]),
                   jnp.stack([jnp.asarray(s.position, float) for s in discs]),
                   jnp.stack([jnp.asarray(s.radiance, float) for s in discs]))
        b, _ = jax.lax.scan(add_disc, jnp.zeros((3, h, w)), stacked)
        out = out + extended_scale * b
    if points:
        stacked = (jnp.stack([jnp.asarray(s.position, float) for s in points]),
                   jnp.stack([jnp.asarray(s.intensity, float) for s in points]))
        b, _ = jax.lax.scan(add_point, jnp.zeros((3, h, w)), stacked)
        out = out + (point_scale / (pixel_pitch * pixel_pitch)) * b
    return out


def convolve(image_ft: Complex[Array, "h wr"], otf: Complex[Array, "h wr"], shape) -> Array:
    """C = IFFT(OTF · FFT(B)) from B's half spectrum and the half-spectrum OTF."""
    return jnp.fft.irfft2(image_ft * otf, s=shape)


def image_spectrum(b: Float[Array, "... h w"]) -> Complex[Array, "... h wr"]:
    """Half spectrum of the geometric image (computed once, shared by all channels where
    the sources' shape is common)."""
    return jnp.fft.rfft2(b)
