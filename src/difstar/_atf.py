"""Amplitude transfer function: the exit pupil sampled on the frequency grid, with the
defocus phase (paper Eq. 2–4, in the Fresnel form of DESIGN.md).

For a sensor at z_R from the exit pupil and an in-focus image at z_i = z_R − Δz, the
Fresnel integral over the pupil gives

    H(f) = P(λ z_R f) exp(i π λ z_R Δz / z_i |f|²),

the pupil scaled by λ z_R and the phase k W with W = ½ (1/z_i − 1/z_R) |x|². The paper's
form (``scaling="paper"``) scales the pupil by λ z_i and uses the sensor at z_i + Δz.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp

from ._custom_types import Array, Float
from ._pupil import AbstractPupil

SCALINGS = ("fresnel", "paper")


def centred_coordinates(n: int, pitch) -> Array:
    """Coordinates of a centred axis: index j ↦ (j − n // 2) · pitch."""
    return (jnp.arange(n) - n // 2) * pitch


def frequency_axes(shape: tuple[int, int], dx) -> tuple[Array, Array]:
    """Centred spatial-frequency axes (cycles/metre) of a ``shape`` grid of pitch ``dx``.

    Returns (fx along columns, fy along rows); fy grows upwards (decreasing row index),
    matching the pupil's y-up convention.
    """
    h, w = shape
    fx = centred_coordinates(w, 1.0 / (w * dx))
    fy = -centred_coordinates(h, 1.0 / (h * dx))
    return fx, fy


def pupil_scale(wavelength, z_image, defocus, scaling: str = "fresnel"):
    """Metres in the pupil per cycle/metre in the image: λ z_R (Fresnel) or λ z_i (paper)."""
    if scaling == "fresnel":
        return wavelength * z_image
    if scaling == "paper":
        return wavelength * (z_image - defocus)
    raise ValueError(f"scaling must be one of {SCALINGS}; got {scaling!r}.")


def intensity_bandwidth(pupil_radius, wavelength, z_image, defocus, pixel_pitch,
                        scaling: str = "fresnel"):
    """The intensity's bandwidth in cycles per pixel: its spectrum (the OTF) vanishes
    beyond 2 r / (the pupil scale), here times the pixel pitch. Over 0.5 the pixels
    undersample the intensity."""
    return 2 * pupil_radius * pixel_pitch / pupil_scale(wavelength, z_image, defocus, scaling)


def defocus_phase_coefficient(wavelength, z_image, defocus, scaling: str = "fresnel"):
    """c such that the ATF phase is c |f|² (radians per (cycles/metre)²)."""
    z_i = z_image - defocus
    if scaling == "fresnel":
        return math.pi * wavelength * z_image * defocus / z_i
    # Paper Eq. 4: k λ² z_i² / 2 · (1/z_i − 1/(z_i + Δz)) = π λ z_i Δz / (z_i + Δz)
    return math.pi * wavelength * z_i * defocus / (z_i + defocus)


def atf(
    pupil: AbstractPupil,
    *,
    wavelength,
    z_image,
    defocus=0.0,
    dx,
    shape: tuple[int, int],
    scaling: str = "fresnel",
    use_defocus: bool = True,
    shift: tuple[float, float] = (0.0, 0.0),
    cell_average: bool = True,
    window: int = 0,
    with_energy: bool = False,
):
    """The centred ATF on a ``shape`` grid whose image-plane pitch is ``dx`` metres.

    ``wavelength``, ``z_image`` (exit pupil to sensor) and ``defocus`` (Δz) in metres.
    ``use_defocus=False`` drops the phase term entirely (a static choice: at Δz = 0 the
    phase is identically 1 and computing it is wasted work). ``shift`` (rows, cols), in
    grid samples, moves the resulting PSF by a phase ramp (used to centre pixel blocks).

    ``cell_average`` makes the whole ATF a cell average, like the pupil's area coverage:
    the defocus factor exp(i c |f|²) is averaged over each cell (to first order in the
    phase, a sinc of its gradient). The PSF then divides the cell's transform out exactly
    (``_grid_psf.cell_correction``); without this factor that division would be wrong for
    defocused PSFs.

    ``window`` m > 0 (even) computes the ATF only on the centred m × m samples and leaves
    the rest exactly 0: the same result wherever the pupil lies inside the window
    (``difstar.choose_grid`` sizes it; ``simulate`` checks it).

    ``with_energy`` also returns the pupil's energy (:func:`atf_energy`), the PSF's
    grid-independent normalisation.
    """
    h, w = shape
    m = int(window)
    if 0 < m < min(h, w):
        # The pupil lies in the centred m × m window: compute the ATF there only and place
        # it in a zero grid (a slice update: a pad would make XLA's CPU backend fuse the
        # whole computation into it and run it several times slower).
        sub, energy = _atf_on(pupil, wavelength, z_image, defocus, dx, shape, scaling,
                              use_defocus, shift, cell_average, m)
        h_atf = jax.lax.dynamic_update_slice(
            jnp.zeros(shape, sub.dtype), sub, (h // 2 - m // 2, w // 2 - m // 2))
    else:
        h_atf, energy = _atf_on(pupil, wavelength, z_image, defocus, dx, shape, scaling,
                                use_defocus, shift, cell_average, 0)
    return (h_atf, energy) if with_energy else h_atf


def atf_energy(pupil, amplitude):
    """The pupil's energy ∫|P|² in frequency cells, from its raster: the exact area (Σ
    coverage) for an area-coverage pupil, Σ|P|² for a plain raster. Divided by the grid's
    cell count it is what |IFFT(ATF)|² sums to over the whole plane (Parseval), so a PSF
    normalised by it sums to 1 over the infinite plane, independent of the grid."""
    if pupil.area_coverage:
        return jnp.sum(amplitude)
    return jnp.sum(amplitude * amplitude)


def _atf_on(pupil, wavelength, z_image, defocus, dx, shape, scaling, use_defocus, shift,
            cell_average, sub):
    """(ATF, pupil energy): the ATF of a ``shape`` grid on its centred ``sub`` × ``sub``
    window (0: all), and the pupil's energy (:func:`atf_energy`)."""
    fx, fy = frequency_axes(shape, dx)
    h, w = shape
    r0, c0, hs, ws = 0, 0, h, w
    if sub:
        r0, c0, hs, ws = h // 2 - sub // 2, w // 2 - sub // 2, sub, sub
        fx, fy = fx[c0 : c0 + ws], fy[r0 : r0 + hs]
    scale = pupil_scale(wavelength, z_image, defocus, scaling)
    df = (1.0 / (shape[1] * dx), 1.0 / (shape[0] * dx))
    # The pupil cell is the frequency cell scaled to the pupil (square when h == w).
    cell = scale * jnp.sqrt(df[0] * df[1])
    x = (scale * fx)[None, :]
    y = (scale * fy)[:, None]
    # on a square grid the cells tile the pupil plane: outlines differentiate cheaply
    tiles = h == w and min(hs, ws) >= 2
    amplitude = (pupil.tiled_coverage if tiles else pupil.coverage)(x, y, cell)
    energy = atf_energy(pupil, amplitude)
    if not (use_defocus or shift != (0.0, 0.0)):
        return amplitude.astype(jnp.result_type(amplitude.dtype, jnp.complex64)), energy
    # Every factor after the pupil is separable, a row factor times a column factor: 2
    # (h + w) transcendentals instead of one complex exponential per sample.
    phase_x = jnp.zeros_like(fx)
    phase_y = jnp.zeros_like(fy)
    gain_x = jnp.ones_like(fx)
    gain_y = jnp.ones_like(fy)
    if use_defocus:
        c = defocus_phase_coefficient(wavelength, z_image, defocus, scaling)
        phase_x = phase_x + c * fx**2
        phase_y = phase_y + c * fy**2
        if cell_average:
            gain_x = jnp.sinc(c * fx * df[0] / math.pi)
            gain_y = jnp.sinc(c * fy * df[1] / math.pi)
    if shift != (0.0, 0.0):
        phase_y = phase_y - 2 * math.pi * shift[0] / h * (jnp.arange(r0, r0 + hs) - h // 2)
        phase_x = phase_x - 2 * math.pi * shift[1] / w * (jnp.arange(c0, c0 + ws) - w // 2)
    along_x = (gain_x * jnp.exp(1j * phase_x))[None, :]
    along_y = (gain_y * jnp.exp(1j * phase_y))[:, None]
    return amplitude * along_y * along_x, energy


def pupil_samples(pupil_radius, *, wavelength, z_image, dx, n: int) -> Float[Array, ""]:
    """Number of frequency-grid samples across the pupil diameter."""
    return 2 * pupil_radius * n * dx / (wavelength * z_image)
