"""Metrics vs scikit-image's SSIM and SciPy's bilinear map_coordinates."""

import inspect

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.ndimage
from skimage.metrics import structural_similarity

from difstar._metrics import grayscale, mse, profile_circle, profile_line, ssim, table1

H, W = 32, 48


def _sk(a, b, **kw):
    return structural_similarity(a, b, data_range=1.0, gaussian_weights=True, sigma=1.5,
                                 use_sample_covariance=False, **kw)


def _images():
    rng = np.random.default_rng(0)
    rand_a = rng.random((H, W))
    rand_b = np.clip(rand_a + 0.1 * rng.normal(size=(H, W)), 0, 1)
    yy, xx = np.mgrid[:H, :W]
    struct_a = 0.5 + 0.4 * np.sin(xx / 3.0) * np.cos(yy / 5.0)
    struct_a[8:20, 10:30] = 1.0  # saturated block with sharp edges
    struct_b = scipy.ndimage.gaussian_filter(struct_a, 1.0) * 0.9 + 0.05
    return [(rand_a, rand_b), (struct_a, struct_b), (struct_a, struct_a)]


@pytest.mark.parametrize("k", range(3))
def test_ssim_matches_skimage(k):
    a, b = _images()[k]
    # float64 throughout, same filter and crop: agreement to round-off
    np.testing.assert_allclose(ssim(jnp.asarray(a), jnp.asarray(b)), _sk(a, b), rtol=0, atol=1e-6)


def test_ssim_per_channel_and_data_range():
    (a, b), (c, d), _ = _images()
    rgb_a, rgb_b = np.stack([a, c, a * 0.5]), np.stack([b, d, b * 0.5])
    s = ssim(jnp.asarray(rgb_a), jnp.asarray(rgb_b))
    assert s.shape == (3,)
    for i in range(3):
        np.testing.assert_allclose(s[i], _sk(rgb_a[i], rgb_b[i]), rtol=0, atol=1e-6)
    np.testing.assert_allclose(s.mean(), _sk(rgb_a, rgb_b, channel_axis=0), rtol=0, atol=1e-6)
    ref = structural_similarity(a * 255, b * 255, data_range=255.0, gaussian_weights=True,
                                sigma=1.5, use_sample_covariance=False)
    np.testing.assert_allclose(ssim(jnp.asarray(a * 255), jnp.asarray(b * 255), data_range=255.0),
                               ref, rtol=0, atol=1e-6)


def test_ssim_jit_and_grad():
    a, b = (jnp.asarray(x) for x in _images()[1])
    f = lambda x, y: ssim(x, y)  # noqa: E731
    np.testing.assert_allclose(jax.jit(f)(a, b), f(a, b), rtol=0, atol=1e-14)
    g = jax.jit(jax.grad(f))(a, b)
    assert np.all(np.isfinite(g))
    # gradient at the identical pair (the maximum) is finite too, and zero
    g0 = jax.jit(jax.grad(f))(a, a)
    assert np.all(np.isfinite(g0))
    np.testing.assert_allclose(g0, 0.0, atol=1e-12)


def test_mse_grayscale_table1():
    (a, b), (c, d), _ = _images()
    pred = np.stack([a, c, b])
    obs = np.stack([b, d, a])
    np.testing.assert_allclose(mse(jnp.asarray(a), jnp.asarray(b)), np.mean((a - b) ** 2),
                               rtol=1e-14)
    gray = grayscale(jnp.asarray(pred))
    np.testing.assert_allclose(gray, 0.2989 * a + 0.5870 * c + 0.1140 * b, rtol=0, atol=1e-15)
    t = jax.jit(table1)(jnp.asarray(pred), jnp.asarray(obs))
    assert set(t) == {"R", "G", "B", "B/W"}
    for i, ch in enumerate("RGB"):
        np.testing.assert_allclose(t[ch]["MSE"], np.mean((pred[i] - obs[i]) ** 2), rtol=1e-12)
        np.testing.assert_allclose(t[ch]["SSIM"], _sk(pred[i], obs[i]), rtol=0, atol=1e-6)
    gp = 0.2989 * pred[0] + 0.5870 * pred[1] + 0.1140 * pred[2]
    go = 0.2989 * obs[0] + 0.5870 * obs[1] + 0.1140 * obs[2]
    np.testing.assert_allclose(t["B/W"]["MSE"], np.mean((gp - go) ** 2), rtol=1e-12)
    np.testing.assert_allclose(t["B/W"]["SSIM"], _sk(gp, go), rtol=0, atol=1e-6)
    g = jax.jit(jax.grad(lambda p: table1(p, jnp.asarray(obs))["B/W"]["SSIM"]))(jnp.asarray(pred))
    assert np.all(np.isfinite(g))


def test_profiles_match_scipy_bilinear():
    img = np.random.default_rng(5).random((3, H, W))
    centre, radius, n = (15.3, 22.7), 9.4, 37
    out = profile_circle(jnp.asarray(img), centre, radius, n)
    theta = 2 * np.pi * np.arange(n) / n
    rows, cols = centre[0] - radius * np.sin(theta), centre[1] + radius * np.cos(theta)
    ref = np.stack([scipy.ndimage.map_coordinates(c, [rows, cols], order=1) for c in img])
    np.testing.assert_allclose(out, ref, rtol=0, atol=1e-13)  # bilinear, float64
    # θ = 0 is to the right of the centre, θ = π/2 above it (smaller row)
    lin = profile_line(jnp.asarray(img[0]), 7.5, 2.25, 40.0, 25)
    ref = scipy.ndimage.map_coordinates(img[0], [np.full(25, 7.5), np.linspace(2.25, 40, 25)],
                                        order=1)
    np.testing.assert_allclose(lin, ref, rtol=0, atol=1e-13)


def test_profiles_exact_on_a_plane():
    # bilinear interpolation reproduces an affine image exactly
    yy, xx = np.mgrid[:H, :W].astype(float)
    img = jnp.asarray(0.3 + 0.01 * yy - 0.02 * xx)
    c = profile_circle(img, (16.0, 24.0), 10.0, 8)
    theta = 2 * np.pi * np.arange(8) / 8
    np.testing.assert_allclose(c, 0.3 + 0.01 * (16 - 10 * np.sin(theta))
                               - 0.02 * (24 + 10 * np.cos(theta)), rtol=0, atol=1e-14)
    # θ = π/2 is straight up: row 16 − 10 = 6, column 24
    np.testing.assert_allclose(c[2], 0.3 + 0.01 * 6 - 0.02 * 24, rtol=0, atol=1e-14)


def test_profiles_jit_and_grad():
    img = jnp.asarray(np.random.default_rng(6).random((3, H, W)))
    f = lambda im, r: profile_circle(im, (16.0, 24.0), r, 12)  # noqa: E731
    np.testing.assert_allclose(jax.jit(f)(img, 5.5), f(img, 5.5), rtol=0, atol=1e-14)
    gi, gr = jax.jit(jax.grad(lambda im, r: jnp.sum(f(im, r) ** 2), argnums=(0, 1)))(img, 5.5)
    assert np.all(np.isfinite(gi)) and np.isfinite(gr)
    gl = jax.jit(jax.grad(lambda im: jnp.sum(profile_line(im, 3.5, 0.0, 47.0, 30))))(img)
    assert np.all(np.isfinite(gl))


def test_bad_inputs():
    a = jnp.zeros((H, W))
    with pytest.raises(ValueError, match="same shape"):
        inspect.unwrap(mse)(a, jnp.zeros((H, W + 1)))
    with pytest.raises(ValueError, match="at least 11×11"):
        ssim(jnp.zeros((8, 40)), jnp.zeros((8, 40)))
    with pytest.raises(ValueError, match=r"shape \(3, h, w\)"):
        inspect.unwrap(table1)(jnp.zeros((4, H, W)), jnp.zeros((4, H, W)))
