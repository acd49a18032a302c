"""Intensity point-spread function: PSF = |IFFT(ATF)|², integrated over each pixel,
normalised to unit sum (paper Eq. 1), with the sampling rules of DESIGN.md checked.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from ._atf import SCALINGS, atf, pupil_scale
from ._custom_types import Array, Float
from ._pupil import AbstractPupil


class SamplingError(ValueError):
    """The requested grid cannot represent the PSF; the message names the rule and a fix."""


def _concrete(x):
    """A Python float of ``x``, or None when ``x`` is a tracer (inside jit/grad)."""
    try:
        return float(np.asarray(x))
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError, TypeError):
        return None


def sampling_report(
    *,
    pupil_radius,
    wavelength,
    z_image,
    defocus,
    pixel_pitch,
    oversample: int,
    n: int,
    scaling: str = "fresnel",
    min_pupil_samples: float = 16.0,
) -> list[str]:
    """The DESIGN.md sampling rules that fail, each as a message with the fix (empty = ok).

    Rule 1, intensity bandwidth: grid pitch p/q ≤ λ N_w / 2.
    Rule 3, defocus phase: phase step between pupil samples < π, i.e. the field N p/q
    exceeds the geometric blur 2 r |Δz| / z_i.
    Rule 4, pupil resolution: at least ``min_pupil_samples`` samples across the pupil.
    (Rule 2, the field holding the scene, is checked by the grid chooser.)
    """
    r = float(pupil_radius)
    lam = float(wavelength)
    z_r = float(z_image)
    dz = float(defocus)
    p = float(pixel_pitch)
    q = int(oversample)
    scale = float(pupil_scale(lam, z_r, dz, scaling))
    dx = p / q
    fails = []
    nw = scale / lam / (2 * r)
    if dx > lam * nw / 2 * (1 + 1e-12):
        need = math.ceil(p / (lam * nw / 2))
        fails.append(
            f"rule 1 (intensity bandwidth): grid pitch p/q = {dx * 1e6:.4g} µm exceeds "
            f"λ·N_w/2 = {lam * nw / 2 * 1e6:.4g} µm (λ = {lam * 1e9:.4g} nm, working f-number "
            f"{nw:.4g}); the PSF would alias. Use oversample >= {need}."
        )
    z_i = z_r - dz
    blur = 2 * r * abs(dz) / z_i
    field = n * dx
    if blur >= field:
        need_n = math.ceil(blur / dx) + 1
        fails.append(
            f"rule 3 (defocus phase): the geometric blur {blur * 1e3:.4g} mm does not fit in "
            f"the grid's field {field * 1e3:.4g} mm, so the defocus phase steps by more than π "
            f"between pupil samples. Use a grid of at least {need_n} samples a side "
            f"(shape x oversample)."
        )
    samples = 2 * r * field / scale
    if samples < min_pupil_samples:
        need_n = math.ceil(min_pupil_samples * scale / (2 * r * dx))
        fails.append(
            f"rule 4 (pupil resolution): only {samples:.3g} samples across the pupil "
            f"(minimum {min_pupil_samples:g}). Use a grid of at least {need_n} samples a side."
        )
    return fails


def bin_pixels(fine: Float[Array, "*b hq wq"], q: int) -> Float[Array, "*b h w"]:
    """Integrate (sum) q × q blocks: the box of one pixel pitch."""
    if q == 1:
        return fine
    *lead, hq, wq = fine.shape
    return fine.reshape(*lead, hq // q, q, wq // q, q).sum(axis=(-3, -1))


def block_centring_shift(n: int, q: int) -> float:
    """Fine-grid shift that puts the PSF's centre at the centre of pixel n // 2's block."""
    return (n // 2) * q + (q - 1) / 2 - (n * q) // 2


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


def psf(
    pupil: AbstractPupil,
    *,
    wavelength,
    z_image,
    defocus=0.0,
    pixel_pitch: float,
    shape: tuple[int, int],
    oversample: int = 1,
    scaling: str = "fresnel",
    check: bool = True,
) -> Float[Array, "h w"]:
    """The intensity PSF on the pixel grid, summing to 1, centred on pixel (H//2, W//2).

    Args:
        pupil: exit-pupil shape (metres).
        wavelength: metres.
        z_image: exit pupil to sensor, z_R (metres).
        defocus: Δz, sensor minus in-focus image plane (metres). A Python ``0`` or
            ``0.0`` drops the defocus phase from the computation.
        pixel_pitch: p, metres.
        shape: (H, W) pixels.
        oversample: q sub-samples per pixel a side; the PSF is computed on a grid of pitch
            p/q and integrated over each pixel.
        scaling: "fresnel" (default, DESIGN.md) or "paper" (paper Eq. 2–4, pupil scaled
            by λ z_i).
        check: raise :class:`SamplingError` when a sampling rule fails (only where the
            inputs are concrete; inside jit the caller checks once outside).
    """
    if scaling not in SCALINGS:
        raise ValueError(f"scaling must be one of {SCALINGS}; got {scaling!r}.")
    if not (isinstance(oversample, (int, np.integer)) and oversample >= 1):
        raise ValueError(f"oversample must be an integer >= 1; got {oversample!r}.")
    h, w = (int(s) for s in shape)
    if h < 2 or w < 2:
        raise ValueError(f"shape must be at least (2, 2) pixels; got {shape!r}.")
    q = int(oversample)
    static_zero = isinstance(defocus, (int, float)) and defocus == 0
    if check:
        vals = [_concrete(v) for v in (pupil.max_radius(), wavelength, z_image, defocus)]
        if all(v is not None for v in vals):
            r, lam, z_r, dz = vals
            fails = sampling_report(
                pupil_radius=r, wavelength=lam, z_image=z_r, defocus=dz,
                pixel_pitch=pixel_pitch, oversample=q, n=min(h, w) * q, scaling=scaling,
            )
            if fails:
                raise SamplingError("difstar.psf: " + " ".join(fails))
    shift = (block_centring_shift(h, q), block_centring_shift(w, q))
    h_atf = atf(
        pupil, wavelength=wavelength, z_image=z_image, defocus=defocus,
        dx=pixel_pitch / q, shape=(h * q, w * q), scaling=scaling,
        use_defocus=not static_zero, shift=shift, cell_average=pupil.area_coverage,
    )
    fine = intensity_from_atf(h_atf, correct_cell=pupil.area_coverage)
    out = bin_pixels(fine, q)
    return out / jnp.sum(out)
