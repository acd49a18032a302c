"""Image comparison as in the paper: MSE, SSIM, Table 1, and the profiles of Fig. 5.

All functions are pure JAX, jittable and differentiable (so they can also serve as
fitting or design objectives). Arrays are indexed [row, col]; RGB stacks are
channel-first (3, h, w).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from ._colour import render_srgb
from ._custom_types import Array, ArrayLike, Float

# The paper's Table 1 grayscale weights for (R, G, B) (the ITU-R BT.601 luma weights as
# MATLAB's rgb2gray rounds them).
GRAY_WEIGHTS = (0.2989, 0.5870, 0.1140)

_K1, _K2, _TRUNCATE = 0.01, 0.03, 3.5


def mse(a: Float[ArrayLike, "*shape"], b: Float[ArrayLike, "*shape"]) -> Float[Array, ""]:
    """Mean squared difference over all elements (units of the inputs, squared)."""
    a, b = jnp.asarray(a), jnp.asarray(b)
    if a.shape != b.shape:
        raise ValueError(f"a and b must have the same shape, got {a.shape} and {b.shape}")
    return jnp.mean((a - b) ** 2)


def _gaussian_kernel(sigma: float) -> tuple[np.ndarray, int]:
    """scipy.ndimage's 1-D Gaussian (radius int(3.5 σ + 0.5), unit sum) and its radius."""
    radius = int(_TRUNCATE * sigma + 0.5)
    x = np.arange(-radius, radius + 1, dtype=np.float64)
    k = np.exp(-0.5 * (x / sigma) ** 2)
    return k / k.sum(), radius


def _gaussian_filter(x: Float[Array, "n h w"], kernel: np.ndarray, radius: int) -> Array:
    """Separable Gaussian filter of each image of a stack, borders as scipy.ndimage's
    mode "reflect" (half-sample symmetric)."""
    xp = jnp.pad(x, ((0, 0), (radius, radius), (radius, radius)), mode="symmetric")[:, None]
    k = jnp.asarray(kernel, dtype=x.dtype)  # symmetric, so correlation = convolution
    conv = lambda img, rhs: lax.conv_general_dilated(  # noqa: E731
        img, rhs, (1, 1), "VALID", precision=lax.Precision.HIGHEST
    )
    out = conv(conv(xp, k[None, None, :, None]), k[None, None, None, :])
    return out[:, 0]


@functools.partial(jax.jit, static_argnames="sigma")
def _ssim_stack(a: Float[Array, "n h w"], b: Float[Array, "n h w"], data_range, sigma) -> Array:
    """Mean SSIM of each of n image pairs (jitted: one compilation per shape and sigma)."""
    return jax.vmap(lambda x, y: _ssim_2d(x, y, data_range, sigma))(a, b)


def _ssim_2d(a: Float[Array, "h w"], b: Float[Array, "h w"], data_range, sigma) -> Array:
    kernel, radius = _gaussian_kernel(sigma)
    ux, uy, uxx, uyy, uxy = _gaussian_filter(jnp.stack([a, b, a * a, b * b, a * b]), kernel, radius)
    vx = uxx - ux * ux  # population (co)variances, as Wang et al. 2004
    vy = uyy - uy * uy
    vxy = uxy - ux * uy
    c1 = (_K1 * data_range) ** 2
    c2 = (_K2 * data_range) ** 2
    s = ((2 * ux * uy + c1) * (2 * vxy + c2)) / ((ux**2 + uy**2 + c1) * (vx + vy + c2))
    # like skimage: drop the border strip (win - 1)//2 wide, where the filter reflects
    pad = radius  # = (win_size - 1) // 2
    return jnp.mean(s[pad : s.shape[0] - pad, pad : s.shape[1] - pad])


def ssim(
    a: Float[ArrayLike, "*c h w"],
    b: Float[ArrayLike, "*c h w"],
    *,
    data_range: float = 1.0,
    sigma: float = 1.5,
) -> Float[Array, "*c"]:
    """Mean structural similarity (Wang et al. 2004) of each image in ``a`` vs ``b``.

    Matches ``skimage.metrics.structural_similarity(a, b, data_range=data_range,
    gaussian_weights=True, sigma=sigma, use_sample_covariance=False)``: K1 = 0.01,
    K2 = 0.03, Gaussian window truncated at 3.5 σ (radius int(3.5 σ + 0.5)), borders
    reflected, and the mean taken over the image cropped by the window radius.

    Input (h, w) gives a scalar; (3, h, w) (or any leading axes) gives one SSIM per
    leading index, e.g. per channel — their mean is skimage's value with
    ``channel_axis=0``. ``data_range`` is the span of possible values (1 for sRGB in
    [0, 1]); ``sigma`` in pixels.
    """
    a, b = jnp.asarray(a), jnp.asarray(b)
    if a.shape != b.shape:
        raise ValueError(f"a and b must have the same shape, got {a.shape} and {b.shape}")
    if a.ndim < 2:
        raise ValueError(f"images must have at least 2 axes (h, w), got shape {a.shape}")
    win = 2 * int(_TRUNCATE * sigma + 0.5) + 1
    if a.shape[-2] < win or a.shape[-1] < win:
        raise ValueError(
            f"images must be at least {win}×{win} pixels for SSIM with sigma={sigma} "
            f"(window of {win} samples), got shape {a.shape}"
        )
    lead = a.shape[:-2]
    flat = _ssim_stack(
        a.reshape(-1, *a.shape[-2:]), b.reshape(-1, *b.shape[-2:]), data_range, float(sigma)
    )
    return flat.reshape(lead)


def grayscale(rgb: Float[ArrayLike, "3 h w"]) -> Float[Array, "h w"]:
    """Weighted sum 0.2989 R + 0.5870 G + 0.1140 B (the paper's Table 1 weights)."""
    rgb = jnp.asarray(rgb)
    w = jnp.asarray(GRAY_WEIGHTS, dtype=rgb.dtype)
    return jnp.tensordot(w, rgb, axes=1, precision=lax.Precision.HIGHEST)


def table1(
    pred_srgb: Float[ArrayLike, "3 h w"], obs_srgb: Float[ArrayLike, "3 h w"]
) -> dict[str, dict[str, Float[Array, ""]]]:
    """MSE and SSIM (data range 1) per channel and in grayscale, like the paper's Table 1.

    Returns ``{"R": {"MSE": ..., "SSIM": ...}, "G": ..., "B": ..., "B/W": ...}``.

    Both inputs are sRGB-encoded images in [0, 1]. The paper forms its grayscale from the
    linear ("truecolour") RGB and gamma-compresses it afterwards; here only the encoded
    images are given, so B/W is :func:`grayscale` of the sRGB values. The two differ
    slightly for saturated colours and agree exactly for neutral pixels.
    """
    pred, obs = jnp.asarray(pred_srgb), jnp.asarray(obs_srgb)
    if pred.shape != obs.shape or pred.ndim != 3 or pred.shape[0] != 3:
        raise ValueError(
            f"pred_srgb and obs_srgb must both have shape (3, h, w), got {pred.shape} "
            f"and {obs.shape}"
        )
    s = ssim(pred, obs, data_range=1.0)
    out = {
        name: {"MSE": mse(pred[i], obs[i]), "SSIM": s[i]} for i, name in enumerate("RGB")
    }
    gp, go = grayscale(pred), grayscale(obs)
    out["B/W"] = {"MSE": mse(gp, go), "SSIM": ssim(gp, go, data_range=1.0)}
    return out


@functools.partial(jax.jit, static_argnames=("pattern", "white_balance", "matrix"))
def compare_raw(pred_cfa: Float[ArrayLike, "h w"], obs_cfa: Float[ArrayLike, "h w"], *,
                pattern: str, white_balance: tuple, matrix: tuple):
    """(sRGB of the predicted mosaic, sRGB of the observed one clipped to [0, 1], their
    :func:`table1`): one compiled program per shape (a fit's captures share it)."""
    m = np.asarray(matrix, float)
    s_pred = render_srgb(pred_cfa, pattern, white_balance=white_balance, matrix=m)
    s_obs = render_srgb(jnp.clip(obs_cfa, 0, 1), pattern, white_balance=white_balance,
                        matrix=m)
    return s_pred, s_obs, table1(s_pred, s_obs)


def _sample(img: Array, rows: Array, cols: Array) -> Array:
    """Bilinear samples of img (h, w) or (..., h, w) at (rows, cols), edge-clamped."""
    f = lambda im: jax.scipy.ndimage.map_coordinates(  # noqa: E731
        im, [rows, cols], order=1, mode="nearest"
    )
    if img.ndim == 2:
        return f(img)
    lead = img.shape[:-2]
    return jax.vmap(f)(img.reshape(-1, *img.shape[-2:])).reshape(*lead, rows.shape[0])


@functools.partial(jax.jit, static_argnames=("n",))  # one program per shape
def profile_circle(
    img: Float[ArrayLike, "*c h w"],
    centre_rc: Float[ArrayLike, "2"] | tuple[float | Float[Array, ""], float | Float[Array, ""]],
    radius_px: float | int | Float[ArrayLike, ""],
    n: int,
) -> Float[Array, "*c n"]:
    """Bilinear samples of ``img`` on a circle (the paper's Fig. 5a/d).

    Sample k is at angle θ_k = 2π k / n, counter-clockwise from the +column direction
    as the image is displayed (row axis pointing down): (row, col) =
    (r0 − R sin θ_k, c0 + R cos θ_k), with ``centre_rc`` = (r0, c0) and R =
    ``radius_px`` in pixels (fractional allowed). Points outside the image take the
    nearest edge value. Leading axes of ``img`` (e.g. channels) are kept.
    """
    img = jnp.asarray(img)
    r0, c0 = centre_rc[0], centre_rc[1]
    theta = 2 * jnp.pi * jnp.arange(n, dtype=img.dtype) / n
    rows = r0 - radius_px * jnp.sin(theta)
    cols = c0 + radius_px * jnp.cos(theta)
    return _sample(img, rows, cols)


@functools.partial(jax.jit, static_argnames=("n",))  # one program per shape
def profile_line(
    img: Float[ArrayLike, "*c h w"],
    row: float | int | Float[ArrayLike, ""],
    col0: float | int | Float[ArrayLike, ""],
    col1: float | int | Float[ArrayLike, ""],
    n: int,
) -> Float[Array, "*c n"]:
    """Bilinear samples of ``img`` along a horizontal line (the paper's Fig. 5b/c/e/f).

    ``n`` samples at (row, linspace(col0, col1, n)), in pixels (fractional allowed,
    both ends included). Points outside the image take the nearest edge value.
    """
    img = jnp.asarray(img)
    cols = jnp.linspace(col0, col1, n, dtype=img.dtype)
    rows = jnp.full((n,), row, dtype=img.dtype)
    return _sample(img, rows, cols)


__all__ = ["GRAY_WEIGHTS", "grayscale", "mse", "profile_circle", "profile_line", "ssim", "table1"]
