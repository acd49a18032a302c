"""The image-fitting API (difstar.fitting): recovery of known parameters from an image
made by an independent NumPy generator (FFT of a high-resolution anti-aliased raster of
an obstructed circle with three struts, pixels integrated by a 4 × 4 midpoint rule),
standard errors, messages for inputs that cannot be right, and the JWST campaign's
manifest."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from difstar.fitting import (
    DiscSource,
    FitData,
    FitInputError,
    Halo,
    Hop,
    ImageModel,
    Light,
    Param,
    Resampling,
    Solve,
    SourceImage,
    chi2_slice,
    fit,
    iris_pupil,
    load_manifest,
    noise_limited_errors,
    obstructed_circle_pupil,
    spike_angles,
)

ROOT = Path(__file__).resolve().parents[1]
ARCSEC = math.pi / (180 * 3600)
LAM = 3.6e-6
P = 0.4  # arcsec per data pixel
TRUE = {"x0": 0.31, "y0": -0.22, "rotation": 4.0, "flux": 1000.0, "background": 2.0}


def _numpy_star(shape=(19, 19), *, x0, y0, rotation, flux, background, fine=4, n=1024,
                radius=0.425, obstruction=0.16, strut_width=0.06, z4=0.0, z11=0.0,
                disc=0.0, blades=0, lam=LAM, pixel_scale=P, blur=0.0):
    """Fraction of power per data pixel by a NumPy FFT of a pupil raster (y up), then
    ``flux`` × that + ``background``. Independent of difstar's engine. ``z4``: Noll
    defocus (m RMS over the radius 1.1 ``radius``, the circle builder's max_radius),
    entering as exp(−i k W) in this FFT's sign convention (the one in which the phase
    ramp of a shift +x0 is exp(+i k θ x): difstar's exp(+i k W) with W = −θ x); ``z11``:
    Noll primary spherical, √5 (6ρ⁴ − 6ρ² + 1), the same way. ``disc``:
    the source is a uniform disc of that radius (data pixels), convolved on the fine
    grid with an 8 × 8 anti-aliased raster of it before the pixels integrate.
    ``blades`` > 0: instead of the obstructed circle, a regular polygon of that many
    sides and circumradius ``radius``, its first vertex at ``rotation`` degrees from +x.
    ``pixel_scale``: arcsec per data pixel. ``blur``: a Gaussian of that σ (data pixels)
    on the fine grid before the pixels integrate (a detector's jitter)."""
    P = pixel_scale  # noqa: N806 - the module's P, overridden
    delta = P * ARCSEC / fine  # rad per fine sample
    dx = lam / (n * delta)  # pupil sample (m)
    half = int(math.ceil(1.05 * radius / dx))
    ss = 4  # anti-aliasing sub-samples a side
    u = (np.arange(-half * ss, half * ss) + 0.5) / ss * dx
    X, Y = np.meshgrid(u, u)  # axis 0: y ascending
    inside = (np.hypot(X, Y) <= radius) & (np.hypot(X, Y) >= obstruction)
    if blades:
        inside = np.ones_like(X, bool)
        for k in range(blades):  # inside every edge: r·n_k ≤ R cos(π/n)
            phi = math.radians(rotation) + math.pi / blades + 2 * math.pi * k / blades
            inside &= X * math.cos(phi) + Y * math.sin(phi) <= radius * math.cos(
                math.pi / blades)
    for a in np.deg2rad(np.array([90.0, 210.0, 330.0]) + rotation) if not blades else []:
        along = X * np.cos(a) + Y * np.sin(a)
        across = -X * np.sin(a) + Y * np.cos(a)
        inside &= ~((along >= 0) & (np.abs(across) <= strut_width / 2))
    cov = inside.reshape(2 * half, ss, 2 * half, ss).mean(axis=(1, 3))
    xc = (np.arange(-half, half) + 0.5) * dx
    ax = 1.5 * delta + x0 * P * ARCSEC
    ay = 1.5 * delta - y0 * P * ARCSEC
    field = cov * np.exp(2j * math.pi * (xc[None, :] * ax + xc[:, None] * ay) / lam)
    if z4 or z11:
        rho2 = (xc[None, :] ** 2 + xc[:, None] ** 2) / (1.1 * radius) ** 2
        w = z4 * math.sqrt(3) * (2 * rho2 - 1) + z11 * math.sqrt(5) * (
            6 * rho2 ** 2 - 6 * rho2 + 1)
        field = field * np.exp(-2j * math.pi * w / lam)
    big = np.zeros((n, n), complex)
    big[:2 * half, :2 * half] = field
    inten = np.abs(np.fft.fftshift(np.fft.fft2(big))) ** 2 / (n * n * np.sum(cov))
    if disc:
        rf, aa = disc * fine, 8  # radius in fine samples; sub-samples a side
        m = int(math.ceil(rf)) + 1
        t = (np.arange(-m * aa, (m + 1) * aa) + 0.5) / aa - 0.5  # fine-sample units
        inside = np.hypot(t[None, :], t[:, None]) <= rf
        k = inside.reshape(2 * m + 1, aa, 2 * m + 1, aa).mean(axis=(1, 3))
        kern = np.zeros((n, n))
        kern[:2 * m + 1, :2 * m + 1] = k / k.sum()
        kern = np.roll(kern, (-m, -m), axis=(0, 1))
        inten = np.real(np.fft.ifft2(np.fft.fft2(inten) * np.fft.fft2(kern)))
    if blur:
        f = np.fft.fftfreq(n)
        g = np.exp(-2 * math.pi**2 * (blur * fine) ** 2 * (f[:, None] ** 2 + f[None, :] ** 2))
        inten = np.real(np.fft.ifft2(np.fft.fft2(inten) * g))
    h, w = shape
    ky = n // 2 + fine * (np.arange(h) - h // 2)
    kx = n // 2 + fine * (np.arange(w) - w // 2)
    blocks = np.zeros((h, w))
    for my in range(fine):
        for mx in range(fine):
            blocks += inten[np.ix_(ky + my, kx + mx)]
    img = blocks[::-1, :]  # rows run down
    return flux * img + background


def _model(**over):
    params = {
        "rotation": Param(0.0, True, (-20, 20)),
        "x0": Param(0.0, True, (-2, 2)),
        "y0": Param(0.0, True, (-2, 2)),
        "flux": Param(800.0, True, scale=100.0),
        "background": Param(0.0, True, scale=1.0),
        "pixel_scale": Param(P),
        "jitter": Param(0.0),
        "obstruction": Param(0.16),
        "strut_width": Param(0.06),
    } | over
    return ImageModel(obstructed_circle_pupil(0.425), params,
                      light=Light.monochromatic(LAM), pad=4, accuracy=3e-3)


@pytest.fixture(scope="module")
def synthetic():
    clean = _numpy_star(**TRUE)
    sigma = 2e-3 * clean.max()
    rng = np.random.default_rng(1)
    noisy = clean + rng.normal(0, sigma, clean.shape)
    return FitData.from_array(noisy, sigma=sigma), sigma


def test_recovers_independent_synthetic_star(synthetic):
    data, _ = synthetic
    res = fit(_model(), data, max_steps=20)
    v, e = res.values, res.errors
    assert res.converged or "max_steps" in res.status, res.status
    assert abs(v["x0"] - TRUE["x0"]) < 0.02 and abs(v["y0"] - TRUE["y0"]) < 0.02
    assert abs(v["rotation"] - TRUE["rotation"]) < max(4 * e["rotation"], 0.5)
    assert abs(v["flux"] / TRUE["flux"] - 1) < 0.01
    assert res.chi2_dof < 3.0
    assert res.residual_rms_peak < 5e-3
    # standard errors: finite, positive, and the truth within a few of them (or the
    # generator's own midpoint-rule error)
    for k in res.free:
        assert 0 < e[k] < float("inf")
    assert abs(v["x0"] - TRUE["x0"]) < max(5 * e["x0"], 0.01)
    assert e["x0"] < 0.01 and e["rotation"] < 1.0
    assert res.model_image.shape == data.image.shape


def test_unconstrained_parameter_is_reported(synthetic):
    data, _ = synthetic
    m = _model(rotation=Param(TRUE["rotation"]), x0=Param(TRUE["x0"]),
               y0=Param(TRUE["y0"]), background=Param(TRUE["background"]),
               jitter=Param(0.0, True, scale=0.1))
    res = fit(m, data, max_steps=3)
    assert any("jitter" in w and "unconstrained" in w for w in res.warnings), res.warnings


def test_bad_inputs():
    with pytest.raises(FitInputError, match="metres"):
        Light.monochromatic(0.9)  # µm given
    with pytest.raises(FitInputError, match="metres"):
        Light.band(795, 1005)  # nm given
    with pytest.raises(FitInputError, match="arcsec"):
        _model(pixel_scale=Param(1.5e-7))  # radians given
    with pytest.raises(FitInputError, match="nm RMS"):
        ImageModel(obstructed_circle_pupil(), {"z4": Param(2e5)},
                   light=Light.monochromatic(LAM), zernike=[4])
    with pytest.raises(FitInputError, match="unknown parameters"):
        _model(focal_length=Param(1.0))
    with pytest.raises(FitInputError, match="outside its bounds"):
        Param(5.0, True, (0, 1))
    with pytest.raises(FitInputError, match="no valid pixel"):
        FitData.from_array(np.full((8, 8), np.nan))
    with pytest.raises(FitInputError, match="sigma"):
        FitData.from_array(np.ones((8, 8)), sigma=0.0)
    # NaN pixels are masked, not fitted
    img = np.ones((8, 8))
    img[2, 3] = np.nan
    d = FitData.from_array(img, sigma=1.0)
    assert not d.mask[2, 3] and d.mask.sum() == 63
    fixed = _model(**{k: Param(1.0 if k == "flux" else 0.0) for k in
                      ("rotation", "x0", "y0", "flux", "background")})
    with pytest.raises(FitInputError, match="no free parameter"):
        fit(fixed, FitData.from_array(np.ones((9, 9)), sigma=1.0))


def test_spike_angles_of_lines():
    h = w = 81
    yy, xx = np.mgrid[0:h, 0:w]
    dx, dy = xx - 40.3, -(yy - 39.8)
    r = np.hypot(dx, dy) + 1.0
    img = np.zeros((h, w))
    for a in (12.0, 71.0, 133.0):
        t = math.radians(a)
        across = -dx * math.sin(t) + dy * math.cos(t)
        img += np.exp(-0.5 * across**2) / r**2
    ang = spike_angles(img, (40.3, 39.8), r_min=10, r_max=35, n_spikes=6)
    np.testing.assert_allclose(sorted(ang), [12.0, 71.0, 133.0], atol=0.5)


def test_spike_angles_near_given_directions():
    """A faint line beside a brighter one: the plain search finds the two brightest, ``near``
    finds the faint line where it is asked for, and NaN where there is only a slope."""
    h = w = 81
    yy, xx = np.mgrid[0:h, 0:w]
    dx, dy = xx - 40.3, -(yy - 39.8)
    r = np.hypot(dx, dy) + 1.0
    img = np.zeros((h, w))
    for a, amp in ((12.0, 1.0), (71.0, 1.0), (133.0, 0.2)):
        t = math.radians(a)
        across = -dx * math.sin(t) + dy * math.cos(t)
        img += amp * np.exp(-0.5 * across**2) / r**2
    top = spike_angles(img, (40.3, 39.8), r_min=10, r_max=35, n_spikes=4)
    np.testing.assert_allclose(sorted(top), [12.0, 71.0], atol=0.5)
    got = spike_angles(img, (40.3, 39.8), r_min=10, r_max=35, near=[135.0, 179.0, 20.0],
                       window=5.0)
    assert abs(got[0] - 133.0) < 0.5
    assert math.isnan(got[1])  # 179 ± 5 (wrapping past 0): the 12° line's flank, no peak
    assert math.isnan(got[2])  # 20 ± 5: the 12° line's slope
    with pytest.raises(FitInputError, match="window"):
        spike_angles(img, (40.3, 39.8), near=[10.0], window=120.0)


def test_jwst_manifest_loads_and_model_matches_data_shape():
    path = ROOT / "fit" / "jwst-nircam" / "manifest.json"
    data_file = ROOT.parent / "shared" / "data" / "measured_psf" / "psf_f090w_star0.fits"
    # real data beside the repository (as CI has it): fail loudly, never skip
    assert data_file.is_file(), f"{data_file} is missing: clone the project beside shared/"
    model, data, opts = load_manifest(path)
    assert data.image.shape == (91, 91)
    assert {"rotation", "jitter", "halo"} <= set(model.free)
    assert [h.name for h in model.halos] == ["halo"]  # one: see fit/jwst-nircam/README.md
    assert opts["stages"]
    two_halos, _, _ = load_manifest(ROOT / "fit" / "jwst-nircam" / "variants" /
                                    "two-halos.json")
    assert {"halo", "halo2"} <= set(two_halos.free)
    assert [(h.name, h.width) for h in two_halos.halos] == [("halo", 4.0), ("halo2", 1.5)]
    with_wavefront, _, _ = load_manifest(ROOT / "fit" / "jwst-nircam" / "variants" /
                                         "segment-wavefront.json")
    assert "z4" in with_wavefront.free
    small = data.cropped(10)
    img = model(small.image.shape)
    assert img.shape == small.image.shape and np.all(np.isfinite(img))
    assert 0.2 < img.max() / small.image.max() < 5


def test_campaign_manifests_find_a_star_anywhere_in_its_window(tmp_path):
    """The JWST and Spitzer manifests start x0, y0 at the data's brightest pixels
    (``"auto"``) with bounds ± 3 px about that start, so the same manifest on another
    star's window, off its centre, starts at that star and not at the window's centre.
    The star is the real JWST one, cut out of its file 6 columns left and 5 rows off its
    centre: the start must move by those pixels against the centred cut."""
    from astropy.io import fits

    src = ROOT.parent / "shared" / "data" / "measured_psf" / "psf_f090w_star0.fits"
    assert src.is_file(), f"{src} is missing: clone the project beside shared/"
    with fits.open(src) as h:
        image, header = np.asarray(h[0].data, float), h[0].header
    starts = {}
    for name, (r0, c0) in {"centred": (8, 8), "off": (3, 14)}.items():
        fits.PrimaryHDU(image[r0:r0 + 75, c0:c0 + 75], header=header).writeto(
            tmp_path / f"{name}.fits")
        manifest = tmp_path / f"{name}.json"
        manifest.write_text(json.dumps({
            "extends": str(ROOT / "fit" / "jwst-nircam" / "manifest.json"),
            "data": {"path": str(tmp_path / f"{name}.fits"),
                     "noise": {"read": None, "gain": 1.0, "floor": 0.0}}}))
        model, _, _ = load_manifest(manifest)
        for q in ("x0", "y0"):
            p = model.params[q]
            assert p.free and p.bounds == pytest.approx((p.value - 3, p.value + 3))
        starts[name] = (model.params["x0"].value, model.params["y0"].value)
    assert abs(starts["centred"][0]) < 1 and abs(starts["centred"][1]) < 1
    # 6 columns further left; 5 rows further from the centre (y's sign: the FITS rows)
    assert starts["off"][0] - starts["centred"][0] == pytest.approx(-6, abs=0.3)
    assert abs(starts["off"][1] - starts["centred"][1]) == pytest.approx(5, abs=0.3)
    for campaign in ("jwst-nircam", "spitzer-irac"):
        spec = json.loads((ROOT / "fit" / campaign / "manifest.json").read_text())["params"]
        assert spec["x0"] == spec["y0"] == {"value": "auto", "free": True,
                                            "bounds_about": [-3, 3]}


def test_jwst_model_mirrored_is_the_mirror_image():
    """An exact symmetry, not the code's own output: the JWST pupil is mirror-symmetric
    about its vertical axis, so the campaign's model (with a wavefront and its
    halo) with the pupil's rotation, the
    upper strut's tilt, the centre's x and the Zernike terms odd in x (Noll 5, 8, 10)
    negated is the left-right mirror of the image. Fails if the pupil, the struts, the
    shift or a Zernike term's orientation (e.g. x and y swapped) breaks the symmetry."""
    model, _, _ = load_manifest(ROOT / "fit" / "jwst-nircam" / "variants" /
                                "segment-wavefront.json")  # the campaign's model with a wavefront
    v = dict(model.values())
    v.update(halo=0.4, halo_width=1.8, rotation=0.7, strut_tilt=2.0, x0=0.31, y0=-0.22,
             z4=160.0, z5=30.0, z6=-55.0, z7=-12.0, z8=-9.0, z9=-5.0, z10=6.0, z11=170.0)
    odd = ("rotation", "strut_tilt", "x0", "z5", "z8", "z10")
    w = {k: (-x if k in odd else x) for k, x in v.items()}
    a = np.asarray(model.image(v, (21, 21)))
    b = np.asarray(model.image(w, (21, 21)))
    assert np.abs(a - b).max() > 0.05 * a.max()  # the wavefront and geometry show
    np.testing.assert_allclose(b, a[:, ::-1], rtol=0, atol=1e-12 * a.max())


def test_converges_from_rough_starts(synthetic):
    """From three starts with every free parameter within ± 20 % (of its bounds' half
    width where it starts at 0), the fit of the independent star lands on the same
    values, within a small fraction of their standard errors."""
    from difstar.fitting._analysis import perturbed_starts

    data, _ = synthetic
    model = _model()
    ref = fit(model, data, max_steps=30)
    starts = perturbed_starts(model, 3, seed=2)
    for s in starts:  # every start is rough but inside the bounds
        for k, v in s.items():
            p = model.params[k]
            assert v != p.value
            if p.bounds:
                assert p.bounds[0] < v < p.bounds[1]
    assert starts == perturbed_starts(model, 3, seed=2)
    for s in starts:
        res = fit(model.with_values(s), data, max_steps=30)
        for k in ref.free:
            assert abs(res.values[k] - ref.values[k]) < 0.05 * ref.errors[k], (k, s)


def test_spike_profile_stage_recovers_the_rotation():
    """A stage on the spikes' angular profiles alone (flux, background and centre held
    at the truth) recovers the rotation of the independent star's struts."""
    true = dict(TRUE, rotation=7.3, flux=1e5)
    clean = _numpy_star((41, 41), **true)
    sigma = 1e-4 * clean.max()
    rng = np.random.default_rng(4)
    data = FitData.from_array(clean + rng.normal(0, sigma, clean.shape), sigma=sigma)
    model = _model(x0=Param(true["x0"]), y0=Param(true["y0"]), flux=Param(true["flux"]),
                   background=Param(true["background"]))
    res = fit(model, data, stages=[{"free": ["rotation"], "spikes": {
        "r_min": 6, "r_max": 20, "n_spikes": 6, "half_width": 6, "bin_width": 0.5}}],
        max_steps=30)
    st = res.stages[0]
    assert st["kind"] == "spikes" and len(st["directions"]) == 3
    assert abs(res.values["rotation"] - true["rotation"]) < max(3 * res.errors["rotation"], 0.05)
    assert res.errors["rotation"] < 0.2
    with pytest.raises(FitInputError, match="spike"):
        fit(model, data, stages=[{"free": ["rotation"], "spikes": {"r_min": 30,
                                                                  "r_max": 31}}])
    # the windows placed on the spikes of the model at its start (1° off), not the data's
    start = model.with_values({"rotation": true["rotation"] + 1.0})
    opts = {"r_min": 6, "r_max": 20, "n_spikes": 6, "half_width": 6, "profiles": False,
            "directions": "model"}
    res = fit(start, data, stages=[{"free": ["rotation"], "spikes": opts}], max_steps=30)
    centre = (20 + true["x0"], 20 + true["y0"])
    expect = spike_angles(start(data.image.shape) - true["background"], centre, r_min=6,
                          r_max=20, n_spikes=6)
    np.testing.assert_allclose(res.stages[0]["directions"], expect, atol=1e-9)
    assert abs(res.values["rotation"] - true["rotation"]) < max(3 * res.errors["rotation"], 0.05)
    with pytest.raises(FitInputError, match="directions"):
        fit(model, data, stages=[{"free": ["rotation"], "spikes": dict(opts, directions="sky")}])


def test_noise_from_residuals_recovers_read_noise_and_gain():
    """Known read noise and gain, drawn around a smooth star (the model): the estimate
    recovers both within 10 %, and σ comes from the model."""
    from difstar.fitting import Noise, noise_from_residuals

    h = w = 121
    yy, xx = np.mgrid[0:h, 0:w]
    r2 = (yy - 60.3) ** 2 + (xx - 59.6) ** 2
    model = 2.0 + 400.0 * np.exp(-r2 / 50.0) + 30.0 / (1 + r2 / 20.0)
    read, gain = 0.8, 5.0
    rng = np.random.default_rng(7)
    img = model + rng.normal(0, 1, model.shape) * np.sqrt(read**2 + (model - 2.0) / gain)
    data = FitData.from_array(img, sigma=1.0)
    noise, d2 = noise_from_residuals(data, model, 2.0, floor=0.01, faint=0.2)
    assert isinstance(noise, Noise)
    assert abs(noise.read / read - 1) < 0.1 and abs(noise.gain / gain - 1) < 0.1
    want = np.sqrt(noise.read**2 + (model - 2.0) / noise.gain + (0.01 * (model - 2.0)) ** 2)
    np.testing.assert_allclose(d2.sigma, want, rtol=1e-12)
    assert np.array_equal(data.image, d2.image) and data.sigma.max() == 1.0  # not modified


def test_noise_from_residuals_with_the_datas_own_intensity():
    """``intensity="data"``: σ² = read² + I/gain + (floor·I)² with I the data's 3 × 3
    mean above the background (computed here pixel by pixel), not the model's; a wrong
    choice is refused."""
    from difstar.fitting import noise_from_residuals

    h = w = 61
    yy, xx = np.mgrid[0:h, 0:w]
    model = 2.0 + 400.0 * np.exp(-((yy - 30.3) ** 2 + (xx - 29.6) ** 2) / 20.0)
    rng = np.random.default_rng(3)
    img = model + rng.normal(0, 1, model.shape) * np.sqrt(0.64 + (model - 2.0) / 5.0)
    mask = np.ones((h, w), bool)
    mask[10, 12] = False
    data = FitData.from_array(img, sigma=1.0, mask=mask)
    noise, d2 = noise_from_residuals(data, model, 2.0, floor=0.02, faint=0.2,
                                     intensity="data")
    inten = np.zeros((h, w))
    for r in range(h):
        for c in range(w):
            win = [img[i, j] for i in range(r - 1, r + 2) for j in range(c - 1, c + 2)
                   if 0 <= i < h and 0 <= j < w and mask[i, j]]
            inten[r, c] = max(np.mean(win) - 2.0, 0.0)

    def want(nz):
        return np.where(mask, np.sqrt(nz.read**2 + inten / nz.gain + (0.02 * inten) ** 2), 1.0)

    np.testing.assert_allclose(d2.sigma, want(noise), rtol=1e-12)
    # another model's residual: other read noise and gain, the same (the data's) I
    n_b, d_b = noise_from_residuals(data, 1.05 * model, 2.0, floor=0.02, faint=0.2,
                                    intensity="data")
    assert (n_b.read, n_b.gain) != (noise.read, noise.gain)
    np.testing.assert_allclose(d_b.sigma, want(n_b), rtol=1e-12)
    with pytest.raises(FitInputError, match="intensity"):
        noise_from_residuals(data, model, 2.0, intensity="both")


def test_relative_sigma_scales_with_the_star():
    """``relative``: σ² = (relative · P)² + (floor · I)² with P the brightest I; the same
    star k times brighter (above the same background) gets σ exactly k times larger, so
    its weights, relative to each other, are the same; bad fractions are refused."""
    from difstar.fitting import noise_from_residuals

    h = w = 61
    yy, xx = np.mgrid[0:h, 0:w]
    star = 400.0 * np.exp(-((yy - 30.3) ** 2 + (xx - 29.6) ** 2) / 20.0) + 3.0 / (
        1 + ((yy - 30) ** 2 + (xx - 30) ** 2) / 30.0)
    noise = np.random.default_rng(4).normal(0, 1, star.shape) * np.sqrt(0.64 + star / 5.0)
    sig = {}
    for k in (1.0, 7.0):
        img = 2.0 + k * (star + noise)
        data = FitData.from_array(img, sigma=1.0)
        nz, d = noise_from_residuals(data, 2.0 + k * star, 2.0, floor=0.03, faint=0.2,
                                     intensity="data", relative=3e-4)
        sig[k] = d.sigma
        assert nz.read > 0 and nz.gain > 0  # still estimated, for the log
        if k == 1.0:
            from scipy.ndimage import uniform_filter

            inten = np.maximum(uniform_filter(img, 3, mode="constant")
                               / uniform_filter(np.ones_like(img), 3, mode="constant")
                               - 2.0, 0.0)
            want = np.sqrt((3e-4 * inten.max()) ** 2 + (0.03 * inten) ** 2)
            np.testing.assert_allclose(d.sigma, want, rtol=1e-12)
    np.testing.assert_allclose(sig[7.0], 7.0 * sig[1.0], rtol=1e-10)
    for bad in (0.0, 1.5, float("nan"), True, "3e-4"):
        with pytest.raises(FitInputError, match="relative"):
            noise_from_residuals(data, 2.0 + star, 2.0, relative=bad)


def test_auto_position_finds_a_star_far_from_the_windows_centre(tmp_path):
    """A manifest's ``"auto"`` x0, y0 start at the brightest pixels' centroid and
    ``bounds_about`` puts the bounds about it: the independent generator's star 6.3 px
    right and 5.2 px up of the centre of its window is fitted to its position, inside
    the bounds_about window."""
    true = dict(TRUE, x0=6.3, y0=-5.2)
    clean = _numpy_star((31, 31), **true)
    sigma = 2e-3 * clean.max()
    np.save(tmp_path / "star.npy", clean + np.random.default_rng(2).normal(0, sigma,
                                                                          clean.shape))
    man = {"data": {"path": "star.npy", "sigma": sigma},
           "pupil": {"builder": "circle", "radius": 0.425},
           "light": {"wavelength": LAM}, "detector": {"pad": 4}, "accuracy": 3e-3,
           "params": {"rotation": TRUE["rotation"], "pixel_scale": P, "obstruction": 0.16,
                      "strut_width": 0.06,
                      "x0": {"value": "auto", "free": True, "bounds_about": [-2, 2]},
                      "y0": {"value": "auto", "free": True, "bounds_about": [-2, 2]},
                      "flux": {"value": "auto", "free": True, "scale": 100.0},
                      "background": {"value": "auto", "free": True, "scale": 1.0}}}
    (tmp_path / "m.json").write_text(json.dumps(man))
    model, data, opts = load_manifest(tmp_path / "m.json")
    px, py = model.params["x0"], model.params["y0"]
    assert abs(px.value - 6.3) < 0.5 and abs(py.value + 5.2) < 0.5
    assert list(px.bounds) == [px.value - 2, px.value + 2]
    res = fit(model, data, max_steps=30)
    assert abs(res.values["x0"] - 6.3) < 0.02 and abs(res.values["y0"] + 5.2) < 0.02
    assert abs(res.values["flux"] / TRUE["flux"] - 1) < 0.01
    assert res.residual_rms_peak < 5e-3


def test_stage_set_puts_values_before_the_stage():
    """A stage's ``set`` puts parameters at values before it solves, whatever the start:
    started at the twin (−z4) of the independent generator's defocus, a stage that sets
    z4 to +300 nm ends at the generator's +400 nm (without it the fit stays in the twin,
    :func:`test_flip_hop_leaves_the_twin_of_a_defocus`). Unknown names and values that
    are not finite numbers are refused."""
    z4 = 400e-9
    model, data = _twin_case(3, z4=z4)
    stage = {"free": ["z4", "flux"], "max_steps": 30}
    res = fit(model, data, stages=[{**stage, "set": {"z4": 300.0}}])
    assert abs(res.values["z4"] - z4 * 1e9) < max(4 * res.errors["z4"], 5.0)
    assert {"stage": 0, "set": {"z4": 300.0}} in res.stages
    for bad in ({"z99": 1.0}, {"z4": float("nan")}, {"z4": "0"}, {}):
        with pytest.raises(FitInputError, match="set"):
            fit(model, data, stages=[{**stage, "set": bad}])


def test_repeat_reaches_the_fixed_point_of_alternating_stages():
    """Flux and jitter in one stage, the background in the next: coupled, so one pass
    from a background 5 below the independent generator's leaves the flux 26 % off;
    ``repeat`` re-runs both until the flux settles, at the generator's values (its
    midpoint rule: 1 %). Too few rounds for the tolerance is a warning; bad repeats are
    refused before any fitting."""
    clean = _numpy_star(**TRUE)
    data = FitData.from_array(clean, sigma=2e-3 * clean.max())
    m = _model(background=Param(-3.0, True, scale=1.0), rotation=Param(TRUE["rotation"]),
               x0=Param(TRUE["x0"]), y0=Param(TRUE["y0"]), jitter=Param(0.3, True, (0, 2)))
    two = [{"free": ["flux", "jitter"]}, {"free": ["background"]}]
    once = fit(m, data, stages=two)
    assert abs(once.values["flux"] / TRUE["flux"] - 1) > 0.1  # one pass is not enough
    res = fit(m, data, stages=two + [{"repeat": {"until": {"flux": 0.1}, "max_rounds": 8}}])
    assert abs(res.values["flux"] / TRUE["flux"] - 1) < 0.01
    assert abs(res.values["background"] - TRUE["background"]) < 0.02
    (log,) = [e for e in res.stages if "repeat" in e]
    assert log["settled"] and 2 <= len(log["rounds"]) <= 8
    moved = [abs(r["moved"]["flux"]) for r in log["rounds"]]
    assert moved[-1] < 0.1 and moved == sorted(moved, reverse=True)
    assert not any("repeat" in w for w in res.warnings)
    short = fit(m, data, stages=two + [{"repeat": {"until": {"flux": 1e-9}, "max_rounds": 1}}])
    assert any("repeat" in w and "max_rounds" in w for w in short.warnings), short.warnings
    for bad in ({"until": {}}, {"until": {"flx": 0.1}}, {"until": {"flux": 0}},
                {"until": {"flux": float("nan")}}, {"until": {"flux": True}},
                {"until": {"flux": 0.1}, "stages": 3}, {"until": {"flux": 0.1}, "stages": 1.5},
                {"until": {"flux": 0.1}, "max_rounds": 0}, {"until": {"flux": 0.1}, "x": 1},
                "flux"):
        with pytest.raises(FitInputError, match="repeat needs 'until'"):
            fit(m, data, stages=two + [{"repeat": bad}])


def test_fainter_copy_has_the_fainter_stars_noise():
    from difstar.fitting import Noise, fainter_copy

    model = np.full((200, 200), 10.0)
    model[50:150, 50:150] = 410.0
    noise = Noise(1.0, 2.0)
    rng = np.random.default_rng(3)
    img = model + rng.normal(0, 1, model.shape) * np.sqrt(1.0 + (model - 10.0) / 2.0)
    data = FitData.from_array(img, sigma=1.0)
    c = fainter_copy(data, model, 10.0, 4.0, noise, seed=1)
    inner, outer = c.image[50:150, 50:150], c.image[:40, :]
    assert abs(inner.mean() - 110.0) < 0.3  # (410 − 10)/4 + 10
    assert abs(inner.var() / (1.0 + 100.0 / 2.0) - 1) < 0.05  # read² + I/gain at I = 100
    assert abs(outer.var() / 1.0 - 1) < 0.05
    np.testing.assert_allclose(c.sigma[60, 60] ** 2, 1.0 + 100.0 / 2.0)
    with pytest.raises(FitInputError, match="factor"):
        fainter_copy(data, model, 10.0, 0.5, noise)


def test_scan_puts_the_solver_in_the_right_basin(synthetic, capsys):
    """From a start 15° off (beyond the struts' 120° pattern's local basins), a stage
    that scans the rotation first recovers it; a verbose fit shows the scan's progress
    (stage 0's scan bar) and the point it chose."""
    data, _ = synthetic
    model = _model(rotation=Param(TRUE["rotation"] + 15.0, True, (-30, 30)),
                   x0=Param(TRUE["x0"]), y0=Param(TRUE["y0"]),
                   flux=Param(TRUE["flux"]), background=Param(TRUE["background"]))
    res = fit(model, data, stages=[{"free": ["rotation"], "scan": {
        "name": "rotation", "half_range": 20, "step": 1.0}}], max_steps=20, verbose=True)
    out = capsys.readouterr()
    assert "stage 0 scan" in out.err and "stage 0: scan of rotation: best" in out.out
    assert abs(res.values["rotation"] - TRUE["rotation"]) < 1.0  # a 19 × 19 px star
    assert res.stages[0]["scan"]["name"] == "rotation"
    # the grid is the multiples of the step: two starts inside one step choose the same
    # point (a rough start and the main fit then take the same basin)
    from difstar.fitting._analysis import _scan
    from difstar.fitting._residuals import _PixelTarget

    fixed = model.with_values({"rotation": 0.0})
    picks = [_scan(fixed, data, _PixelTarget(data),
                   {k: p.value for k, p in fixed.params.items()} | {"rotation": start},
                   name="rotation", half_range=20, step=1.0)["rotation"]
             for start in (TRUE["rotation"] + 14.6, TRUE["rotation"] + 15.3)]
    assert picks[0] == picks[1] and picks[0] == round(picks[0])
    assert abs(picks[0] - TRUE["rotation"]) <= 1.0


def _noisy_dng(path, clean, pattern, black, white, gain, read, *, seed):
    """``clean`` (DN above black) with Poisson noise in electrons and read noise in DN,
    rounded, clipped at ``white`` and written as a Bayer DNG: (raw, path)."""
    from difstar.io import write_dng

    rng = np.random.default_rng(seed)
    dn = black + rng.poisson(clean * gain) / gain + rng.normal(0, read, clean.shape)
    raw = np.clip(np.round(dn), 0, white).astype(np.uint16)
    return raw, write_dng(path, raw, pattern=pattern, black_level=black, white_level=white)


def test_chi2_slice_has_its_minimum_at_the_generators_rotation():
    """The slice through χ² along the rotation, other parameters at the independent
    generator's values (noise-free image, σ as in ``synthetic``), is lowest within one
    step of the generator's rotation and twice as high 3° away; its values are the χ²
    the fitter reports; bad names and grids are refused."""
    clean = _numpy_star(**TRUE)
    data = FitData.from_array(clean, sigma=2e-3 * clean.max())
    m = _model()
    v = dict(m.values(), **TRUE)
    grid = np.arange(1.0, 7.01, 0.25)
    c = chi2_slice(m, data, v, "rotation", grid)
    assert abs(grid[np.argmin(c)] - TRUE["rotation"]) <= 0.25
    assert c[0] > 2 * c.min() and c[-1] > 2 * c.min()
    at = fit(m.with_values(v), data, stages=[{"free": ["flux"], "max_steps": 1}])
    assert c[12] == pytest.approx(at.chi2, rel=0.05)  # grid[12] = 4.0, flux barely moved
    for name, g in (("rotaton", grid), ("rotation", []), ("rotation", [1.0, np.nan])):
        with pytest.raises(FitInputError, match="chi2_slice"):
            chi2_slice(m, data, v, name, g)


def test_a_scan_shows_its_progress_point_by_point(capsys):
    """``chi2_slice``'s ``each`` sees every grid value with its χ² in turn; a stage's scan
    in a verbose fit draws a bar on stderr that counts the grid's points (a scan of a
    few hundred model images takes seconds), and a quiet one draws nothing."""
    from difstar.fitting._analysis import scan_grid
    from difstar.fitting._residuals import _PixelTarget

    clean = _numpy_star(**TRUE)
    data = FitData.from_array(clean, sigma=2e-3 * clean.max())
    m = _model()
    v = dict(m.values(), **TRUE)
    seen = []
    c = chi2_slice(m, data, v, "rotation", [3.0, 4.0, 5.0], each=lambda x, q: seen.append((x, q)))
    assert seen == [(3.0, c[0]), (4.0, c[1]), (5.0, c[2])]
    kw = dict(name="rotation", half_range=1.0, step=0.5)
    grid, cost = scan_grid(m, data, _PixelTarget(data), v, progress="stage 1 scan", **kw)
    err = capsys.readouterr().err
    assert grid.size == 5 and "stage 1 scan" in err and "5/5" in err
    assert f"lowest {cost.min():.6g}" in err
    _, quiet = scan_grid(m, data, _PixelTarget(data), v, **kw)
    assert capsys.readouterr().err == "" and np.array_equal(quiet, cost)


def test_model_images_and_chi2_at_the_generators_values():
    """At the independent generator's values the public ``model_images`` is the
    generator's image to its 4 × 4 midpoint rule (within 1 % of the peak, 0.2 % RMS),
    and ``chi2_at`` is Σ ((data − model) / σ)² over the used pixels, a masked pixel
    left out."""
    from difstar import chi2_at, model_images

    clean = _numpy_star(**TRUE)
    sigma = 2e-3 * clean.max()
    mask = np.ones(clean.shape, bool)
    mask[3, 4] = False
    data = FitData.from_array(clean, sigma=sigma, mask=mask)
    v = dict(_model().values(), **TRUE)
    (img,) = model_images(_model(), v, data)
    assert img.shape == clean.shape
    assert np.max(np.abs(img - clean)) < 1e-2 * clean.max()
    assert np.sqrt(np.mean((img - clean) ** 2)) < 2e-3 * clean.max()
    expect = float(np.sum(((clean - img) / sigma)[mask] ** 2))
    assert chi2_at(_model(), data, v) == pytest.approx(expect, rel=1e-9)
    assert chi2_at(_model(), [data, data], v) == pytest.approx(2 * expect, rel=1e-9)


@pytest.mark.parametrize("pattern", ["RGGB", "GBRG"])
def test_fit_from_a_raw_mosaic_of_the_independent_star(tmp_path, pattern):
    """The independent star written as a Bayer DNG (Poisson–Gaussian noise, a saturated
    core), read back by LibRaw, fitted on its green photosites: the centre and flux
    come back, and saturated pixels are left out."""
    true = dict(TRUE, flux=3.0e5, background=0.0)
    clean = _numpy_star((25, 25), **true)[:24, :24]  # DN above black; centre (12, 12)
    black, white, gain, read = 512, 16383, 2.0, 3.0
    raw, path = _noisy_dng(tmp_path / "star.dng", clean, pattern, black, white, gain, read,
                           seed=5)
    data = FitData.from_raw(path, channel="G", gain_e_per_dn=gain, read_noise_dn=read,
                            pixel_scale=P)
    tile = np.array(list(pattern)).reshape(2, 2)
    green = np.tile(tile, (12, 12)) == "G"
    assert np.array_equal(data.mask, green & (raw < white))
    assert (raw >= white).any() and not data.mask[raw >= white].any()
    scale = white - black
    model = _model(rotation=Param(true["rotation"]),
                   flux=Param(true["flux"] / scale * 0.9, True, scale=0.1),
                   background=Param(0.0, True, scale=1e-3))
    res = fit(model, data, max_steps=40)
    assert abs(res.values["x0"] - true["x0"]) < 0.03 and abs(res.values["y0"] - true["y0"]) < 0.03
    assert abs(res.values["flux"] * scale / true["flux"] - 1) < 0.02
    assert 0.5 < res.chi2_dof < 2.0  # the noise model is right
    with pytest.raises(FitInputError, match="channel"):
        FitData.from_raw(path, channel="Y", gain_e_per_dn=gain, read_noise_dn=read)


def test_three_colours_of_one_raw_in_their_own_bands(tmp_path):
    """One Bayer DNG whose R, G and B photosites see the independent star at 4.4, 3.6
    and 3.0 µm (each colour its own flux): its three colours fitted together, each in
    its own light, share the centre and rotation and keep their own flux."""
    lams = {"R": 4.4e-6, "G": 3.6e-6, "B": 3.0e-6}
    fluxes = {"R": 2.0e5, "G": 3.0e5, "B": 1.5e5}
    pattern = "RGGB"
    colour = np.tile(np.array(list(pattern)).reshape(2, 2), (12, 12))
    clean = np.zeros((24, 24))
    for c in "RGB":
        star = _numpy_star((25, 25), **dict(TRUE, flux=fluxes[c], background=0.0),
                           lam=lams[c])[:24, :24]
        clean = np.where(colour == c, star, clean)
    black, white, gain, read = 512, 65535, 2.0, 3.0
    _, path = _noisy_dng(tmp_path / "rgb.dng", clean, pattern, black, white, gain, read,
                         seed=6)
    datas = [FitData.from_raw(path, channel=c, gain_e_per_dn=gain, read_noise_dn=read,
                              pixel_scale=P, light=Light.monochromatic(lams[c]))
             for c in "RGB"]
    scale = white - black
    model = _model(rotation=Param(TRUE["rotation"]),
                   flux=Param(2e5 / scale, True, scale=0.5),
                   background=Param(0.0, True, scale=1e-3))
    res = fit(model, datas, per_capture=("flux", "background"), max_steps=40)
    v = res.values
    assert abs(v["x0"] - TRUE["x0"]) < 0.03 and abs(v["y0"] - TRUE["y0"]) < 0.03
    for i, c in enumerate("RGB"):
        assert abs(v[f"flux@{i}"] * scale / fluxes[c] - 1) < 0.02, (c, v[f"flux@{i}"])
    assert 0.5 < res.chi2_dof < 2.0
    # in one light for all three, the fit is measurably worse: the bands matter
    wrong = fit(model, [dataclasses.replace(d, light=None) for d in datas],
                per_capture=("flux", "background"), max_steps=40)
    assert wrong.chi2_dof > 2 * res.chi2_dof
    with pytest.raises(FitInputError, match="light"):
        FitData.from_array(np.ones((8, 8)), sigma=1.0, light=3.6e-6)


def test_two_captures_share_the_pupil_and_keep_their_own_centres(synthetic):
    """Two exposures of the independent star (other centre, other flux) fitted together:
    one rotation for both, a centre and flux each; the joint rotation is better
    constrained than either capture's alone."""
    data1, sigma = synthetic
    true2 = dict(TRUE, x0=-0.4, y0=0.35, flux=2500.0)
    clean2 = _numpy_star(**true2)
    rng = np.random.default_rng(9)
    data2 = FitData.from_array(clean2 + rng.normal(0, sigma, clean2.shape), sigma=sigma)
    res = fit(_model(), [data1, data2], max_steps=30)
    v, e = res.values, res.errors
    assert "x0@0" in res.free and "x0@1" in res.free and "x0" not in res.free
    for i, t in enumerate((TRUE, true2)):
        assert abs(v[f"x0@{i}"] - t["x0"]) < 0.02 and abs(v[f"y0@{i}"] - t["y0"]) < 0.02
        assert abs(v[f"flux@{i}"] / t["flux"] - 1) < 0.01
    assert isinstance(res.model_image, list) and len(res.residual) == 2
    alone = fit(_model(), data1, max_steps=30)
    assert e["rotation"] < alone.errors["rotation"]
    assert abs(v["rotation"] - TRUE["rotation"]) < max(4 * e["rotation"], 0.5)


def test_hop_leaves_a_neighbouring_basin(synthetic):
    """A stage that cannot leave where it started (one solver step here) ends far from
    the rotation; a hop stage that re-runs it from 25° back keeps the lower χ², which is
    the right rotation's."""
    data, _ = synthetic
    model = _model(rotation=Param(TRUE["rotation"] + 25.0, True, (-40, 40)),
                   x0=Param(TRUE["x0"]), y0=Param(TRUE["y0"]),
                   flux=Param(TRUE["flux"]), background=Param(TRUE["background"]))
    stuck = {"free": ["rotation"], "max_steps": 1}
    alone = fit(model, data, stages=[stuck])
    assert abs(alone.values["rotation"] - TRUE["rotation"]) > 10.0
    res = fit(model, data, stages=[stuck, {"hop": {"name": "rotation", "offsets": [-25.0],
                                                   "stages": 1}}])
    assert abs(res.values["rotation"] - TRUE["rotation"]) < 1.0
    hop = [s for s in res.stages if "hop" in s][0]
    assert len(hop["tried"]) == 2 and hop["tried"][1]["chi2"] < hop["tried"][0]["chi2"]
    # the same procedure as types (difstar.fitting.Solve, Hop): the same fit
    typed = fit(model, data, stages=[Solve(free=["rotation"], max_steps=1),
                                     Hop(name="rotation", offsets=[-25.0], stages=1)])
    assert typed.values == res.values
    assert [s.get("hop") for s in typed.stages] == [s.get("hop") for s in res.stages]
    with pytest.raises(FitInputError, match="hop"):
        fit(model, data, stages=[{"hop": {"name": "rotation", "offsets": [1.0]}}])


def _twin_case(seed, flux_bounds=None, **terms):
    """Noisy data of the independent star with the given Zernike terms (m RMS: ``z4``,
    ``z11``) and a model started at their twin (every term negated), flux free (within
    ``flux_bounds`` if given: then the solver carries it instead of taking it in closed
    form)."""
    clean = _numpy_star(**TRUE, **terms)
    sigma = 2e-3 * clean.max()
    data = FitData.from_array(
        clean + np.random.default_rng(seed).normal(0, sigma, clean.shape), sigma=sigma)
    fixed = {k: Param(TRUE[k]) for k in ("rotation", "x0", "y0", "background")}
    zs = {k: Param(-v * 1e9, True, (-1000, 1000)) for k, v in terms.items()}
    model = ImageModel(obstructed_circle_pupil(0.425),
                       fixed | zs | {"flux": Param(TRUE["flux"], True, flux_bounds,
                                                   scale=None if flux_bounds else 100.0),
                                     "pixel_scale": Param(P), "obstruction": Param(0.16),
                                     "strut_width": Param(0.06)},
                       light=Light.monochromatic(LAM), zernike=[int(k[1:]) for k in terms],
                       pad=4, accuracy=3e-3)
    return model, data


def test_flip_hop_leaves_the_twin_of_a_defocus():
    """An in-focus image cannot tell W(x, y) from −W(−x, −y) for a centrally symmetric
    pupil; with three struts the twin of a defocus is a neighbouring minimum. A fit
    started at −z4 stays in it; a hop that negates z4 and re-runs the stage ends at the
    independent generator's +z4 with the lower χ²."""
    z4 = 400e-9
    model, data = _twin_case(3, z4=z4)
    stage = {"free": ["z4", "flux"], "max_steps": 30}
    twin = fit(model, data, stages=[stage])
    assert twin.values["z4"] < 0  # the twin: a minimum the solver does not leave
    res = fit(model, data, stages=[stage, {"hop": {"flip": ["z4"], "stages": 1}}])
    assert abs(res.values["z4"] - z4 * 1e9) < max(4 * res.errors["z4"], 5.0)
    assert res.chi2 < twin.chi2
    assert res.chi2_dof < 2.0
    hop = [s for s in res.stages if "hop" in s][0]
    assert hop["tried"][1]["change"] == "z4 negated"
    with pytest.raises(FitInputError, match="flip"):
        fit(model, data, stages=[stage, {"hop": {"flip": ["z99"]}}])
    # a second start put by hand (set) works the same way
    res = fit(model, data, stages=[stage, {"hop": {"set": {"z4": 300.0}, "stages": 1}}])
    assert abs(res.values["z4"] - z4 * 1e9) < max(4 * res.errors["z4"], 5.0)
    assert [s for s in res.stages if "hop" in s][0]["tried"][1]["change"] == "set z4=300"


def test_a_fit_plans_its_psf_for_the_wavefront_it_finds():
    """The PSF plan follows the Zernike terms' values (1.5 × them), not their bounds: a
    model started near zero plans a coarse pupil, and a fit whose answer needs a finer
    one solves again on it. Started at z4 = +40 nm, the fit of the independent
    generator's z4 = 400 nm ends on a plan that holds at its answer, within 4 standard
    errors of the generator's value."""
    z4 = 400e-9
    model, data = _twin_case(3, z4=z4)
    model = model.with_values({"z4": 40.0})
    shape = model.padded_shape(data.image.shape)
    start = model.plan(shape)
    assert model.plan_holds({"z4": 40.0}, shape)
    assert not model.plan_holds({"z4": 400.0}, shape)
    # planning for the bounds (±1000 nm) would have asked for more than the answer needs
    need = model.with_values({"z4": 400.0}).plan(shape, margin=1.0).subcells
    assert start.subcells < need < model.with_values({"z4": 1000.0}).plan(shape).subcells
    res = fit(model, data, stages=[{"free": ["z4", "flux"], "max_steps": 30}])
    assert abs(res.values["z4"] - z4 * 1e9) < max(4 * res.errors["z4"], 5.0)
    end = model.with_values(res.values)
    assert end.plan(shape).subcells > start.subcells
    assert end.plan_holds(res.values, shape)
    assert res.chi2_dof < 2.0


def test_a_fit_says_when_its_plan_never_caught_up(monkeypatch):
    """Where the answer still needs a finer PSF plan after the last re-plan, the fit
    warns (its values stand on a plan made for smaller Zernike terms) rather than
    returning them as if the plan held."""
    import difstar.fitting._solve as solve_mod

    model, data = _twin_case(3, z4=400e-9)
    monkeypatch.setattr(solve_mod, "MAX_REPLANS", 0)
    monkeypatch.setattr(type(model), "plan_holds", lambda self, *a, **k: False)
    with pytest.warns(RuntimeWarning, match="finer PSF plan after 1 solves"):
        fit(model, data, stages=[{"free": ["flux"], "max_steps": 2}])


def test_grouped_flip_hop_negates_the_even_terms_together():
    """The twin of a wavefront with defocus and spherical aberration negates both terms
    at once. Started at the twin (−z4, −z11) of the independent generator's wavefront, a
    hop whose flip entry is the group [z4, z11] ends at the generator's (+z4, +z11) with
    the lowest χ² of the hop's tries (the single flips are tried as well)."""
    z4, z11 = 400e-9, 150e-9
    # a bounded flux is carried by the solver: from the twin the solve then stays in it,
    # as the hop needs to show its use (with the flux in closed form, variable
    # projection, or with smaller terms, 300 and 120 nm, this start reaches the
    # generator's wavefront by itself)
    model, data = _twin_case(5, flux_bounds=(500.0, 2000.0), z4=z4, z11=z11)
    stage = {"free": ["z4", "z11", "flux"], "max_steps": 30}
    res = fit(model, data, stages=[stage, {"hop": {"flip": ["z4", "z11", ["z4", "z11"]],
                                                   "stages": 1}}])
    tried = [s for s in res.stages if "hop" in s][0]["tried"]
    assert [t["change"] for t in tried] == ["none", "z4 negated", "z11 negated",
                                            "z4, z11 negated"]
    twin, group = tried[0]["chi2"], tried[3]["chi2"]
    assert group < twin and group <= min(t["chi2"] for t in tried) * (1 + 1e-9)
    assert abs(res.values["z4"] - z4 * 1e9) < max(4 * res.errors["z4"], 5.0)
    assert abs(res.values["z11"] - z11 * 1e9) < max(4 * res.errors["z11"], 5.0)
    with pytest.raises(FitInputError, match="flip"):
        fit(model, data, stages=[stage, {"hop": {"flip": [["z4", "z99"]]}}])
    with pytest.raises(FitInputError, match="flip"):
        fit(model, data, stages=[stage, {"hop": {"flip": [[]]}}])


def test_disc_source_through_a_response_curve_in_an_exposure_bracket():
    """Three exposures (×1, ×4, ×16) of an extended disc source by the independent
    generator (the disc convolved on a fine raster), through the camera's response curve
    written here in NumPy (toe, knee; the ×16 core is deep in the shoulder) and clipped
    pixels masked: one shared flux, centre, disc radius and knee recovered."""
    radius, knee, toe, white = 1.6, 8.0, 0.02, 1.0
    lin = _numpy_star(**dict(TRUE, flux=1.0, background=0.0), disc=radius)
    lin = lin / lin.max() * 0.35  # the ×1 capture's peak, in units of full scale

    def response(e):  # the camera fitter's curve: toe, then a softplus knee to 1
        u = np.sqrt(e**2 + toe**2) - toe
        return 1 - np.log1p(np.exp(knee * (1 - u))) / np.log1p(np.exp(knee))

    rng = np.random.default_rng(5)
    datas = []
    for t in (1.0, 4.0, 16.0):
        img = white * response(lin * t) + 0.01
        sig = np.sqrt(1e-3**2 + 2e-4 * img)
        noisy = img + rng.normal(0, 1, img.shape) * sig
        datas.append(FitData.from_array(noisy, sigma=sig, exposure=t, saturation=0.995))
    assert datas[2].mask.sum() < datas[0].mask.sum()  # the clipped core is left out
    flux_true = 0.35 / _numpy_star(**dict(TRUE, flux=1.0, background=0.0), disc=radius).max()
    params = {
        "rotation": Param(TRUE["rotation"]), "pixel_scale": Param(P),
        "obstruction": Param(0.16), "strut_width": Param(0.06), "jitter": Param(0.0),
        "x0": Param(0.0, True, (-2, 2)), "y0": Param(0.0, True, (-2, 2)),
        "flux": Param(0.9 * flux_true, True, scale=0.1 * flux_true),
        "background": Param(0.0, True, scale=1e-2),
        "source_radius": Param(1.2, True, (0.0, 4.0)),
        "knee": Param(12.0, True, (1.0, 100.0)), "toe": Param(toe), "white": Param(white),
    }
    model = ImageModel(obstructed_circle_pupil(0.425), params, light=Light.monochromatic(LAM),
                       pad=6, accuracy=3e-3, source="disc", response=True)
    res = fit(model, datas, per_capture=(), max_steps=40)
    v = res.values
    assert abs(v["source_radius"] - radius) < 0.03, v["source_radius"]
    # the knee is seen only in the shoulder's few pixels: within 4 standard errors,
    # and those a few per cent
    assert abs(v["knee"] - knee) < 4 * res.errors["knee"] and res.errors["knee"] < 0.08 * knee
    assert abs(v["flux"] / flux_true - 1) < 0.01
    assert abs(v["x0"] - TRUE["x0"]) < 0.02 and abs(v["y0"] - TRUE["y0"]) < 0.02
    assert res.chi2_dof < 1.5


def test_user_image_source():
    """A source given as an image (three points one pixel apart, weights 1:2:1): the
    truth is the independent star at the three positions, weighted."""
    w = np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 1.0], [0.0, 0.0, 0.0]])
    truth = sum(wi * _numpy_star(**dict(TRUE, x0=TRUE["x0"] + dx, background=0.0))
                for dx, wi in ((-1, 1.0), (0, 2.0), (1, 1.0))) / 4 + TRUE["background"]
    sigma = 2e-3 * truth.max()
    data = FitData.from_array(truth + np.random.default_rng(2).normal(0, sigma, truth.shape),
                              sigma=sigma)
    model = ImageModel(obstructed_circle_pupil(0.425),
                       {"rotation": Param(TRUE["rotation"]), "x0": Param(0.0, True, (-2, 2)),
                        "y0": Param(0.0, True, (-2, 2)),
                        "flux": Param(800.0, True, scale=100.0),
                        "background": Param(0.0, True, scale=1.0), "pixel_scale": Param(P),
                        "obstruction": Param(0.16), "strut_width": Param(0.06)},
                       light=Light.monochromatic(LAM), pad=4, accuracy=3e-3, source=w)
    res = fit(model, data, max_steps=30)
    v = res.values
    assert abs(v["x0"] - TRUE["x0"]) < 0.02 and abs(v["y0"] - TRUE["y0"]) < 0.02
    assert abs(v["flux"] / TRUE["flux"] - 1) < 0.01
    assert res.chi2_dof < 2.0


def test_source_layers_as_classes():
    """The source is a layer like the detector's: ``source="disc"`` is
    ``DiscSource()`` (the same parameters and image), and a ``SourceImage``'s transfer
    on a window's frequencies is NumPy's FFT of the image wrapped about its centre
    pixel on that window (an exact transform, to 1e-13), for odd and even windows; the
    caller's array is never changed."""
    light = Light.monochromatic(LAM)
    base = {"pixel_scale": Param(P), "source_radius": Param(1.3)}
    by_name = ImageModel(obstructed_circle_pupil(), base, light=light, source="disc", pad=4)
    by_class = ImageModel(obstructed_circle_pupil(), base, light=light, source=DiscSource(),
                          pad=4)
    assert list(by_name.params) == list(by_class.params)
    assert by_class.units["source_radius"] == "data px"
    np.testing.assert_array_equal(by_name((15, 15)), by_class((15, 15)))
    src = np.random.default_rng(3).uniform(0, 1, (5, 4))
    kept = src.copy()
    layer = SourceImage(src)
    for hp, wp in ((23, 23), (22, 17), (16, 30)):
        big = np.zeros((hp, wp))
        big[:5, :4] = src / src.sum()
        want = np.fft.rfft2(np.roll(big, (-2, -2), axis=(0, 1)))
        got = layer.transfer({}, np.fft.rfftfreq(wp)[None, :], np.fft.fftfreq(hp)[:, None])
        np.testing.assert_allclose(got, want, atol=1e-13)
    np.testing.assert_array_equal(src, kept)
    point = ImageModel(obstructed_circle_pupil(), {}, light=light)
    assert point.source is None and "source_radius" not in point.params
    # the co-add's kernel as a class or by name: the same model
    ps = {"pixel_scale": Param(P)}
    a = ImageModel(obstructed_circle_pupil(), ps, light=light, resampling="lanczos3")
    b = ImageModel(obstructed_circle_pupil(), ps, light=light, resampling=Resampling(3))
    assert a.resampling == b.resampling == 3
    with pytest.raises(FitInputError, match="order 7"):
        Resampling(7)


def test_source_response_and_exposure_inputs_are_checked():
    light = Light.monochromatic(LAM)
    with pytest.raises(FitInputError, match="source"):
        ImageModel(obstructed_circle_pupil(), {}, light=light, source="gaussian")
    with pytest.raises(FitInputError, match="source image"):
        ImageModel(obstructed_circle_pupil(), {}, light=light, source=-np.ones((3, 3)))
    with pytest.raises(FitInputError, match="knee"):
        ImageModel(obstructed_circle_pupil(), {"knee": Param(-1.0)}, light=light,
                   response=True)
    with pytest.raises(FitInputError, match="unknown parameters"):
        ImageModel(obstructed_circle_pupil(), {"knee": Param(5.0)}, light=light)
    with pytest.raises(FitInputError, match="source_radius"):
        ImageModel(obstructed_circle_pupil(), {"source_radius": Param(-1.0)}, light=light,
                   source="disc")
    with pytest.raises(FitInputError, match="exposure"):
        FitData.from_array(np.ones((8, 8)), sigma=1.0, exposure=0.0)
    with pytest.raises(FitInputError, match="saturation"):
        FitData.from_array(np.ones((8, 8)), sigma=1.0, saturation=float("nan"))
    d = FitData.from_array(np.arange(64.0).reshape(8, 8), sigma=1.0, saturation=60.0)
    assert d.mask.sum() == 60 and d.cropped(2).exposure == 1.0


def test_disc_transform_against_scipy():
    """2 J1(x)/x against SciPy's Bessel function, values and derivative (−2 J2(x)/x)."""
    import jax
    import scipy.special as sp

    from difstar.fitting._detector import disc_transform

    x = np.linspace(1e-6, 150.0, 20001)
    np.testing.assert_allclose(np.asarray(disc_transform(x)), 2 * sp.j1(x) / x, atol=5e-9)
    g = np.asarray(jax.vmap(jax.grad(disc_transform))(x))
    np.testing.assert_allclose(g, -2 * sp.jv(2, x) / x, atol=2e-8)
    assert float(disc_transform(0.0)) == pytest.approx(1.0, abs=1e-9)
    assert np.isfinite(float(jax.grad(disc_transform)(0.0)))


def test_iris_builder_recovers_a_heptagon():
    """A 7-blade iris (a regular heptagon, the paper's lens) by the independent
    generator: rotation, size and centre recovered through the iris builder."""
    true = dict(TRUE, rotation=7.0)
    clean = _numpy_star(**true, blades=7, radius=0.40)
    sigma = 2e-3 * clean.max()
    data = FitData.from_array(clean + np.random.default_rng(8).normal(0, sigma, clean.shape),
                              sigma=sigma)
    model = ImageModel(iris_pupil(7, 0.40),
                       {"rotation": Param(9.0, True, (-10, 30)),
                        "x0": Param(0.0, True, (-2, 2)), "y0": Param(0.0, True, (-2, 2)),
                        "flux": Param(900.0, True, scale=100.0),
                        "background": Param(0.0, True, scale=1.0), "pixel_scale": Param(P),
                        "iris_radius": Param(0.37, True, (0.3, 0.5))},
                       light=Light.monochromatic(LAM), pad=4, accuracy=3e-3)
    res = fit(model, data, max_steps=40)
    v, e = res.values, res.errors
    assert abs(v["rotation"] - 7.0) < max(4 * e["rotation"], 0.3), (v["rotation"], e)
    assert abs(v["iris_radius"] / 0.40 - 1) < 0.01
    assert abs(v["x0"] - true["x0"]) < 0.02 and abs(v["y0"] - true["y0"]) < 0.02
    assert res.chi2_dof < 2.0
    with pytest.raises(FitInputError, match="blades"):
        iris_pupil(2)


def test_reject_outliers_masks_what_the_model_cannot_explain():
    """On the independent generator's star with known additions: a hot pixel and a
    neighbour's core beyond ``r_min`` are masked with their ± ``grow`` squares (cut at
    ``r_min``), a core pixel the model misses by as much is kept, every other pixel is
    kept, the input is not changed; options that cannot be right are refused."""
    from difstar.fitting import reject_outliers

    clean = _numpy_star((41, 41), **TRUE)
    sigma = 2e-3 * clean.max()
    noisy = clean + np.random.default_rng(5).normal(0, sigma, clean.shape)
    noisy[20 - 1, 20 + 2] += 0.5 * clean.max()  # core mismatch: 2.2 px from the centre
    noisy[5, 30] += 0.2 * clean.max()  # a hot pixel
    noisy[33:35, 8:10] += 0.1 * clean.max()  # a neighbour's core
    data = FitData.from_array(noisy, sigma=sigma)
    before = (data.image.copy(), data.mask.copy(), data.sigma.copy())
    centre = (20 + TRUE["x0"], 20 + TRUE["y0"])  # x0 columns right, y0 rows down
    out, n, largest = reject_outliers(data, clean, 0.0, centre, above=20, r_min=5, grow=1)
    want = np.zeros(clean.shape, bool)
    want[4:7, 29:32] = True
    want[32:36, 7:11] = True
    assert np.array_equal(~out.mask, want) and n == want.sum() == 25
    assert out.mask[19, 22]  # the core is kept
    r = np.hypot(*np.subtract(np.indices(clean.shape)[::-1], np.reshape(centre, (2, 1, 1))))
    z = np.abs(noisy - clean) / sigma
    assert largest == z[out.mask & (r >= 5)].max() and largest < 6  # the noise
    for a, b in zip(before, (data.image, data.mask, data.sigma)):
        assert np.array_equal(a, b)
    assert np.array_equal(out.image, data.image) and np.array_equal(out.sigma, data.sigma)
    # nothing more than ``above`` σ away beyond r_min: nothing masked
    _, n, largest = reject_outliers(FitData.from_array(clean + 1e-9, sigma=sigma), clean,
                                    0.0, centre, above=20, r_min=5)
    assert n == 0 and largest == pytest.approx(1e-9 / sigma)
    # ``relative``: σ at least that fraction of the peak, so a star 10 times brighter
    # with the same noise loses the same pixels (on its own σ, its noise would go too)
    bright = FitData.from_array(10 * noisy, sigma=sigma)
    opts = {"above": 5, "r_min": 5, "grow": 0, "relative": 0.02}
    faint_mask = reject_outliers(data, clean, TRUE["background"], centre, **opts)[0].mask
    bright_mask = reject_outliers(bright, 10 * clean, 10 * TRUE["background"], centre,
                                  **opts)[0].mask
    assert np.array_equal(faint_mask, bright_mask)
    assert not faint_mask[5, 30] and not faint_mask[33:35, 8:10].any()
    assert faint_mask.sum() >= data.mask.sum() - 10  # the hot pixel, the neighbour: 5
    own = reject_outliers(bright, 10 * clean, 10 * TRUE["background"], centre, above=20,
                          r_min=5, grow=0)[0].mask
    assert (~own).sum() > 3 * (~faint_mask).sum()  # its own σ: noise pixels go too
    for bad in ({"above": 0}, {"above": float("nan")}, {"r_min": -1}, {"grow": 1.5},
                {"grow": True}, {"above": "20"}, {"relative": 0}, {"relative": 1.5}):
        with pytest.raises(FitInputError, match="reject: needs above"):
            reject_outliers(data, clean, 0.0, centre, **bad)
    with pytest.raises(FitInputError, match="shape"):
        reject_outliers(data, clean[:-1], 0.0, centre)


def test_reject_stage_keeps_a_neighbour_out_of_the_fit():
    """A neighbour's core (3 × 3 px at 10 % of the peak, 6 px out) on the independent
    generator's star: fitted with it, the rotation and the background are pulled far off
    the generator's values; a stage that masks what lies more than 20 σ from the model
    (with a 1-px margin) refits them to the generator's values within the recovery
    test's tolerances, and logs what it masked (the 5 × 5 square less what lies within
    r_min)."""
    clean = _numpy_star(**TRUE)
    sigma = 2e-3 * clean.max()
    noisy = clean + np.random.default_rng(1).normal(0, sigma, clean.shape)
    noisy[2:5, 9:12] += 0.1 * clean.max()
    data = FitData.from_array(noisy, sigma=sigma)
    first = {"free": "all", "max_steps": 20}
    plain = fit(_model(), data, stages=[first])
    res = fit(_model(), data, stages=[first, {**first, "reject": {"above": 20, "r_min": 4,
                                                                   "grow": 1}}])
    tol = max(4 * res.errors["rotation"], 0.5)
    assert abs(plain.values["rotation"] - TRUE["rotation"]) > 2 * tol
    assert abs(plain.values["background"] - TRUE["background"]) > 0.2
    v = res.values
    assert abs(v["rotation"] - TRUE["rotation"]) < tol
    assert abs(v["background"] - TRUE["background"]) < 0.05
    assert abs(v["x0"] - TRUE["x0"]) < 0.02 and abs(v["y0"] - TRUE["y0"]) < 0.02
    assert abs(v["flux"] / TRUE["flux"] - 1) < 0.01
    (log,) = [e for e in res.stages if "rejected" in e]
    assert log["stage"] == 1 and 20 <= log["rejected"] <= 25
    assert res.mask.sum() == data.mask.sum() - log["rejected"] and not res.mask[3, 10]


def test_stage_keys_and_options_are_checked_before_any_fitting(synthetic):
    """A typo in a stage's key or in one of its options is refused, naming it and the
    known ones, before any fitting (it was passed over in silence)."""
    data, _ = synthetic
    for stage, match in (
            ({"free": "all", "noise_from_residual": {"floor": 0.03}}, "unknown keys"),
            ({"free": "all", "reject": {"abvoe": 20}}, "reject has unknown options"),
            ({"free": "all", "spikes": {"rmin": 12}}, "spikes has unknown options"),
            ({"free": "all", "scan": ["rotation"]}, "scan must be a mapping"),
            ({"hop": {"name": "rotation", "offsets": [1]}, "free": "all"}, "hop stage")):
        with pytest.raises(FitInputError, match=match):
            fit(_model(), data, stages=[{"free": "all", "max_steps": 1}, stage])
    from difstar.fitting._stages import _check_stage_keys  # from a manifest: any JSON value

    with pytest.raises(FitInputError, match="stage 1 must be a mapping"):
        _check_stage_keys(1, "all")


@pytest.mark.parametrize("a", [2, 3])
def test_lanczos_transfer_is_the_mean_of_resamplings(a):
    """A co-add of frames taken at sub-pixel offsets u, each resampled back onto one grid
    with a Lanczos kernel (SWarp's RESAMPT = LANCZOS3), is on average the frame
    convolved with the continuous kernel. A Gaussian star at 64 offsets, resampled and
    averaged, against the FFT of the unmoved star times lanczos_transfer:
    - a = 2, the plain taps summed directly (out[n] = Σ in[k] L(n + u − k)), divided by
      the kernel's integral from scipy's quad: to 1e-7 of the peak (the star, σ = 2 px,
      has 3e-9 of its spectrum left at the Nyquist frequency);
    - a = 3, Pillow's own Lanczos resampling, which normalises its taps at each offset
      (their sum departs from 1 by up to 0.6 %): to 1e-4 of the peak."""
    from PIL import Image
    from scipy.integrate import quad

    from difstar.fitting._detector import lanczos_kernel, lanczos_transfer

    h = w = 41
    c, s = 20.0, 2.0
    yy, xx = np.mgrid[0:h, 0:w]

    def star(dx, dy):
        return np.exp(-0.5 * ((xx - c - dx) ** 2 + (yy - c - dy) ** 2) / s**2)

    offsets = [(u, (7 * u) % 1.0) for u in np.arange(64) / 64]
    frames = []
    for ux, uy in offsets:
        img = star(ux, uy)  # the frame: the star at an offset u
        if a == 3:  # Pillow: output pixel n reads input n + u (the box stays inside)
            box = (ux, uy, w - 1 + ux, h - 1 + uy)
            out = Image.fromarray(img.astype(np.float32)).resize((w - 1, h - 1),
                                                                 Image.LANCZOS, box=box)
            frames.append(np.asarray(out, float))
        else:
            k = np.arange(w)
            tx = lanczos_kernel(k[:, None] + ux - k[None, :], a)
            ty = lanczos_kernel(k[:, None] + uy - k[None, :], a)
            frames.append(ty @ img @ tx.T)
    mean = np.mean(frames, axis=0)
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.rfftfreq(w)[None, :]
    pred = np.fft.irfft2(np.fft.rfft2(star(0, 0)) * lanczos_transfer(fx, a)
                         * lanczos_transfer(fy, a), s=(h, w))
    if a == 3:
        err, tol = np.abs(mean - pred[:-1, :-1]).max(), 1e-4
    else:
        area = quad(lambda x: np.sinc(x) * np.sinc(x / a), -a, a, epsabs=1e-13)[0]
        err, tol = np.abs(mean / area**2 - pred).max(), 1e-7
    assert err < tol
    assert lanczos_transfer(np.array(0.0), a) == pytest.approx(1.0, abs=1e-12)
    # the blur is real: the mean differs from the unmoved star by far more
    assert np.abs(mean[:h - 1, :w - 1] - star(0, 0)[:h - 1, :w - 1]).max() > 20 * tol


def test_resampling_option_is_checked_and_blurs_the_model():
    """``resampling`` takes null or 'lanczos2' … 'lanczos5' (a clear error otherwise) and
    multiplies the model's spectrum by the kernel's transfer: the flux stays, the peak
    drops; ``with_resampling`` gives the same model as the constructor."""
    with pytest.raises(FitInputError, match="resampling"):
        ImageModel(obstructed_circle_pupil(), {}, light=Light.monochromatic(3.6e-6),
                   resampling="bicubic")
    kw = dict(light=Light.monochromatic(3.6e-6), pad=8)
    params = {"pixel_scale": 0.6, "flux": 1.0}
    plain = ImageModel(obstructed_circle_pupil(), params, **kw)((33, 33))
    lz = ImageModel(obstructed_circle_pupil(), params, resampling="LANCZOS3", **kw)((33, 33))
    assert lz.sum() == pytest.approx(plain.sum(), rel=1e-3)
    assert lz.max() < plain.max()
    base = ImageModel(obstructed_circle_pupil(), params, **kw)
    np.testing.assert_array_equal(base.with_resampling("lanczos3")((33, 33)), lz)
    with pytest.raises(FitInputError, match="resampling"):
        base.with_resampling("cubic")
    assert base.resampling == 0  # the original is left as it was


def test_noise_limited_errors_match_weighted_linear_least_squares(synthetic):
    """With only ``flux`` and ``background`` free the model is linear in them, so the
    Cramér–Rao errors are those of weighted linear least squares on the columns
    (unit-flux image, 1): NumPy's normal equations on the model image, against the
    Jacobian by jax.jacfwd, to 1e-9 relative, for two σ maps and a mask. Background
    alone: 1 / √Σ σ⁻², exactly. A bad σ is refused, naming it."""
    data, sigma = synthetic
    model = _model(rotation=Param(0.0), x0=Param(0.0), y0=Param(0.0))
    vals = model.values() | {"flux": 800.0, "background": 0.3}
    mask = np.ones(data.image.shape, bool)
    mask[:3] = False
    d = dataclasses.replace(data, mask=mask)
    unit = model(d.image.shape, {"flux": 1.0, "background": 0.0})
    s1 = np.full(d.image.shape, sigma)
    s2 = sigma * (1 + np.sqrt(np.abs(unit) * 800 / sigma))
    got = noise_limited_errors(model, d, vals, [s1, s2])
    for s, e in zip([s1, s2], got):
        a = np.stack([unit[mask], np.ones(mask.sum())], axis=1) / s[mask][:, None]
        ref = np.sqrt(np.diag(np.linalg.inv(a.T @ a)))
        assert e["flux"] == pytest.approx(ref[0], rel=1e-9)
        assert e["background"] == pytest.approx(ref[1], rel=1e-9)
    bg_only = _model(rotation=Param(0.0), x0=Param(0.0), y0=Param(0.0), flux=Param(800.0))
    (e,) = noise_limited_errors(bg_only, d, vals, [s2])
    assert e["background"] == pytest.approx(1 / np.sqrt(np.sum(s2[mask] ** -2.0)), rel=1e-12)
    bad = s1.copy()
    bad[10, 10] = np.nan
    with pytest.raises(FitInputError, match=r"sigmas\[1\]"):
        noise_limited_errors(model, d, vals, [s1, bad])
    with pytest.raises(FitInputError, match="shape"):
        noise_limited_errors(model, d, vals, [s1[:5]])


#: two halos, as the JWST campaign's two-halo variants name them
TWO_HALOS = (Halo("halo", 4.0), Halo("halo2", 1.5))


@pytest.mark.parametrize("which", ["halo", "halo2"])
def test_halos_are_gaussian_mixtures_against_scipy(which):
    """Each halo moves a fraction ``a`` of the light into a Gaussian of σ ``width`` px:
    the image is (1 − a)·I + a·(I ⊛ G). Against scipy.ndimage.gaussian_filter (wrap,
    truncated at 12 σ) of the unblurred model on the same padded window, cropped, to
    1e-9 of the peak; both halos together are the one applied after the other; the flux
    stays."""
    from scipy.ndimage import gaussian_filter

    kw = dict(light=Light.monochromatic(3.6e-6), halos=TWO_HALOS)
    params = {"pixel_scale": 0.6, "flux": 1.0}
    h, p = 31, 10
    plain = ImageModel(obstructed_circle_pupil(), params, pad=0, **kw)((h + 2 * p, h + 2 * p))

    def mixed(img, a, s):
        return (1 - a) * img + a * gaussian_filter(img, s, mode="wrap", truncate=12.0)

    a, s = 0.4, 2.5
    got = ImageModel(obstructed_circle_pupil(), params | {which: a, f"{which}_width": s},
                     pad=p, **kw)((h, h))
    want = mixed(plain, a, s)[p:p + h, p:p + h]
    assert np.abs(got - want).max() < 1e-9 * plain.max()
    both = ImageModel(obstructed_circle_pupil(),
                      params | {"halo": 0.2, "halo_width": 4.0, "halo2": a, "halo2_width": s},
                      pad=p, **kw)((h, h))
    want2 = mixed(mixed(plain, 0.2, 4.0), a, s)[p:p + h, p:p + h]
    assert np.abs(both - want2).max() < 1e-9 * plain.max()
    full = ImageModel(obstructed_circle_pupil(), params | {which: a, f"{which}_width": s},
                      pad=0, **kw)((h + 2 * p, h + 2 * p))
    assert full.sum() == pytest.approx(plain.sum(), rel=1e-12)


def test_a_list_of_named_halos_against_scipy():
    """Halos are a list, each under the name its user gives: three of them (scattered
    light, charge diffusion, a co-add's misregistration) are the three Gaussian mixtures
    of scipy.ndimage.gaussian_filter applied one after the other, to 1e-9 of the peak;
    the default model has one halo (``halo``) and none is numbered for the user."""
    from scipy.ndimage import gaussian_filter

    kw = dict(light=Light.monochromatic(3.6e-6))
    params = {"pixel_scale": 0.6, "flux": 1.0}
    h, p = 31, 12
    # σ ≥ 2.5 px (a sampled Gaussian's spectrum is the continuous one's to 1e-13 at the
    # Nyquist frequency, exp(−π² σ² / 2)) and 12 σ within the window (scipy's wrap)
    halos = [{"name": "scatter", "width": 3.0}, "diffusion", Halo("wings", 2.5)]
    plain = ImageModel(obstructed_circle_pupil(), params, pad=0, halos=[],
                       **kw)((h + 2 * p, h + 2 * p))
    model = ImageModel(obstructed_circle_pupil(), params | {
        "scatter": 0.1, "diffusion": 0.3, "diffusion_width": 3.5, "wings": 0.2}, pad=p,
        halos=halos, **kw)
    assert [q.name for q in model.halos] == ["scatter", "diffusion", "wings"]
    assert model.params["scatter_width"].value == 3.0
    assert model.halos[1].width == 4.0 and model.params["diffusion_width"].value == 3.5
    assert model.units["wings_width"] == "data px, Gaussian sigma"
    want = plain
    for a, s in ((0.1, 3.0), (0.3, 3.5), (0.2, 2.5)):
        want = (1 - a) * want + a * gaussian_filter(want, s, mode="wrap", truncate=12.0)
    got = model((h, h))
    assert np.abs(got - want[p:p + h, p:p + h]).max() < 1e-9 * plain.max()
    default = ImageModel(obstructed_circle_pupil(), params, **kw)
    assert [q.name for q in default.halos] == ["halo"]
    assert not any(k.startswith("halo2") for k in default.params)
    with pytest.raises(FitInputError, match="unknown parameters.*halo2"):
        ImageModel(obstructed_circle_pupil(), {"halo2": 0.1}, **kw)


@pytest.mark.parametrize("halos, match", [
    (["halo", "halo"], "given twice"),
    (["x0"], "are taken"),
    (["a", "a_width"], "are taken"),
    (["source_radius"], "are taken"),  # a disc source's, even where the source is a point
    (["z4"], "Zernike"),
    (["2b"], "letters, digits"),
    ([{"name": "h", "width": 0.0}], "width 0.0"),
    ([{"name": "h", "width": float("nan")}], "finite"),
    ([{"name": "h", "sigma": 2.0}], "name, width"),
    ("halo", "a list of halos"),
])
def test_bad_halos_are_refused(halos, match):
    with pytest.raises(FitInputError, match=match):
        ImageModel(obstructed_circle_pupil(), {}, light=Light.monochromatic(3.6e-6),
                   halos=halos)


def test_halo_fraction_outside_0_1_is_refused():
    for params in ({"halo": 1.5}, {"halo": {"value": 0.1, "free": True, "bounds": [0, 2]}},
                   {"halo_width": -1.0}):
        with pytest.raises(FitInputError, match="halo"):
            ImageModel(obstructed_circle_pupil(), params, light=Light.monochromatic(3.6e-6))


def _assert_matches_central_differences(jac, img, base, names, x0):
    """Each column of ``jac`` (the Jacobian of ``img(x, base)`` at ``x0``, parameters
    ``names``) against central differences of step 1e-5 × max(1, |value|), to 1e-5 of
    the largest difference."""
    import jax

    at = jax.jit(lambda x: img(x, base))  # one compiled program, not op by op
    for i, k in enumerate(names):
        h = 1e-5 * max(1.0, abs(base[k]))
        e = np.zeros(len(names))
        e[i] = h
        fd = (np.asarray(at(x0 + e)) - np.asarray(at(x0 - e))) / (2 * h)
        assert np.abs(jac[..., i] - fd).max() < 1e-5 * np.abs(fd).max() + 1e-12, k


def test_image_model_jacobian_matches_finite_differences():
    """jax.jacfwd of the model image in the detector's and the source's parameters
    (both halos, the jitter, the rotation, the shift) against central differences, in
    float64, to 1e-5 of the largest derivative; finite where a halo or the jitter is
    zero (the hard point: the width's derivative vanishes there) and under jit."""
    import jax
    import jax.numpy as jnp

    model = ImageModel(obstructed_circle_pupil(), {"pixel_scale": 0.6},
                       light=Light.monochromatic(3.6e-6), pad=6, resampling="lanczos3",
                       halos=TWO_HALOS)
    names = ["jitter", "halo", "halo_width", "halo2", "halo2_width", "rotation", "x0"]
    base = model.values() | {"jitter": 0.4, "halo": 0.2, "halo_width": 3.0, "halo2": 0.3,
                             "halo2_width": 1.5, "rotation": 3.0, "x0": 0.2}
    shape = (15, 15)
    plan = model.plan((15 + 2 * 6, 15 + 2 * 6))  # concrete, outside any trace

    def img(x, at):
        v = {k: jnp.asarray(val, float) for k, val in at.items()}
        v.update({k: x[i] for i, k in enumerate(names)})
        return model.image(v, shape, plan)

    x0 = jnp.asarray([base[k] for k in names], float)
    jac = np.asarray(jax.jit(jax.jacfwd(lambda x: img(x, base)))(x0))
    _assert_matches_central_differences(jac, img, base, names, x0)
    hard = base | {"jitter": 0.0, "halo": 0.0, "halo2": 0.0}
    xh = jnp.asarray([hard[k] for k in names], float)
    jh = np.asarray(jax.jit(jax.jacfwd(lambda x: img(x, hard)))(xh))
    assert np.all(np.isfinite(jh))
    assert np.abs(jh[..., names.index("halo2")]).max() > 0  # the light it would move


def test_fit_jacobian_residual_and_images_from_one_program():
    """The errors' Jacobian (the fit's residual (model − data)/σ over its free
    parameters, physical units) against central differences of the model image itself,
    and the residual and model image it returns with it against that image, in float64."""
    import jax.numpy as jnp

    from difstar.fitting._residuals import _PixelTarget
    from difstar.fitting._solve import _jacobian

    model = ImageModel(obstructed_circle_pupil(), {
        "pixel_scale": Param(0.6), "x0": Param(0.2, True, (-2.0, 2.0)),
        "rotation": Param(3.0, True, (-30.0, 30.0)), "flux": Param(50.0, True, scale=10.0),
        "background": Param(0.5, True, scale=1.0)},
        light=Light.monochromatic(3.6e-6), pad=4)
    rng = np.random.default_rng(0)
    sigma = 0.05 + 0.01 * rng.random((13, 13))
    data = FitData.from_array(rng.random((13, 13)), sigma=sigma)
    base = model.values()
    names = model.free
    plan = model.plan(model.padded_shape((13, 13)))

    def img(x, at):
        v = {k: jnp.asarray(val, float) for k, val in at.items()}
        v.update({k: x[i] for i, k in enumerate(names)})
        return model.image(v, (13, 13), plan)

    x0 = jnp.asarray([base[k] for k in names], float)
    jac, r, m = _jacobian(model, data, base, [_PixelTarget(data)])
    expected = np.asarray(img(x0, base))
    np.testing.assert_allclose(m[0], expected, rtol=1e-12, atol=1e-12 * expected.max())
    np.testing.assert_allclose(r, ((expected - data.image) / sigma).ravel(), rtol=1e-10,
                               atol=1e-10)
    _assert_matches_central_differences(jac.reshape(13, 13, -1) * sigma[..., None], img,
                                        base, names, x0)


def _three_stars(**kw):
    """Three stars fitted together: a rotation and jitter shared, a centre, flux and
    background each."""
    return ImageModel(obstructed_circle_pupil(), {
        "pixel_scale": Param(0.6), "x0": Param(0.2, True, (-2.0, 2.0)),
        "y0": Param(-0.1, True, (-2.0, 2.0)),
        "rotation": Param(3.0, True, (-30.0, 30.0)), "flux": Param(50.0, True, scale=10.0),
        "background": Param(0.5, True, scale=1.0), "jitter": Param(0.3, True, (0.0, 2.0))},
        light=Light.monochromatic(3.6e-6), pad=4, **kw).for_captures(
            ("x0", "y0", "flux", "background"), 3)


def test_joint_fit_of_three_stars_one_psf_moved_and_compressed_jacobian():
    """Three stars fitted together (a rotation and jitter shared; a centre, flux and
    background each). Their model images, one PSF moved to each star by a phase ramp,
    against each star's own image from the PSF engine with the move as a wavefront
    tilt (an independent way to move it), to 2e-6 of the peak (both PSFs at accuracy
    1e-5; they differ by 4e-7 of it, and by 3e-5 at the default 1e-2). The errors' Jacobian,
    whose star parameters share directions with the other stars' (column_blocks: 2 + 4
    directions, not 2 + 12), against central differences of the stars' images, in
    float64; every star's column exactly 0 on the other stars' pixels. Where a flux
    taken in closed form is shared, the residuals are coupled: no compression."""
    import jax.numpy as jnp

    from difstar._normal_equations import column_colours
    from difstar.fitting._residuals import _PixelTarget, _residual_fn, column_blocks
    from difstar.fitting._solve import _jacobian

    model = _three_stars(accuracy=1e-5)
    rng = np.random.default_rng(0)
    datas = [FitData.from_array(rng.random((13, 13)), sigma=0.05) for _ in range(3)]
    targets = [_PixelTarget(d) for d in datas]
    base = model.values() | {"x0@1": -0.3, "y0@2": 0.4, "flux@2": 20.0}
    names = model.free
    owners, rows = column_blocks(model, names, targets)
    assert column_colours(owners).max() + 1 == 2 + 4 < len(names) == 2 + 12
    assert column_blocks(model.for_captures(("x0", "y0"), 3), ["rotation", "x0@0"],
                         targets, lin=["flux"]) is None
    jac, _, images = _jacobian(model, datas, base, targets)
    plan = model.plan(model.padded_shape((13, 13)))
    x0 = jnp.asarray([base[k] for k in names], float)
    res = _residual_fn(model, datas, targets)

    def values(x, at):
        v = {k: jnp.asarray(val, float) for k, val in at.items()}
        v.update({k: x[j] for j, k in enumerate(names)})
        return v

    for i in range(3):
        tilted = np.asarray(model.image(model.capture_values(values(x0, base), i), (13, 13),
                                        plan))
        assert np.abs(images[i] - tilted).max() < 2e-6 * tilted.max(), i
        block = jac[169 * i:169 * (i + 1)].reshape(13, 13, -1) * 0.05
        _assert_matches_central_differences(
            block, lambda x, at, i=i: res(values(x, at))[1][i], base, names, x0)
        others = [j for j, k in enumerate(names) if "@" in k and not k.endswith(f"@{i}")]
        assert np.all(block[..., others] == 0)


def test_incoherent_part_is_the_mean_over_segment_phasing_errors():
    """``incoherent`` = f: the image is (1 − f) × the whole pupil's + f × the segments'
    patterns added incoherently. The truth: the whole 18-segment pupil propagated by
    ``difstar.psf`` with a piston on each segment, averaged over the 18 patterns
    φ_k = 2π k m / 18 (m = 0 … 17), whose cross terms between segments cancel exactly
    (Σ_m e^(2πi (k − l) m / 18) = 0 for k ≠ l): that average is the incoherent sum,
    and (1 − f) × the pupil without pistons + f × it the mean image for phasing errors
    with e^(−φ²) = 1 − f. The truth's pupil is sampled finely (accuracy 1e-5, the
    pistons' steps at the gaps then resolved); agreement to 2e-4 of the peak (the
    model's own PSF accuracy is 1e-3); the light within the window agrees to 1e-3."""
    import equinox as eqx
    import jax.numpy as jnp

    from difstar._psf import plan_psf, psf
    from difstar._pupil import hex_segment_centres, hex_segments
    from difstar.fitting import PupilBuilder
    from difstar.fitting._params import _PITCH, ARCSEC

    f2f, gap, lam, scale, f = 1.32, 0.007, 1e-6, 0.02, 0.35

    def whole(v):
        return hex_segments(2, v["flat_to_flat"], v["gap"])

    def one(v):
        return hex_segments(0, v["flat_to_flat"], v["gap"], include_centre=True)

    r = 2 * (f2f + gap) + f2f / math.sqrt(3)
    builder = PupilBuilder("segments", whole, {"flat_to_flat": f2f, "gap": gap,
                                               "incoherent": 0.0}, 1.05 * r,
                           segment=one, segment_radius=1.05 * f2f / math.sqrt(3))
    shape = (31, 31)
    model = ImageModel(builder, {"pixel_scale": scale, "incoherent": f},
                       light=Light.monochromatic(lam), pad=0, accuracy=1e-3)
    got = model(shape)
    pure = model(shape, {"incoherent": 1.0})

    class Pistons(eqx.Module):
        centres: Any
        opds: Any

        def opd(self, x, y):
            d2 = ((x[..., None] - self.centres[:, 0]) ** 2
                  + (y[..., None] - self.centres[:, 1]) ** 2)
            return self.opds[jnp.argmin(d2, axis=-1)]  # the nearest segment's piston

    pupil = whole({"flat_to_flat": f2f, "gap": gap})
    centres = hex_segment_centres(2, f2f + gap)
    kw = dict(wavelength=lam, z_image=_PITCH / (scale * ARCSEC), pixel_pitch=_PITCH,
              shape=shape, sampling="pixel")
    plan = plan_psf(pupil, accuracy=1e-5, **kw)
    k = np.arange(18)
    # the 18 pistoned PSFs by one compiled program (the pistons its argument), the
    # pupil without pistons by another: run op by op they took most of this test's time
    pistoned = eqx.filter_jit(lambda wavefront: psf(pupil, plan=plan, **kw,
                                                    wavefront=wavefront))
    mean = np.mean([np.asarray(pistoned(Pistons(centres, lam * ((k * m) % 18) / 18)))
                     for m in range(18)], axis=0)
    plain = eqx.filter_jit(lambda: psf(pupil, plan=plan, **kw))
    want = (1 - f) * np.asarray(plain()) + f * mean
    assert np.abs(pure - mean).max() < 2e-4 * mean.max()
    assert np.abs(got - want).max() < 2e-4 * want.max()
    assert got.sum() == pytest.approx(want.sum(), rel=1e-3)
    assert pure.max() < 0.2 * model(shape, {"incoherent": 0.0}).max()  # it does spread


def test_incoherent_part_jacobian_matches_finite_differences():
    """jax.jacfwd of a JWST-like image in ``incoherent``, the rotation and the shift
    (the segment's pattern rotates and moves with the pupil's) against central
    differences to 1e-5 of the largest derivative, in float64; finite at
    ``incoherent`` = 0 and 1 (the bounds' ends)."""
    import jax
    import jax.numpy as jnp

    from difstar.fitting import jwst_pupil

    model = ImageModel(jwst_pupil(), {"pixel_scale": 0.03,
                                      "incoherent": {"value": 0.3, "free": True}},
                       light=Light.monochromatic(1e-6), pad=4)
    names = ["incoherent", "rotation", "x0"]
    shape = (13, 13)
    plan = model.plan((13 + 8, 13 + 8))  # concrete, outside any trace (both plans)

    def img(x, at):
        v = {k: jnp.asarray(val, float) for k, val in at.items()}
        v.update({k: x[i] for i, k in enumerate(names)})
        return model.image(v, shape, plan)

    base = model.values() | {"incoherent": 0.3, "rotation": 2.0, "x0": 0.2}
    x0 = jnp.asarray([base[k] for k in names], float)
    jac = np.asarray(jax.jit(jax.jacfwd(lambda x: img(x, base)))(x0))
    _assert_matches_central_differences(jac, img, base, names, x0)
    for end in (0.0, 1.0):
        at = base | {"incoherent": end}
        jh = np.asarray(jax.jit(jax.jacfwd(lambda x: img(x, at)))(
            jnp.asarray([at[k] for k in names], float)))
        assert np.all(np.isfinite(jh)) and np.abs(jh[..., 0]).max() > 0


def test_projection_is_numpys_least_squares_and_differentiates_exactly():
    """The closed-form flux and background of a solve (variable projection) are NumPy's
    least-squares solution of the affine residual, and the projected residual's
    derivative (through the solve, as the solver's Jacobian takes it) matches central
    differences."""
    import jax
    import jax.numpy as jnp

    from difstar.fitting._residuals import closed_form

    rng = np.random.default_rng(0)
    p, c = rng.normal(size=(50,)), rng.normal(size=(50,))
    w = rng.uniform(0.5, 2.0, 50)

    def parts(theta):  # a PSF-like column that moves with theta, and the background's
        shape = jnp.exp(-theta * jnp.arange(50) / 50.0) * p
        return -c * w, jnp.stack([1e3 * shape * w, w], axis=1)

    r, beta = closed_form(*parts(0.7))
    a = np.stack([1e3 * np.exp(-0.7 * np.arange(50) / 50.0) * p * w, w], axis=1)
    want, *_ = np.linalg.lstsq(a, c * w, rcond=None)
    assert np.allclose(beta, want, rtol=1e-10)
    assert np.allclose(r, a @ want - c * w, atol=1e-10)

    def projected(theta):
        return closed_form(*parts(theta))[0]

    jac = np.asarray(jax.jacfwd(projected)(0.7))
    h = 1e-6
    fd = (np.asarray(projected(0.7 + h)) - np.asarray(projected(0.7 - h))) / (2 * h)
    assert np.allclose(jac, fd, rtol=1e-6, atol=1e-8)


def test_linear_parts_rebuild_the_residual_of_two_captures():
    """The affine parts (r0, A) of two captures' pixel residuals, one flux shared and a
    background each, give back the residual the model computes at any flux and
    backgrounds."""
    import jax.numpy as jnp

    from difstar.fitting._residuals import _linear_parts, _PixelTarget, _residual_fn

    clean = _numpy_star(**TRUE)
    datas = [FitData.from_array(clean, sigma=1.0, exposure=e) for e in (1.0, 4.0)]
    model = _model().for_captures(("x0", "y0", "background"), 2)
    targets = [_PixelTarget(d) for d in datas]
    res = _residual_fn(model, datas, targets)
    arrays = [t.arrays for t in targets]
    v = {k: jnp.asarray(p.value, float) for k, p in model.params.items()}
    lin = ["flux", "background@0", "background@1"]
    v1 = {**v, "flux": jnp.asarray(1.0), "background@0": jnp.asarray(0.0),
          "background@1": jnp.asarray(0.0)}
    r0, a = _linear_parts(model, lin, res(v1, arrays)[1], v1, arrays)
    beta = np.array([930.0, 1.5, -0.7])
    want = res({**v, **{q: jnp.asarray(x) for q, x in zip(lin, beta)}}, arrays)[0]
    assert np.allclose(np.asarray(r0) + np.asarray(a) @ beta, want, rtol=1e-10, atol=1e-9)


def test_the_errors_normal_matrix_of_a_field_from_its_compressed_directions():
    """The standard errors of stars fitted together come from JᵀJ built from the
    Jacobian along its compressed directions (_normal_matrix: 2 + 4 directions for 14
    parameters); against JᵀJ of the dense Jacobian (_jacobian, checked against central
    differences above), to 1e-10 of its largest entry, in float64, with the same
    residual and model images; for one star, the dense path."""
    from difstar.fitting._residuals import _PixelTarget
    from difstar.fitting._solve import _by_blocks, _jacobian, _normal_matrix

    model = _three_stars()
    rng = np.random.default_rng(1)
    datas = [FitData.from_array(rng.random((13, 13)), sigma=0.05) for _ in range(3)]
    targets = [_PixelTarget(d) for d in datas]
    values = model.values() | {"x0@1": -0.3, "y0@2": 0.4, "flux@2": 20.0}
    assert _by_blocks(model, targets)
    jac, r, images = _jacobian(model, datas, values, targets)
    jtj, r2, images2 = _normal_matrix(model, datas, values, targets)
    want = jac.T @ jac
    np.testing.assert_allclose(jtj, want, rtol=0, atol=1e-10 * np.abs(want).max())
    np.testing.assert_allclose(r2, r, rtol=1e-12, atol=1e-12)
    for a, b in zip(images2, images):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)
    single = ImageModel(obstructed_circle_pupil(), {
        "pixel_scale": Param(0.6), "x0": Param(0.2, True, (-2.0, 2.0)),
        "y0": Param(-0.1, True, (-2.0, 2.0)), "flux": Param(50.0, True, scale=10.0)},
        light=Light.monochromatic(3.6e-6), pad=4)
    assert not _by_blocks(single, targets[:1])


def test_each_stars_flux_and_background_solved_alone_equal_the_joint_solve():
    """Three stars each with their own flux and background in closed form: one 2 × 2
    solve per star (``projected``) gives the residual and the values of the solve over
    all six columns at once (the dense least squares), to 1e-10; where one flux is
    shared, the dense solve is the one used."""
    import jax.numpy as jnp

    from difstar.fitting._residuals import (
        _linear_parts,
        _PixelTarget,
        _residual_fn,
        closed_form,
        projected,
    )

    rng = np.random.default_rng(4)
    clean = _numpy_star(**TRUE)
    datas = [FitData.from_array(clean * f + b + rng.normal(0, 1.0, clean.shape), sigma=1.0,
                                exposure=e)
             for f, b, e in ((1.0, 2.0, 1.0), (0.3, -1.0, 2.0), (2.0, 0.5, 0.5))]
    model = _model().for_captures(("x0", "y0", "flux", "background"), 3)
    targets = [_PixelTarget(d) for d in datas]
    res = _residual_fn(model, datas, targets)
    arrays = [t.arrays for t in targets]
    lin = ["flux@0", "flux@1", "flux@2", "background@0", "background@1", "background@2"]
    v1 = {k: jnp.asarray(p.value, float) for k, p in model.params.items()} | {
        q: jnp.asarray(1.0 if q.startswith("flux") else 0.0) for q in lin}
    images = res(v1, arrays)[1]
    r, beta = projected(model, lin, images, v1, arrays)
    r_all, beta_all = closed_form(*_linear_parts(model, lin, images, v1, arrays))
    np.testing.assert_allclose(beta, beta_all, rtol=1e-10)
    np.testing.assert_allclose(r, r_all, rtol=1e-10, atol=1e-10 * float(jnp.abs(r_all).max()))
    shared = _model().for_captures(("x0", "y0", "background"), 3)
    lin2 = ["flux", "background@0", "background@1", "background@2"]
    v2 = {k: jnp.asarray(p.value, float) for k, p in shared.params.items()} | {
        "flux": jnp.asarray(1.0)} | {q: jnp.asarray(0.0) for q in lin2[1:]}
    images2 = _residual_fn(shared, datas, targets)(v2, arrays)[1]
    np.testing.assert_allclose(
        projected(shared, lin2, images2, v2, arrays)[1],
        closed_form(*_linear_parts(shared, lin2, images2, v2, arrays))[1], rtol=1e-12)


def test_flux_in_closed_form_ends_where_the_solver_carrying_it_ends(synthetic):
    """The same fit of the independent star with flux and background taken in closed
    form (unbounded: projected) and carried by the solver (bounded): the same values to
    a small fraction of their standard errors, the same χ²."""
    from difstar.fitting._residuals import _PixelTarget
    from difstar.fitting._solve import projected_names

    data, _ = synthetic
    free = _model()
    carried = _model(flux=Param(800.0, True, (100.0, 5000.0)),
                     background=Param(0.0, True, (-50.0, 50.0)))
    assert projected_names(free, free.free, _PixelTarget(data)) == ["flux", "background"]
    assert projected_names(carried, carried.free, _PixelTarget(data)) == []
    a = fit(free, data, max_steps=40)
    b = fit(carried, data, max_steps=40)
    for k in a.free:
        assert abs(a.values[k] - b.values[k]) < 0.02 * a.errors[k], k
    assert a.chi2 == pytest.approx(b.chi2, rel=1e-6)


def test_scan_says_when_the_data_cannot_tell_two_rotations(synthetic):
    """Three struts at 120° make spikes every 60°, and a real pupil's image does not
    change under a half turn: the star's rotation θ and θ + 60° give the same image. A
    scan whose bounds hold both finds both and says so in the result's warnings; a scan
    inside one period says nothing."""
    data, _ = synthetic
    held = {k: Param(TRUE[k]) for k in ("x0", "y0", "flux", "background")}
    stage = {"free": ["rotation"], "max_steps": 5,
             "scan": {"name": "rotation", "half_range": 110, "step": 1.0}}
    wide = fit(_model(rotation=Param(0.0, True, (-40, 70)), **held), data, stages=[stage])
    scan = [s for s in wide.stages if "scan" in s][0]
    (twin, dchi2), *_ = scan["rivals"]  # which of the two is lowest: rounding's choice
    low, high = sorted([scan["best"], twin])
    assert abs(low - TRUE["rotation"]) <= 1.0 and high == low + 60 and dchi2 < 0.1
    assert any("hardly tell" in w for w in wide.warnings)
    narrow = fit(_model(rotation=Param(0.0, True, (-20, 20)), **held), data, stages=[stage])
    assert [s for s in narrow.stages if "scan" in s][0]["rivals"] == []
    assert not any("hardly tell" in w for w in narrow.warnings)


def test_a_later_stage_keeps_an_earlier_plan_that_is_fine_enough():
    """A stage plans for 1.5 × its start's Zernike terms; where a plan made before for
    the same window is already fine enough for them (the plan of 1 × them, a free term
    at least at a tenth of its bounds' reach), that plan serves, and with it the programs
    compiled for it. Terms beyond its reach get a finer plan of their own, and
    plan_holds still asks of an answer the plan it needs, not the plan it was given."""
    model, data = _twin_case(3, z4=400e-9)  # z4 free within ±1000 nm
    shape = model.padded_shape(data.image.shape)
    start = model.with_values({"z4": 0.0}).plan(shape)
    grown = model.with_values({"z4": 200.0})
    # planned afresh, 1.5 × 200 nm would ask for more sub-cells than the start's plan
    assert grown.plan(shape, reuse=False).subcells > start.subcells
    assert grown.plan(shape) is start
    assert grown.plan_holds({"z4": 200.0}, shape)
    far = model.with_values({"z4": 400.0})
    assert not grown.plan_holds({"z4": 400.0}, shape)
    assert far.plan(shape).subcells > start.subcells
    assert far.plan_holds({"z4": 400.0}, shape)
    # a plan once finer keeps serving the smaller terms it covers
    assert model.with_values({"z4": 300.0}).plan(shape) is far.plan(shape)
