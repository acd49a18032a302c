"""Bayer colour filter array: masks, mosaic of an RGB image, white balance on the mosaic.

Conventions: arrays are indexed [row, col]; an RGB stack is channel-first (3, h, w) with
channels (R, G, B) = (0, 1, 2). A pattern string names the colours of the 2×2 tile read
row by row from pixel (0, 0), as rawpy/libraw and colour-demosaicing do: for "RGGB",
pixel (0, 0) is R, (0, 1) and (1, 0) are G, (1, 1) is B.

The pattern fixes array layouts, so it is a static Python string (close over it or mark
it static under ``jax.jit``); the masks are built with NumPy at trace time.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ._custom_types import Array, ArrayLike, Float

PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")
_CHANNEL = {"R": 0, "G": 1, "B": 2}


def check_pattern(pattern: str) -> str:
    """Return ``pattern`` if it is one of :data:`PATTERNS`, else raise a ValueError."""
    if not isinstance(pattern, str) or pattern not in PATTERNS:
        raise ValueError(f"pattern must be one of {PATTERNS} (a static string), got {pattern!r}")
    return pattern


def channel_index(shape: tuple[int, int], pattern: str) -> np.ndarray:
    """NumPy int array (h, w): the channel (0 R, 1 G, 2 B) of each pixel of the mosaic."""
    check_pattern(pattern)
    h, w = (int(s) for s in shape)
    tile = np.array([[_CHANNEL[pattern[0]], _CHANNEL[pattern[1]]],
                     [_CHANNEL[pattern[2]], _CHANNEL[pattern[3]]]])
    rows = np.arange(h) % 2
    cols = np.arange(w) % 2
    return tile[rows[:, None], cols[None, :]]


def bayer_masks_np(shape: tuple[int, int], pattern: str) -> np.ndarray:
    """NumPy float64 (3, h, w) 0/1 masks (R, G, B); the trace-time twin of
    :func:`bayer_masks`."""
    idx = channel_index(shape, pattern)
    return (idx[None] == np.arange(3)[:, None, None]).astype(np.float64)


def bayer_masks(shape: tuple[int, int], pattern: str) -> Float[Array, "3 h w"]:
    """0/1 masks of the R, G and B pixels of a Bayer mosaic of ``shape`` = (h, w).

    Exactly one mask is 1 at each pixel. ``pattern`` is one of "RGGB", "BGGR", "GRBG",
    "GBRG" (static). Returned in the default float dtype.
    """
    return jnp.asarray(bayer_masks_np(shape, pattern), dtype=float)


def mosaic(rgb: Float[Array, "3 h w"], pattern: str) -> Float[Array, "h w"]:
    """Bayer mosaic of a channel-first RGB image: each pixel keeps its own channel.

    Units are those of ``rgb`` (for difstar, normalised raw values ζ in [0, 1]).
    Differentiable: the gradient flows to the picked channel only.
    """
    # selected by the pixel's row and column parity (iotas that XLA fuses), not by
    # constant masks or take_along_axis: constant (h, w) masks are read from memory on
    # every call, and take_along_axis's transpose is a scatter-add XLA folds slowly
    return _by_site(shape=rgb.shape[1:], pattern=pattern, pick=lambda c: rgb[c])


def _parity(shape: tuple[int, int]):
    """(row % 2, column % 2) as int32 (h, w) iotas."""
    rows = jax.lax.broadcasted_iota(jnp.int32, tuple(shape), 0) % 2
    cols = jax.lax.broadcasted_iota(jnp.int32, tuple(shape), 1) % 2
    return rows, cols


def _by_site(*, shape, pattern: str, pick):
    """An (h, w) array whose pixel takes ``pick(c)`` (broadcastable to (h, w)) for its
    own channel c (0 R, 1 G, 2 B) of the Bayer ``pattern``."""
    check_pattern(pattern)
    rows, cols = _parity(shape)
    ch = [_CHANNEL[x] for x in pattern]  # the 2×2 tile, row by row
    top = jnp.where(cols == 0, pick(ch[0]), pick(ch[1]))
    bottom = jnp.where(cols == 0, pick(ch[2]), pick(ch[3]))
    return jnp.where(rows == 0, top, bottom)


def white_balance(
    cfa: Float[Array, "h w"], gains: Float[ArrayLike, "3"], pattern: str
) -> Float[Array, "h w"]:
    """Multiply each pixel of a Bayer mosaic by its channel's gain (R, G, B).

    ``gains`` are dimensionless multipliers (as in a RAW file's as-shot white balance,
    usually normalised to G = 1). No clipping is done here.
    """
    gains = jnp.asarray(gains)
    if gains.shape != (3,):
        raise ValueError(f"gains must have shape (3,) for (R, G, B), got {gains.shape}")
    return cfa * _by_site(shape=cfa.shape, pattern=pattern, pick=lambda c: gains[c])


__all__ = ["PATTERNS", "bayer_masks", "mosaic", "white_balance"]
