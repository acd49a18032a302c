"""Colour rendering of a RAW mosaic: white balance → demosaic → camera RGB to linear sRGB
matrix → clip to [0, 1] → sRGB transfer curve (the paper's "Post-processing rendering").

Conventions: RGB stacks are channel-first (3, h, w); linear values are relative (1 =
sensor saturation after white balance); encoded sRGB values are in [0, 1]. colour-science
is imported lazily, only where a constant is taken from it, so ``import difstar`` stays
cheap.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jax import lax

from ._cfa import white_balance as _white_balance
from ._custom_types import Array, ArrayLike, Float
from ._demosaic import demosaic

# IEC 61966-2-1: linear segment below this linear value, power law above.
_SRGB_THRESHOLD = 0.0031308


def camera_to_srgb(
    rgb_cam: Float[Array, "3 h w"], matrix: Float[ArrayLike, "3 3"]
) -> Float[Array, "3 h w"]:
    """Apply a 3×3 colour matrix: out[i] = Σ_j matrix[i, j] · rgb_cam[j] at each pixel.

    ``matrix`` maps white-balanced camera RGB to linear sRGB (rows: sR, sG, sB). No
    clipping here.
    """
    matrix = jnp.asarray(matrix, dtype=rgb_cam.dtype)
    if matrix.shape != (3, 3):
        raise ValueError(f"matrix must have shape (3, 3), got {matrix.shape}")
    return jnp.einsum("ij,jhw->ihw", matrix, rgb_cam, precision=lax.Precision.HIGHEST)


def srgb_encode(linear: Float[ArrayLike, "*shape"]) -> Float[Array, "*shape"]:
    """sRGB transfer curve (IEC 61966-2-1) of linear values, after clipping to [0, 1]:

        V = 12.92 L                     for L ≤ 0.0031308
        V = 1.055 L^(1/2.4) − 0.055     otherwise.

    Gradients: finite everywhere. The clip is written with ``where`` so that at exactly
    0 and 1 the gradient is the one-sided derivative from inside (12.92 at 0,
    1.055/2.4 at 1), and 0 outside [0, 1]. The power is evaluated on a safe argument
    (1 on the linear segment) so its infinite derivative at 0 never reaches the gradient.
    """
    x = jnp.asarray(linear)
    x = jnp.where(x < 0, 0.0, jnp.where(x > 1, 1.0, x))
    power = x > _SRGB_THRESHOLD
    x_safe = jnp.where(power, x, 1.0)
    # exp(log(x)/2.4): the same power (a few ulp), but XLA's CPU pow is ~3× slower
    return jnp.where(power, 1.055 * jnp.exp(jnp.log(x_safe) * (1 / 2.4)) - 0.055, 12.92 * x)


def xyz_to_srgb_linear_matrix() -> Float[np.ndarray, "3 3"]:
    """colour-science's CIE XYZ → linear sRGB matrix (D65 white, no adaptation), float64."""
    import colour  # noqa: PLC0415  (lazy: keep `import difstar` cheap)

    return np.array(colour.RGB_COLOURSPACES["sRGB"].matrix_XYZ_to_RGB, dtype=np.float64)


def render_srgb(
    cfa: Float[Array, "h w"],
    pattern: str,
    *,
    white_balance: Float[ArrayLike, "3"],
    matrix: Float[ArrayLike, "3 3"],
    demosaic_method: str = "malvar2004",
    highlight: str = "clip",
) -> Float[Array, "3 h w"]:
    """Render a normalised RAW mosaic ζ to an sRGB-encoded image (3, h, w) in [0, 1].

    white balance (per-channel gains on the mosaic) → demosaic (``demosaic_method``
    "malvar2004" or "bilinear") → highlight clip → ``matrix`` (white-balanced camera RGB
    → linear sRGB) → clip to [0, 1] → sRGB transfer curve. The pattern and ``highlight``
    are static.

    ``highlight="clip"`` (default, what dcraw/LibRaw do by default): the white-balanced
    camera RGB is clipped above at min(white_balance), the largest value every channel
    can still record (a RAW value of 1 times the smallest gain; 1 for gains normalised
    to G = 1). A pixel saturated in every channel then becomes (g, g, g) and renders
    neutral through any matrix whose rows sum to 1; without the clip, gains such as
    [2, 1, 2] turn it into (2, 1, 2), which a real camera matrix renders magenta. For an
    identity matrix and min(white_balance) ≥ 1 the clip changes nothing (the final clip
    to [0, 1] does the same). ``highlight="none"``: no clip before the matrix.
    """
    if highlight not in ("clip", "none"):
        raise ValueError(f"highlight must be 'clip' or 'none'; got {highlight!r}")
    balanced = _white_balance(cfa, white_balance, pattern)
    rgb_cam = demosaic(balanced, pattern, method=demosaic_method)
    if highlight == "clip":
        rgb_cam = jnp.minimum(rgb_cam, jnp.min(jnp.asarray(white_balance, rgb_cam.dtype)))
    return srgb_encode(camera_to_srgb(rgb_cam, matrix))


__all__ = ["camera_to_srgb", "render_srgb", "srgb_encode", "xyz_to_srgb_linear_matrix"]
