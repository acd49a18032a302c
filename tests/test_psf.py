"""The PSF against independent truths: the exact polygon transform (Lee & Mittra), the
Airy pattern, the geometric defocus disc; energy; spike counts; sampling errors; jit and
gradients."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.ndimage
import scipy.signal

import difstar
from difstar._atf import atf
from helpers import airy_psf, polygon_psf_exact

F = 51.5e-3
P = 3.917e-6
R22 = F / (2 * 22)  # exit-pupil circumradius at f/22 (pupil magnification 1)


def _rel_rms(a, b):
    return float(np.sqrt(np.mean((a - b) ** 2)) / np.sqrt(np.mean(b**2)))


@pytest.mark.parametrize("wavelength", [450e-9, 600e-9])
def test_polygon_in_focus_matches_exact_transform(wavelength):
    # point samples: the exact transform (Lee & Mittra, NumPy) × p², fraction of power
    pup = difstar.RegularPolygon(7, R22, 0.3)
    n = 256
    got = np.asarray(difstar.psf(pup, wavelength=wavelength, z_image=F, pixel_pitch=P,
                                 shape=(n, n), sampling="point"))
    exact = polygon_psf_exact(np.asarray(pup.vertices), wavelength=wavelength, z=F,
                              pixel_pitch=P, shape=(n, n))
    assert _rel_rms(got, exact) < 1e-10


def test_polygon_pixel_integral_matches_gauss_legendre_of_exact_transform():
    # f/8-like hexagon: the pixel integral against a 10 × 10 Gauss–Legendre rule per
    # pixel of the exact transform (converged far below the tolerance)
    pup = difstar.RegularPolygon(6, F / 16, 0.0)
    lam, n, m = 530e-9, 48, 10
    got = np.asarray(difstar.psf(pup, wavelength=lam, z_image=F, pixel_pitch=P, shape=(n, n)))
    x, wt = np.polynomial.legendre.leggauss(m)
    fine = polygon_psf_exact(np.asarray(pup.vertices), wavelength=lam, z=F, pixel_pitch=P,
                             shape=(n, n))  # only for the scale
    u = ((np.arange(n) - n // 2)[:, None] + 0.5 * x[None, :]).ravel() * P
    v = -u
    from helpers import polygon_ft
    amp = polygon_ft(np.asarray(pup.vertices), 2 * np.pi * u[None, :] / (lam * F),
                     2 * np.pi * v[:, None] / (lam * F))
    area = 3 * np.sqrt(3) / 2 * (F / 16) ** 2
    dens = np.abs(amp) ** 2 / ((lam * F) ** 2 * area)
    ref = np.einsum("aibj,i,j->ab", dens.reshape(n, m, n, m), wt / 2, wt / 2) * P * P
    assert _rel_rms(got, ref) < 1e-5
    assert _rel_rms(got, fine) > 1e-2  # point samples differ from the pixel integral


def test_circle_in_focus_is_airy():
    lam, nw = 550e-9, 22.0
    r = F / (2 * nw)
    n = 256
    got = np.asarray(difstar.psf(difstar.Circle(r), wavelength=lam, z_image=F, pixel_pitch=P,
                                 shape=(n, n), sampling="point"))
    yy, xx = np.mgrid[:n, :n] - n // 2
    rad = np.hypot(yy, xx) * P
    # peak intensity of a fraction-of-power PSF: area / (λ z)² per m²
    airy = airy_psf(rad, wavelength=lam, f_number=nw) * np.pi * r**2 / (lam * F) ** 2 * P**2
    assert _rel_rms(got, airy) < 1e-3
    # first dark ring at 1.22 λ N (f/64 so it spans ~11 pixels): the radial profile,
    # interpolated from the pixels, has its first minimum there
    nw = 64.0
    got = np.asarray(difstar.psf(difstar.Circle(F / (2 * nw)), wavelength=lam, z_image=F,
                                 pixel_pitch=P, shape=(n, n), sampling="point"))
    radii = np.linspace(0.6, 1.5, 181) * 1.22 * lam * nw
    prof = scipy.ndimage.map_coordinates(got, [n // 2 + 0 * radii, n // 2 + radii / P], order=3)
    r_min = radii[int(np.argmin(prof))]
    assert r_min == pytest.approx(1.22 * lam * nw, rel=0.01)


def test_large_defocus_approaches_geometric_disc():
    # f/2.8-like pupil, Δz = 1 mm: W020 = ½(1/z_i − 1/z_R) r²/λ ≈ 30 waves; blur radius
    # r Δz / z_i. Geometric optics is the limit; diffraction at 30 waves moves the encircled
    # energies by up to 0.02 (the Hankel integral gives 0.8305 at 0.9 r_geo, against 0.8095).
    lam = 550e-9
    r = F / (2 * 2.8)
    z_r = F
    dz = 1e-3
    n = 128
    got = np.asarray(difstar.psf(difstar.Circle(r), wavelength=lam, z_image=z_r, defocus=dz,
                                 pixel_pitch=P, shape=(n, n), accuracy=1e-2))
    r_geo = r * dz / (z_r - dz)
    yy, xx = np.mgrid[:n, :n] - n // 2
    rad = np.hypot(yy, xx) * P
    # encircled energy follows (ρ/R)² inside the disc, 1 outside (geometric optics)
    # (the pixels counted cover area count·p², not exactly π (frac r_geo)²)
    for frac in (0.3, 0.5, 0.7, 0.9):
        inside = rad <= frac * r_geo
        expected = inside.sum() * P**2 / (np.pi * r_geo**2)
        assert got[inside].sum() == pytest.approx(expected, abs=0.03)
    assert got[rad <= 1.15 * r_geo].sum() > 0.97


@pytest.mark.parametrize("blades,spikes", [(7, 14), (6, 6), (8, 8), (5, 10)])
def test_spike_count(blades, spikes):
    pup = difstar.RegularPolygon(blades, R22, 0.1)
    n = 256
    p = np.asarray(difstar.psf(pup, wavelength=530e-9, z_image=F, pixel_pitch=P, shape=(n, n)))
    theta = np.linspace(0, 2 * np.pi, 1440, endpoint=False)
    ring = np.zeros_like(theta)
    for rr in np.arange(40, 100):  # average over radii to wash out the rings
        rows = n // 2 - rr * np.sin(theta)
        cols = n // 2 + rr * np.cos(theta)
        ring += scipy.ndimage.map_coordinates(p, [rows, cols], order=1) * rr**2
    ring = np.concatenate([ring, ring[:50]])
    peaks, _ = scipy.signal.find_peaks(ring, prominence=0.2 * ring.max())
    peaks = peaks[peaks < 1440]
    assert len(peaks) == spikes


def test_energy_and_centring():
    # fraction of power: the window holds less than all of it; the peak is the centre pixel
    pup = difstar.RegularPolygon(7, R22, 0.0)
    for shape, sampling in [((64, 64), "pixel"), ((65, 63), "point"), ((64, 80), "pixel")]:
        p = difstar.psf(pup, wavelength=600e-9, z_image=F, pixel_pitch=P, shape=shape,
                        sampling=sampling)
        assert 0.97 < float(jnp.sum(p)) < 1.0
        pk = np.unravel_index(int(jnp.argmax(p)), p.shape)
        assert pk == (shape[0] // 2, shape[1] // 2)


def test_unreachable_accuracy_and_bad_arguments_are_clear_errors():
    pup = difstar.Circle(R22)
    with pytest.raises(difstar.SamplingError, match="accuracy target .* memory"):
        difstar.psf(pup, wavelength=450e-9, z_image=F, defocus=5e-3, pixel_pitch=P,
                    shape=(1024, 1024), accuracy=1e-7)
    with pytest.raises(ValueError, match="sampling must be one of"):
        difstar.psf(pup, wavelength=450e-9, z_image=F, pixel_pitch=P, shape=(8, 8),
                    sampling="area")
    with pytest.raises(ValueError, match="oversample must be an integer"):
        difstar.psf(pup, wavelength=450e-9, z_image=F, pixel_pitch=P, shape=(8, 8), oversample=0)
    with pytest.raises(ValueError, match="plan_psf"):
        jax.jit(lambda r: difstar.psf(difstar.Circle(r), wavelength=450e-9, z_image=F,
                                      pixel_pitch=P, shape=(8, 8)))(R22)


def test_paper_scaling_option_differs_as_expected():
    # paper form scales the pupil by λ z_i: with Δz > 0 its PSF is larger by z_R / z_i
    pup = difstar.Circle(R22)
    kw = dict(wavelength=530e-9, z_image=F, defocus=0.0, pixel_pitch=P, shape=(64, 64))
    a = difstar.psf(pup, scaling="fresnel", **kw)
    b = difstar.psf(pup, scaling="paper", **kw)
    np.testing.assert_allclose(a, b, atol=1e-15)  # identical in focus
    with pytest.raises(ValueError, match="scaling must be one of"):
        difstar.psf(pup, scaling="nope", **kw)


# planned outside jit (Δz, rotation and radius are traced below): with the defocus phase,
# for pupils up to 1.1 R22
PLAN = difstar.plan_psf(difstar.RegularPolygon(7, 1.1 * R22, 0.0), wavelength=530e-9,
                        z_image=F, defocus=0.5e-3, pixel_pitch=P, shape=(32, 32))


def _psf_fn(dz, rot, r):
    pup = difstar.RegularPolygon(7, r, rot)
    p = difstar.psf(pup, wavelength=530e-9, z_image=F, defocus=dz, pixel_pitch=P,
                    shape=(32, 32), plan=PLAN)
    w = jnp.linspace(0.0, 1.0, 32)
    return jnp.sum(p * (w[:, None] + 2 * w[None, :] ** 2))


def test_psf_jit_equals_nojit():
    args = (jnp.asarray(0.5e-3), jnp.asarray(0.2), jnp.asarray(R22))
    assert float(jax.jit(_psf_fn)(*args)) == pytest.approx(float(_psf_fn(*args)), rel=1e-12)


def _check_gradients(fn, dz, grad=None):
    """grad of ``fn(dz, rotation, size)`` finite and within 1e-4 of central differences
    (steps 1e-6 m, 1e-6 rad, 1e-9 m); returns the gradients. ``grad``: the compiled
    ``jax.jit(jax.grad(fn, argnums=(0, 1, 2)))`` where the caller already has it."""
    args = [jnp.asarray(dz), jnp.asarray(0.2), jnp.asarray(R22)]
    if grad is None:
        grad = jax.jit(jax.grad(fn, argnums=(0, 1, 2)))
    grads = grad(*args)
    fn = jax.jit(fn)  # the differences: one compiled program, not op by op
    steps = (1e-6, 1e-6, 1e-9)
    for i, (g, eps) in enumerate(zip(grads, steps)):
        assert np.isfinite(g)
        hi = list(args)
        lo = list(args)
        hi[i] = hi[i] + eps
        lo[i] = lo[i] - eps
        fd = (fn(*hi) - fn(*lo)) / (2 * eps)
        assert float(g) == pytest.approx(float(fd), rel=1e-4, abs=1e-12)
    return args, grads


@pytest.mark.parametrize("dz", [0.0, 0.3e-3])
def test_psf_gradients_match_finite_differences(dz):
    # Δz = 0 is a hard point: the defocus phase's derivative must stay finite there.
    _check_gradients(_psf_fn, dz)


def test_fft_passes_by_blocks_have_the_gradients(monkeypatch):
    """The FFT passes a few rows at a time (FFT_BLOCK_BYTES so small that each block holds
    8 rows, the last padded, as on large windows): jit, grad and jacfwd through them, in
    Δz (at 0, a hard point), rotation and size, match central differences."""
    from difstar import _psf_engine

    monkeypatch.setattr(_psf_engine, "FFT_BLOCK_BYTES", 1)
    plan = difstar.plan_psf(difstar.RegularPolygon(7, 1.1 * R22, 0.0), wavelength=530e-9,
                            z_image=F, defocus=0.5e-3, pixel_pitch=P, shape=(30, 30),
                            method="fft")
    assert plan.pupil_window > 8 and plan.pupil_window % 8 != 0

    def f(dz, rot, r):
        p = difstar.psf(difstar.RegularPolygon(7, r, rot), wavelength=530e-9, z_image=F,
                        defocus=dz, pixel_pitch=P, shape=(30, 30), plan=plan)
        w = jnp.linspace(0.0, 1.0, 30)
        return jnp.sum(p * (w[:, None] + 2 * w[None, :] ** 2))

    # grad and jacfwd compiled once for both Δz (the same programs, given Δz as an
    # array): made in the loop, each was traced and compiled again for the second
    grad = jax.jit(jax.grad(f, argnums=(0, 1, 2)))
    jacfwd = jax.jit(jax.jacfwd(f, argnums=(0, 1, 2)))
    for dz in (0.0, 0.3e-3):
        args, grads = _check_gradients(f, dz, grad)
        assert float(jax.jit(f)(*args)) == pytest.approx(float(f(*args)), rel=1e-12)
        forward = jacfwd(*args)
        for fw, g in zip(forward, grads):
            assert float(fw) == pytest.approx(float(g), rel=1e-10, abs=1e-14)


def test_vertex_gradient_finite_on_grid_line():
    # A vertex placed exactly on a frequency-grid line (x = 0 column).
    n = 32
    v0 = np.asarray(difstar.RegularPolygon(6, R22, np.pi / 2).vertices)  # first vertex on x=0
    plan = difstar.plan_psf(difstar.Polygon(v0), wavelength=530e-9, z_image=F, pixel_pitch=P,
                            shape=(n, n), method="mft")

    def f(v):
        p = difstar.psf(difstar.Polygon(v), wavelength=530e-9, z_image=F, pixel_pitch=P,
                        shape=(n, n), plan=plan)
        w = jnp.linspace(0.0, 1.0, n)
        return jnp.sum(p * (w[:, None] ** 2 + 0.5 * w[None, :]))

    g = jax.jit(jax.grad(f))(jnp.asarray(v0))
    assert np.all(np.isfinite(np.asarray(g)))
    f = jax.jit(f)  # the differences: compiled, not op by op
    eps = 1e-8  # 1e-5 of the radius
    for k in (0, 1):
        e = np.zeros_like(v0)
        e[0, k] = eps
        fd = (f(jnp.asarray(v0 + e)) - f(jnp.asarray(v0 - e))) / (2 * eps)
        assert float(g[0, k]) == pytest.approx(float(fd), rel=1e-4, abs=1e-3)


def test_atf_drops_phase_statically_at_zero_defocus():
    pup = difstar.Circle(R22)
    kw = dict(wavelength=530e-9, z_image=F, dx=P, shape=(32, 32))
    a = atf(pup, defocus=0.0, use_defocus=False, **kw)
    b = atf(pup, defocus=0.0, use_defocus=True, **kw)
    np.testing.assert_allclose(a, b, atol=1e-15)


@pytest.mark.parametrize("method", ["fft", "mft"])
def test_undersampled_pixels_both_transforms_match_hankel(method):
    # f/2.8 with 3.917 µm pixels: the pupil spans more frequencies than one pixel pitch
    # resolves (λN = 1.5 µm < p), so the pruned FFTs must fold the pupil onto their
    # range (aliased frequencies coincide at the pixel centres) instead of cutting it
    import references as R

    lam, r, n = 530e-9, F / 5.6, 48
    dz = R.defocus_from_waves(2.0, wavelength=lam, radius=r, z_image=F)
    got = np.asarray(difstar.psf(difstar.Circle(r), wavelength=lam, z_image=F, defocus=dz,
                                 pixel_pitch=P, shape=(n, n), sampling="point", method=method))
    ref = R.circle_psf(radius=r, wavelength=lam, z=F, pixel_pitch=P, shape=(n, n),
                       sampling="point",
                       phase=R.radial_phase(wavelength=lam, radius=r, waves=2.0))
    assert _rel_rms(got, ref) < 1e-3


def test_gradients_wrt_zernike_coefficients_and_spectral_weights_match_fd():
    # f/8 circle, 64²: d(spike-region light)/d(Noll 4, 6, 11 coefficients) and d/d(a
    # spectral weight), against central differences (float64)
    import equinox as eqx

    r = F / 16
    lam = 530e-9
    zern = difstar.Zernike({4: 0.05 * lam, 6: -0.03 * lam, 11: 0.04 * lam}, radius=r)
    kw = dict(z_image=F, pixel_pitch=P, shape=(64, 64))
    wl = jnp.asarray([480e-9, 530e-9, 600e-9])
    plan = difstar.plan_psf(difstar.Circle(r), wavelength=wl, wavefront=zern, **kw)
    w = jnp.linspace(0.0, 1.0, 64)
    weight_map = w[:, None] ** 2 + 0.3 * w[None, :]

    def f(coeffs, weights):
        z = eqx.tree_at(lambda t: t.coefficients, zern, coeffs)
        p = difstar.psf(difstar.Circle(r), wavelength=wl, weights=weights, wavefront=z,
                        plan=plan, **kw)
        return jnp.sum(p * weight_map)

    c0 = zern.coefficients
    w0 = jnp.asarray([0.2, 0.5, 0.3])
    gc, gw = jax.jit(jax.grad(f, argnums=(0, 1)))(c0, w0)
    assert np.all(np.isfinite(gc)) and np.all(np.isfinite(gw))
    f = jax.jit(f)  # the differences: compiled, not op by op
    for i in range(3):
        e = jnp.zeros(3).at[i].set(1e-10)
        fd = (f(c0 + e, w0) - f(c0 - e, w0)) / 2e-10
        assert float(gc[i]) == pytest.approx(float(fd), rel=1e-5, abs=1e-3)
        e = jnp.zeros(3).at[i].set(1e-6)
        fd = (f(c0, w0 + e) - f(c0, w0 - e)) / 2e-6
        assert float(gw[i]) == pytest.approx(float(fd), rel=1e-6, abs=1e-9)
    jf = jax.jacfwd(f)(c0, w0)  # forward mode through the sampled-pupil path
    np.testing.assert_allclose(jf, gc, rtol=1e-8)


@pytest.mark.parametrize("dz", [0.0, 0.3e-3])
def test_plain_call_plans_and_traces_once(monkeypatch, dz):
    """A plain call (concrete inputs, no plan) makes its plan once and compiles once:
    a repeated call reuses both, another rotation reuses the compiled program, and the
    values equal those of the call with an explicit plan (and the exact transform in
    focus, test_polygon_in_focus_matches_exact_transform)."""
    import difstar._psf as mod

    plans, traces = [], []
    real_plan, real_eval = mod.plan_psf, mod._evaluate_all
    monkeypatch.setattr(mod, "plan_psf", lambda *a, **k: plans.append(1) or real_plan(*a, **k))
    monkeypatch.setattr(mod, "_evaluate_all",
                        lambda *a, **k: traces.append(1) or real_eval(*a, **k))
    kw = dict(wavelength=530e-9, z_image=F, defocus=dz, pixel_pitch=P, shape=(38, 34))
    first = difstar.psf(difstar.RegularPolygon(7, R22, 0.1), **kw)
    again = difstar.psf(difstar.RegularPolygon(7, R22, 0.1), **kw)
    assert len(plans) == 1 and len(traces) == 1
    turned = difstar.psf(difstar.RegularPolygon(7, R22, 0.3), **kw)
    assert len(traces) == 1
    # the call with an explicit plan under jit (its inputs closed over, concrete): run
    # op by op it took most of this test's time
    ref_plan = real_plan(difstar.RegularPolygon(7, R22, 0.3), **kw)
    ref = jax.jit(lambda: difstar.psf(difstar.RegularPolygon(7, R22, 0.3), plan=ref_plan,
                                      **kw))()
    np.testing.assert_array_equal(np.asarray(first), np.asarray(again))
    np.testing.assert_allclose(np.asarray(turned), np.asarray(ref), rtol=1e-10,
                               atol=1e-12 * float(np.max(ref)))


def test_a_plan_for_a_smaller_window_is_refused_where_it_would_wrap():
    """The field is periodic with the plan's period: a plan made for a 64² window, given
    to a call for 512² (the window alone longer than the period), was used as it was
    and wrapped the PSF onto itself without a word. A call within the period keeps it:
    the plan for 64² on 100² gives the PSF of a plan made for 100² to 1e-3 of its peak.
    Point samples: the period does not depend on the sampling, and pixel sampling's nodes
    made this test 4× longer."""
    from difstar._validate import InputError

    cam, scene = difstar.paper_camera("defocused")
    g = difstar.geometry_of(cam, scene)
    kw = dict(wavelength=530e-9, z_image=float(g.z_exit_pupil), defocus=float(g.defocus),
              pixel_pitch=float(cam.sensor.pixel_pitch), sampling="point")
    pup = cam.lens.pupil
    small = difstar.plan_psf(pup, shape=(64, 64), **kw)
    with pytest.raises(InputError, match=r"plan's period .* shorter than this window"):
        difstar.psf(pup, shape=(512, 512), plan=small, **kw)
    # under jit (the inputs closed over, so still concrete and checked): a call with a
    # plan otherwise runs op by op, 4x as long
    got = np.asarray(jax.jit(lambda: difstar.psf(pup, shape=(100, 100), plan=small, **kw))())
    want = np.asarray(difstar.psf(pup, shape=(100, 100), **kw))
    assert np.abs(got - want).max() < 1e-3 * want.max()


@pytest.mark.parametrize("method", ["fft", "mft"])
def test_psf_each_gives_each_wavelengths_psf(method):
    """``psf_each`` (the simulation's three channels: their sampled pupils made at once)
    against the Hankel integral of a defocused circle at each wavelength (1e-3, the
    engine's accuracy), and against ``psf`` called one wavelength at a time (the same
    numbers, 1e-12); jit, grad and jacfwd in Δz (0 is a hard point) and the radius
    finite and within 1e-4 of central differences. A plan is required and checked."""
    import references as R
    from difstar._psf import psf_each

    lams = jnp.asarray([600e-9, 530e-9, 450e-9])
    r, n = F / 11, 40
    dz = R.defocus_from_waves(1.5, wavelength=530e-9, radius=r, z_image=F)
    plan = difstar.plan_psf(difstar.Circle(r), wavelength=lams, z_image=F, defocus=dz,
                            pixel_pitch=P, shape=(n, n), sampling="point", method=method)
    kw = dict(z_image=F, pixel_pitch=P, shape=(n, n), plan=plan)
    # under jit (the inputs closed over, still concrete and checked): op by op it takes
    # 3x as long
    got = np.asarray(jax.jit(lambda: psf_each(difstar.Circle(r), lams, defocus=dz, **kw))())
    assert got.shape == (3, n, n)
    for c, lam in enumerate(np.asarray(lams)):
        one = np.asarray(difstar.psf(difstar.Circle(r), wavelength=lam, defocus=dz, **kw))
        np.testing.assert_allclose(got[c], one, rtol=1e-12, atol=1e-14 * one.max())
        waves = 1.5 * 530e-9 / lam  # W020 in this wavelength's waves
        ref = R.circle_psf(radius=r, wavelength=lam, z=F, pixel_pitch=P, shape=(n, n),
                           sampling="point",
                           phase=R.radial_phase(wavelength=lam, radius=r, waves=waves))
        assert _rel_rms(got[c], ref) < 1e-3

    w = jnp.linspace(0.0, 1.0, n) * jnp.arange(1.0, 4.0)[:, None, None]

    def f(d, radius):
        p = psf_each(difstar.Circle(radius), lams, defocus=d, **kw)
        return jnp.sum(p * (w[..., :, None] + 2 * w[..., None, :] ** 2))

    fj = jax.jit(f)
    # grad and jacfwd compiled once for both Δz (an array argument): made in the loop,
    # each was traced and compiled again for the second
    grad = jax.jit(jax.grad(f, argnums=(0, 1)))
    jacfwd = jax.jit(jax.jacfwd(f, argnums=(0, 1)))
    for d in (0.0, dz):
        args = (jnp.asarray(d), jnp.asarray(0.9 * r))
        grads = grad(*args)
        forward = jacfwd(*args)
        for i, eps in enumerate((1e-8, 1e-9)):  # metres of Δz, of radius
            hi, lo = list(args), list(args)
            hi[i], lo[i] = hi[i] + eps, lo[i] - eps
            fd = float(fj(*hi) - fj(*lo)) / (2 * eps)
            assert np.isfinite(float(grads[i]))
            assert float(grads[i]) == pytest.approx(fd, rel=1e-4, abs=1e-3)
            assert float(forward[i]) == pytest.approx(float(grads[i]), rel=1e-10, abs=1e-8)
    with pytest.raises(TypeError, match="plan"):
        psf_each(difstar.Circle(r), lams, defocus=dz, z_image=F, pixel_pitch=P,
                 shape=(n, n), plan=None)
    with pytest.raises(ValueError, match="wavelengths must be a 1-D array"):
        psf_each(difstar.Circle(r), lams[None], defocus=dz, **kw)


def test_psf_each_counts_every_sampled_pupil_in_its_memory_check(monkeypatch):
    """``psf_each`` holds every wavelength's sampled pupil at once (``psf`` one at a
    time): a memory limit between the two refuses ``psf_each`` before any work, with the
    window named, and lets ``psf`` run."""
    from difstar._psf import psf_bytes, psf_each
    from difstar._validate import InputError

    lams = jnp.asarray([600e-9, 530e-9, 450e-9])
    r, n = F / 11, 40
    plan = difstar.plan_psf(difstar.Circle(r), wavelength=lams, z_image=F, defocus=1e-4,
                            pixel_pitch=P, shape=(n, n), sampling="point", method="fft")
    one = psf_bytes(plan, (n, n), 3, 0, P)
    each = psf_bytes(plan, (n, n), 3, 0, P, pupils=3)
    assert each > one
    monkeypatch.setenv("DIFSTAR_MEMORY_LIMIT", str((one + each) // 2))
    kw = dict(z_image=F, defocus=1e-4, pixel_pitch=P, shape=(n, n), plan=plan)
    difstar.psf(difstar.Circle(r), wavelength=lams, **kw)
    with pytest.raises(InputError, match="40 x 40 px window"):
        psf_each(difstar.Circle(r), lams, **kw)
