"""The PSF engine behind :func:`difstar.psf`: one plan, two exact methods, nothing folded in.

Given the pupil, wavelength, z_R (exit pupil to sensor), Δz, the pixel pitch, the window
and an accuracy target, :func:`plan_psf` decides (outside jit, on concrete values) how the
window is computed, and :func:`evaluate` computes it (pure, jittable, differentiable):

``"exact"`` — in focus, polygonal pupils, no wavefront error: the closed-form transform of
    the polygon (Lee & Mittra; :mod:`._mft`) at exactly the points needed. No grid, no
    period, no aliasing.
``"mft"`` / ``"fft"`` — everything else: the pupil (area coverage × the phase of defocus and of any
    wavefront error, averaged over each cell's covered part on ``subcells`` × ``subcells``
    sub-cells) on a square frequency grid of spacing 1/L, transformed by a matrix DFT to
    exactly the points needed. The field is periodic with period L (the pupil is sampled),
    so L is chosen so that its copies do not reach the window to the accuracy target;
    the window itself is never a period, unlike an FFT on a grid of the window's size.
    For large windows the same transform runs as pruned FFTs of length L/p ("fft": the
    pupil's rows first, then only the window's columns; sub-pixel nodes are phase
    ramps), which the plan picks where it costs less.

The points needed: the pixel centres (``sampling="point"``) or, for the integral of the
intensity over each pixel's square (``sampling="pixel"``, fill factor 1), ``nodes`` ×
``nodes`` Gauss–Legendre nodes per pixel; the intensity is band-limited (its spectrum, the
OTF, vanishes beyond 2 r/(λ z_R)), so the rule's error is bounded by that of one
exponential at the band edge, and ``nodes`` is the fewest that meet the target.

Every value is the fraction of the power through the pupil that lands on the pixel
(summed over the infinite plane it is 1): the point value is the intensity at the
centre times the pixel's area, the pixel value the intensity's integral over the pixel.

Conventions: rows run down, y up: row k at y = −(k − H//2)·p, column k at x = (k − W//2)·p.
The field is U(x) ∝ ∫ P(ξ) e^{i k W(ξ)} e^{+2πi x·ξ/(λ z_R)} dξ with W = ½(1/z_i − 1/z_R)|ξ|²
+ the wavefront's OPD: beyond focus (Δz > 0) the geometric blur is the pupil turned by
180°, as rays that crossed the axis draw it.
"""

from __future__ import annotations

import math
from functools import cache

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._atf import defocus_phase_coefficient, intensity_bandwidth, pupil_scale
from ._custom_types import Array, Float
from ._fft_size import fast_length
from ._mft import _area, _intensity_plain
from ._xla import stored


class SamplingError(ValueError):
    """The requested grid cannot represent the PSF; the message names the rule and a fix."""


#: Default accuracy target of :func:`difstar.psf`: relative RMS error over the window.
DEFAULT_ACCURACY = 1e-3

METHODS = ("exact", "mft", "fft")
SAMPLINGS = ("pixel", "point")

# Calibration of the period (tests/test_psf_truths.py and BENCHMARKS.md measure the
# result): the copies of the field sit L apart; the area-coverage cell correction leaves
# each attenuated by about |x|/L near the window, so the fold-in error on a window of
# extent E falls as (E/L)². L = E (1 + guard) with guard = _GUARD_A / sqrt(accuracy).
_GUARD_A = 0.05
_MIN_GUARD = 0.5
# Largest phase step (radians, along a diagonal) across one sub-cell: the covered part's
# phase average carries an error growing as the square of the step (measured on a circle
# at f/8: 1.3e-3 at 0.42 rad, 3.4e-4 at 0.21, 9e-5 at 0.11), so 0.22 rad keeps it a
# third of a 1e-3 target on a pupil of 230 samples across.
_STEP_A = 0.22
_STEP_REF_SAMPLES = 230
_MIN_PUPIL_SAMPLES = 48


class PSFPlan(eqx.Module):
    """How :func:`evaluate` computes a window (all static; :func:`plan_psf` makes it).

    method: "exact" or "mft". nodes: Gauss–Legendre nodes per pixel a side (1: the pixel
    centre). period: L, metres in the image plane (mft). pupil_window: samples a side of
    the frequency grid holding the pupil at the shortest wavelength (mft). subcells:
    sub-cells a side over which each cell's phase is averaged (mft). use_defocus: whether
    the defocus phase is computed.
    """

    method: str = eqx.field(static=True)
    nodes: int = eqx.field(static=True, default=1)
    period: float = eqx.field(static=True, default=0.0)
    pupil_window: int = eqx.field(static=True, default=0)
    subcells: int = eqx.field(static=True, default=1)
    use_defocus: bool = eqx.field(static=True, default=False)

    def __check_init__(self):
        if self.method not in METHODS:
            raise ValueError(f"PSFPlan.method must be one of {METHODS}; got {self.method!r}.")
        if self.method != "exact" and not (self.period > 0 and self.pupil_window >= 4):
            raise ValueError(f"PSFPlan: method {self.method!r} needs period > 0 and "
                             "pupil_window >= 4.")


# --- pixel integration --------------------------------------------------------------------


@cache
def gauss_legendre(m: int) -> tuple[np.ndarray, np.ndarray]:
    """Nodes in (−½, ½) and weights summing to 1: the mean over one pixel a side."""
    x, w = np.polynomial.legendre.leggauss(int(m))
    return 0.5 * x, 0.5 * w


def nodes_for(bandwidth_cycles_per_pixel: float, accuracy: float) -> int:
    """Fewest Gauss–Legendre nodes a side whose error on exp(2πi ν x) over a pixel, for
    every |ν| up to the intensity's bandwidth (cycles per pixel), is below ``accuracy``/10.
    The intensity is a superposition of such exponentials (its OTF), so that bounds the
    error of its pixel integral relative to the OTF's total."""
    nu = abs(float(bandwidth_cycles_per_pixel))
    freqs = np.linspace(0.0, nu, 64)
    for m in range(1, 64):
        x, w = gauss_legendre(m)
        err = np.max(np.abs(np.exp(2j * np.pi * freqs[:, None] * x[None, :]) @ w
                            - np.sinc(freqs)))
        if err <= accuracy / 10:
            return m
    return 64


# --- planning -------------------------------------------------------------------------------


def defocus_blur(radius: float, z_image: float, defocus: float) -> float:
    """The geometric blur's diameter on the sensor (metres) of a pupil of ``radius``,
    ``z_image`` from the sensor, with the sensor ``defocus`` behind the in-focus plane:
    2 r |Δz| / |z_R − Δz|. A plan's period holds the window plus this blur."""
    return 2 * radius * abs(defocus) / abs(z_image - defocus) if z_image != defocus \
        else math.inf


def _guard(accuracy: float) -> float:
    return max(_MIN_GUARD, _GUARD_A / math.sqrt(accuracy))


def plan_psf(
    *,
    pupil_radius: float,
    wavelengths,
    z_image: float,
    defocus: float,
    pixel_pitch: float,
    shape: tuple[int, int],
    sampling: str,
    accuracy: float,
    exact_ok: bool,
    wavefront_slope: float = 0.0,
    scaling: str = "fresnel",
    method: str | None = None,
    period: float | None = None,
) -> PSFPlan:
    """The plan for a window (concrete numbers; see the module's docstring).

    ``exact_ok``: the pupil is a polygon and there is no wavefront error.
    ``wavefront_slope``: the largest slope |∇OPD| of the wavefront error over the pupil
    (metres per metre; 0 without one), for the sub-cell rule.
    ``period``: L chosen by the caller (metres; a whole number of pixels for "fft"), in
    place of the guard rule's: ``choose_grid``'s ``n`` or ``padding``, the grid the
    paper's method transforms. The sub-cells still follow the accuracy.
    """
    lams = [float(v) for v in np.atleast_1d(np.asarray(wavelengths, float))]
    lam_min = min(lams)
    r, z_r, dz, p = float(pupil_radius), float(z_image), float(defocus), float(pixel_pitch)
    h, w = (int(s) for s in shape)
    scale_min = float(pupil_scale(lam_min, z_r, dz, scaling))
    nodes = 1 if sampling == "point" else nodes_for(
        intensity_bandwidth(r, lam_min, z_r, dz, p, scaling), accuracy)
    # defocus phase at the pupil's edge (radians): model it only where it matters
    peak = max(abs(defocus_phase_coefficient(lam, z_r, dz, scaling))
               * (r / float(pupil_scale(lam, z_r, dz, scaling))) ** 2 for lam in lams)
    use_defocus = peak > 0.1 * accuracy
    if method is None and exact_ok and not use_defocus and wavefront_slope == 0:
        method = "exact"
    if method == "exact":
        if not exact_ok or use_defocus:
            raise ValueError(
                "difstar.psf: method='exact' needs a Polygon or RegularPolygon pupil, no "
                f"wavefront and no defocus (this one has {peak:.3g} rad at the pupil edge); "
                "use method='mft' or leave method unset.")
        return PSFPlan("exact", nodes=nodes)
    if method not in (None, "mft", "fft"):
        raise ValueError(f"difstar.psf: method must be one of {METHODS} or None; got {method!r}.")
    # period: the window, the geometric blur and the guard against the copies
    extent = max(h, w) * p
    blur = defocus_blur(r, z_r, dz) if use_defocus else 0.0
    given = period is not None
    if not given:
        period = extent * (1 + _guard(accuracy)) + blur
        scale_max = max(float(pupil_scale(lam, z_r, dz, scaling)) for lam in lams)
        # enough samples across the pupil at the longest wavelength (its fewest)
        period = max(period, _MIN_PUPIL_SAMPLES * scale_max / (2 * r))
    elif not (math.isfinite(period) and period > 0):
        raise ValueError(f"plan_psf: period must be a finite length > 0; got {period!r}.")
    m = math.ceil(2 * r * period / scale_min) + 4
    m += m % 2
    if method is None:
        method = "fft" if _fft_cost(m, h, w, nodes, period / p) < _mft_cost(m, h, w, nodes) \
            else "mft"
    if method == "fft" and not given:
        period = fast_length(math.ceil(period / p)) * p  # a whole number of pixels
        m = math.ceil(2 * r * period / scale_min) + 4
        m += m % 2
    df = 1.0 / period
    # phase step across one cell at the pupil's edge: defocus 2 c f_edge df, wavefront
    # |∇φ| × the cell's size in the pupil (diagonally: √2)
    step = 0.0
    for lam in lams:
        sc = float(pupil_scale(lam, z_r, dz, scaling))
        c = abs(defocus_phase_coefficient(lam, z_r, dz, scaling)) if use_defocus else 0.0
        step = max(step, math.sqrt(2) * (2 * c * (r / sc) * df
                                         + 2 * math.pi / lam * wavefront_slope * sc * df))
    # the error comes from the edge cells, whose share of the pupil falls as 1/M
    sub_step = _STEP_A * math.sqrt(accuracy / 1e-3 * m / _STEP_REF_SAMPLES)
    subcells = max(1, math.ceil(step / sub_step))
    return PSFPlan(method, nodes=nodes, period=period, pupil_window=m, subcells=subcells,
                   use_defocus=use_defocus)


def _mft_cost(m, h, w, nodes):
    """Relative cost of the matrix DFT (complex multiply-adds)."""
    hn, wn = h * nodes, w * nodes
    return min(m * m * wn + m * wn * hn, m * m * hn + m * hn * wn)


def _fft_cost(m, h, w, nodes, n):
    """Relative cost of the pruned FFTs, in the matrix DFT's units (an FFT's flop runs
    about 4× slower than a matrix product's on a CPU)."""
    n = max(float(n), 2.0)
    return 4 * 0.6 * n * math.log2(n) * (nodes * m + nodes * nodes * w)


# --- evaluation -----------------------------------------------------------------------------


def _node_positions(nodes: int) -> np.ndarray:
    """Where a pixel is sampled, in pixels from its centre: its centre, or its nodes."""
    return gauss_legendre(nodes)[0] if nodes > 1 else np.zeros(1)


def _offsets(n: int, nodes: int) -> np.ndarray:
    """Pixel offsets from the centre pixel (n//2) of every node, (n·nodes,), ascending."""
    return ((np.arange(n) - n // 2)[:, None] + _node_positions(nodes)[None, :]).ravel()


def _cell_centres(count: int, step: float) -> Array:
    """Centres of ``count`` cells of size ``step`` about 0, ascending."""
    return jnp.asarray((np.arange(count) - (count - 1) / 2) * step)


def _integrate(values: Array, shape: tuple[int, int], nodes: int) -> Array:
    """Weighted mean of each pixel's nodes: (…, H·m, W·m) → (…, H, W)."""
    if nodes == 1:
        return values
    h, w = shape
    _, wt = gauss_legendre(nodes)
    wt = jnp.asarray(wt, values.dtype)
    v = values.reshape(*values.shape[:-2], h, nodes, w, nodes)
    return jnp.einsum("...aibj,i,j->...ab", v, wt, wt)


def exact_window(vertices, wavelength, *, z_image, pixel_pitch, shape, nodes) -> Array:
    """In-focus polygon: fraction of power per pixel (point or Gauss–Legendre mean × p²).

    Dimensionless: the pupil is scaled by β = 2π p/(λ z_R) and the offsets are in
    pixels, so |A(k)|²·p²/((λz)² area) = |A_β(offset)|²/(4π² area_β)."""
    h, w = shape
    beta = (2 * math.pi * pixel_pitch) / (wavelength * z_image)
    wv = vertices * beta
    u = jnp.asarray(_offsets(w, nodes), wv.dtype)
    t = jnp.asarray(-_offsets(h, nodes), wv.dtype)  # rows run along −y
    inten = _intensity_plain(wv, u, t)
    return _integrate(inten, shape, nodes) / (4 * math.pi**2 * _area(wv))


def _subcell_atf(pupil, wavefront, wavelength, z_image, defocus, scaling, plan: PSFPlan):
    """The pupil's cell averages of P e^{iφ} on the plan's M × M frequency window, (M, M)
    complex, rows along +y, and the pupil's energy Σ|P|² (in cells).

    Each cell is split into s × s sub-cells: coverage × the phase at the sub-cell's centre
    × the sinc of the defocus phase's gradient over it (the sub-cell's average of a
    locally linear phase), then averaged. The coverage sums exactly to the cell's."""
    cov = _subcell_coverage(pupil, wavelength, z_image, defocus, scaling, plan)
    return _atf_of_coverage(cov, wavefront, wavelength, z_image, defocus, scaling, plan)


def _subcell_grid(wavelength, z_image, defocus, scaling, plan: PSFPlan):
    """The sub-cells' centres: frequencies f (M·s,) and pupil coordinates x = scale·f, and
    a sub-cell's side in the pupil."""
    m, s = plan.pupil_window, plan.subcells
    df = 1.0 / plan.period
    scale = pupil_scale(wavelength, z_image, defocus, scaling)
    f = _cell_centres(m * s, df / s)  # sub-cell centres
    return f, scale * f, scale * (df / s)


def _subcell_coverage(pupil, wavelength, z_image, defocus, scaling, plan: PSFPlan):
    """The pupil's coverage of each sub-cell, (M·s, M·s), rows along +y."""
    _, xs, cell = _subcell_grid(wavelength, z_image, defocus, scaling, plan)
    return pupil.tiled_coverage(xs[None, :], xs[:, None], cell)


def _atf_of_coverage(cov, wavefront, wavelength, z_image, defocus, scaling, plan: PSFPlan):
    """:func:`_subcell_atf` from the sub-cells' coverage ``cov``."""
    m, s = plan.pupil_window, plan.subcells
    df = 1.0 / plan.period
    f, xs, _ = _subcell_grid(wavelength, z_image, defocus, scaling, plan)
    phase_x = jnp.zeros_like(f)
    gain = jnp.ones_like(f)
    if plan.use_defocus:
        c = defocus_phase_coefficient(wavelength, z_image, defocus, scaling)
        phase_x = c * f * f
        gain = jnp.sinc(c * f * (df / s) / math.pi)
    # the defocus phase and its sinc are separable: e^{iφ(x)} e^{iφ(y)}, M exponentials a
    # side, stored (fused into the M × M product, XLA would evaluate M² of them)
    side = stored(lambda a: a[0] * jnp.exp(1j * a[1]), (gain, phase_x), phase_x[-1])
    amp = cov * (side[:, None] * side[None, :])
    if wavefront is not None:
        amp = amp * jnp.exp(1j * (2 * math.pi / wavelength)
                            * wavefront.opd(xs[None, :], xs[:, None]))
    if s > 1:
        amp = amp.reshape(m, s, m, s).mean(axis=(1, 3))
    energy = jnp.sum(cov) / (s * s)
    return amp, energy


def _fraction_of_power(inten: Array, energy, *, pixel_pitch, shape, plan: PSFPlan) -> Array:
    """|Σ H e|² at every node, (H·m, W·m) laid out as :func:`_offsets`, to the fraction of
    the pupil's power per pixel: the cell correction, the pixel rule, the normalisation."""
    h, w = shape
    L = plan.period
    # the cell correction: the coverage is the pupil convolved with one cell, whose
    # transform, sinc(x/L) sinc(y/L), divides out exactly from the principal term
    cx = jnp.asarray(np.sinc(_offsets(w, plan.nodes) * pixel_pitch / L) ** 2)
    cy = jnp.asarray(np.sinc(_offsets(h, plan.nodes) * pixel_pitch / L) ** 2)
    inten = inten / (cy[:, None] * cx[None, :])
    # density |Σ H e|² / (L² energy) per m²; × p² per pixel
    return _integrate(inten, shape, plan.nodes) * ((pixel_pitch / L) ** 2 / energy)


def _mft_transform(amp, energy, *, pixel_pitch, shape, plan: PSFPlan) -> Array:
    """Fraction of power per pixel by a matrix DFT (see module) from the pupil's sampled
    transfer ``amp`` and its ``energy`` (:func:`_subcell_atf`)."""
    h, w = shape
    m = plan.pupil_window
    L = plan.period
    df = 1.0 / L
    f = _cell_centres(m, df)
    x = _offsets(w, plan.nodes) * pixel_pitch  # metres
    y = -_offsets(h, plan.nodes) * pixel_pitch  # rows run along −y
    ex = jnp.exp(2j * math.pi * f[:, None] * jnp.asarray(x)[None, :])  # (m, W·n)
    ey = jnp.exp(2j * math.pi * jnp.asarray(y)[:, None] * f[None, :])  # (H·n, m)
    # smaller intermediate first: (H·n, m) @ (m, m) @ (m, W·n)
    if h >= w:
        field = ey @ (amp @ ex)
    else:
        field = (ey @ amp) @ ex
    inten = jnp.real(field) ** 2 + jnp.imag(field) ** 2
    return _fraction_of_power(inten, energy, pixel_pitch=pixel_pitch, shape=shape, plan=plan)


def _fold(a: Array, n: int) -> Array:
    """``a`` (…, m) folded onto n samples along its last axis: at the pixel centres
    (x = k p) frequencies n/L = 1/p apart are the same, so a pupil wider than the DFT's
    frequency range adds onto it instead of being cut off (undersampled pixels)."""
    m = a.shape[-1]
    if m <= n:
        return a
    k = -(-m // n)
    a = jnp.pad(a, [(0, 0)] * (a.ndim - 1) + [(0, k * n - m)])
    return a.reshape(*a.shape[:-1], k, n).sum(axis=-2)


def _first(a: Array, count: int) -> Array:
    """The first ``count`` samples of ``a``'s last axis, periodic (its length n): a slice
    where count ≤ n, else the period repeated (a window wider than the period)."""
    n = a.shape[-1]
    return a[..., :count] if count <= n else a[..., np.arange(count) % n]


#: Bytes of one block of the FFT passes' rows (each n samples long, at every node): the
#: passes run block by block, so that a block's transforms stay in the processor's cache.
#: On the paper's defocused 1250² window (rows of 3375 samples) blocks of 128 rows run the
#: passes 1.5× faster than all 986 or 1250 rows at once (54 → 36 ms on 2 cores).
FFT_BLOCK_BYTES = 4 * 2**20


def _row_blocks(fn, x: Array, n: int, nodes: int) -> Array:
    """``fn`` applied to ``x`` (j, R, C) a block of its R rows at a time, (j, b, C) →
    (nodes, b, O), and the results joined: (nodes, R, O). Blocks hold about
    :data:`FFT_BLOCK_BYTES` of ``nodes`` n-long complex rows; the rows are padded with
    zeros to a whole number of blocks (one program body) and the padding cut off."""
    rows = x.shape[-2]
    itemsize = jnp.dtype(jnp.result_type(x.dtype, jnp.complex64)).itemsize
    per_block = max(8, FFT_BLOCK_BYTES // (nodes * n * itemsize))
    if rows <= per_block:
        return fn(x)
    count = -(-rows // per_block)
    b = -(-rows // count)
    x = jnp.pad(x, ((0, 0), (0, count * b - rows), (0, 0)))
    blocks = jnp.swapaxes(x.reshape(x.shape[0], count, b, x.shape[-1]), 0, 1)
    out = jax.lax.map(fn, blocks)  # (count, nodes, b, O)
    return jnp.swapaxes(out, 0, 1).reshape(out.shape[1], count * b, -1)[:, :rows]


def _fft_transform(amp, energy, *, pixel_pitch, shape, plan: PSFPlan) -> Array:
    """As :func:`_mft_transform`, by pruned FFTs of length n = L/p: the field at the pixel
    centres is the n-point inverse DFT of the pupil window (zero beyond it; frequencies
    offset by half a sample change the field only by a unimodular factor), along the
    pupil's rows first, keeping the window's columns, then along those columns, keeping
    its rows. Sub-pixel nodes shift the output by phase ramps on the pupil."""
    h, w = shape
    m = plan.pupil_window
    L = plan.period
    n = int(round(L / pixel_pitch))
    df = 1.0 / L
    f = _cell_centres(m, df)
    xg = _node_positions(plan.nodes)
    k = len(xg)
    # the window's columns x = (c − W//2) p and rows y = −(r − H//2) p, c, r = 0, 1, …,
    # are the transforms' first W and H outputs: the inverse DFT's outputs moved by W//2
    # (a phase ramp on its inputs) and the forward DFT's (outputs at −k) moved by H//2;
    # a slice of them, not a gather (a third of each pass's time)
    j = np.arange(m)
    to_cols = np.exp(-2j * np.pi * j * (w // 2) / n)
    to_rows = np.exp(2j * np.pi * j * (h // 2) / n)
    # first pass, all column nodes at once (x offset b p: a phase ramp on the pupil's
    # rows), keeping the window's columns: (k, m, W)
    ramp_x = jnp.exp(2j * math.pi * jnp.asarray(xg)[:, None] * pixel_pitch * f[None, :]) \
        * jnp.asarray(to_cols)
    firsts = _row_blocks(
        lambda rows: _first(jnp.fft.ifft(_fold(rows * ramp_x[:, None, :], n), n=n, axis=-1), w),
        amp[None], n, k) * n
    firsts_t = jnp.swapaxes(firsts, -1, -2)  # (k, W, m)

    def second(a):  # one row node (y offset −a p) over every column node: (k, W, H)
        ramp_y = jnp.exp(2j * math.pi * f * (-a * pixel_pitch)) * jnp.asarray(to_rows)

        def rows_of(cols):
            field_t = _first(jnp.fft.fft(_fold(cols * ramp_y, n), n=n, axis=-1), h)
            return jnp.real(field_t) ** 2 + jnp.imag(field_t) ** 2

        return _row_blocks(rows_of, firsts_t, n, k)

    # one row node at a time (lax.map): one program body, the memory of one
    inten = jax.lax.map(second, jnp.asarray(xg)) if k > 1 else second(xg[0])[None]
    # (row node, column node, W, H) → :func:`_offsets`' layout (H, row node, W, column
    # node) → (H·m, W·m)
    inten = inten.transpose(3, 0, 2, 1).reshape(h * k, w * k)
    return _fraction_of_power(inten, energy, pixel_pitch=pixel_pitch, shape=shape, plan=plan)


def evaluate(pupil, wavelength, *, z_image, defocus, pixel_pitch, shape, scaling,
             wavefront, plan: PSFPlan) -> Float[Array, "h w"]:
    """One wavelength's window, fraction of power per pixel, by the plan's method."""
    if plan.method == "exact":
        return exact_window(pupil.vertices, wavelength, z_image=z_image,
                            pixel_pitch=pixel_pitch, shape=shape, nodes=plan.nodes)
    amp, energy = _subcell_atf(pupil, wavefront, wavelength, z_image, defocus, scaling, plan)
    return _transform(plan)(amp, energy, pixel_pitch=pixel_pitch, shape=shape, plan=plan)


def _transform(plan: PSFPlan):
    """The transform of a sampled pupil's plan: pruned FFTs or the matrix DFT."""
    return _fft_transform if plan.method == "fft" else _mft_transform


def evaluate_each(pupil, wavelengths, *, z_image, defocus, pixel_pitch, shape, scaling,
                  wavefront, plan: PSFPlan) -> Float[Array, "c h w"]:
    """One window per wavelength of ``wavelengths`` (C,), each as :func:`evaluate` gives
    it (not weighted together). The pupil's coverage of every wavelength's grid is made at
    once (the raster vmapped over the wavelengths: one trace and one compiled body of its
    many small operations instead of C), then each wavelength's phases and transform."""
    if plan.method == "exact":
        return jnp.stack([evaluate(pupil, lam, z_image=z_image, defocus=defocus,
                                   pixel_pitch=pixel_pitch, shape=shape, scaling=scaling,
                                   wavefront=wavefront, plan=plan) for lam in wavelengths])
    # only the coverage vectorised: under vmap the defocus phase's barrier (_xla.stored)
    # would become a select, and its exponentials be evaluated M² times (2-2.5x slower)
    covs = jax.vmap(lambda lam: _subcell_coverage(pupil, lam, z_image, defocus, scaling,
                                                  plan))(wavelengths)
    transform = _transform(plan)

    def one(cov_lam):
        cov, lam = cov_lam
        amp, energy = _atf_of_coverage(cov, wavefront, lam, z_image, defocus, scaling, plan)
        return transform(amp, energy, pixel_pitch=pixel_pitch, shape=shape, plan=plan)

    # a loop, not unrolled: one compiled body for the wavelengths (a RAW fit's step
    # compiled about 0.3 s sooner), and not vmapped (see above)
    return jax.lax.map(one, (covs, wavelengths))
