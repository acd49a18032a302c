"""Radiometry (``difstar._radiometry``): the image follows the pupil's area over its
distance squared, so the f-number, the focus and the exposure time change RAW values as
a camera's would; point sources deliver I · A_entrance / r_ent².

Truths are analytic and computed here without difstar's geometry: the regular n-gon's
area n R² sin(2π/n) / 2, the thin-lens focus equation solved by bisection, the entrance
pupil at the front principal plane for m_p = 1. Images are summed over the whole
periodic grid (crop = n), where the FFT convolution conserves the object's total
exactly (Σ image = Σ object × Σ PSF); Σ PSF (= 1 less what the finite grid leaves out)
is divided out where the test is about radiometry, not sampling. float64.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import difstar

sim = eqx.filter_jit(difstar.simulate)

F = 51.5e-3  # the paper's lens (m_p = 1: both pupils at the principal planes)
ZP = -3e-3
PITCH = 3.917e-6
OMEGA_REF = math.pi / (4 * 22.0**2)  # the written-down reference: circular f/22 at ∞


def ngon_area(n: int, r: float) -> float:
    return 0.5 * n * r * r * math.sin(2 * math.pi / n)


def image_distance(focus_distance: float) -> float:
    """s' (rear principal plane to sensor) for a lens focused by extension at r_f from
    the sensor: 1/f = 1/(r_f − z_p − s') + 1/s', the root near f, by bisection."""
    if math.isinf(focus_distance):
        return F
    big_l = focus_distance - ZP

    def g(s):
        return 1 / (big_l - s) + 1 / s - 1 / F

    lo, hi = F * (1 + 1e-12), 2 * F  # g(lo) > 0 > g(hi) for L > 4 f
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if g(mid) > 0 else (lo, mid)
    return 0.5 * (lo + hi)


def camera(f_number=22.0, focus=1.0, *, blades=7, pupil=None, phi0=(0.02, 0.02, 0.02)):
    pupil = difstar.RegularPolygon(blades, F / (2 * f_number)) if pupil is None else pupil
    lens = difstar.Lens(pupil, focal_length=F, focus_distance=focus, principal_separation=ZP)
    sensor = difstar.Sensor(pixel_pitch=PITCH, phi0=phi0)
    return difstar.Camera(lens, sensor)


def scene(sources=(difstar.DiscSource(0.2e-3),), distance=1.0, t=1.0):
    return difstar.Scene(object_distance=distance, sources=sources, exposure_time=t)


def full_grid(n=256, q=2):
    """The whole periodic grid as the crop, in focus (no defocus phase)."""
    return difstar.Grid(n=n, oversample=q, crop=(n, n), use_defocus=False)


def totals(pred):
    return np.asarray(pred.image).sum(axis=(1, 2)), np.asarray(pred.psf).sum(axis=(1, 2))


# ------------------------------------------------------------------- the f-number


def test_f8_against_f22_at_the_same_exposure_gains_22_over_8_squared():
    """The issue's case: at the same exposure time and focus, unsaturated, opening from
    f/22 to f/8 multiplies the linear image's total by (22/8)² = 7.5625 within 1 % (the
    pupils' area ratio, R ∝ 1/N), and the RAW values rise with it (they fell before)."""
    sc = scene(t=2e-3)
    grid = full_grid()
    p22 = sim(camera(22.0), sc, grid)
    p8 = sim(camera(8.0), sc, grid)
    t22, _ = totals(p22)
    t8, _ = totals(p8)
    expected = ngon_area(7, F / 16) / ngon_area(7, F / 44)  # same z: the areas' ratio
    assert expected == pytest.approx((22 / 8) ** 2, rel=1e-12)
    np.testing.assert_allclose(t8 / t22, expected, rtol=1e-2)
    # unsaturated (the comparison is about the linear range), and the RAW follows
    assert float(jnp.max(p8.zeta)) < 0.8
    assert float(jnp.mean(p8.cfa)) > 5 * float(jnp.mean(p22.cfa))


def test_linear_image_total_is_the_radiance_times_the_pupils_solid_angle():
    """Absolute: Σ C = L · (A_exit / z²) / Ω_ref × (the disc's image area in pixels) ×
    Σ PSF, with A_exit the 7-gon's area, z = s' (exit pupil at the rear principal plane)
    and |M| = s' / (r_o − z_p − s') (in focus), all computed here."""
    r_o = 1.0
    cam, sc = camera(22.0, focus=r_o), scene(distance=r_o)
    pred = sim(cam, sc, full_grid())
    tot, psf_sum = totals(pred)
    s_img = image_distance(r_o)
    m = s_img / (r_o - ZP - s_img)
    area_px = math.pi * (m * 0.2e-3 / PITCH) ** 2
    expect = ngon_area(7, F / 44) / s_img**2 / OMEGA_REF * area_px
    np.testing.assert_allclose(tot / psf_sum, expect, rtol=2e-3)  # disc coverage ~1e-4


# ------------------------------------------------------------------- the pupil's area


@pytest.mark.parametrize("n", [3, 5, 7, 9, 16])
def test_regular_polygon_area_is_the_analytic_ngon(n):
    r = 1.3e-3
    got = float(difstar.pupil_area(difstar.RegularPolygon(n, r, 0.3)))
    assert got == pytest.approx(ngon_area(n, r), rel=1e-12)


def test_other_pupils_areas():
    r = 1.0e-3
    sq = difstar.Polygon(np.array([[-r, -r], [r, -r], [r, r], [-r, r]]))
    assert float(difstar.pupil_area(sq)) == pytest.approx(4 * r * r, rel=1e-12)
    assert float(difstar.pupil_area(difstar.Circle(r))) == pytest.approx(math.pi * r * r,
                                                                          rel=1e-12)
    # rotated and shifted: the same area
    moved = difstar.Transformed(sq, 0.3, (1e-4, -2e-4))
    assert float(difstar.pupil_area(moved)) == pytest.approx(4 * r * r, rel=1e-12)
    # a central obstruction removes its disc
    ob = difstar.Obstructed(difstar.Circle(r), difstar.Circle(0.3 * r))
    assert float(difstar.pupil_area(ob)) == pytest.approx(math.pi * r * r * (1 - 0.09),
                                                           rel=1e-12)
    # vanes remove (about) width × their length inside the annulus: 4 vanes of width w
    # from the obstruction to the rim (the rectangles' ends are cut by the circles:
    # within w²/r of the rectangle); by the raster of exact area coverage
    w = 0.02 * r
    spid = difstar.Obstructed(difstar.Circle(r), difstar.Circle(0.3 * r),
                              difstar.Spiders(4, w, 0.1, 2 * r))
    expect = math.pi * r * r * 0.91 - 4 * w * 0.7 * r
    assert float(difstar.pupil_area(spid)) == pytest.approx(expect, rel=2e-3)


def test_pupil_area_gradient_is_the_analytic_one():
    n, r = 7, 1.17e-3
    g = jax.grad(lambda rr: difstar.pupil_area(difstar.RegularPolygon(n, rr)))(r)
    assert float(g) == pytest.approx(n * r * math.sin(2 * math.pi / n), rel=1e-12)


# ------------------------------------------------------------------------ the focus


@pytest.mark.parametrize("focus", [1.0, 0.45, 0.3])
def test_focusing_closer_dims_as_z_inf_over_z_squared(focus):
    """The exit pupil (at P' for m_p = 1) moves out with the lens: z = s'; the image
    irradiance of an extended source falls as (z_∞ / z)² = (f / s')²."""
    sc = scene(distance=2.0)
    inf = float(difstar.irradiance_scale(camera(22.0, math.inf), sc))
    near = float(difstar.irradiance_scale(camera(22.0, focus), sc))
    assert near / inf == pytest.approx((F / image_distance(focus)) ** 2, rel=1e-10)
    # and the absolute scale: the 7-gon's solid angle at z = f over Ω_ref
    assert inf == pytest.approx(ngon_area(7, F / 44) / F**2 / OMEGA_REF, rel=1e-12)


def test_focusing_closer_dims_the_image_itself():
    """Through the chain: the centre of a disc much larger than the PSF's core (the PSF's
    tails beyond it are < 2e-2 of its light and nearly the same at both settings),
    imaged in focus at 1 m and at 0.3 m: the ratio of the irradiances is (s'₁ / s'₀.₃)²
    within 0.5 %."""
    vals = {}
    for r in (1.0, 0.3):
        m = image_distance(r) / (r - ZP - image_distance(r))
        radius = 60 * PITCH / m  # 60 px on the sensor at either distance
        pred = sim(camera(22.0, focus=r), scene((difstar.DiscSource(radius),), distance=r),
                   full_grid(256, 1))
        vals[r] = float(pred.image[1, 128, 128])
    expect = (image_distance(1.0) / image_distance(0.3)) ** 2
    assert vals[0.3] / vals[1.0] == pytest.approx(expect, rel=5e-3)


# -------------------------------------------------------------------- point sources


def test_point_source_total_is_its_intensity_times_the_entrance_pupils_solid_angle():
    """P = I · A_ent / r_ent² (A_ent = A_exit for m_p = 1, the entrance pupil at the
    front principal plane: r_ent = r_o − z_p − s'); the linear image's total is
    P / (p² Ω_ref) × Σ PSF, and the sensor sees it × t / φ0 (a linear response)."""
    r_o, intensity = 1.0, np.array([2e-7, 1e-7, 3e-7])
    pt = difstar.PointSource((0.7 * PITCH / 0.0574, -0.2 * PITCH / 0.0574), intensity)
    cam = camera(22.0, focus=r_o)
    pred = sim(cam, scene((pt,), distance=r_o, t=0.5), full_grid())
    tot, psf_sum = totals(pred)
    r_ent = r_o - ZP - image_distance(r_o)
    power = intensity * ngon_area(7, F / 44) / r_ent**2
    np.testing.assert_allclose(tot / psf_sum, power / (PITCH**2 * OMEGA_REF), rtol=1e-9)


def test_point_source_and_disc_of_equal_intensity_give_equal_images():
    """A disc of radiance L and radius r is, seen from afar, a point of I = π r² L: the
    two totals agree to the disc's coverage accuracy (6e-4 for this disc, 2.9 px in
    radius on the sensor), and so does the light in the spikes beyond 20 px (the disc
    only smooths their fringes)."""
    r_o, r, L = 1.0, 2e-4, 1.0
    cam = camera(22.0, focus=r_o)
    grid = full_grid()
    disc = sim(cam, scene((difstar.DiscSource(r, (0.0, 0.0), (L, L, L)),), distance=r_o),
               grid)
    point = sim(cam, scene((difstar.PointSource((0.0, 0.0), (math.pi * r * r * L,) * 3),),
                           distance=r_o), grid)
    np.testing.assert_allclose(totals(point)[0], totals(disc)[0], rtol=2e-3)
    far = np.ones((256, 256), bool)
    far[128 - 20:128 + 21, 128 - 20:128 + 21] = False
    a, b = np.asarray(point.image[1])[far].sum(), np.asarray(disc.image[1])[far].sum()
    assert a == pytest.approx(b, rel=2e-2)  # the spikes' light beyond 20 px


def test_point_source_on_a_pixel_centre_images_as_the_psf():
    cam = camera(22.0)
    pred = sim(cam, scene((difstar.PointSource((0.0, 0.0), (1e-7, 1e-7, 1e-7)),)),
               full_grid(128, 1))
    for c in range(3):
        img, psf = np.asarray(pred.image[c]), np.asarray(pred.psf[c])
        np.testing.assert_allclose(img / img.sum(), psf / psf.sum(), rtol=0,
                                   atol=1e-12 * psf.max())


def test_mixed_sources_add_up():
    """Discs and points in one list (in any order) give the sum of their images."""
    cam = camera(22.0)
    d = difstar.DiscSource(0.1e-3, (3e-4, 0.0), (1.0, 0.5, 0.2))
    p = difstar.PointSource((-2e-4, 1e-4), (1e-8, 2e-8, 3e-8))
    grid = full_grid(128, 1)
    both = sim(cam, scene((p, d)), grid).image
    apart = sim(cam, scene((d,)), grid).image + sim(cam, scene((p,)), grid).image
    np.testing.assert_allclose(np.asarray(both), np.asarray(apart), rtol=0,
                               atol=1e-12 * float(jnp.max(apart)))


def test_point_source_through_the_chosen_grid_and_its_position_gradient():
    """choose_grid sizes its windows from a point too, and the image moves smoothly
    with the point's position (bilinear placement: a finite, non-zero gradient)."""
    from difstar._sampling import choose_grid

    cam = camera(22.0)
    sc = scene((difstar.PointSource((1e-5, 2e-5), (1e-7,) * 3),), t=2.0)
    grid = choose_grid(cam, sc, crop=(32, 32))
    pred = sim(cam, sc, grid)
    assert np.all(np.isfinite(np.asarray(pred.cfa)))

    def loss(x):
        s = eqx.tree_at(lambda s: s.sources[0].position, sc, jnp.stack([x, 2e-5]))
        return jnp.sum(difstar.simulate(cam, s, grid).image[1] * jnp.arange(32.0)[None, :])

    # the gradient and the differences compiled, not run op by op (4x as long)
    g = jax.jit(jax.grad(loss))(1e-5)
    loss = jax.jit(loss)
    h = 1e-8
    fd = (loss(1e-5 + h) - loss(1e-5 - h)) / (2 * h)
    assert np.isfinite(float(g)) and float(g) != 0.0
    assert float(g) == pytest.approx(float(fd), rel=1e-5)


def test_bad_point_sources_are_refused():
    from difstar._validate import InputError, check_camera_scene

    cam = camera(22.0)
    with pytest.raises(InputError, match=r"sources\[0\]\.intensity.*> 0"):
        check_camera_scene(cam, scene((difstar.PointSource((0.0, 0.0), (0.0, 0.0, 0.0)),)))
    with pytest.raises(InputError, match=r"sources\[1\]\.intensity\[2\]"):
        check_camera_scene(cam, scene((difstar.DiscSource(1e-4),
                                       difstar.PointSource((0.0, 0.0), (1.0, 1.0, -1.0)))))
    with pytest.raises(InputError, match=r"sources\[0\]\.position\[0\]"):
        check_camera_scene(cam, scene((difstar.PointSource((np.nan, 0.0)),)))
    with pytest.raises(TypeError, match=r"Scene.sources\[0\] must be a DiscSource or a "):
        scene(("a star",))


# -------------------------------------------------------------- φ0 and the examples


@pytest.mark.parametrize("config", ["focused", "defocused"])
def test_paper_examples_phi0_converted_once_for_their_configuration(config):
    """The paper's φ0 is characterised at its configuration (seconds at f/22 and that
    focus); the example's Sensor holds it × (A_exit / z²) / Ω_ref, so that C t / φ0 —
    and hence every RAW and sRGB value — is what it was. z = s' (m_p = 1)."""
    from difstar._examples import PAPER, PAPER_CONFIGS

    cam, _ = difstar.paper_camera(config)
    z = image_distance(PAPER_CONFIGS[config]["focus_distance"])
    k = ngon_area(7, F / 44) / z**2 / OMEGA_REF
    np.testing.assert_allclose(np.asarray(cam.sensor.phi0), np.asarray(PAPER["phi0"]) * k,
                               rtol=1e-9)


@pytest.mark.parametrize("config", ["focused", "defocused"])
def test_paper_example_renders_as_before(config, monkeypatch):
    """The converted example gives the RAW and sRGB of the model before radiometry (the
    image of a unit radiance is 1 whatever the pupil, φ0 the paper's per-configuration
    seconds), to rounding. (The figures themselves are checked by tests/test_chain.py,
    test_colour.py and test_hard_cases.py against their stored values.)"""
    from difstar import _chain
    from difstar._examples import PAPER
    from difstar._radiometry import Radiometry

    cam, sc = difstar.paper_camera(config)
    sc = eqx.tree_at(lambda s: s.sources, sc, (difstar.DiscSource(0.5e-3),))
    grid = difstar.Grid(n=128, crop=(64, 64), use_defocus=config == "defocused")
    # each simulation compiled (run op by op, each took 3x as long), each by a program
    # of its own: the second is traced after the patch below, not the first's reused
    new = eqx.filter_jit(lambda *a: difstar.simulate(*a))(cam, sc, grid)
    monkeypatch.setattr(_chain, "radiometry",
                        lambda *a: Radiometry(jnp.asarray(OMEGA_REF), jnp.asarray(OMEGA_REF)))
    before = eqx.filter_jit(lambda *a: difstar.simulate(*a))(
        eqx.tree_at(lambda c: c.sensor.phi0, cam, jnp.asarray(PAPER["phi0"], float)), sc,
        grid)
    np.testing.assert_allclose(np.asarray(new.cfa), np.asarray(before.cfa), rtol=1e-12,
                               atol=1e-14)
    np.testing.assert_allclose(np.asarray(new.srgb), np.asarray(before.srgb), rtol=1e-12,
                               atol=1e-12)
    assert float(jnp.max(new.cfa)) > 0.5  # the comparison is not of dark frames


def test_phi0_from_configuration_keeps_that_configuration_and_follows_the_others():
    cam8, cam22, sc = camera(8.0), camera(22.0), scene()
    phi0 = difstar.phi0_from_configuration((0.01, 0.02, 0.03), cam22, sc)
    k = ngon_area(7, F / 44) / image_distance(1.0) ** 2 / OMEGA_REF
    np.testing.assert_allclose(np.asarray(phi0), np.array([0.01, 0.02, 0.03]) * k, rtol=1e-9)
    # the same φ0 at f/8: the irradiance scale 7.5625 × larger
    r = difstar.irradiance_scale(cam8, sc) / difstar.irradiance_scale(cam22, sc)
    assert float(r) == pytest.approx((22 / 8) ** 2, rel=1e-12)


# ---------------------------------------------------------------- differentiability


def test_irradiance_scale_jit_grad_jacfwd():
    sc = scene()

    def scale(radius, focus):
        cam = camera(22.0, focus, pupil=difstar.RegularPolygon(7, radius))
        return difstar.irradiance_scale(cam, sc)

    r0, f0 = F / 44, 0.8
    eager = float(scale(r0, f0))
    assert float(jax.jit(scale)(r0, f0)) == pytest.approx(eager, rel=1e-14)
    g = jax.grad(scale, argnums=(0, 1))(r0, f0)
    jf = jax.jacfwd(scale, argnums=(0, 1))(r0, f0)
    z = image_distance(f0)
    # analytic in R: 2 × scale / R
    assert float(g[0]) == pytest.approx(2 * eager / r0, rel=1e-10)
    assert float(jf[0]) == pytest.approx(float(g[0]), rel=1e-12)
    # in the focus distance: finite differences of the analytic (z_∞/z)² law
    h = 1e-5
    fd = (ngon_area(7, r0) / OMEGA_REF) * (image_distance(f0 + h) ** -2
                                          - image_distance(f0 - h) ** -2) / (2 * h)
    assert float(g[1]) == pytest.approx(fd, rel=1e-6)
    assert float(jf[1]) == pytest.approx(float(g[1]), rel=1e-12)
    assert z > F


def test_chain_gradient_through_the_scale_matches_finite_differences():
    """d(Σ image)/d(circumradius) of the whole chain (area × PSF): finite and equal to
    central differences."""
    sc = scene()
    grid = full_grid(64, 1)

    def total(radius):
        cam = camera(22.0, pupil=difstar.RegularPolygon(7, radius))
        return jnp.sum(difstar.simulate(cam, sc, grid).image[1])

    r0 = F / 44
    g = float(jax.jit(jax.grad(total))(r0))
    total = jax.jit(total)  # the differences: one compiled program, not op by op
    h = 1e-4 * r0
    fd = float((total(r0 + h) - total(r0 - h)) / (2 * h))
    assert np.isfinite(g) and g == pytest.approx(fd, rel=1e-5)
