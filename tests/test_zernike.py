"""Zernike wavefronts (Noll): orthonormality by an independent quadrature, Noll's closed
forms and orientation, prysm's implementation, jit and derivatives, and the exact
Δz ↔ Noll-4 conversion (float64, tests/conftest.py)."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.special

from difstar._zernike import (
    Zernike,
    defocus_to_noll4,
    defocus_to_w020,
    noll4_to_defocus,
    noll4_to_w020,
    noll_to_nm,
    radial_coefficients,
    zernike_noll,
)

from helpers import fd_grad

R = 1.3e-3  # circle radius, metres


def _disc_quadrature(n_rho=12, n_theta=48):
    """Polar product rule on the unit disc: Gauss–Legendre in ρ on [0, 1] (weight ρ put
    in the integrand), uniform trapezoid in θ. Exact for ρ-polynomials of degree
    ≤ 2 n_rho − 2 and trigonometric polynomials of degree < n_theta. Returns x, y, w with
    Σ w = π."""
    t, wt = np.polynomial.legendre.leggauss(n_rho)
    rho = 0.5 * (t + 1)
    w_rho = 0.5 * wt * rho
    theta = 2 * np.pi * np.arange(n_theta) / n_theta
    rr, tt = np.meshgrid(rho, theta, indexing="ij")
    w = np.outer(w_rho, np.full(n_theta, 2 * np.pi / n_theta))
    return (rr * np.cos(tt)).ravel(), (rr * np.sin(tt)).ravel(), w.ravel()


def test_noll_to_nm_matches_noll_table_and_prysm():
    # Noll (1976), Table 1
    table = [(0, 0), (1, 1), (1, -1), (2, 0), (2, -2), (2, 2), (3, -1), (3, 1), (3, -3),
             (3, 3), (4, 0), (4, 2), (4, -2), (4, 4), (4, -4), (5, 1), (5, -1), (5, 3),
             (5, -3), (5, 5), (5, -5), (6, 0)]
    assert [noll_to_nm(j) for j in range(1, 23)] == table
    from prysm.polynomials import noll_to_nm as p_noll  # test extra: fail if missing

    for j in range(1, 100):
        assert noll_to_nm(j) == tuple(p_noll(j)), j
    for bad in (0, -1, 1.5, True, "4"):
        with pytest.raises(ValueError, match="Noll index"):
            noll_to_nm(bad)


def test_radial_coefficients_factorial_sum():
    assert radial_coefficients(4, 0) == (6, -6, 1)  # 6ρ⁴ − 6ρ² + 1
    assert radial_coefficients(3, 1) == (3, -2)  # 3ρ³ − 2ρ
    assert radial_coefficients(6, 2) == (15, -20, 6)
    with pytest.raises(ValueError):
        radial_coefficients(3, 2)


def test_orthonormal_over_unit_disc():
    """⟨Z_j Z_k⟩ = (1/π) ∫∫ Z_j Z_k ρ dρ dθ = δ_jk for j, k ≤ 21 (n ≤ 5: products are
    ρ-polynomials of degree ≤ 11 and trig of degree ≤ 10, integrated exactly)."""
    x, y, w = _disc_quadrature()
    assert w.sum() == pytest.approx(np.pi, rel=1e-14)
    z = np.stack([np.asarray(zernike_noll(j, x * R, y * R, R)) for j in range(1, 22)])
    gram = (z * w) @ z.T / np.pi
    np.testing.assert_allclose(gram, np.eye(21), rtol=0, atol=1e-12)  # quadrature exact


def _polar(n=200, seed=0):
    rng = np.random.default_rng(seed)
    rho = np.sqrt(rng.uniform(0, 1, n))
    th = rng.uniform(-np.pi, np.pi, n)
    return rho, th, rho * np.cos(th) * R, rho * np.sin(th) * R


def test_closed_forms_and_orientation():
    rho, th, x, y = _polar()
    s3, s5, s6, s8, s10 = (math.sqrt(v) for v in (3, 5, 6, 8, 10))
    closed = {
        1: np.ones_like(rho),
        2: 2 * rho * np.cos(th),  # tilt about y: x-tilt
        3: 2 * rho * np.sin(th),
        4: s3 * (2 * rho**2 - 1),  # defocus
        5: s6 * rho**2 * np.sin(2 * th),  # astigmatism at ±45°
        6: s6 * rho**2 * np.cos(2 * th),  # astigmatism along x / y
        7: s8 * (3 * rho**3 - 2 * rho) * np.sin(th),  # coma along y
        8: s8 * (3 * rho**3 - 2 * rho) * np.cos(th),  # coma along x
        9: s8 * rho**3 * np.sin(3 * th),  # trefoil
        10: s8 * rho**3 * np.cos(3 * th),
        11: s5 * (6 * rho**4 - 6 * rho**2 + 1),  # primary spherical
        12: s10 * (4 * rho**4 - 3 * rho**2) * np.cos(2 * th),
        13: s10 * (4 * rho**4 - 3 * rho**2) * np.sin(2 * th),
        22: math.sqrt(7) * (20 * rho**6 - 30 * rho**4 + 12 * rho**2 - 1),
    }
    for j, ref in closed.items():
        np.testing.assert_allclose(zernike_noll(j, x, y, R), ref, rtol=0, atol=1e-13,
                                   err_msg=f"Z{j}")
    # orientation, y up: Z6 is +√6 on the x axis edge and −√6 on the y axis edge; Z5 is
    # +√6 at 45° (x = y > 0); Z7 (coma, sin) is +√8 at the top edge (0, R), Z8 at (R, 0)
    z = lambda j, px, py: float(zernike_noll(j, px, py, R))  # noqa: E731
    assert z(6, R, 0) == pytest.approx(s6) and z(6, 0, R) == pytest.approx(-s6)
    assert z(5, R / math.sqrt(2), R / math.sqrt(2)) == pytest.approx(s6)
    assert z(7, 0, R) == pytest.approx(s8) and z(7, R, 0) == pytest.approx(0, abs=1e-15)
    assert z(8, R, 0) == pytest.approx(s8) and z(8, 0, -R) == pytest.approx(0, abs=1e-15)
    assert z(4, 0, 0) == pytest.approx(-s3) and z(11, 0, 0) == pytest.approx(s5)


def test_against_prysm():
    """prysm's Noll Zernikes (unit RMS, sin for m < 0), j ≤ 45, inside and just outside
    the circle."""
    from prysm.polynomials import noll_to_nm as p_noll, zernike_nm

    rho, th, x, y = _polar(300, seed=1)
    rho = np.concatenate([rho, [0.0, 1.0, 1.2]])
    th = np.concatenate([th, [0.3, 2.0, -1.0]])
    x, y = rho * np.cos(th) * R, rho * np.sin(th) * R
    for j in range(1, 46):
        n, m = p_noll(j)
        ref = zernike_nm(n, m, rho, th, norm=True)
        np.testing.assert_allclose(zernike_noll(j, x, y, R), ref, rtol=1e-11, atol=1e-11,
                                   err_msg=f"Z{j}")


def test_opd_sum_broadcast_and_validation():
    zern = Zernike({11: 3e-8, 4: -1e-7, 7: 2e-8}, radius=R)
    assert zern.indices == (4, 7, 11)
    np.testing.assert_array_equal(zern.coefficients, [-1e-7, 2e-8, 3e-8])
    assert {j: float(c) for j, c in zern.as_dict().items()} == {4: -1e-7, 7: 2e-8, 11: 3e-8}
    x = np.linspace(-R, R, 7)[None, :]
    y = np.linspace(-R, R, 5)[:, None]
    w = zern.opd(x, y)
    assert w.shape == (5, 7)
    ref = sum(c * zernike_noll(j, x, y, R) for j, c in ((4, -1e-7), (7, 2e-8), (11, 3e-8)))
    np.testing.assert_allclose(w, ref, rtol=1e-14, atol=0)
    # RMS over the disc = √Σ c² (orthonormality), by the quadrature
    qx, qy, qw = _disc_quadrature()
    rms = np.sqrt(np.sum(qw * np.asarray(zern.opd(qx * R, qy * R)) ** 2) / np.pi)
    assert rms == pytest.approx(math.sqrt(1e-14 + 4e-16 + 9e-16), rel=1e-12)
    np.testing.assert_allclose(zern.phase(x, y, 500e-9), 2 * np.pi * w / 500e-9, rtol=1e-14)
    assert Zernike({}, R).opd(x, y).shape == (5, 7)

    with pytest.raises(ValueError, match=r"Noll indices must be integers >= 1"):
        Zernike({0: 1e-8}, R)
    with pytest.raises(ValueError, match=r"Noll indices must be integers >= 1"):
        Zernike({2.5: 1e-8}, R)
    with pytest.raises(ValueError, match=r"Zernike.coefficients\[4\] must be finite"):
        Zernike({4: float("nan")}, R)
    with pytest.raises(ValueError, match=r"Zernike.coefficients\[4\] must be a scalar"):
        Zernike({4: [1e-8, 2e-8]}, R)
    with pytest.raises(ValueError, match=r"Zernike.coefficients must be a mapping"):
        Zernike([1e-8], R)
    for bad in (0.0, -1e-3, float("inf"), float("nan")):
        with pytest.raises(ValueError, match=r"Zernike.radius"):
            Zernike({4: 1e-8}, bad)


def test_jit_grad_jacfwd_and_finite_differences():
    x = jnp.asarray(np.linspace(-R, R, 9)[None, :])
    y = jnp.asarray(np.linspace(-R, R, 9)[:, None])
    zern = Zernike({2: 1e-8, 4: -5e-8, 6: 2e-8, 8: 1e-8, 11: 3e-8}, radius=R)
    opd = eqx.filter_jit(lambda z: z.opd(x, y))
    np.testing.assert_allclose(opd(zern), zern.opd(x, y), rtol=1e-14, atol=1e-24)

    # the jacobian of the OPD w.r.t. the coefficients is the stack of the Z_j (linear)
    jac = jax.jit(jax.jacfwd(lambda c: eqx.tree_at(lambda z: z.coefficients, zern, c).opd(x, y)))(
        zern.coefficients)
    assert jac.shape == (9, 9, 5)
    for i, j in enumerate(zern.indices):
        np.testing.assert_allclose(jac[..., i], zernike_noll(j, x, y, R), rtol=1e-13, atol=1e-13)

    # a nonlinear loss of the phase: grad (filter_grad over the module) vs central FD
    lam = 550e-9

    def loss(z):
        return jnp.sum(jnp.cos(z.phase(x, y, lam)) * (x / R + 0.3) ** 2)

    g = eqx.filter_jit(eqx.filter_grad(loss))(zern).coefficients
    for i in range(5):
        def f(c, i=i):
            return float(loss(eqx.tree_at(lambda z: z.coefficients, zern,
                                          zern.coefficients.at[i].set(c))))
        # step 1e-12 m: phase step k h |Z| ≤ 3e-4 rad (|Z11| ≤ 29 on the grid's corners), so
        # the central difference's truncation error is ~(3e-4)²/6 ≈ 2e-8 relative
        np.testing.assert_allclose(g[i], fd_grad(f, float(zern.coefficients[i]), 1e-12),
                                   rtol=1e-6)

    # built from traced coefficients inside jit (validation skips tracers)
    @jax.jit
    def from_traced(c4):
        return Zernike({4: c4, 11: 2 * c4}, R).opd(x, y)

    np.testing.assert_allclose(from_traced(1e-8), Zernike({4: 1e-8, 11: 2e-8}, R).opd(x, y),
                               rtol=1e-14, atol=1e-24)
    # gradient w.r.t. the coordinates is finite at the centre (no arctan2 / sqrt)
    gx = jax.grad(lambda px: zern.opd(px, 0.0))(0.0)
    assert np.isfinite(gx)
    # dW/dx at 0 = c2 · 2/R − c8 · 2√8/R  (Z2 = 2x/R, Z8 = √8 (3ρ³ − 2ρ) cos θ)
    assert float(gx) == pytest.approx((2 * 1e-8 - 2 * math.sqrt(8) * 1e-8) / R, rel=1e-12)


Z_R = 59.25e-3  # exit pupil → sensor, metres (the paper's defocused example)
RP = 1.1705e-3  # its pupil circumradius, metres


@pytest.mark.parametrize("dz", [-4.78e-3, -1e-5, 0.0, 2e-6, 4.78e-3, 2e-2])
def test_defocus_noll4_round_trip(dz):
    c4 = defocus_to_noll4(dz, Z_R, RP)
    back = noll4_to_defocus(c4, Z_R, RP)
    assert float(back) == pytest.approx(dz, rel=1e-12, abs=1e-20)
    # closed form (1/z_i − 1/z_R) R² / (4√3)
    z_i = Z_R - dz
    assert float(c4) == pytest.approx((1 / z_i - 1 / Z_R) * RP**2 / (4 * math.sqrt(3)),
                                      rel=1e-9, abs=1e-22)
    assert float(noll4_to_w020(c4)) == pytest.approx(float(defocus_to_w020(dz, Z_R, RP)),
                                                     rel=1e-14, abs=1e-25)


def test_defocus_noll4_vectorised_and_differentiable():
    dz = jnp.linspace(-5e-3, 5e-3, 11)
    c4 = defocus_to_noll4(dz, Z_R, RP)
    np.testing.assert_allclose(noll4_to_defocus(c4, Z_R, RP), dz, rtol=1e-12, atol=1e-18)
    # d c4 / d Δz = R² / (4√3 z_i²) (exact derivative of (1/z_i − 1/z_R) R²/(4√3))
    g = jax.vmap(jax.grad(lambda d: defocus_to_noll4(d, Z_R, RP)))(dz)
    np.testing.assert_allclose(g, RP**2 / (4 * math.sqrt(3) * (Z_R - dz) ** 2), rtol=1e-13)


@pytest.mark.parametrize("dz", [-4.78e-3, 4.78e-3, 3e-4])
def test_noll4_equals_fresnel_defocus_phase_up_to_piston(dz):
    """Independent truth 1: the ATF's documented Fresnel phase π λ z_R Δz / z_i |f|² with
    pupil coordinate x = λ z_R f equals k (c4 Z4 + W020/2) at every point (also outside
    the circle). Independent truth 2: a least-squares fit of that wavefront on the disc
    onto {Z1, Z4} gives c4 (and W020/2 as the piston)."""
    lam = 530e-9
    z_i = Z_R - dz
    x = np.linspace(-1.5 * RP, 1.5 * RP, 31)[None, :]
    y = np.linspace(-1.5 * RP, 1.5 * RP, 29)[:, None]
    f2 = (x**2 + y**2) / (lam * Z_R) ** 2
    atf_phase = np.pi * lam * Z_R * dz / z_i * f2
    c4 = float(defocus_to_noll4(dz, Z_R, RP))
    piston = float(defocus_to_w020(dz, Z_R, RP)) / 2
    zern = Zernike({1: piston, 4: c4}, RP)
    np.testing.assert_allclose(zern.phase(x, y, lam), atf_phase, rtol=1e-12,
                               atol=1e-12 * np.abs(atf_phase).max())

    qx, qy, qw = _disc_quadrature()
    w = 0.5 * (1 / z_i - 1 / Z_R) * (qx**2 + qy**2) * RP**2
    basis = np.stack([np.asarray(zernike_noll(j, qx * RP, qy * RP, RP)) for j in (1, 4, 11)], 1)
    sw = np.sqrt(qw)
    fit, *_ = np.linalg.lstsq(basis * sw[:, None], w * sw, rcond=None)
    np.testing.assert_allclose(fit, [piston, c4, 0.0], rtol=1e-12, atol=1e-12 * abs(c4))

    # the paper-style W020 = Δz/(8N²), N = z_R/(2R), misses exactly the factor z_R/z_i
    n_w = Z_R / (2 * RP)
    w020 = float(defocus_to_w020(dz, Z_R, RP))
    assert w020 == pytest.approx(dz / (8 * n_w**2) * Z_R / z_i, rel=1e-12)
    if abs(dz) > 1e-3:  # an error of order Δz/z_R: 8 % at 4.78 mm
        assert abs(dz / (8 * n_w**2) / w020 - 1) > 0.07


# --- a radial truth for the engine's aberrated-circle tests --------------------------------
# (importable: `from test_zernike import hankel_psf, hankel_psf_pixels`)


def hankel_psf(r, wavelength, z, radius, opd_of_rho=None, n_nodes=600):
    """Intensity of a clear circular pupil of ``radius`` with a radially symmetric
    wavefront W(ρ) = ``opd_of_rho(ρ)`` (metres, ρ = r_pupil/radius), at image radii ``r``
    (metres) a distance ``z`` from the pupil, as a fraction of the power per unit area:

        I(r) = |2π ∫_0^R e^{i k W(ρ'/R)} J0(2π r ρ' / (λ z)) ρ' dρ'|² / (λ² z² π R²)

    (the Fresnel/Fraunhofer transform of the pupil; ∫ I dA = 1). Gauss–Legendre in ρ'
    with ``n_nodes`` nodes (exact enough while 2π r R/(λ z) ≪ n_nodes)."""
    t, w = np.polynomial.legendre.leggauss(n_nodes)
    rho = 0.5 * (t + 1)
    w = 0.5 * w
    phase = np.zeros_like(rho) if opd_of_rho is None else 2 * np.pi / wavelength * opd_of_rho(rho)
    r = np.asarray(r, dtype=float)
    arg = 2 * np.pi * radius / (wavelength * z) * r[..., None] * rho
    amp = 2 * np.pi * radius**2 * np.sum(w * np.exp(1j * phase) * scipy.special.j0(arg) * rho,
                                         axis=-1)
    return np.abs(amp) ** 2 / (wavelength**2 * z**2 * np.pi * radius**2)


def hankel_psf_pixels(shape, pixel_pitch, wavelength, z, radius, opd_of_rho=None, sub=8,
                      table_step=1 / 64):
    """``hankel_psf`` integrated over square pixels of ``pixel_pitch`` on a ``shape`` grid
    centred like difstar's (centre pixel at index n//2), as a fraction of the power per
    pixel: a cubic spline of the radial profile (step ``table_step`` pixels) sampled at
    ``sub`` × ``sub`` Gauss–Legendre points per pixel."""
    import scipy.interpolate

    h, w = shape
    r_max = np.hypot(h, w) / 2 + 2
    r_tab = np.arange(0, r_max + table_step, table_step) * pixel_pitch
    prof = hankel_psf(r_tab, wavelength, z, radius, opd_of_rho)
    spline = scipy.interpolate.CubicSpline(r_tab, prof, bc_type=((1, 0.0), (2, 0.0)))
    t, wt = np.polynomial.legendre.leggauss(sub)
    offs, ow = 0.5 * t, 0.5 * wt
    yy = (np.arange(h) - h // 2)[:, None, None, None] + offs[None, None, :, None]
    xx = (np.arange(w) - w // 2)[None, :, None, None] + offs[None, None, None, :]
    rr = np.hypot(yy, xx) * pixel_pitch
    vals = spline(rr)
    return np.einsum("hwab,a,b->hw", vals, ow, ow) * pixel_pitch**2


def test_hankel_truth_airy_strehl_and_energy():
    lam, n_f, radius = 550e-9, 8.0, 1e-3
    z = 2 * radius * n_f
    # no aberration: the Airy pattern, (πR²/(λ²z²)) [2 J1(v)/v]², v = 2π R r/(λ z)
    r = np.linspace(1e-9, 40 * lam * n_f, 400)
    v = 2 * np.pi * radius * r / (lam * z)
    airy = np.pi * radius**2 / (lam * z) ** 2 * (2 * scipy.special.j1(v) / v) ** 2
    np.testing.assert_allclose(hankel_psf(r, lam, z, radius), airy, rtol=0,
                               atol=1e-12 * airy.max())
    # pure Noll 4: on-axis Strehl = sinc²(k W020 / 2) exactly (W020 = 2√3 c4; the piston
    # and the sign do not matter)
    peak0 = np.pi * radius**2 / (lam * z) ** 2
    for waves in (-0.2, 0.1, 0.45):
        c4 = waves * lam
        zern = Zernike({4: c4}, radius)
        w_rho = lambda p, zern=zern: np.asarray(zern.opd(p * radius, 0.0))  # noqa: E731
        a = 2 * np.pi / lam * 2 * math.sqrt(3) * c4
        assert hankel_psf(0.0, lam, z, radius, w_rho) / peak0 == pytest.approx(
            (np.sin(a / 2) / (a / 2)) ** 2, rel=1e-12)
    # Noll 11 is not symmetric in sign with Noll 4 present: the combined PSF differs
    both = lambda s: (lambda p: np.asarray(Zernike({4: -0.2 * lam, 11: s * 0.3 * lam},  # noqa: E731
                                                   radius).opd(p * radius, 0.0)))
    assert not np.allclose(hankel_psf(r[:50], lam, z, radius, both(1)),
                           hankel_psf(r[:50], lam, z, radius, both(-1)), rtol=1e-3)
    # pixel-integrated: the unaberrated window energy equals the Airy encircled energy
    # 1 − J0²(v) − J1²(v) to the square/disc difference; for a window of half-width 64 px
    # the square holds slightly more than the inscribed disc and less than the circumscribed
    pix = lam * n_f / 2  # Nyquist pixels
    img = hankel_psf_pixels((128, 128), pix, lam, z, radius)
    ee = lambda rr: 1 - scipy.special.j0(rr) ** 2 - scipy.special.j1(rr) ** 2  # noqa: E731
    k = 2 * np.pi * radius / (lam * z)
    assert ee(k * 63.5 * pix) < img.sum() < ee(k * 63.5 * math.sqrt(2) * pix)
    # the centre pixel against a direct 2-D Gauss–Legendre of the point profile
    t, wt = np.polynomial.legendre.leggauss(24)
    yy, xx = np.meshgrid(0.5 * t * pix, 0.5 * t * pix, indexing="ij")
    direct = np.sum(np.outer(wt, wt) / 4 * hankel_psf(np.hypot(yy, xx), lam, z, radius)) * pix**2
    assert img[64, 64] == pytest.approx(direct, rel=1e-6)
