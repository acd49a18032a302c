"""Geometry against the paper's numbers and against the thin-lens equation."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import difstar
from difstar._geometry import camera_geometry, lens_extension


def test_paper_defocus_4p78mm():
    # Paper: f = 51.5 mm, z_p ≈ −3 mm, r_o = 100 cm, r_f = 45 cm → "a 4.78 mm defocus".
    g = camera_geometry(focal_length=51.5e-3, object_distance=1.0, focus_distance=0.45,
                        principal_separation=-3e-3)
    assert float(g.defocus) == pytest.approx(4.78e-3, abs=0.01e-3)  # paper quotes 3 digits


def test_lens_extension_solves_eq6():
    f, zp, rf = 51.5e-3, -3e-3, 0.45
    d = float(lens_extension(f, rf, zp))
    s_prime = f + d
    s = rf - zp - s_prime
    assert 1 / s + 1 / s_prime == pytest.approx(1 / f, rel=1e-12)


def test_focused_has_zero_defocus_and_thin_lens_magnification():
    g = camera_geometry(focal_length=51.5e-3, object_distance=1.0, focus_distance=1.0,
                        principal_separation=-3e-3)
    assert abs(float(g.defocus)) < 1e-15
    # Gaussian magnification −s_i/s_o with 1/s_o + 1/s_i = 1/f
    s_o, s_i = float(g.s_object), float(g.s_image)
    assert 1 / s_o + 1 / s_i == pytest.approx(1 / 51.5e-3, rel=1e-12)
    assert float(g.magnification) == pytest.approx(-s_i / s_o, rel=1e-12)


def test_infinity_focus_puts_exit_pupil_at_f_mp():
    g = camera_geometry(focal_length=50e-3, object_distance=1e9, focus_distance=jnp.inf,
                        pupil_magnification=0.8)
    assert float(g.extension) == 0.0
    assert float(g.z_exit_pupil) == pytest.approx(40e-3, rel=1e-12)


def test_geometry_grad_finite_and_matches_fd():
    def dz(rf):
        return camera_geometry(focal_length=51.5e-3, object_distance=1.0, focus_distance=rf,
                               principal_separation=-3e-3).defocus
    g = jax.grad(dz)(0.45)
    eps = 1e-6
    fd = (dz(0.45 + eps) - dz(0.45 - eps)) / (2 * eps)
    assert np.isfinite(g)
    assert float(g) == pytest.approx(float(fd), rel=1e-6)
    assert float(jax.jit(dz)(0.45)) == pytest.approx(float(dz(0.45)), rel=1e-14)


def test_too_close_focus_is_a_clear_error():
    cam, scene = difstar.paper_camera("focused")
    bad = difstar.Lens(cam.lens.pupil, focal_length=51.5e-3, focus_distance=0.1,
                       principal_separation=-3e-3)
    cam = difstar.Camera(bad, cam.sensor)
    with pytest.raises(ValueError, match="focus_distance .* too close"):
        difstar.simulate(cam, scene, difstar.Grid(n=64, crop=(32, 32)))
