"""Radiometry: how much light the pupil lets through to the sensor.

The PSF carries the *fraction* of the power through the pupil (it sums to 1); this
module decides the *amount*, in one place, for :func:`difstar.simulate`.

- An extended source of radiance L (per channel) gives the image irradiance
  E = L · A_exit / z² (paraxial, on axis), with A_exit the exit pupil's open area (the
  polygon's, not a circle's; obstructions and vanes removed) and z the distance from the
  exit pupil to the sensor (``Geometry.z_exit_pupil``, so focusing closer dims the image
  as the working f-number grows). A_exit / z² is the exit pupil's solid angle Ω_exit
  seen from the image; for a circular pupil it is π / (4 N_w²).
- A point source of intensity I at distance r_ent from the entrance pupil delivers the
  power P = I · A_entrance / r_ent² (A_entrance = A_exit / m_p², m_p the pupil
  magnification), which the PSF spreads over the pixels.

Both are divided by one written-down reference solid angle, Ω_ref = π / (4 · 22²), that
of a circular f/22 pupil focused at infinity. The sensor then sees ζ = Z(C t / φ0) with C
the image in units of "radiance at f/22", so φ0 is measured in seconds at a unit
radiance through that reference pupil: the knee's radiant exposure is
H_knee = φ0 · Ω_ref · (one radiance unit) (J m⁻² for radiance in W m⁻² sr⁻¹). One
camera's φ0 then holds at every aperture, focus and exposure time; a φ0 characterised
in the older, per-configuration sense (seconds at that configuration's aperture and
focus, as the paper's) converts with :func:`phi0_from_configuration`.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp

from ._atf import centred_coordinates
from ._custom_types import Array, Float
from ._model import geometry_of
from ._pupil import Circle, Obstructed, Transformed

REFERENCE_F_NUMBER = 22.0
REFERENCE_SOLID_ANGLE = math.pi / (4.0 * REFERENCE_F_NUMBER**2)  # sr, circular f/22 at ∞

_RASTER_SAMPLES = 512  # a side, for pupils without a closed-form area (vanes)


def pupil_area(pupil) -> Float[Array, ""]:
    """The pupil's open area in m² (differentiable): the closed form where the shape has
    one (polygons, regular polygons, curved irises, circles, unions, masks, rigid
    transforms of them, an outer pupil less a central obstruction); otherwise the sum of
    its exact area coverage on a 512² raster over its bounding square (vanes)."""
    if isinstance(pupil, Circle):
        return math.pi * pupil.radius**2
    if isinstance(pupil, Transformed):  # a rotation and a shift keep the area
        return pupil_area(pupil.pupil)
    if isinstance(pupil, Obstructed) and pupil.spiders is None:
        outer = pupil_area(pupil.outer)
        return outer if pupil.obstruction is None else outer - pupil_area(pupil.obstruction)
    if hasattr(pupil, "area") and not isinstance(pupil, Obstructed):
        return pupil.area()
    return _raster_area(pupil)


def _raster_area(pupil) -> Float[Array, ""]:
    n = _RASTER_SAMPLES
    cell = 2.04 * pupil.max_radius() / n
    x = centred_coordinates(n, cell)
    cov = pupil.coverage(x[None, :], x[:, None], cell)
    return jnp.sum(cov) * cell * cell


def entrance_distance(lens, geometry) -> Float[Array, ""]:
    """r_ent: the object plane to the entrance pupil (m). The entrance pupil, the image of
    the stop in object space, lies f (1/m_p − 1) behind the front principal plane (at it
    for m_p = 1), as the exit pupil lies f (1 − m_p) behind the rear one."""
    return geometry.s_object + lens.focal_length * (1.0 / lens.pupil_magnification - 1.0)


class Radiometry(eqx.Module):
    """How much light the pupil passes, for one camera and scene.

    exit_solid_angle: Ω_exit = A_exit / z_R² (sr), the image irradiance per unit
        radiance of an extended source.
    entrance_solid_angle: Ω_ent = A_exit / (m_p² r_ent²) (sr), the power collected per
        unit intensity of a point source.
    ``extended_scale`` and ``point_scale`` are the two over :data:`REFERENCE_SOLID_ANGLE`:
    the factors ``simulate`` applies to the sources' radiance and intensity.
    """

    exit_solid_angle: Float[Array, ""]
    entrance_solid_angle: Float[Array, ""]

    @property
    def extended_scale(self) -> Float[Array, ""]:
        return self.exit_solid_angle / REFERENCE_SOLID_ANGLE

    @property
    def point_scale(self) -> Float[Array, ""]:
        return self.entrance_solid_angle / REFERENCE_SOLID_ANGLE


def radiometry(camera, scene, geometry=None) -> Radiometry:
    """The pupil's solid angles for ``camera`` photographing ``scene`` (jit, grad and
    jacfwd go through it: the pupil's area and the geometry are differentiable).
    ``geometry`` defaults to :func:`difstar.geometry_of` (camera, scene)."""
    if geometry is None:
        geometry = geometry_of(camera, scene)
    lens = camera.lens
    area = pupil_area(lens.pupil)
    z = geometry.z_exit_pupil
    r_ent = entrance_distance(lens, geometry)
    m_p = lens.pupil_magnification
    return Radiometry(area / (z * z), area / (m_p * m_p * r_ent * r_ent))


def irradiance_scale(camera, scene, geometry=None) -> Float[Array, ""]:
    """Ω_exit / Ω_ref: the image irradiance of a unit-radiance extended source through
    this camera, relative to the reference pupil (circular f/22 at infinity focus).
    Stopping down from f/8 to f/22 divides it by (22/8)² = 7.6; focusing closer divides
    it by (z / z_∞)²."""
    return radiometry(camera, scene, geometry).extended_scale


def phi0_from_configuration(phi0_seconds, camera, scene) -> Float[Array, "3"]:
    """Convert a φ0 characterised at one configuration (seconds, with the image of a
    unit radiance taken as 1 whatever the aperture and focus: the paper's convention and
    difstar's before radiometry) to the φ0 ``Sensor`` takes (seconds at the reference
    pupil): φ0 · Ω_exit / Ω_ref for that camera and scene. Both render that
    configuration identically; only the converted one holds at other apertures and
    focus settings."""
    return jnp.asarray(phi0_seconds, dtype=float) * irradiance_scale(camera, scene)


__all__ = [
    "REFERENCE_F_NUMBER", "REFERENCE_SOLID_ANGLE", "Radiometry", "entrance_distance",
    "irradiance_scale", "phi0_from_configuration", "pupil_area", "radiometry",
]
