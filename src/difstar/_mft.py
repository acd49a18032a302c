"""Fast, alias-free in-focus path: the polygon's Fourier transform as separable matrices.

In focus, a polygonal pupil's amplitude PSF has a closed form (Lee & Mittra 1983):

    A(k) = (i/|k|²) Σ_edges (k·n_e) L_e e^{−i k·m_e} sinc(k·t_e L_e / 2),   A(0) = area,

and since  L sinc(k·t L/2) e^{−i k·m} = (e^{−i k·a} − e^{−i k·b}) / (i k·t)  for the edge
a → b, each edge's term is a difference of two *separable* exponentials, outer products
of one row and one column vector: e^{−i k·a} = e^{−i kx ax} e^{−i ky ay}. So the PSF on
any window costs O(edges × pixels) multiply-adds and O(edges × (H + W)) exponentials,
has no grid, no period and no aliasing, and is differentiable with respect to the
vertices. Where k·t L is small (the direction along an edge) the sinc form is used
instead, with a safe division, so values and gradients stay finite (k = 0 included).
The intensity is centrosymmetric (a real pupil), so only half of it is evaluated.

``focused_image`` uses it for the whole linear image of an in-focus scene: the PSF is
evaluated on the offsets the crop needs (crop + the object's diameter) and linearly
convolved with the geometric image by a real FFT of a fast size, so the grid is set by
the scene alone, not by the spikes' slow decay.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from ._custom_types import Array, Float
from ._psf import bin_pixels

_SMALL = 1e-2  # |k·t L / 2| below which the edge term uses its series form


def _edge_term(a, b, kx, ky):
    """One edge a → b of the Lee–Mittra sum (before the 1j/|k|² factor), (h, w)."""
    kxx = kx[None, :]
    kyy = ky[:, None]
    ea = jnp.exp(-1j * kx * a[0])[None, :] * jnp.exp(-1j * ky * a[1])[:, None]
    eb = jnp.exp(-1j * kx * b[0])[None, :] * jnp.exp(-1j * ky * b[1])[:, None]
    d = b - a
    length = jnp.sqrt(d[0] * d[0] + d[1] * d[1])
    tx, ty = d[0] / length, d[1] / length
    kn = kxx * ty - kyy * tx  # k·n, n = (ty, −tx) outward for CCW
    kt = kxx * tx + kyy * ty  # k·t
    half = 0.5 * kt * length
    small = jnp.abs(half) < _SMALL
    safe_kt = jnp.where(small, 1.0, kt)
    general = (ea - eb) * (-1j / safe_kt)
    h2 = half * half
    series = (0.5 * length) * (ea + eb) * (1.0 + h2 / 3.0 + h2 * h2 * (2.0 / 15.0))
    return kn * jnp.where(small, series, general)


def _edge_sum(vertices, kx, ky):
    v1 = jnp.roll(vertices, -1, axis=0)
    total = _edge_term(vertices[0], v1[0], kx, ky)
    for e in range(1, vertices.shape[0]):
        total = total + _edge_term(vertices[e], v1[e], kx, ky)
    return total


def polygon_amplitude(
    vertices: Float[Array, "n 2"], kx: Float[Array, " w"], ky: Float[Array, " h"]
) -> Array:
    """∫_P exp(−i k·x) dA on the outer grid (ky rows) × (kx columns), shape (h, w).

    Where |k·t L/2| is small an edge's term (e^{−i k·a} − e^{−i k·b}) / (i k·t) is
    replaced by its series L (e^{−i k·a} + e^{−i k·b})/2 · tan(h)/h, h = k·t L/2 (the
    midpoint exponential is their mean over cos h), so values and gradients stay finite
    (k = 0 and directions along an edge included)."""
    dt = jnp.result_type(vertices.dtype, kx.dtype, jnp.float32)
    cdt = jnp.result_type(dt, jnp.complex64)
    v0 = vertices
    v1 = jnp.roll(vertices, -1, axis=0)
    kxx = kx[None, :]
    kyy = ky[:, None]
    total = _edge_sum(vertices, kx.astype(dt), ky.astype(dt))
    k2 = kxx * kxx + kyy * kyy
    zero = k2 == 0
    area = 0.5 * jnp.sum(v0[:, 0] * v1[:, 1] - v1[:, 0] * v0[:, 1])
    return jnp.where(zero, area.astype(cdt), 1j * total / jnp.where(zero, 1.0, k2))


def _mirror_plan(n_fine: int, centre2: int):
    """Centrosymmetry plan for one axis of fine samples at offsets t_j = j − c (2c =
    ``centre2``, an integer). Returns the offsets to compute, all ≤ 0 (as 2t), and for
    each sample j the index into them of t_j (t_j ≤ 0) or of −t_j (t_j > 0)."""
    t2 = 2 * np.arange(n_fine) - int(centre2)
    need = np.union1d(t2[t2 <= 0], -t2[t2 > 0])
    idx = np.searchsorted(need, np.where(t2 <= 0, t2, -t2))
    return t2, need, idx


def polygon_psf(
    vertices: Float[Array, "n 2"],
    *,
    wavelength,
    z_image,
    pixel_pitch: float,
    shape: tuple[int, int],
    oversample: int = 1,
    centre: tuple[int, int] | None = None,
) -> Float[Array, "h w"]:
    """In-focus PSF of a polygonal exit pupil on an (H, W) pixel window centred at
    pixel ``centre`` (default (H//2, W//2)), exact (no aliasing), integrated over each pixel by a q × q midpoint rule
    when ``oversample`` q > 1. Normalised physically (Parseval): its sum over the infinite
    plane is 1, so a window holds the energy that falls in it.

    A real pupil's amplitude obeys A(−k) = A(k)*, so the intensity is centrosymmetric:
    it is evaluated only for row offsets ≤ 0 (columns of both signs) and mirrored, which
    halves the work."""
    h, w = shape
    q = int(oversample)
    dx = pixel_pitch / q
    ch, cw = (h // 2, w // 2) if centre is None else (int(centre[0]), int(centre[1]))
    s = 2 * math.pi / (wavelength * z_image)
    # fine sample j sits at offset (j − c)·dx from the PSF centre, c = centre·q + (q−1)/2
    # (the centre of the centre pixel's q × q block); 2c is an integer
    t2r, need_r, idx_r = _mirror_plan(h * q, 2 * ch * q + q - 1)
    t2c, cols, _ = _mirror_plan(w * q, 2 * cw * q + q - 1)
    cols = np.union1d(t2c, -t2c)  # every column offset and its negative
    u = jnp.asarray(cols * 0.5 * dx) * s
    v = -jnp.asarray(need_r * 0.5 * dx) * s
    amp = polygon_amplitude(vertices, u, v)
    v0 = vertices
    v1 = jnp.roll(vertices, -1, axis=0)
    area = 0.5 * jnp.sum(v0[:, 0] * v1[:, 1] - v1[:, 0] * v0[:, 1])
    # (dx / λz)² first: λz² · area underflows float32 in the gradient of 1/area
    scale = (dx / (wavelength * z_image)) ** 2 / area
    half = (jnp.real(amp) ** 2 + jnp.imag(amp) ** 2) * scale
    neg = t2r <= 0
    top = half[_take(idx_r[neg])][:, _take(np.searchsorted(cols, t2c))]
    bottom = half[_take(idx_r[~neg])][:, _take(np.searchsorted(cols, -t2c))]
    # assembled by two slice updates: a concatenate here makes XLA's CPU backend fuse the
    # whole closed-form evaluation into it and run ~8× slower
    inten = jnp.zeros((h * q, w * q), half.dtype)
    inten = jax.lax.dynamic_update_slice(inten, top, (0, 0))
    inten = jax.lax.dynamic_update_slice(inten, bottom, (top.shape[0], 0))
    return bin_pixels(inten, q)


def _take(idx: np.ndarray):
    """A static index array as a slice where it is a run of step ±1 (an XLA slice and
    reverse, far cheaper on the CPU than a gather), else the array itself."""
    if idx.size == 0:
        return slice(0, 0)
    if idx.size == 1 or np.all(np.diff(idx) == 1):
        return slice(int(idx[0]), int(idx[-1]) + 1)
    if np.all(np.diff(idx) == -1):
        stop = int(idx[-1]) - 1
        return slice(int(idx[0]), None if stop < 0 else stop, -1)
    return idx


def focused_image(
    vertices: Float[Array, "n 2"],
    b: Float[Array, "3 hb wb"],
    wavelengths: Float[Array, "3"],
    *,
    z_image,
    pixel_pitch: float,
    crop: tuple[int, int],
    oversample: int = 1,
) -> tuple[Array, Array]:
    """Linear image (3, h, w) of an in-focus scene on the ``crop``, and the PSFs on it.

    ``b`` is the geometric image on an (hb, wb) grid centred like the crop (odd sizes
    hold a source centred on the crop's centre pixel); every source pixel reaches every
    crop pixel through the exact PSF, with no wrap-around: the PSF is evaluated on the
    (h + hb − 1) × (w + wb − 1) offsets the crop needs and the convolution is linear
    (zero-padded real FFT of a fast size).
    """
    from ._sampling import fast_length

    h, w = crop
    hb, wb = b.shape[-2:]
    kh, kw = h + hb - 1, w + wb - 1  # PSF offsets needed, centred at (kh//2, kw//2)
    nh, nw = fast_length(kh + hb - 1), fast_length(kw + wb - 1)
    b_ft = jnp.fft.rfft2(b, s=(nh, nw))  # once for all channels
    # full[i + j] pairs PSF index i (offset i − kh//2) with b index j (offset j − hb//2);
    # PSF indices i ≥ kh land on output rows [kh, nh) ∪ [0, hb − 1): outside the crop
    # [r0, r0 + h) when these hold (always, for even crops and odd source windows)
    r0 = kh // 2 + hb // 2 - h // 2
    c0 = kw // 2 + wb // 2 - w // 2
    clean = r0 >= hb - 1 and r0 + h <= kh and c0 >= wb - 1 and c0 + w <= kw
    psfs, imgs = [], []
    for c in range(3):
        # The PSF on the whole (nh, nw) FFT grid, centred at (kh//2, kw//2): indices
        # beyond the kh × kw offsets the crop needs wrap only onto output indices outside
        # the crop, so they need no zeroing and the transform needs no zero padding
        # (XLA's CPU backend fuses the closed form into a pad and runs it ~6× slower).
        if clean:
            p = polygon_psf(vertices, wavelength=wavelengths[c], z_image=z_image,
                            pixel_pitch=pixel_pitch, shape=(nh, nw), oversample=oversample,
                            centre=(kh // 2, kw // 2))
            p_ft = jnp.fft.rfft2(p)
        else:  # (odd crops or even source windows) zero-pad instead
            p = polygon_psf(vertices, wavelength=wavelengths[c], z_image=z_image,
                            pixel_pitch=pixel_pitch, shape=(kh, kw), oversample=oversample)
            p_ft = jnp.fft.rfft2(p, s=(nh, nw))
        full = jnp.fft.irfft2(p_ft * b_ft[c], s=(nh, nw))
        imgs.append(full[r0 : r0 + h, c0 : c0 + w])
        psfs.append(p[kh // 2 - h // 2 : kh // 2 - h // 2 + h, kw // 2 - w // 2 : kw // 2 - w // 2 + w])
    return jnp.stack(psfs), jnp.stack(imgs)
