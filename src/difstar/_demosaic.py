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

from ._cfa import bayer_masks_np, check_pattern
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


def _convolve_reflect(x: Float[Array, "c h w"], kernels: np.ndarray) -> Float[Array, "c h w"]:
    """Channel c convolved with kernels[c] (true convolution, odd square kernels), borders
    as scipy.ndimage.convolve(mode="reflect")."""
    r = kernels.shape[-1] // 2
    h, w = x.shape[-2:]
    xp = jnp.pad(x, ((0, 0), (r, r), (r, r)), mode="symmetric")
    # A sum of shifted slices, one per non-zero tap (XLA fuses it into one pass; its CPU
    # grouped convolution ran ~10× slower). Convolution: out[y] = Σ_t k[t] x[y − t], so
    # tap (i, j) of the kernel reads the padded input at offset (2r − i, 2r − j).
    out = None
    for i in range(2 * r + 1):
        for j in range(2 * r + 1):
            k = kernels[:, i, j]
            if not np.any(k):
                continue
            term = jnp.asarray(k, x.dtype)[:, None, None] * xp[:, 2 * r - i : 2 * r - i + h,
                                                               2 * r - j : 2 * r - j + w]
            out = term if out is None else out + term
    return out


def _check_cfa(cfa) -> None:
    if cfa.ndim != 2 or cfa.shape[0] < 2 or cfa.shape[1] < 2:
        raise ValueError(f"cfa must be a 2-D mosaic of at least 2×2 pixels, got shape {cfa.shape}")


def demosaic_bilinear(cfa: Float[Array, "h w"], pattern: str) -> Float[Array, "3 h w"]:
    """Bilinear demosaic of a Bayer mosaic → (3, h, w) RGB in the units of ``cfa``."""
    _check_cfa(cfa)
    masks = jnp.asarray(bayer_masks_np(cfa.shape, pattern), dtype=cfa.dtype)
    return _convolve_reflect(cfa[None] * masks, np.stack([_H_RB, _H_G, _H_RB]))


def demosaic_malvar2004(cfa: Float[Array, "h w"], pattern: str) -> Float[Array, "3 h w"]:
    """Malvar–He–Cutler (2004) gradient-corrected bilinear demosaic → (3, h, w) RGB.

    Not clipped: the 5×5 kernels have negative taps, so values may leave [0, 1] near
    edges of bright features.
    """
    _check_cfa(cfa)
    r_m, g_m, b_m = bayer_masks_np(cfa.shape, pattern).astype(bool)
    filt = _convolve_reflect(
        jnp.broadcast_to(cfa, (4, *cfa.shape)),
        np.stack([_GR_GB, _RG_RB_BG_BR, _RG_BR_BG_RB, _RB_BB_BR_RR]),
    )
    g_at_rb, rb_g_rbbr, rb_g_brrb, rb_at_br = filt[0], filt[1], filt[2], filt[3]

    # Rows/columns holding R or B pixels, built exactly as colour-demosaicing does.
    r_rows = np.broadcast_to(np.any(r_m, axis=1)[:, None], cfa.shape)
    r_cols = np.broadcast_to(np.any(r_m, axis=0)[None, :], cfa.shape)
    b_rows = np.broadcast_to(np.any(b_m, axis=1)[:, None], cfa.shape)
    b_cols = np.broadcast_to(np.any(b_m, axis=0)[None, :], cfa.shape)

    zero = jnp.zeros_like(cfa)
    r = jnp.where(r_m, cfa, zero)
    g = jnp.where(g_m, cfa, zero)
    b = jnp.where(b_m, cfa, zero)

    g = jnp.where(r_m | b_m, g_at_rb, g)
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
