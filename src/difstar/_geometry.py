"""Camera geometry: focus by lens extension (paper Eq. 6), defocus, magnification.

A prime lens is a thick lens with principal planes P (front) and P' (rear) separated by
``z_p`` (distance from P to P' along the light; the paper's Nikkor 50 mm has z_p ≈ −3 mm,
i.e. P' lies in front of P). Focusing at ``r_f`` (measured from the sensor) moves the
whole lens forward by δz so that ``1/f = 1/(r_f − z_p − s') + 1/s'`` with ``s' = f + δz``.

The exit pupil is the image of the stop; with pupil magnification ``m_p`` (exit over
entrance pupil diameter) it sits ``f (1 − m_p)`` behind P', so at infinity focus it is
``f m_p`` in front of the sensor and moves with the lens.

All lengths in metres.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ._custom_types import Array, Float


class Geometry(eqx.Module):
    """Everything the optics need, derived from the lens, the focus and the object.

    Attributes (metres unless stated):
        extension: δz, the lens's forward travel from infinity focus.
        s_prime: s', rear principal plane to sensor.
        s_object: object to front principal plane.
        s_image: rear principal plane to the object's in-focus image.
        z_exit_pupil: z_R, exit pupil to sensor.
        z_in_focus: z_i, exit pupil to the object's in-focus image.
        defocus: Δz = z_R − z_i (positive: the sensor lies behind the in-focus plane).
        magnification: M on the sensor (negative: the image is inverted), from the chief
            ray through the exit pupil's centre, so it includes the defocused sensor's
            scale z_R / z_i.
        working_f_number: z_R / (2 r_pupil) for the exit-pupil radius given.
    """

    extension: Float[Array, ""]
    s_prime: Float[Array, ""]
    s_object: Float[Array, ""]
    s_image: Float[Array, ""]
    z_exit_pupil: Float[Array, ""]
    z_in_focus: Float[Array, ""]
    defocus: Float[Array, ""]
    magnification: Float[Array, ""]
    working_f_number: Float[Array, ""]


def lens_extension(focal_length, focus_distance, principal_separation,
                   xp=jnp) -> Array | float:
    """δz solving paper Eq. 6 for a lens focused at ``focus_distance`` from the sensor.

    With L = r_f − z_p, s + s' = L and 1/s + 1/s' = 1/f give s' = (L − sqrt(L² − 4 f L))/2
    (the root with the sensor near the focal plane). Requires L > 4 f (closer than that
    the lens cannot form a real image). ``xp``: NumPy for concrete values checked at the
    boundary (no traced operation).
    """
    f = focal_length
    big_l = focus_distance - principal_separation
    disc = big_l * big_l - 4.0 * f * big_l
    s_prime = 0.5 * (big_l - xp.sqrt(xp.maximum(disc, 0.0)))
    return s_prime - f


def exit_pupil_distance(focal_length: float, focus_distance: float,
                        principal_separation: float, pupil_magnification: float) -> float:
    """z_R, the exit pupil's distance from the sensor (metres), for concrete values:
    f · pupil magnification + the lens extension, as :func:`camera_geometry` has it
    (``focus_distance`` inf: focused at infinity, no extension)."""
    ext = 0.0 if math.isinf(focus_distance) else float(
        lens_extension(focal_length, focus_distance, principal_separation, xp=np))
    return focal_length * pupil_magnification + ext


def camera_geometry(
    *,
    focal_length,
    object_distance,
    focus_distance=None,
    principal_separation=0.0,
    pupil_magnification=1.0,
    pupil_radius=None,
) -> Geometry:
    """Geometry of a prime lens focused at ``focus_distance`` imaging an object at
    ``object_distance`` (both measured from the sensor plane, metres; ``None`` focus
    means focused on the object; ``jnp.inf`` means infinity focus).

    ``pupil_radius`` is the exit pupil's largest radius (metres), used only for the
    working f-number.
    """
    f = jnp.asarray(focal_length, dtype=float)
    zp = jnp.asarray(principal_separation, dtype=float)
    r_o = jnp.asarray(object_distance, dtype=float)
    if focus_distance is None:
        r_f = r_o
    else:
        r_f = jnp.asarray(focus_distance, dtype=float)
    delta = jnp.where(jnp.isinf(r_f), 0.0, lens_extension(f, jnp.where(jnp.isinf(r_f), 1.0, r_f), zp))
    s_prime = f + delta
    s_obj = r_o - zp - s_prime
    s_img = 1.0 / (1.0 / f - 1.0 / s_obj)
    z_r = f * pupil_magnification + delta
    dz = s_prime - s_img
    z_i = z_r - dz
    m = -(s_img / s_obj) * (z_r / z_i)
    if pupil_radius is None:
        nw = jnp.asarray(jnp.nan)
    else:
        nw = z_r / (2.0 * pupil_radius)
    return Geometry(delta, s_prime, s_obj, s_img, z_r, z_i, dz, m, nw)


def check_geometry(*, focal_length, object_distance, focus_distance, principal_separation):
    """Raise a clear ValueError for a geometry that cannot form an image (concrete inputs)."""
    f = float(focal_length)
    if not f > 0:
        raise ValueError(f"lens.focal_length must be > 0 metres; got {f}.")
    for name, r in (("scene.object_distance", object_distance), ("camera.focus_distance", focus_distance)):
        if r is None:
            continue
        r = float(r)
        if r != float("inf") and r - float(principal_separation) <= 4 * f:
            raise ValueError(
                f"{name} = {r} m is too close: a lens of focal length {f} m can only focus "
                f"beyond {4 * f + float(principal_separation):.4g} m from the sensor."
            )
