"""Independent truths and helpers for the tests (NumPy/SciPy, not difstar's code)."""

from __future__ import annotations

import numpy as np
import scipy.special


def polygon_ft(vertices: np.ndarray, kx: np.ndarray, ky: np.ndarray) -> np.ndarray:
    """Exact ∫_P exp(-i k·x) dA of a polygon (Lee & Mittra 1983), NumPy float64.

    By the divergence theorem with F = i k e^{-ik·x}/|k|²:
    Σ_edges (i/|k|²)(k·n_e) L_e e^{-ik·m_e} sinc(k·t_e L_e / 2); the area at k = 0.
    """
    v0 = np.asarray(vertices, float)
    v1 = np.roll(v0, -1, axis=0)
    kx = np.asarray(kx, float)
    ky = np.asarray(ky, float)
    k2 = kx * kx + ky * ky
    out = np.zeros(np.broadcast(kx, ky).shape, complex)
    for a, b in zip(v0, v1):
        d = b - a
        length = np.hypot(*d)
        tx, ty = d / length
        nx, ny = ty, -tx
        mx, my = (a + b) / 2
        kn = kx * nx + ky * ny
        kt = kx * tx + ky * ty
        out += kn * length * np.exp(-1j * (kx * mx + ky * my)) * np.sinc(kt * length / (2 * np.pi))
    with np.errstate(invalid="ignore", divide="ignore"):
        out = 1j * out / k2
    area = 0.5 * np.sum(v0[:, 0] * v1[:, 1] - v1[:, 0] * v0[:, 1])
    return np.where(k2 == 0, area, out)


def polygon_psf_exact(vertices, *, wavelength, z, pixel_pitch, shape):
    """Point-sampled in-focus PSF of a polygonal pupil on a (H, W) pixel grid, centred at
    (H//2, W//2), normalised analytically (Parseval): Σ over the infinite grid = 1."""
    h, w = shape
    u = (np.arange(w) - w // 2) * pixel_pitch
    v = -(np.arange(h) - h // 2) * pixel_pitch
    kx = 2 * np.pi * u[None, :] / (wavelength * z)
    ky = 2 * np.pi * v[:, None] / (wavelength * z)
    amp = polygon_ft(vertices, kx, ky)
    v0 = np.asarray(vertices, float)
    v1 = np.roll(v0, -1, axis=0)
    area = 0.5 * np.sum(v0[:, 0] * v1[:, 1] - v1[:, 0] * v0[:, 1])
    return np.abs(amp) ** 2 * pixel_pitch**2 / ((wavelength * z) ** 2 * area)


def airy_psf(r, *, wavelength, f_number):
    """Airy intensity at radius r (metres), peak 1: [2 J1(x)/x]², x = π r / (λ N)."""
    x = np.pi * np.asarray(r, float) / (wavelength * f_number)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = (2 * scipy.special.j1(x) / x) ** 2
    return np.where(x == 0, 1.0, out)


def fd_grad(f, x, eps):
    """Central finite difference of scalar f at scalar x."""
    return (f(x + eps) - f(x - eps)) / (2 * eps)
