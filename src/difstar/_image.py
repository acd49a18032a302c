"""The geometric image of the object and its convolution with the PSF.

The object is a set of uniform discs (the paper's source is a 10.5 mm diffuser disc)
and/or a pixel array already in sensor coordinates. The geometric image B is the object
scaled by the magnification M (negative: inverted) and rasterised by area coverage on
the pixel grid, so it is differentiable with respect to the discs' size and position.
The predicted image is C = IFFT(OTF · FFT(B)) (circular convolution on the grid).
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
    metres, x right, y up. radiance: (3,) relative radiance per channel (R, G, B), the
    paper's normalised object intensity I_o in [0, 1] (the exposure scale φ0 absorbs
    absolute units).
    """

    radius: Float[Array, ""]
    position: Float[Array, "2"]
    radiance: Float[Array, "3"]

    def __init__(self, radius, position=(0.0, 0.0), radiance=(1.0, 1.0, 1.0)):
        self.radius = jnp.asarray(radius, dtype=float)
        self.position = jnp.asarray(position, dtype=float)
        self.radiance = jnp.asarray(radiance, dtype=float)


def geometric_image(
    sources: tuple[DiscSource, ...],
    *,
    magnification,
    pixel_pitch: float,
    shape: tuple[int, int],
) -> Float[Array, "3 h w"]:
    """B: per-channel geometric image on a centred (H, W) pixel grid.

    A source at object position (x, y) images at M (x, y) on the sensor (y up, so the
    row coordinate is −y); its radius is |M| r. Each pixel is split into 4 × 4 sub-cells
    for the disc's coverage, so even a disc a few pixels across has its area right to
    ~1e-4.
    """
    h, w = shape
    x = centred_coordinates(w, pixel_pitch)[None, :]
    y = -centred_coordinates(h, pixel_pitch)[:, None]

    def add(out, s):
        radius, position, radiance = s
        cov = disc_coverage(
            jnp.abs(magnification) * radius,
            magnification * position[0],
            magnification * position[1],
            x, y, pixel_pitch, subsamples=4,
        )
        return out + radiance[:, None, None] * cov[None], None

    if not sources:
        return jnp.zeros((3, h, w))
    # one source at a time (lax.scan): traced and compiled once whatever their number,
    # with the memory of one coverage map
    stacked = (jnp.stack([jnp.asarray(s.radius, float) for s in sources]),
               jnp.stack([jnp.asarray(s.position, float) for s in sources]),
               jnp.stack([jnp.asarray(s.radiance, float) for s in sources]))
    out, _ = jax.lax.scan(add, jnp.zeros((3, h, w)), stacked)
    return out


def convolve(image_ft: Complex[Array, "h wr"], otf: Complex[Array, "h wr"], shape) -> Array:
    """C = IFFT(OTF · FFT(B)) from B's half spectrum and the half-spectrum OTF."""
    return jnp.fft.irfft2(image_ft * otf, s=shape)


def image_spectrum(b: Float[Array, "... h w"]) -> Complex[Array, "... h wr"]:
    """Half spectrum of the geometric image (computed once, shared by all channels where
    the sources' shape is common)."""
    return jnp.fft.rfft2(b)
