"""The FFT path with only the work the crop needs (pruned transforms, linear convolution).

The paper's chain transforms the whole n × n grid three times per channel: the field
IFFT(ATF), the OTF FFT(PSF) and the image IFFT(OTF · FFT(B)). When the pupil covers only
a W × W window of the frequency grid and the sources only an s × s window of the image,
most of that work multiplies zeros or computes pixels nobody looks at:

- the field's first 1-D pass runs over the W columns the pupil covers, not all n·q
  (a window placed anywhere in the grid changes the field only by a unimodular,
  separable phase, which the intensity does not see);
- of the field's second pass only the rows the crop needs are computed, and only their
  needed columns are kept; the PSF's normalisation is the pupil's energy (Parseval),
  as on the full path, so no other pixel of the period is needed;
- only the PSF offsets the crop can reach from the source window are kept, (h + s − 1)
  × (w + s − 1), and the image is their *linear* convolution with the sources' window
  by a real FFT of a fast size ≥ h + s − 1 instead of a circular one of size n. The
  periodic PSF's values are used unchanged, so the result equals the full path's up to
  rounding (``tests/test_sampling.py`` checks values and gradients in float64).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ._atf import _atf_on
from ._fft_size import fast_length
from ._grid_psf import cell_sinc
from ._xla import stored


def applies(grid) -> bool:
    """Whether ``grid`` (FFT path with a source window) gains from the pruned chain."""
    s = grid.source_window
    h, w = grid.crop
    return grid.method == "fft" and 0 < s < grid.n and h + s - 1 <= grid.n and w + s - 1 <= grid.n


def _unshifted(nf: int, start_px: int, count_px: int, q: int) -> np.ndarray:
    """Unshifted fine-grid indices of the centres of pixels [start_px, start_px +
    count_px) of a centred grid of n pixels, nf = n·q fine samples (the axis is fine
    sample nf//2; pixel i's centre is at offset (i − n//2)·q fine samples from it)."""
    n = nf // q
    jc = nf // 2 + (np.arange(start_px, start_px + count_px) - n // 2) * q
    return (jc - nf // 2) % nf


def psf_region(pupil, wavelength, geometry, *, pixel_pitch: float, grid, rows: tuple[int, int],
               cols: tuple[int, int]):
    """One channel's PSF at the centres of the pixels at offsets ``rows`` = (first, count)
    and ``cols`` from the centre pixel, normalised by the pupil's energy as on the full
    path (``_chain.channel_psf``)."""
    n, q = grid.n, grid.oversample
    nf = n * q
    m = grid.pupil_window if 0 < grid.pupil_window < nf else 0
    # the window's ATF, stored apart (see _xla.stored): fused into the zero padding of
    # the first pass, XLA's CPU backend evaluates it several times slower than the FFT
    sub, energy = stored(
        lambda lam: _atf_on(pupil, lam, geometry.z_exit_pupil, geometry.defocus,
                            pixel_pitch / q, (nf, nf), grid.scaling, grid.use_defocus, (0.0, 0.0),
                            pupil.area_coverage, m),
        wavelength, wavelength)
    ir = _unshifted(nf, n // 2 + rows[0], rows[1], q)
    ic = _unshifted(nf, n // 2 + cols[0], cols[1], q)
    # the field (up to a unimodular separable phase): along the window's rows first,
    # keeping only the columns the region needs, then along those columns, keeping only
    # its rows. Both passes run along the last axis: only the smaller (window × region)
    # array is transposed, and the field comes out transposed (its intensity is turned
    # back, a region-sized real array).
    g = jnp.fft.ifft(sub, n=nf, axis=1)[:, ic]
    field_t = jnp.fft.ifft(g.T, n=nf, axis=1)[:, ir]
    reg = (jnp.real(field_t) ** 2 + jnp.imag(field_t) ** 2).T
    if pupil.area_coverage:
        wc = 1.0 / np.fft.ifftshift(cell_sinc(nf)) ** 2  # the cell correction, unshifted
        reg = reg * jnp.asarray(wc[ir], reg.dtype)[:, None] * jnp.asarray(wc[ic], reg.dtype)[None, :]
    return reg * (nf**2 * q * q / energy)


def image(pupil, wavelengths, geometry, bw, *, pixel_pitch: float, grid):
    """(psfs on the crop, linear image on the crop), both (3, h, w), from the sources'
    geometric image ``bw`` (3, s, s) on the centred source window."""

    h, w = grid.crop
    s = bw.shape[-1]
    kh, kw = h + s - 1, w + s - 1  # offsets [−h/2 − (s−1)/2, …) reachable from the window
    lh, lw = fast_length(kh), fast_length(kw)
    b_ft = jnp.fft.rfft2(bw, s=(lh, lw))  # once for the three channels
    rows = (-(h // 2) - (s - 1) // 2, kh)
    cols = (-(w // 2) - (s - 1) // 2, kw)
    psfs, imgs = [], []
    for c in range(3):
        p = psf_region(pupil, wavelengths[c], geometry, pixel_pitch=pixel_pitch, grid=grid,
                       rows=rows, cols=cols)
        # linear convolution: full[t] = Σ_b B[b] P[t − b]; crop pixel i is t = i + s − 1,
        # and a circular transform of length ≥ kh leaves those t unwrapped
        full = jnp.fft.irfft2(jnp.fft.rfft2(p, s=(lh, lw)) * b_ft[c], s=(lh, lw))
        imgs.append(full[s - 1 : s - 1 + h, s - 1 : s - 1 + w])
        psfs.append(p[(s - 1) // 2 : (s - 1) // 2 + h, (s - 1) // 2 : (s - 1) // 2 + w])
    return jnp.stack(psfs), jnp.stack(imgs)
