"""The n × n grid path's PSF helpers (``simulate``'s ``fft`` method and the pruned
transforms): intensity from a centred ATF, the area-coverage cell correction, pixel
binning."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ._custom_types import Array, Float


def bin_pixels(fine: Float[Array, "*b hq wq"], q: int) -> Float[Array, "*b h w"]:
    """Integrate (sum) q × q blocks: the box of one pixel pitch."""
    if q == 1:
        return fine
    *lead, hq, wq = fine.shape
    return fine.reshape(*lead, hq // q, q, wq // q, q).sum(axis=(-3, -1))


def cell_correction(shape: tuple[int, int]) -> Array:
    """sinc(j/N) sinc(k/M) on the centred image grid.

    Area coverage samples the pupil convolved with one square frequency cell, so the
    computed amplitude is the true one times this sinc (the cell's transform, in grid
    units). Dividing by it restores the principal term exactly and leaves the aliases
    from beyond the field attenuated by ~|u|/(m L) near the centre, which is what makes
    the FFT PSF converge faster than the 1/N of a binary raster (BENCHMARKS.md).
    """
    h, w = shape
    return jnp.asarray(cell_sinc(h))[:, None] * jnp.asarray(cell_sinc(w))[None, :]


def cell_sinc(n: int) -> np.ndarray:
    """sinc(j/n) on a centred axis of n samples (the 1-D factor of ``cell_correction``)."""
    return np.sinc((np.arange(n) - n // 2) / n)


def intensity_from_atf(h_atf, *, correct_cell: bool = True) -> Array:
    """|IFFT(ATF)|² for a centred ATF, centred, unnormalised."""
    field = jnp.fft.fftshift(jnp.fft.ifft2(jnp.fft.ifftshift(h_atf)))
    intensity = jnp.real(field) ** 2 + jnp.imag(field) ** 2
    if correct_cell:
        intensity = intensity / cell_correction(h_atf.shape) ** 2
    return intensity
