"""Bayer masks, mosaic and white balance vs rawpy-style pattern semantics and
colour-demosaicing's mosaicing/masks."""

import inspect

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from colour_demosaicing import masks_CFA_Bayer, mosaicing_CFA_Bayer

from difstar._cfa import PATTERNS, bayer_masks, mosaic, white_balance

SHAPE = (32, 48)
# rawpy/libraw semantics: the pattern names the 2×2 tile row by row from pixel (0, 0)
TILES = {
    "RGGB": [[0, 1], [1, 2]],
    "BGGR": [[2, 1], [1, 0]],
    "GRBG": [[1, 0], [2, 1]],
    "GBRG": [[1, 2], [0, 1]],
}


@pytest.mark.parametrize("pattern", PATTERNS)
def test_masks_match_pattern_semantics(pattern):
    m = np.asarray(bayer_masks(SHAPE, pattern))
    assert m.shape == (3, *SHAPE)
    np.testing.assert_array_equal(m.sum(0), 1.0)  # exactly one channel per pixel
    tile = np.array(TILES[pattern])
    for r in range(4):
        for c in range(4):
            assert m[tile[r % 2, c % 2], r, c] == 1.0
    # and colour-demosaicing's masks (tuple R, G, B of bools)
    np.testing.assert_array_equal(m, np.stack(masks_CFA_Bayer(SHAPE, pattern)).astype(float))


def test_rggb_corner_pixels():
    rgb = jnp.stack([jnp.full((2, 2), 1.0), jnp.full((2, 2), 2.0), jnp.full((2, 2), 3.0)])
    np.testing.assert_array_equal(mosaic(rgb, "RGGB"), [[1.0, 2.0], [2.0, 3.0]])
    np.testing.assert_array_equal(mosaic(rgb, "BGGR"), [[3.0, 2.0], [2.0, 1.0]])


@pytest.mark.parametrize("pattern", PATTERNS)
@pytest.mark.parametrize("shape", [SHAPE, (33, 47)])
def test_mosaic_matches_colour_demosaicing(pattern, shape):
    rgb = np.random.default_rng(1).random((3, *shape))
    out = mosaic(jnp.asarray(rgb), pattern)
    ref = mosaicing_CFA_Bayer(np.moveaxis(rgb, 0, -1), pattern)
    np.testing.assert_array_equal(out, ref)  # a pure selection: exact


@pytest.mark.parametrize("pattern", PATTERNS)
def test_white_balance(pattern):
    cfa = np.random.default_rng(2).random(SHAPE)
    gains = np.array([2.1, 1.0, 1.7])
    out = white_balance(jnp.asarray(cfa), jnp.asarray(gains), pattern)
    masks = np.stack(masks_CFA_Bayer(SHAPE, pattern))
    ref = cfa * np.tensordot(gains, masks, axes=1)
    np.testing.assert_allclose(out, ref, rtol=0, atol=1e-15)  # one multiply per pixel


def test_jit_equals_no_jit_and_grad_finite():
    rgb = jnp.asarray(np.random.default_rng(3).random((3, *SHAPE)))
    gains = jnp.array([2.0, 1.0, 1.5])
    f = lambda x, g: white_balance(mosaic(x, "GRBG"), g, "GRBG")  # noqa: E731
    np.testing.assert_allclose(jax.jit(f)(rgb, gains), f(rgb, gains), rtol=0, atol=0)
    gx, gg = jax.grad(lambda x, g: jnp.sum(f(x, g) ** 2), argnums=(0, 1))(rgb, gains)
    assert np.all(np.isfinite(gx)) and np.all(np.isfinite(gg))
    # each pixel's gradient reaches only its own channel
    masks = np.asarray(bayer_masks(SHAPE, "GRBG"))
    assert np.all(np.asarray(gx)[masks == 0] == 0)
    assert np.all(np.asarray(gx)[masks == 1] != 0)


def test_bad_pattern_and_gains():
    with pytest.raises(ValueError, match=r"pattern must be one of .*RGGB.*got 'RGBG'"):
        bayer_masks(SHAPE, "RGBG")
    with pytest.raises(ValueError, match="pattern must be one of"):
        mosaic(jnp.zeros((3, 4, 4)), "rggb")
    # the annotation already rejects this at test time; check the run-time guard users get
    with pytest.raises(ValueError, match=r"gains must have shape \(3,\)"):
        inspect.unwrap(white_balance)(jnp.zeros((4, 4)), jnp.ones(4), "RGGB")
