"""Sensor response (paper Eq. 5 and 7): ζ = Z(E), E = C t / φ0.

C is the image of the normalised object intensity, t the exposure time (seconds) and
φ0 the per-channel reference exposure (seconds, absorbing the paper's κ). Z is monotone,
0 at E = 0 and saturates smoothly at 1, with the shape of the paper's Fig. 4: a toe at
low exposure, a linear part, a knee into saturation:

    u = sqrt(E² + e_t²) − e_t                  (toe of width ~e_t; u ≈ E − e_t above it)
    ζ = 1 − softplus(k (1 − u)) / softplus(k)   (knee of width ~1/k; ζ(0) = 0, ζ → 1)

Both steps are smooth and increasing, so Z has finite gradients everywhere, including at
E = 0 and deep in saturation.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ._custom_types import Array, ArrayLike, Float


class Response(eqx.Module):
    """Per-channel response-curve parameters, each of shape (3,) for (R, G, B).

    toe: e_t, dimensionless exposure where the toe ends (≥ 0; 0 = no toe).
    knee: k, sharpness of the shoulder into saturation (> 0; larger = harder clip).
    """

    toe: Float[Array, "3"]
    knee: Float[Array, "3"]

    def __init__(self, toe=(0.0, 0.0, 0.0), knee=(60.0, 60.0, 60.0)):
        self.toe = jnp.broadcast_to(jnp.asarray(toe, dtype=float), (3,))
        self.knee = jnp.broadcast_to(jnp.asarray(knee, dtype=float), (3,))


def _safe_hypot(a, b):
    r2 = a * a + b * b
    ok = r2 > 0
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, r2, 1.0)), 0.0)


def response_curve(exposure: ArrayLike, toe, knee) -> Array:
    """Z(E) for one channel (or broadcast parameters)."""
    e = jnp.maximum(exposure, 0.0)
    u = _safe_hypot(e, toe) - toe
    # u − softplus(k(u − 1))/k rescaled so that Z(0) = 0 exactly; written in this form
    # so saturation has no cancellation
    return 1.0 - jax.nn.softplus(knee * (1.0 - u)) / jax.nn.softplus(knee)


def exposure(image: Float[Array, "3 h w"], *, exposure_time, phi0: Float[Array, "3"]) -> Array:
    """E = C t / φ0 per channel."""
    return image * (exposure_time / phi0)[:, None, None]


def sensor(
    image: Float[Array, "3 h w"], *, exposure_time, phi0: Float[Array, "3"], response: Response
) -> Float[Array, "3 h w"]:
    """Normalised pixel values ζ in [0, 1] for every channel at every pixel."""
    e = exposure(image, exposure_time=exposure_time, phi0=phi0)
    return response_curve(e, response.toe[:, None, None], response.knee[:, None, None])
