"""Optical transfer function by the double-transform method (paper Eq. 1).

The PSF is real, so its transform is taken with a real-input FFT (half the spectrum).
The PSF is centred at (H//2, W//2); ``ifftshift`` moves that centre to index (0, 0) so
the OTF carries no linear phase and OTF(0) = Σ PSF = 1.
"""

from __future__ import annotations

import jax.numpy as jnp

from ._custom_types import Array, Complex, Float


def otf(psf: Float[Array, "h w"]) -> Complex[Array, "h wr"]:
    """Half-spectrum OTF (``rfft2`` layout, shape (H, W//2 + 1)) of a centred PSF."""
    return jnp.fft.rfft2(jnp.fft.ifftshift(psf))


def mtf(psf: Float[Array, "h w"]) -> Float[Array, "h w"]:
    """Full, centred modulation transfer function |OTF| (for plots and checks)."""
    return jnp.abs(jnp.fft.fftshift(jnp.fft.fft2(jnp.fft.ifftshift(psf))))
