"""Demosaicing of a Bayer mosaic: bilinear and Malvar–He–Cutler (2004).

Both follow colour-demosaicing's ``demosaicing_CFA_Bayer_bilinear`` and
``demosaicing_CFA_Bayer_Malvar2004`` exactly, borders included: those filter with
``scipy.ndimage.convolve`` in its default mode "reflect" (half-sample symmetric,
``d c b a | a b c d | d c b a``), which is ``jnp.pad(mode="symmetric")`` here. The
output is channel-first (3, h, w) (colour-demosaicing returns (h, w, 3)) and is not
clipped. The pattern is static (see :mod:`difstar._cfa`).

The filters are linear in the mosaic, so gradients are exact and finite everywhere.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ._cfa import _parity, check_pattern
from ._custom_types import Array, Float

METHODS = ("malvar2004", "bilinear")

# Bilinear kernels (Losson et al. 2010), as in colour-demosaicing.
_H_G = np.array([[0, 1, 0], [1, 4, 1], [0, 1, 0]], float) / 4
_H_RB = np.array([[1, 2, 1], [2, 4, 2], [1, 2, 1]], float) / 4

# Malvar, He & Cutler (2004) kernels, as in colour-demosaicing.
_GR_GB = np.array(
    [[0, 0, -1, 0, 0], [0, 0, 2, 0, 0], [-1, 2, 4, 2, -1], [0, 0, 2, 0, 0], [0, 0, -1, 0, 0]],
    float,
) / 8
_RG_RB_BG_BR = np.array(
    [[0, 0, 0.5, 0, 0], [0, -1, 0, -1, 0], [-1, 4, 5, 4, -1], [0, -1, 0, -1, 0], [0, 0, 0.5, 0, 0]],
    float,
) / 8
_RG_BR_BG_RB = _RG_RB_BG_BR.T
_RB_BB_BR_RR = np.array(
    [
        [0, 0, -1.5, 0, 0],
        [0, 2, 0, 2, 0],
        [-1.5, 0, 6, 0, -1.5],
        [0, 2, 0, 2, 0],
        [0, 0, -1.5, 0, 0],
    ],
    float,
) / 8


def _filter(xp: Array, kernel: np.ndarray, shape: tuple[int, int]) -> Array:
    """One true convolution of the padded plane(s) ``xp`` (pad r = kernel radius) by an
    odd square ``kernel``, as a sum of shifted slices over its nonzero taps only."""
    r = kernel.shape[-1] // 2
    h, w = shape
    out = None
    for i, j in zip(*np.nonzero(kernel)):
        term = float(kernel[i, j]) * xp[..., 2 * r - i : 2 * r - i + h, 2 * r - j : 2 * r - j + w]
        out = term if out is None else out + term
    return out


def _pad_reflect(x: Array, r: int) -> Array:
    """Pad the last two axes by r as scipy.ndimage's mode "reflect" (half-sample
    symmetric) does."""
    return jnp.pad(x, ((0, 0),) * (x.ndim - 2) + ((r, r), (r, r)), mode="symmetric")


def _check_cfa(cfa) -> None:
    if cfa.ndim != 2 or cfa.shape[0] < 2 or cfa.shape[1] < 2:
        raise ValueError(f"cfa must be a 2-D mosaic of at least 2×2 pixels, got shape {cfa.shape}")


def _sites(shape: tuple[int, int], pattern: str):
    """Boolean (h, w) arrays, built from iotas (no constants): R sites, B sites, rows
    holding R, columns holding R, rows holding B, columns holding B."""
    rows, cols = _parity(shape)
    r_at = pattern.index("R")
    b_at = pattern.index("B")
    r_row, r_col, b_row, b_col = r_at // 2, r_at % 2, b_at // 2, b_at % 2
    r_rows, r_cols = rows == r_row, cols == r_col
    b_rows, b_cols = rows == b_row, cols == b_col
    return r_rows & r_cols, b_rows & b_cols, r_rows, r_cols, b_rows, b_cols


def demosaic_bilinear(cfa: Float[Array, "h w"], pattern: str) -> Float[Array, "3 h w"]:
    """Bilinear demosaic of a Bayer mosaic → (3, h, w) RGB in the units of ``cfa``."""
    _check_cfa(cfa)
    check_pattern(pattern)
    r_m, b_m, *_ = _sites(cfa.shape, pattern)
    zero = jnp.zeros_like(cfa)
    planes = jnp.stack([jnp.where(r_m, cfa, zero), jnp.where(r_m | b_m, zero, cfa),
                        jnp.where(b_m, cfa, zero)])
    xp = _pad_reflect(planes, 1)
    return jnp.stack([_filter(xp[c], k, cfa.shape) for c, k in enumerate((_H_RB, _H_G, _H_RB))])


def demosaic_malvar2004(cfa: Float[Array, "h w"], pattern: str) -> Float[Array, "3 h w"]:
    """Malvar–He–Cutler (2004) gradient-corrected bilinear demosaic → (3, h, w) RGB.

    Not clipped: the 5×5 kernels have negative taps, so values may leave [0, 1] near
    edges of bright features.
    """
    _check_cfa(cfa)
    check_pattern(pattern)
    xp = _pad_reflect(cfa, 2)
    g_at_rb, rb_g_rbbr, rb_g_brrb, rb_at_br = (
        _filter(xp, k, cfa.shape) for k in (_GR_GB, _RG_RB_BG_BR, _RG_BR_BG_RB, _RB_BB_BR_RR))
    r_m, b_m, r_rows, r_cols, b_rows, b_cols = _sites(cfa.shape, pattern)

    zero = jnp.zeros_like(cfa)
    r = jnp.where(r_m, cfa, zero)
    g = jnp.where(r_m | b_m, g_at_rb, cfa)
    b = jnp.where(b_m, cfa, zero)
    r = jnp.where(r_rows & b_cols, rb_g_rbbr, r)
    r = jnp.where(b_rows & r_cols, rb_g_brrb, r)
    b = jnp.where(b_rows & r_cols, rb_g_rbbr, b)
    b = jnp.where(r_rows & b_cols, rb_g_brrb, b)
    r = jnp.where(b_rows & b_cols, rb_at_br, r)
    b = jnp.where(r_rows & r_cols, rb_at_br, b)
    return jnp.stack([r, g, b])


def demosaic(
    cfa: Float[Array, "h w"], pattern: str, *, method: str = "malvar2004"
) -> Float[Array, "3 h w"]:
    """Demosaic a Bayer mosaic with ``method`` "malvar2004" (default) or "bilinear"."""
    check_pattern(pattern)
    if method == "malvar2004":
        return demosaic_malvar2004(cfa, pattern)
    if method == "bilinear":
        return demosaic_bilinear(cfa, pattern)
    raise ValueError(f"method must be one of {METHODS}, got {method!r}")


__all__ = ["METHODS", "demosaic", "demosaic_bilinear", "demosaic_malvar2004"]
