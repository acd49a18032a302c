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
from ._fft_size import fast_length
from ._grid_psf import bin_pixels
from ._xla import stored

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


def _vertex_exp(tabs, j):
    """E_j = e^{−i k·w_j} on the outer grid, as (re, im), from the 1-D tables."""
    cx, sx, cy, sy = tabs
    return (cy[j][:, None] * cx[j][None, :] - sy[j][:, None] * sx[j][None, :],
            -(sy[j][:, None] * cx[j][None, :] + cy[j][:, None] * sx[j][None, :]))


def _edge_sum(w, u, t, tabs):
    """The Lee–Mittra edge sum S = Σ_e T_e on the outer grid (t rows) × (u columns), as
    (re, im); the transform is A = i S/|k|².

    With d = b − a the edge vector, p = k × d (= k·n L) and q = k·d (= k·t L):
        T = −i (p/q) (E_a − E_b)                      (general)
        T = (p/2) (E_a + E_b) P(q/2),  P(h) = 1 + h²/3 + 2h⁴/15 ≈ tan(h)/h   (|q| small)
    with E = e^{−i k·v} of the edge's start and end vertex."""
    n = w.shape[0]
    uu, tt = jnp.asarray(u)[None, :], jnp.asarray(t)[:, None]
    E = [_vertex_exp(tabs, j) for j in range(n)]
    re = im = 0.0
    for e in range(n):
        f = (e + 1) % n
        dx, dy = w[f, 0] - w[e, 0], w[f, 1] - w[e, 1]
        p = uu * dy - tt * dx
        q = uu * dx + tt * dy
        small = jnp.abs(q) < _SMALL
        qs = jnp.where(small, 1.0, q)
        h2 = 0.25 * q * q
        sp = 0.5 * p * (1.0 + h2 * (1.0 / 3.0 + h2 * (2.0 / 15.0)))
        (ar, ai), (br, bi) = E[e], E[f]
        # p/q is written twice (as p/q and −p/q): XLA's CPU fusion will not fuse a
        # division whose value its consumer reads twice, and would store a plane of it
        # per edge (memory-bound: 3–6× slower); two single-use divisions fuse
        re = re + jnp.where(small, sp * (ar + br), (p / qs) * (ai - bi))
        im = im + jnp.where(small, sp * (ai + bi), (-p / qs) * (ar - br))
    return re, im


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
    written by hand (:func:`_intensity_bwd`: the shape derivative, two sums per edge,
    instead of autodiff's hundred intermediate planes; the same values to rounding,
    tests/test_hard_cases.py checks it against autodiff and finite differences)."""
    return _intensity_plain(w, u, t)


def _intensity_fwd(w, u, t):
    tabs = _tables(w, u, t)
    re, im = _edge_sum(w, u, t, tabs)
    zero, inv = _inverse_k2(u, t)
    area = _area(w)
    out = jnp.where(zero, area * area, (re * re + im * im) * (inv * inv))
    return out, (w, tabs)


def _intensity_bwd(u, t, res, g):
    """Gradient of Σ g·|A|² with respect to the vertices, by the shape derivative.

    A = ∫_P e^{−i k·x} dA (= i S/|k|², S the edge sum). Moving vertex j moves its two
    edges' points linearly (hat functions), so
        ∂A/∂w_j = N_{j−1} J^b_{j−1} + N_j J^a_j,   N_e = (d_y, −d_x) (d = b − a),
        J^a = ∫₀¹ (1 − s) e^{−i k·(a + s d)} ds = (Δ − i q E_a)/q² = E_a f(q),
        J^b = ∫₀¹ s e^{−i k·(a + s d)} ds = (i q E_b − Δ)/q² = E_b f(−q),
    with q = k·d, Δ = E_a − E_b and f(q) = Σₙ (−iq)ⁿ/(n + 2)! (used where |q| is small,
    against the cancellation in Δ − i q E_a). With C = 2 g A*, the gradient needs per
    edge only R^a = Σ_k Re(C J^a) and R^b = Σ_k Re(C J^b): 14 reductions for 7 edges,
    each with one division, over C stored once (see :func:`._xla.stored`)."""
    w, tabs = res
    n = w.shape[0]
    zero, inv = _inverse_k2(u, t)

    def cotangent(ops):  # C = 2 g conj(A) = 2 g conj(i S inv) = s (im + i re)
        w, tabs, g = ops
        re, im = _edge_sum(w, u, t, tabs)
        s = jnp.where(zero, 0.0, -2.0 * g * inv)
        return s * im, s * re

    cr, ci = stored(cotangent, (w, tabs, g), jnp.sum(w))
    uu, tt = jnp.asarray(u)[None, :], jnp.asarray(t)[:, None]
    # series where |q| < lim: terms to (−iq)⁶/8! (truncation q⁷/9!) against the general
    # form's cancellation (ε/q²): 2e-8 and 5e-7 at 0.5 in float32, 1e-22 and 2e-12 at
    # 1e-2 in float64
    lim = 0.5 if jnp.finfo(cr.dtype).bits <= 32 else 1e-2
    ra, rb = [], []
    for e in range(n):
        f = (e + 1) % n
        dx, dy = w[f, 0] - w[e, 0], w[f, 1] - w[e, 1]
        q = uu * dx + tt * dy
        small = jnp.abs(q) < lim
        q2 = jnp.where(small, 1.0, q * q)
        h2 = q * q
        fr = 0.5 - h2 * (1.0 / 24 - h2 * (1.0 / 720 - h2 / 40320))
        fi = -q * (1.0 / 6 - h2 * (1.0 / 120 - h2 / 5040))
        (ar, ai), (br, bi) = _vertex_exp(tabs, e), _vertex_exp(tabs, f)
        dr, di = ar - br, ai - bi
        # Re(C Z) = cr Zr − ci Zi; each sum divides once (XLA stores a division that its
        # consumer reads twice)
        za_r, za_i = ar * fr - ai * fi, ar * fi + ai * fr  # E_a f(q)
        zb_r, zb_i = br * fr + bi * fi, bi * fr - br * fi  # E_b conj(f(q))
        ga = jnp.where(small, cr * za_r - ci * za_i,
                       (cr * (dr + q * ai) - ci * (di - q * ar)) / q2)
        gb = jnp.where(small, cr * zb_r - ci * zb_i,
                       (-cr * (q * bi + dr) - ci * (q * br - di)) / q2)
        ra.append(jnp.sum(ga))
        rb.append(jnp.sum(gb))
    ra, rb = jnp.stack(ra), jnp.stack(rb)
    d = jnp.roll(w, -1, axis=0) - w
    normal = jnp.stack([d[:, 1], -d[:, 0]], axis=1)  # N_e, edge e from w_e to w_{e+1}
    gw = normal * ra[:, None] + jnp.roll(normal * rb[:, None], 1, axis=0)
    if np.any(u == 0) and np.any(t == 0):  # k = 0: |A|² = area², ∂area/∂w_j = (N_{j−1} + N_j)/2
        g0 = jnp.sum(jnp.where(zero, g, 0.0)) * 2.0 * _area(w)
        gw = gw + g0 * 0.5 * (normal + jnp.roll(normal, 1, axis=0))
    return (gw,)


polygon_intensity.defvjp(_intensity_fwd, _intensity_bwd)


@functools.partial(jax.custom_vjp, nondiff_argnums=(1, 2))
def _intensity_planes(w, u, t):
    """:func:`polygon_intensity` of each polygon ``w`` (m, n, 2) on rows ``t`` × columns
    ``u``, (m, len t, len u), computed once and stored as one array (see
    :func:`._xla.stored`: under differentiation the intensity has consumers besides the
    PSF's, each of which would re-evaluate it)."""

    def planes(w):  # batched arithmetic, not a stack (a concatenate of the closed forms)
        return jax.vmap(lambda wi: _intensity_fwd(wi, u, t)[0])(w)

    return stored(planes, w, jnp.sum(w))


def _planes_fwd(w, u, t):
    return _intensity_planes(w, u, t), w


def _planes_bwd(u, t, w, g):
    return (jnp.stack([_intensity_bwd(u, t, (wi, _tables(wi, u, t)), gi)[0]
                       for wi, gi in zip(w, g)]),)


_intensity_planes.defvjp(_planes_fwd, _planes_bwd)


def _run(x, axis: int, idx: np.ndarray):
    """``x`` at the static indices ``idx`` (a run of step ±1) along ``axis``, as a slice."""
    lo, hi = int(idx.min()), int(idx.max()) + 1
    x = jax.lax.slice_in_dim(x, lo, hi, axis=axis)
    return jnp.flip(x, axis) if idx.size > 1 and idx[1] < idx[0] else x


def _symmetric_intensity(w, r2, c2):
    """:func:`polygon_intensity` of each polygon ``w`` (m, n, 2) on rows ``r2``/2 ×
    columns ``c2``/2 (``r2``, ``c2``: integer runs of step ±2), (m, rows, columns).

    A real pupil's intensity is centrosymmetric, I(−k) = I(k): it is evaluated on the
    row offsets ≤ 0 only (every column offset and its negative) and mirrored. Its
    gradient (autodiff of the mirror) folds the cotangent back onto that half-plane."""
    rows = np.union1d(r2[r2 <= 0], -r2[r2 > 0])  # every |row offset|, as ≤ 0
    cols = np.union1d(c2, -c2)
    half = _intensity_planes(w, np.asarray(cols * 0.5, w.dtype), np.asarray(rows * 0.5, w.dtype))
    parts = []
    for sel, sign in ((r2 > 0, -1), (r2 <= 0, 1)):  # I(t, u) = I(−t, −u)
        if np.any(sel):
            block = _run(half, 1, np.searchsorted(rows, sign * r2[sel]))
            parts.append(_run(block, 2, np.searchsorted(cols, sign * c2)))
    if r2.size > 1 and r2[1] > r2[0]:  # ascending rows: the t ≤ 0 block comes first
        parts = parts[::-1]
    return jnp.concatenate(parts, axis=1) if len(parts) > 1 else parts[0]


def polygon_intensities(
    vertices: Float[Array, "n 2"],
    wavelengths,
    *,
    z_image,
    pixel_pitch: float,
    shape: tuple[int, int],
    oversample: int = 1,
    centre: tuple[int, int] | None = None,
) -> tuple[Array, Array]:
    """(I, s): for each wavelength, the in-focus intensity of a polygonal exit pupil on
    an (H, W) pixel window centred at pixel ``centre`` (default (H//2, W//2)), exact (no
    aliasing), integrated over each pixel by a q × q midpoint rule when ``oversample``
    q > 1, (m, H, W); and the scales (m,) that make it the PSF, ``s[:, None, None] * I``
    (see :func:`polygon_psf`). Kept apart so that a caller can apply the scale where it
    costs least."""
    h, w = shape
    q = int(oversample)
    dx = pixel_pitch / q
    ch, cw = (h // 2, w // 2) if centre is None else (int(centre[0]), int(centre[1]))
    # fine sample j sits at offset (j − c)·dx from the PSF centre, c = centre·q + (q−1)/2
    # (the centre of the centre pixel's q × q block); 2c is an integer
    # (rows run along −y: row offset o sits at y = −o)
    r2 = (2 * ch * q + q - 1) - 2 * np.arange(h * q)
    c2 = 2 * np.arange(w * q) - (2 * cw * q + q - 1)
    # dimensionless: offsets in units of dx, the pupil scaled by β = 2π dx/(λz), so that
    # k·x = offset·(β x) and |A(k)|² = β⁻⁴ |A_β(offset)|²; with the Parseval scale
    # (dx/λz)²/area the PSF is |A_β|² / (4π² area_β) (O(1) numbers, safe in float32)
    wv = jnp.stack([vertices * ((2 * math.pi * dx) / (lam * z_image)) for lam in wavelengths])
    scale = jnp.stack([1.0 / (4 * math.pi**2 * _area(wi)) for wi in wv])
    return bin_pixels(_symmetric_intensity(wv, r2, c2), q), scale


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
    pixel by a q × q midpoint rule when ``oversample`` q > 1. Normalised physically
    (Parseval): its sum over the infinite plane is 1, so a window holds the energy that
    falls in it. Its gradient runs on a half-plane (a real pupil's intensity is
    centrosymmetric)."""
    inten, scale = polygon_intensities(vertices, [wavelength], z_image=z_image,
                                       pixel_pitch=pixel_pitch, shape=shape,
                                       oversample=oversample, centre=centre)
    return inten[0] * scale[0]


def _conv_offsets(crop: tuple[int, int], window: tuple[int, int]):
    """(kh, kw, r0, c0): the PSF offsets the ``crop`` needs from a ``window`` source,
    (h + hb − 1) × (w + wb − 1) centred at (kh//2, kw//2), and where the crop starts in
    the convolution's output (see :func:`conv_size`)."""
    (h, w), (hb, wb) = crop, window
    kh, kw = h + hb - 1, w + wb - 1
    return kh, kw, kh // 2 + hb // 2 - h // 2, kw // 2 + wb // 2 - w // 2


def conv_size(crop: tuple[int, int], window: tuple[int, int]):
    """((nh, nw), clean): the FFT size of :func:`focused_image`'s convolution of a
    ``window`` (hb, wb) source with the PSF on a ``crop`` (h, w), and whether the PSF is
    evaluated on that whole FFT grid.

    The crop needs the PSF on kh × kw = (h + hb − 1) × (w + wb − 1) offsets. Evaluated on
    a whole n ≥ kh grid, centred at kh//2, PSF index i (offset i − kh//2) and source
    index j (offset j − hb//2) land on output index (i + j) mod n, and the crop is
    [r0, r0 + h), r0 = kh//2 + hb//2 − h//2. A wrapped pair (i + j ≥ n) lands below
    i + j − n < hb − 1 ≤ r0, and an unneeded PSF index (i ≥ kh) on [kh, n) ∪ [0, hb − 1):
    outside the crop whenever r0 ≥ hb − 1 and r0 + h ≤ kh ("clean": even crops with odd
    windows), so n = kh suffices. Otherwise the PSF is zero-padded and the convolution
    made linear: n ≥ kh + hb − 1."""

    (h, w), (hb, wb) = crop, window
    kh, kw, r0, c0 = _conv_offsets(crop, window)
    clean = r0 >= hb - 1 and r0 + h <= kh and c0 >= wb - 1 and c0 + w <= kw
    if clean:
        return (fast_length(kh), fast_length(kw)), True
    return (fast_length(kh + hb - 1), fast_length(kw + wb - 1)), False


def window_rfft2(b, shape: tuple[int, int]):
    """``jnp.fft.rfft2(b, s=shape)`` of a small window ``b`` (…, hb, wb): the row
    transforms run only over its hb rows (the zero rows transform to zero)."""
    return jnp.fft.fft(jnp.fft.rfft(b, n=shape[1], axis=-1), n=shape[0], axis=-2)


def focused_image(
    vertices: Float[Array, "n 2"],
    b: Float[Array, "3 hb wb"],
    wavelengths: Float[Array, 3],
    *,
    z_image,
    pixel_pitch: float,
    crop: tuple[int, int],
    oversample: int = 1,
) -> tuple[Array, Array]:
    """Linear image (3, h, w) of an in-focus scene on the ``crop``, and the PSFs on it.

    ``b`` is the geometric image on an (hb, wb) grid centred like the crop (odd sizes
    hold a source centred on the crop's centre pixel); every source pixel reaches every
    crop pixel through the exact PSF, and nothing wraps onto the crop: the PSF is
    evaluated on the whole FFT grid of :func:`conv_size` (at least the
    (h + hb − 1) × (w + wb − 1) offsets the crop needs; where that cannot keep wrapped
    terms off the crop, on exactly those offsets, zero-padded to a linear convolution).
    """
    h, w = crop
    hb, wb = b.shape[-2:]
    (nh, nw), clean = conv_size(crop, (hb, wb))
    kh, kw, r0, c0 = _conv_offsets(crop, (hb, wb))  # PSF offsets, centred at (kh//2, kw//2)
    b_ft = window_rfft2(b, (nh, nw))  # once for all channels

    def intensities(shape, centre):
        return polygon_intensities(vertices, [wavelengths[c] for c in range(b.shape[0])],
                                   z_image=z_image, pixel_pitch=pixel_pitch, shape=shape,
                                   oversample=oversample, centre=centre)

    if clean:
        # The PSF on the whole (nh, nw) FFT grid, centred at (kh//2, kw//2): indices
        # beyond the kh × kw offsets the crop needs wrap only onto output indices outside
        # the crop, so they need no zeroing and the transform needs no zero padding
        inten, scale = intensities((nh, nw), (kh // 2, kw // 2))
        p_ft = jnp.fft.rfft2(inten)
    else:  # (odd crops or even source windows) zero-pad instead
        inten, scale = intensities((kh, kw), None)
        p_ft = jnp.fft.rfft2(inten, s=(nh, nw))
    # the PSF's scale applied to the source's transform (the smaller array)
    full = jnp.fft.irfft2(p_ft * (b_ft * scale[:, None, None]), s=(nh, nw))
    # the crop of the PSFs, taken apart (see _xla.stored): as a plain slice beside the FFT, XLA
    # would evaluate the closed form for it a second time
    i0, j0 = kh // 2 - h // 2, kw // 2 - w // 2
    psfs = stored(lambda a: a[0][..., i0 : i0 + h, j0 : j0 + w] * a[1][:, None, None],
                  (inten, scale), jnp.sum(vertices))
    return psfs, full[:, r0 : r0 + h, c0 : c0 + w]

