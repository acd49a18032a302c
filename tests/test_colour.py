"""Colour rendering vs colour-science (sRGB curve, XYZ→sRGB matrix) and
colour-demosaicing (the full render chain)."""

import inspect

import colour
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from colour_demosaicing import demosaicing_CFA_Bayer_Malvar2004, masks_CFA_Bayer

from difstar._colour import camera_to_srgb, render_srgb, srgb_encode, xyz_to_srgb_linear_matrix

from helpers import fd_grad


def test_srgb_encode_matches_colour():
    x = np.concatenate([np.linspace(-0.1, 1.1, 241), [0.0, 0.0031308, 0.00313, 0.0031309, 1.0],
                        np.geomspace(1e-8, 1, 50)])
    ref = colour.models.eotf_inverse_sRGB(np.clip(x, 0, 1))
    np.testing.assert_allclose(srgb_encode(jnp.asarray(x)), ref, rtol=0, atol=1e-14)  # float64
    ref2 = colour.cctf_encoding(np.clip(x, 0, 1), function="sRGB")
    np.testing.assert_allclose(srgb_encode(jnp.asarray(x)), ref2, rtol=0, atol=1e-14)


def test_srgb_encode_grad():
    g = jax.jit(jax.grad(srgb_encode))
    # exactly at the clip limits: finite, the one-sided derivative from inside
    assert np.isfinite(g(0.0)) and np.isfinite(g(1.0))
    np.testing.assert_allclose(g(0.0), 12.92, rtol=1e-14)
    np.testing.assert_allclose(g(1.0), 1.055 / 2.4, rtol=1e-14)
    assert g(-0.5) == 0.0 and g(1.5) == 0.0  # clipped
    # finite differences away from the kink at 0.0031308 (step 1e-6 relative, central)
    enc = jax.jit(srgb_encode)
    f = lambda x: float(enc(jnp.asarray(x)))  # noqa: E731
    for x in [1e-4, 0.002, 0.01, 0.2, 0.5, 0.9]:
        np.testing.assert_allclose(g(x), fd_grad(f, x, 1e-6 * x), rtol=1e-6)
    # a whole image with zeros and saturated pixels: no NaN in the gradient
    img = jnp.asarray(np.random.default_rng(0).uniform(-0.2, 1.2, (3, 8, 8))).at[:, 0, 0].set(0.0)
    gi = jax.jit(jax.grad(lambda a: jnp.sum(srgb_encode(a))))(img)
    assert np.all(np.isfinite(gi))


def test_srgb_encode_jit():
    x = jnp.linspace(-0.1, 1.1, 101)
    np.testing.assert_allclose(jax.jit(srgb_encode)(x), srgb_encode(x), rtol=0, atol=1e-15)


def test_xyz_matrix_is_colours():
    m = xyz_to_srgb_linear_matrix()
    np.testing.assert_array_equal(m, colour.RGB_COLOURSPACES["sRGB"].matrix_XYZ_to_RGB)
    # D65 white (Y = 1) → linear sRGB (1, 1, 1) within the standard's 4-digit rounding
    white = colour.xy_to_XYZ(colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"])
    np.testing.assert_allclose(m @ white, 1.0, atol=1e-3)


def test_camera_to_srgb():
    rgb = np.random.default_rng(1).random((3, 6, 7))
    m = np.random.default_rng(2).normal(size=(3, 3))
    np.testing.assert_allclose(camera_to_srgb(jnp.asarray(rgb), jnp.asarray(m)),
                               np.einsum("ij,jhw->ihw", m, rgb), rtol=0, atol=1e-14)
    with pytest.raises(ValueError, match=r"matrix must have shape \(3, 3\)"):
        inspect.unwrap(camera_to_srgb)(jnp.asarray(rgb), jnp.eye(4))


def _render_reference(cfa, pattern, gains, matrix):
    masks = np.stack(masks_CFA_Bayer(cfa.shape, pattern))
    balanced = cfa * np.tensordot(gains, masks, axes=1)
    rgb = demosaicing_CFA_Bayer_Malvar2004(balanced, pattern)  # (h, w, 3)
    srgb_lin = np.clip(rgb @ matrix.T, 0, 1)
    return np.moveaxis(colour.cctf_encoding(srgb_lin, function="sRGB"), -1, 0)


@pytest.mark.parametrize("pattern", ["RGGB", "GBRG"])
def test_render_srgb_matches_reference_chain(pattern):
    rng = np.random.default_rng(3)
    cfa = rng.random((32, 48)) * 0.6
    cfa[5:9, 10:16] = 1.0  # saturated patch
    gains = np.array([2.0, 1.0, 1.6])
    matrix = np.array([[1.6, -0.5, -0.1], [-0.2, 1.5, -0.3], [0.0, -0.4, 1.4]])
    out = render_srgb(jnp.asarray(cfa), pattern, white_balance=jnp.asarray(gains),
                      matrix=jnp.asarray(matrix))
    assert out.shape == (3, 32, 48)
    assert float(out.min()) >= 0.0 and float(out.max()) <= 1.0
    ref = _render_reference(cfa, pattern, gains, matrix)
    np.testing.assert_allclose(out, ref, rtol=0, atol=1e-12)  # float64 round-off only


def test_render_srgb_jit_and_grad():
    rng = np.random.default_rng(4)
    cfa = jnp.asarray(rng.random((16, 20)) * 0.5).at[3, 3].set(0.0).at[8, 8].set(1.0)
    gains = jnp.array([2.0, 1.0, 1.6])
    matrix = jnp.eye(3)
    f = lambda c, g, m: render_srgb(c, "RGGB", white_balance=g, matrix=m,  # noqa: E731
                                    demosaic_method="bilinear")
    np.testing.assert_allclose(jax.jit(f)(cfa, gains, matrix), f(cfa, gains, matrix),
                               rtol=0, atol=1e-14)
    grads = jax.jit(jax.grad(lambda c, g, m: jnp.sum(f(c, g, m)), argnums=(0, 1, 2)))(
        cfa, gains, matrix)
    for gr in grads:
        assert np.all(np.isfinite(gr))


def test_render_srgb_bad_method():
    with pytest.raises(ValueError, match="method must be one of"):
        render_srgb(jnp.zeros((4, 4)), "RGGB", white_balance=jnp.ones(3), matrix=jnp.eye(3),
                    demosaic_method="vng")
