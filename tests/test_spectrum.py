"""Spectral weighting: Planck's law against Wien's law and colour-science, illuminants and
user tables, channel weights (trapezoid, normalisation, derivatives), the Gauss rule of a
channel's spectral weight, and choose_wavelengths against a dense 5 nm sum (float64)."""

import math

import colour
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.integrate
import scipy.optimize
import scipy.special

from difstar._spectrum import (
    WIEN_B,
    airy_family,
    as_sensitivities,
    blackbody,
    channel_weights,
    choose_wavelengths,
    dense_weights,
    error_table,
    gauss_nodes,
    illuminant,
    trapezoid_weights,
    user_spectrum,
)

from helpers import fd_grad

NIKON_D7000 = "/work/shared/data/raw/spectral_sensitivity/Nikon_D7000_380_780_5.json"
H, C, K = 6.62607015e-34, 299792458.0, 1.380649e-23  # CODATA 2018, exact


@pytest.mark.parametrize("temperature", [2856.0, 5000.0, 6504.0, 10000.0])
def test_planck_peak_is_wien(temperature):
    """λ_max T = 2.897771955e-3 m K (CODATA 2018), found by maximising B_λ numerically."""
    assert WIEN_B == pytest.approx(2.897771955e-3, rel=1e-9)
    res = scipy.optimize.minimize_scalar(
        lambda lam_nm: -blackbody(lam_nm * 1e-9, temperature), bounds=(100, 3000),
        method="bounded", options={"xatol": 1e-9})
    assert res.x * 1e-9 * temperature == pytest.approx(2.897771955e-3, rel=1e-7)  # xatol
    assert blackbody(2.897771955e-3 / temperature, temperature) == pytest.approx(1.0, rel=1e-12)
    assert -res.fun == pytest.approx(1.0, rel=1e-12)


def test_planck_against_colour():
    wl_nm = np.arange(360.0, 831.0, 5.0)
    for t in (3000.0, 5000.0, 6500.0):
        # colour's planck_law with the exact constants (c1 = 2πhc², c2 = hc/k): the same law
        ref = colour.colorimetry.planck_law(wl_nm * 1e-9, t, c1=2 * np.pi * H * C**2,
                                            c2=H * C / K)
        np.testing.assert_allclose(blackbody(wl_nm * 1e-9, t, absolute=True), ref, rtol=1e-12)
        # sd_blackbody (per nm, CIE's rounded c1 = 3.741771e-16, c2 = 0.014388): c2 is
        # 1.6e-5 high, which changes B by ≈ 1.6e-5 · c2/(λT) ≤ 2.2e-4 (360 nm, 3000 K)
        sd = colour.sd_blackbody(t, colour.SpectralShape(360, 830, 5))
        x = H * C / K / (wl_nm * 1e-9 * t)
        np.testing.assert_allclose(blackbody(wl_nm * 1e-9, t, absolute=True) * 1e-9,
                                   sd.values, rtol=1.7e-5 * x.max() + 2e-6)
        # relative = absolute / its value at the Wien peak
        rel = blackbody(wl_nm * 1e-9, t)
        peak = blackbody(WIEN_B / t, t, absolute=True)
        np.testing.assert_allclose(rel, ref / peak, rtol=1e-12)


def test_planck_jax_differentiable():
    lam = jnp.asarray([450e-9, 550e-9, 650e-9])
    f = jax.jit(lambda t: blackbody(lam, t))
    np.testing.assert_allclose(f(5000.0), blackbody(np.asarray(lam), 5000.0), rtol=1e-13)
    g = jax.jacfwd(f)(5000.0)
    for i in range(3):
        # central FD with a 0.01 K step: truncation ~1e-10 relative
        ref = fd_grad(lambda t, i=i: float(blackbody(np.asarray(lam), t)[i]), 5000.0, 1e-2)
        np.testing.assert_allclose(g[i], ref, rtol=1e-7)


def test_illuminants():
    wl = np.arange(380e-9, 781e-9, 5e-9)
    for name in ("A", "D50", "D65", "LED-B3"):
        sd = colour.SDS_ILLUMINANTS[name]
        ref = np.array([sd[w] for w in np.round(wl * 1e9)])
        np.testing.assert_allclose(illuminant(name, wl), ref, rtol=1e-12)  # on the table
    # between table entries: colour-science's own interpolation
    np.testing.assert_allclose(illuminant("D65", [552.5e-9]),
                               colour.SDS_ILLUMINANTS["D65"][552.5], rtol=1e-12)
    # CIE A is defined as Planck's law with c2 = 1.435e-2 m K at 2848 K (≈ 2856 K with
    # today's c2), 100 at 560 nm: within 1e-3 (CIE's table has 6 significant digits)
    c2 = 1.435e-2
    planck_a = lambda lam: lam**-5 / np.expm1(c2 / (lam * 2848.0))  # noqa: E731
    np.testing.assert_allclose(illuminant("A", wl), 100 * planck_a(wl) / planck_a(560e-9),
                               rtol=1e-3)
    with pytest.raises(ValueError, match="LED-B3"):
        illuminant("LED-X9", wl)
    with pytest.raises(ValueError, match="tabulated over 380–780 nm"):
        illuminant("LED-B3", [370e-9, 500e-9])
    with pytest.raises(ValueError, match="look like nanometres"):
        illuminant("D65", [550.0])


def test_user_spectrum():
    wl = np.array([400e-9, 500e-9, 700e-9])
    v = np.array([0.0, 1.0, 3.0])
    np.testing.assert_allclose(user_spectrum(wl, v, [450e-9, 600e-9, 700e-9]), [0.5, 2.0, 3.0],
                               rtol=1e-14)
    with pytest.raises(ValueError, match="fill=0.0"):
        user_spectrum(wl, v, [350e-9])
    np.testing.assert_array_equal(user_spectrum(wl, v, [350e-9, 800e-9], fill=0.0), [0, 0])
    with pytest.raises(ValueError, match="strictly increasing"):
        user_spectrum(wl[::-1], v, [450e-9])
    with pytest.raises(ValueError, match="finite and ≥ 0"):
        user_spectrum(wl, [0, -1, 2], [450e-9])


def test_trapezoid_weights():
    wl = np.array([400e-9, 410e-9, 430e-9, 460e-9])
    np.testing.assert_allclose(trapezoid_weights(wl), [5e-9, 15e-9, 25e-9, 15e-9], rtol=1e-12)
    # integrates a linear function exactly
    f = 3 * wl + 1e-6
    assert trapezoid_weights(wl) @ f == pytest.approx(scipy.integrate.trapezoid(f, wl),
                                                      rel=1e-14)


def test_channel_weights_product_and_normalisation():
    wl = np.arange(380e-9, 781e-9, 5e-9)
    sens = as_sensitivities(NIKON_D7000)(wl).T  # (3, n)
    cw = channel_weights(5000.0, NIKON_D7000, wl)
    src = blackbody(wl, 5000.0)
    dl = np.full(wl.size, 5e-9)
    dl[[0, -1]] = 2.5e-9
    np.testing.assert_allclose(cw.weights, sens * src * dl, rtol=1e-13)
    np.testing.assert_allclose(cw.normalised.sum(axis=1), 1.0, rtol=0, atol=1e-14)
    assert np.all(cw.normalised >= 0)
    # arrays in, same result; a transmission multiplies every channel
    cw2 = channel_weights(src, sens, wl, transmission=np.full(wl.size, 0.5))
    np.testing.assert_allclose(cw2.weights, 0.5 * cw.weights, rtol=1e-14)
    np.testing.assert_allclose(cw2.normalised, cw.normalised, rtol=1e-13)
    # the channel totals are the camera's raw response: their ratios give the white
    # balance (colour-science's white_balance_multipliers on the same data, 5 nm; the
    # rectangle vs trapezoid rule differs only by the two end samples)
    from difstar.io._sensitivity import load_spectral_sensitivity, white_balance_from_sensitivities

    s = load_spectral_sensitivity(NIKON_D7000)
    bb = colour.sd_blackbody(5000, s.shape)
    wb = white_balance_from_sensitivities(s, illuminant=bb)
    resp = cw.weights.sum(axis=1)
    np.testing.assert_allclose(resp[1] / resp, wb, rtol=2e-3)
    # the flat single channel
    flat = channel_weights("E", None, wl)
    assert flat.weights.shape == (1, wl.size)
    with pytest.raises(ValueError, match="no weight"):
        channel_weights(5000.0, NIKON_D7000, np.arange(800e-9, 900e-9, 5e-9))


def test_channel_weights_differentiable_in_temperature_and_transmission():
    wl = np.arange(400e-9, 701e-9, 10e-9)

    def green_centroid(t, tau):
        cw = channel_weights(blackbody(jnp.asarray(wl), t), "Nikon 5100 (NPL)", wl,
                             transmission=1 - tau * jnp.asarray((wl - 400e-9) / 300e-9))
        return cw.normalised[1] @ jnp.asarray(wl)

    g = jax.jit(jax.grad(green_centroid, argnums=(0, 1)))(5000.0, 0.2)
    f = lambda t, tau: float(green_centroid(t, tau))  # noqa: E731
    # central FD: 1 K and 1e-4 steps, truncation ≤ 1e-8 relative
    np.testing.assert_allclose(g[0], fd_grad(lambda t: f(t, 0.2), 5000.0, 1.0), rtol=1e-6)
    np.testing.assert_allclose(g[1], fd_grad(lambda u: f(5000.0, u), 0.2, 1e-4), rtol=1e-6)


def test_gauss_nodes_exact_for_polynomials_and_legendre_limit():
    dense = dense_weights(5000.0, "Nikon 5100 (NPL)")
    wl = dense.wavelengths
    for c in range(3):
        m = dense.normalised[c]
        for k in (1, 2, 3, 5, 8):
            nodes, weights = gauss_nodes(wl, m, k)
            assert np.all(weights > 0) and weights.sum() == pytest.approx(1.0, abs=1e-14)
            assert wl[0] < nodes.min() and nodes.max() < wl[-1]
            t = (wl - 580e-9) / 200e-9  # polynomials of degree ≤ 2k − 1, exact
            tn = (nodes - 580e-9) / 200e-9
            for d in range(2 * k):
                assert weights @ tn**d == pytest.approx(m @ t**d, abs=1e-12), (c, k, d)
            if k == 1:  # the centroid
                assert nodes[0] == pytest.approx(m @ wl, rel=1e-14)
    # a uniform measure on a fine midpoint grid of [−1, 1] → Gauss–Legendre (the midpoint
    # rule's moments differ from the continuum's by O(h²) = 1e-10)
    n = 100_000
    x = -1 + (np.arange(n) + 0.5) * 2 / n
    nodes, weights = gauss_nodes(x, np.full(n, 2 / n), 6)
    ref_x, ref_w = np.polynomial.legendre.leggauss(6)
    np.testing.assert_allclose(nodes, ref_x, atol=1e-8)
    np.testing.assert_allclose(weights, ref_w, atol=1e-8)


def _airy_broadband_reference(radii, temperature, band, reference):
    """Independent dense 5 nm reference (own Planck, own trapezoid, own Airy)."""
    wl = np.arange(band[0], band[1] + 1e-12, 5e-9)
    src = wl**-5 / np.expm1(H * C / (K * wl * temperature))
    w = src * np.gradient(wl)  # interior h, not the ends: replaced by the trapezoid below
    w[[0, -1]] = src[[0, -1]] * 2.5e-9
    w /= w.sum()
    s = reference / wl[:, None]
    v = np.pi * np.asarray(radii)[None, :] * s
    a = np.where(v == 0, 1.0, 2 * scipy.special.j1(np.where(v == 0, 1, v)) / np.where(v == 0, 1, v))
    return w @ (s**2 * a**2)


@pytest.mark.parametrize("accuracy", [1e-2, 1e-3, 1e-4])
def test_choose_wavelengths_meets_target_flat_channel(accuracy):
    """The issue's broadband case: 5000 K over 400–700 nm, one flat channel. The chosen
    rule, applied to the Airy PSF at radii it was not chosen on (an independent grid of
    radii up to 15 λN), matches the independent dense 5 nm sum to the target (relative
    to the peak)."""
    band = (400e-9, 700e-9)
    ch = choose_wavelengths(5000.0, None, accuracy, band=band)
    (nodes,), (weights,) = ch.wavelengths, ch.weights
    assert weights.sum() == pytest.approx(1.0, abs=1e-14) and np.all(weights > 0)
    assert ch.errors[0] <= accuracy
    radii = np.random.default_rng(0).uniform(0, 15, 301)
    ref_lam = 550e-9
    ref = _airy_broadband_reference(radii, 5000.0, band, ref_lam)
    approx = weights @ airy_family(radii, reference=ref_lam)(nodes)
    err = np.max(np.abs(approx - ref)) / ref.max()
    assert err <= accuracy, (len(nodes), err)
    # fewest: one wavelength fewer misses the target (on the chooser's own family)
    k = len(nodes)
    assert np.isfinite(ch.table[0, k - 1]) and np.all(np.isnan(ch.table[0, k:]))
    if k > 1:
        assert ch.table[0, k - 2] > accuracy


def test_choose_wavelengths_camera_channels_and_table():
    acc = 1e-3
    ch = choose_wavelengths("LED-B3", NIKON_D7000, acc)
    assert len(ch.wavelengths) == 3
    dense = dense_weights("LED-B3", NIKON_D7000)
    for c in range(3):
        nodes, weights = ch.wavelengths[c], ch.weights[c]
        assert weights.sum() == pytest.approx(1.0, abs=1e-14) and np.all(weights > 0)
        # a smooth test family not used in choosing: slit (spike) profiles sinc²(x λ_ref/λ)
        # × (λ_ref/λ), x up to 10 periods, against the dense 5 nm sum
        xs = np.linspace(0, 10, 201)

        def slit(lam):
            s = 550e-9 / np.asarray(lam)[:, None]
            return s * np.sinc(xs[None, :] * s) ** 2

        ref = dense.normalised[c] @ slit(dense.wavelengths)
        err = np.max(np.abs(weights @ slit(nodes) - ref)) / ref.max()
        assert err <= 2 * acc, (c, len(nodes), err)  # a different family: within 2×
    wl_pad, w_pad = ch.padded()
    assert wl_pad.shape == w_pad.shape == (3, max(len(w) for w in ch.wavelengths))
    np.testing.assert_allclose(w_pad.sum(axis=1), 1.0, atol=1e-14)
    # error falls with the number of wavelengths; the table matches choose_wavelengths'
    table = error_table("LED-B3", NIKON_D7000, ks=(1, 2, 3, 4, 6, 8))
    assert table.shape == (3, 6)
    assert np.all(table[:, 0] > 5 * table[:, 2]) and np.all(table[:, -1] < 1e-4)
    k = len(ch.wavelengths[0])
    np.testing.assert_allclose(ch.table[0, :k], error_table("LED-B3", NIKON_D7000,
                                                            ks=range(1, k + 1))[0], rtol=1e-12)


def test_choose_wavelengths_errors():
    with pytest.raises(ValueError, match="accuracy target"):
        choose_wavelengths(5000.0, None, 1e-9, band=(400e-9, 700e-9), max_wavelengths=3)
    with pytest.raises(ValueError, match="accuracy must be > 0"):
        choose_wavelengths(5000.0, None, 0.0)
    with pytest.raises(ValueError, match="MSDS_CAMERA_SENSITIVITIES"):
        choose_wavelengths(5000.0, "Canon Nope", 1e-3)
    # a loose target: one wavelength per channel, the channel's weighted mean (the
    # trichromatic special case), weight exactly 1
    ch = choose_wavelengths(5000.0, "Nikon 5100 (NPL)", 0.5)
    dense = dense_weights(5000.0, "Nikon 5100 (NPL)")
    for c in range(3):
        assert ch.weights[c].tolist() == [1.0]
        assert math.isclose(ch.wavelengths[c][0], dense.normalised[c] @ dense.wavelengths,
                            rel_tol=1e-14)
