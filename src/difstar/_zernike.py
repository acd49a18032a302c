"""Wavefront aberrations as Zernike polynomials (Noll's indexing and normalisation).

Convention (Noll 1976, J. Opt. Soc. Am. 66, 207):

    Z_j(ρ, θ) = √(n+1) R_n^0(ρ)                    m = 0
              = √(2(n+1)) R_n^m(ρ) cos(m θ)        m ≠ 0, j even
              = √(2(n+1)) R_n^m(ρ) sin(m θ)        m ≠ 0, j odd

    R_n^m(ρ) = Σ_{s=0}^{(n−m)/2} (−1)^s (n−s)! / (s! ((n+m)/2 − s)! ((n−m)/2 − s)!) ρ^(n−2s)

with ρ = r / radius and θ the angle from +x towards +y (pupil-plane coordinates in metres,
x right, y up). Every term has unit RMS over the unit disc (⟨Z_j Z_k⟩ = δ_jk), so a
coefficient is the RMS wavefront error it contributes, in metres. Examples: Z4 = √3(2ρ²−1)
(defocus), Z5 = √6 ρ² sin 2θ, Z6 = √6 ρ² cos 2θ (astigmatism), Z7 = √8(3ρ³−2ρ) sin θ,
Z8 = √8(3ρ³−2ρ) cos θ (coma), Z11 = √5(6ρ⁴−6ρ²+1) (spherical).

The polynomials are evaluated as polynomials in x and y (ρ^m cos mθ and ρ^m sin mθ are the
real and imaginary parts of ((x + i y)/radius)^m), with no arctan2 or square root, so they
are smooth everywhere, including at the centre, for values and gradients. Outside the
circle (ρ > 1) the polynomials are simply continued; the pupil mask decides where the
wavefront matters.

Phase convention (difstar's Fresnel ATF, ``_atf.py``): the wavefront W (metres) enters the
pupil function as exp(+i k W), k = 2π/λ, the same sign as the defocus term
k · ½ (1/z_i − 1/z_R) r². A positive Noll-4 coefficient therefore acts like a positive Δz
(sensor behind the in-focus plane); see :func:`defocus_to_noll4`.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._custom_types import Array, ArrayLike, Float


def noll_to_nm(j: Any) -> tuple[int, int]:
    """Noll index j ≥ 1 → (n, m), radial order n and signed azimuthal order m.

    m > 0 is a cos(mθ) term (even j), m < 0 a sin(|m|θ) term (odd j), m = 0 rotationally
    symmetric. Within a radial order, |m| increases with j; for equal |m| the even j is
    the cosine. j = 1..11: (0,0) (1,1) (1,−1) (2,0) (2,−2) (2,2) (3,−1) (3,1) (3,−3)
    (3,3) (4,0).
    """
    if isinstance(j, bool) or not isinstance(j, numbers.Integral) or j < 1:
        raise ValueError(f"Noll index must be an integer >= 1; got {j!r}.")
    j = int(j)
    n = 0
    while (n + 1) * (n + 2) // 2 < j:
        n += 1
    k = j - n * (n + 1) // 2 - 1  # position within the radial order, 0..n
    m = 2 * ((k + 1) // 2) if n % 2 == 0 else 2 * (k // 2) + 1
    if m != 0 and j % 2 == 1:
        m = -m
    return n, m


def radial_coefficients(n: int, m: int) -> tuple[int, ...]:
    """Integer coefficients a_s of R_n^|m|(ρ) = Σ_s a_s ρ^(n−2s), s = 0..(n−|m|)/2
    (the explicit factorial sum)."""
    m = abs(m)
    if n < 0 or m > n or (n - m) % 2:
        raise ValueError(f"no Zernike polynomial with n={n}, m={m}.")
    return tuple(
        (-1) ** s
        * math.factorial(n - s)
        // (
            math.factorial(s)
            * math.factorial((n + m) // 2 - s)
            * math.factorial((n - m) // 2 - s)
        )
        for s in range((n - m) // 2 + 1)
    )


def zernike_noll(j: int, x: ArrayLike, y: ArrayLike, radius: Any) -> Array:
    """The unit-RMS Noll Zernike Z_j at pupil-plane points (x, y), metres (broadcast),
    on a circle of ``radius`` metres. Dimensionless."""
    n, m = noll_to_nm(j)
    u = jnp.asarray(x) / radius
    v = jnp.asarray(y) / radius
    u, v = jnp.broadcast_arrays(u, v)
    rho2 = u * u + v * v
    ma = abs(m)
    # R_n^m(ρ) = ρ^m Σ_s a_s (ρ²)^((n−m)/2 − s): Horner in ρ²
    radial = jnp.zeros_like(rho2)
    for a in radial_coefficients(n, m):
        radial = radial * rho2 + a
    if m == 0:
        return math.sqrt(n + 1) * radial
    # ρ^m cos mθ + i ρ^m sin mθ = (u + i v)^m, by repeated multiplication
    re, im = u, v
    for _ in range(ma - 1):
        re, im = re * u - im * v, re * v + im * u
    angular = re if m > 0 else im
    return math.sqrt(2 * (n + 1)) * radial * angular


def _concrete(a) -> np.ndarray | None:
    try:
        return np.asarray(a)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
        return None


class Zernike(eqx.Module):
    """A wavefront as a sum of unit-RMS Noll Zernike terms on a circle.

    ``Zernike({4: -0.2 * 550e-9, 11: 0.3 * 550e-9}, radius=1.17e-3)``: ``coefficients``
    maps Noll index j ≥ 1 to the term's coefficient, metres of wavefront RMS over the
    circle of ``radius`` metres (for a polygonal or obstructed pupil, usually its
    circumradius: the normalisation is over that circle, not over the pupil's shape).

    Fields: ``indices`` (static tuple of Noll indices, sorted), ``coefficients`` (JAX
    array, one per index: differentiable, replaceable with ``eqx.tree_at``), ``radius``
    (static float, metres). :meth:`opd` gives the optical path difference, metres.
    """

    indices: tuple[int, ...] = eqx.field(static=True)
    coefficients: Float[Array, " k"]
    radius: float = eqx.field(static=True)

    def __init__(self, coefficients: Mapping[int, ArrayLike] | Any, radius: Any):
        if not isinstance(coefficients, Mapping):
            raise ValueError(
                "Zernike.coefficients must be a mapping {Noll index j >= 1: coefficient in "
                f"metres RMS}}; got {type(coefficients).__name__}."
            )
        for j in coefficients:
            if isinstance(j, bool) or not isinstance(j, numbers.Integral) or j < 1:
                raise ValueError(
                    f"Zernike.coefficients: Noll indices must be integers >= 1; got {j!r}."
                )
        indices = tuple(sorted(int(j) for j in coefficients))
        if len(set(indices)) != len(indices):
            raise ValueError(f"Zernike.coefficients: repeated Noll index in {indices}.")
        values = [jnp.asarray(coefficients[j], dtype=float) for j in sorted(coefficients)]
        for j, c in zip(indices, values, strict=True):
            if c.shape != ():
                raise ValueError(
                    f"Zernike.coefficients[{j}] must be a scalar (metres RMS); got shape {c.shape}."
                )
            cc = _concrete(c)
            if cc is not None and not np.isfinite(cc):
                raise ValueError(f"Zernike.coefficients[{j}] must be finite; got {float(cc)}.")
        try:
            r = float(radius)
        except (TypeError, jax.errors.ConcretizationTypeError):
            raise ValueError(
                f"Zernike.radius must be a concrete number of metres; got {radius!r}."
            ) from None
        if not (math.isfinite(r) and r > 0):
            raise ValueError(f"Zernike.radius must be a finite number > 0 metres; got {r}.")
        self.indices = indices
        self.coefficients = (
            jnp.stack(values) if values else jnp.zeros((0,), dtype=jnp.asarray(0.0).dtype)
        )
        self.radius = r

    def as_dict(self) -> dict[int, Array]:
        """{Noll index: coefficient (metres RMS)}."""
        return {j: self.coefficients[i] for i, j in enumerate(self.indices)}

    def opd(self, x: ArrayLike, y: ArrayLike) -> Array:
        """Optical path difference W(x, y) = Σ_j c_j Z_j(x/radius, y/radius), metres, at
        pupil-plane coordinates x, y (metres, x right, y up; broadcast together).

        Polynomial in x, y (continued outside the circle), smooth everywhere; linear in
        the coefficients. The pupil function is P(x, y) · exp(+i 2π/λ · W(x, y)).
        """
        x = jnp.asarray(x)
        y = jnp.asarray(y)
        shape = jnp.broadcast_shapes(x.shape, y.shape)
        dtype = jnp.result_type(x, y, self.coefficients, float)
        out = jnp.zeros(shape, dtype=dtype)
        for i, j in enumerate(self.indices):
            out = out + self.coefficients[i] * zernike_noll(j, x, y, self.radius)
        return out

    def phase(self, x: ArrayLike, y: ArrayLike, wavelength: ArrayLike) -> Array:
        """k W(x, y) = 2π W / λ, radians (``wavelength`` in metres)."""
        return (2 * math.pi) * self.opd(x, y) / wavelength


# --- defocus Δz ↔ Noll 4 --------------------------------------------------------------


def defocus_to_w020(defocus: ArrayLike, z_image: ArrayLike, radius: ArrayLike) -> Array:
    """W020 = ½ (1/z_i − 1/z_R) R², metres: the peak (edge-of-circle) defocus wavefront
    of Δz = ``defocus`` with z_R = ``z_image`` (exit pupil to sensor), z_i = z_R − Δz,
    on a circle of ``radius`` R. Exact in difstar's Fresnel convention."""
    defocus, z_image, radius = (jnp.asarray(a, dtype=float) for a in (defocus, z_image, radius))
    z_i = z_image - defocus
    # ½ (1/z_i − 1/z_R) R² = ½ Δz R² / (z_i z_R): no cancellation at small Δz
    return 0.5 * defocus * radius**2 / (z_i * z_image)


def defocus_to_noll4(defocus: ArrayLike, z_image: ArrayLike, radius: ArrayLike) -> Array:
    """Noll-4 coefficient (metres RMS) equivalent to a defocus Δz (metres), exactly.

    difstar's Fresnel model (``_atf.py``) puts the sensor at z_R = ``z_image`` from the
    exit pupil, the in-focus image at z_i = z_R − Δz, and the defocus into the pupil as
    exp(i k W) with

        W(r) = ½ (1/z_i − 1/z_R) r² = W020 ρ²,   ρ = r / R,   W020 = ½ (1/z_i − 1/z_R) R²,

    an exact quadratic in r (the Fresnel approximation is already made; nothing further
    is expanded). On the circle of ``radius`` R,

        W020 ρ² = W020/2 + (W020 / (2√3)) · √3 (2ρ² − 1) = W020/2 + c4 Z4,

    so c4 = W020 / (2√3) = (1/z_i − 1/z_R) R² / (4√3), plus a piston W020/2 that does not
    change the PSF. This holds at every point of the plane, so it is exact for any pupil
    shape inside or outside the circle (only the piston differs from a "least-squares
    over the pupil" fit, and piston is invisible).

    Why the paper-style W020 = Δz / (8N²) is only approximate: writing N = z_R / (2R)
    (the working f-number at the sensor), the exact value is

        W020 = ½ Δz R² / (z_i z_R) = Δz / (8N²) · z_R / z_i = Δz / (8N²) / (1 − Δz/z_R),

    so Δz/(8N²) drops the factor z_R/z_i, an error of relative order Δz/z_R (8.8 % for
    the paper's defocused example: Δz = 4.78 mm, z_R = 59.2 mm, z_i = 54.5 mm); it needs N to be
    the working f-number z_R/(2R), not the lens's nominal N = f/D (they differ by the
    focus extension and pupil magnification). It is additionally asymmetric in the sign
    of Δz, which the linear formula cannot express.

    ``defocus``, ``z_image``, ``radius`` in metres (arrays broadcast; differentiable).
    """
    return defocus_to_w020(defocus, z_image, radius) / (2 * math.sqrt(3.0))


def noll4_to_defocus(c4: ArrayLike, z_image: ArrayLike, radius: ArrayLike) -> Array:
    """The exact inverse of :func:`defocus_to_noll4`: Δz (metres) from the Noll-4
    coefficient ``c4`` (metres RMS), with z_R = ``z_image`` and circle ``radius``.

    W020 = 2√3 c4; 1/z_i = 1/z_R + 2 W020 / R²; Δz = z_R − z_i
    = z_R · (2 W020 z_R / R²) / (1 + 2 W020 z_R / R²). Requires 1 + 2 W020 z_R / R² > 0
    (a real image in front of infinity); otherwise the result is not finite/meaningful.
    """
    c4, z_image, radius = (jnp.asarray(a, dtype=float) for a in (c4, z_image, radius))
    w020 = 2 * math.sqrt(3.0) * c4
    a = 2 * w020 * z_image / radius**2  # = z_R (1/z_i − 1/z_R)
    return z_image * a / (1 + a)


def noll4_to_w020(c4: ArrayLike) -> Array:
    """W020 = 2√3 c4 (metres): the edge-of-circle defocus wavefront of a Noll-4 term
    (relative to the circle's centre, ignoring the piston)."""
    return 2 * math.sqrt(3.0) * jnp.asarray(c4, dtype=float)


__all__ = [
    "Zernike",
    "defocus_to_noll4",
    "defocus_to_w020",
    "noll4_to_defocus",
    "noll4_to_w020",
    "noll_to_nm",
    "radial_coefficients",
    "zernike_noll",
]
