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

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from ._custom_types import Array, Float
from ._psf import bin_pixels

_SMALL = 2e-2  # |k·d| (k·t L) below which an edge's term uses its series form


def _tables(w, u, t):
    """Per-vertex 1-D tables cos/sin(w_x u), cos/sin(w_y t), each (n, len).

    Computed in a scan so that they are materialised as 1-D arrays: XLA's CPU backend
    otherwise fuses the sines into the 2-D loop that broadcasts them and evaluates four
    transcendentals per vertex per pixel (10× slower)."""

    def body(carry, v):
        pu, pt = v[0] * u, v[1] * t
        return carry, (jnp.cos(pu), jnp.sin(pu), jnp.cos(pt), jnp.sin(pt))

    return jax.lax.scan(body, 0, w)[1]


def _edge_parts(w, u, t, tabs):
    """The Lee–Mittra edge sum Σ_e T_e on the outer grid (t rows) × (u columns), as (re,
    im), with everything an edge needs for its derivatives: per edge (p, q, small, Ea,
    Eb), E = e^{−i k·v} of the edge's start and end vertex.

    With d = b − a the edge vector, p = k × d (= k·n L) and q = k·d (= k·t L):
        T = −i (p/q) (E_a − E_b)                      (general)
        T = (p/2) (E_a + E_b) P(q/2),  P(h) = 1 + h²/3 + 2h⁴/15 ≈ tan(h)/h   (|q| small)
    so an edge's term depends only on its direction and its two vertex exponentials."""
    cx, sx, cy, sy = tabs
    n = w.shape[0]
    uu, tt = jnp.asarray(u)[None, :], jnp.asarray(t)[:, None]
    E = [(cy[j][:, None] * cx[j][None, :] - sy[j][:, None] * sx[j][None, :],
          -(sy[j][:, None] * cx[j][None, :] + cy[j][:, None] * sx[j][None, :]))
         for j in range(n)]
    re = im = 0.0
    edges = []
    for e in range(n):
        f = (e + 1) % n
        dx, dy = w[f, 0] - w[e, 0], w[f, 1] - w[e, 1]
        p = uu * dy - tt * dx
        q = uu * dx + tt * dy
        small = jnp.abs(q) < _SMALL
        r = p / jnp.where(small, 1.0, q)
        h2 = 0.25 * q * q
        sp = 0.5 * p * (1.0 + h2 * (1.0 / 3.0 + h2 * (2.0 / 15.0)))
        (ar, ai), (br, bi) = E[e], E[f]
        re = re + jnp.where(small, sp * (ar + br), r * (ai - bi))
        im = im + jnp.where(small, sp * (ai + bi), r * (br - ar))
        edges.append((p, q, small, E[e], E[f]))
    return re, im, edges


def _area(w):
    w1 = jnp.roll(w, -1, axis=0)
    return 0.5 * jnp.sum(w[:, 0] * w1[:, 1] - w1[:, 0] * w[:, 1])


def _intensity_plain(w, u, t):
    """|∫_P(w) e^{−i k·x} dA|² at k = (u_j, t_i), (len t, len u): the forward, written for
    autodiff (the reference for :func:`polygon_intensity`'s hand-written gradient)."""
    return _intensity_fwd(w, u, t)[0]


def _inverse_k2(u, t):
    """(k = 0, 1/|k|² with 1 at k = 0), computed in the loop from the 1-D offsets (as
    NumPy they would be (h, w) constants read from memory)."""
    uu, tt = jnp.asarray(u)[None, :], jnp.asarray(t)[:, None]
    k2 = uu * uu + tt * tt
    zero = k2 == 0
    return zero, 1.0 / jnp.where(zero, 1.0, k2)


@functools.partial(jax.custom_vjp, nondiff_argnums=(1, 2))
def polygon_intensity(w, u, t):
    """|A(k)|², A(k) = ∫_P exp(−i k·x) dA of the polygon ``w`` (n, 2; counter-clockwise),
    on the grid of rows ``t`` × columns ``u`` (static NumPy arrays, same units as 1/w).

    Exact (Lee & Mittra), finite with finite gradients everywhere, k = 0 and the
    directions along an edge (where the series form is used) included. Its gradient is
    written by hand: one pass over the grid per vertex coordinate, instead of autodiff's
    hundred intermediate planes (the same values to rounding;
    tests/test_hard_cases.py checks it against autodiff and finite differences)."""
    return _intensity_plain(w, u, t)


def _intensity_fwd(w, u, t):
    tabs = _tables(w, u, t)
    re, im, _ = _edge_parts(w, u, t, tabs)
    zero, inv = _inverse_k2(u, t)
    area = _area(w)
    out = jnp.where(zero, area * area, (re * re + im * im) * (inv * inv))
    return out, (w, tabs)


def _intensity_bwd(u, t, res, g):
    w, tabs = res
    n = w.shape[0]
    re, im, edges = _edge_parts(w, u, t, tabs)
    zero, inv = _inverse_k2(u, t)
    gz = jnp.where(zero, 0.0, 2.0 * g * (inv * inv))
    gr, gi = gz * re, gz * im  # cotangents of the edge sum's real and imaginary parts
    uu, tt = jnp.asarray(u)[None, :], jnp.asarray(t)[:, None]

    def dot(zr, zi):  # Σ Re(conj(gr + i gi) (zr + i zi))
        return gr * zr + gi * zi

    # per edge: X = ∂T/∂d (d = b − a), Ya/Yb = ∂T/∂E_a · (−i E_a), ∂T/∂E_b · (−i E_b);
    # then ∂T/∂a = −X + k Ya and ∂T/∂b = X + k Yb
    xs, ya, yb = [], [], []
    for p, q, small, (ar, ai), (br, bi) in edges:
        qs = jnp.where(small, 1.0, q)
        r = p / qs
        dr, di = ar - br, ai - bi
        # general: T = −i r Δ, ∂r/∂d = |k|² (−d_y, d_x)/q² so ∂T/∂d_x ∝ −i (−|k|²d_y/q²) Δ;
        # written with (p, q) only: ∂r/∂d_x = −(t q + u p)/q², ∂r/∂d_y = (u q − t p)/q²
        rx = -(tt * q + uu * p) / (qs * qs)
        ry = (uu * q - tt * p) / (qs * qs)
        h = 0.5 * q
        h2 = h * h
        pp = 1.0 + h2 * (1.0 / 3.0 + h2 * (2.0 / 15.0))
        dpp = h * (2.0 / 3.0 + h2 * (8.0 / 15.0))  # P'(h)
        sr, si = ar + br, ai + bi
        # series: T = (p/2) Σ P(q/2): ∂T/∂d_x = (Σ/2)(−t P + p u P'/2), ∂/∂d_y = (Σ/2)(u P + p t P'/2)
        cxs = 0.5 * (-tt * pp + 0.5 * p * uu * dpp)
        cys = 0.5 * (uu * pp + 0.5 * p * tt * dpp)
        # X = ∂T/∂d: general −i r' Δ = (r' di, −r' dr); series c Σ
        xr = jnp.where(small, cxs * sr, rx * di)
        xi = jnp.where(small, cxs * si, -rx * dr)
        yr_ = jnp.where(small, cys * sr, ry * di)
        yi_ = jnp.where(small, cys * si, -ry * dr)
        xs.append((jnp.sum(dot(xr, xi)), jnp.sum(dot(yr_, yi_))))
        # Y: general Ya = −r E_a, Yb = r E_b; series Ya = (p/2)P (−i E_a) = s (ai, −ar)
        s = 0.5 * p * pp
        yar = jnp.where(small, s * ai, -r * ar)
        yai = jnp.where(small, -s * ar, -r * ai)
        ybr = jnp.where(small, s * bi, r * br)
        ybi = jnp.where(small, -s * br, r * bi)
        ya.append((yar, yai))
        yb.append((ybr, ybi))
    grads = []
    for j in range(n):
        e_prev = (j - 1) % n
        zr = ya[j][0] + yb[e_prev][0]
        zi = ya[j][1] + yb[e_prev][1]
        gy = dot(zr, zi)
        gxj = xs[e_prev][0] - xs[j][0] + jnp.sum(gy * uu)
        gyj = xs[e_prev][1] - xs[j][1] + jnp.sum(gy * tt)
        grads.append(jnp.stack([gxj, gyj]))
    gw = jnp.stack(grads)
    if np.any(u == 0) and np.any(t == 0):  # k = 0: |A|² = area², ∂area/∂w_j = (w_{j+1,y} − w_{j−1,y}, w_{j−1,x} − w_{j+1,x})/2
        g0 = jnp.sum(jnp.where(zero, g, 0.0)) * 2.0 * _area(w)
        wn, wp = jnp.roll(w, -1, axis=0), jnp.roll(w, 1, axis=0)
        gw = gw + g0 * 0.5 * jnp.stack([wn[:, 1] - wp[:, 1], wp[:, 0] - wn[:, 0]], axis=1)
    return (gw,)


polygon_intensity.defvjp(_intensity_fwd, _intensity_bwd)


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
    pixel ``centre`` (default (H//2, W//2)), exact (no aliasing), integrated over each
    pixel by a q × q midpoint rule when ``oversample`` q > 1. Normalised physically (Parseval): its sum over the infinite
    plane is 1, so a window holds the energy that falls in it.

    A real pupil's amplitude obeys A(−k) = A(k)*, so the intensity is centrosymmetric:
    it is evaluated only for row offsets ≤ 0 (columns of both signs) and mirrored, which
    halves the work."""
    h, w = shape
    q = int(oversample)
    dx = pixel_pitch / q
    ch, cw = (h // 2, w // 2) if centre is None else (int(centre[0]), int(centre[1]))
    # fine sample j sits at offset (j − c)·dx from the PSF centre, c = centre·q + (q−1)/2
    # (the centre of the centre pixel's q × q block); 2c is an integer
    t2r, need_r, idx_r = _mirror_plan(h * q, 2 * ch * q + q - 1)
    t2c, cols, _ = _mirror_plan(w * q, 2 * cw * q + q - 1)
    cols = np.union1d(t2c, -t2c)  # every column offset and its negative
    # dimensionless: offsets in units of dx, the pupil scaled by β = 2π dx/(λz), so that
    # k·x = offset·(β x) and |A(k)|² = β⁻⁴ |A_β(offset)|²; with the Parseval scale
    # (dx/λz)²/area the PSF is |A_β|² / (4π² area_β) (O(1) numbers, safe in float32)
    dt = jnp.result_type(vertices.dtype, jnp.float32)
    beta = (2 * math.pi * dx) / (wavelength * z_image)
    wv = vertices * beta
    u = np.asarray(cols * 0.5, dtype=dt)
    t = np.asarray(-need_r * 0.5, dtype=dt)
    half = polygon_intensity(wv, u, t) / (4 * math.pi**2 * _area(wv))
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
