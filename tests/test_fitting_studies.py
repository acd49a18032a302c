"""The studies of a fitted star (difstar.fitting._studies) and their fit-image options
(--shifted, --contaminated, --noise-limit): the changed images against exact moves and
the Lanczos3 kernel's own formula, the noise limit against the Fisher information of a
linear model written out by hand, and the command line on a small synthetic star made
by the independent NumPy generator of tests/test_fitting.py."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from test_fit_image_cli import _manifest
from test_fitting import TRUE, _numpy_star

from difstar.cli._fit_image import main
from difstar.fitting import (
    FitInputError,
    contaminated_image,
    load_manifest,
    noise_limit,
    shifted_image,
)


def _gaussian(shape, x, y, s=2.0):
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]]
    return np.exp(-0.5 * ((xx - x) ** 2 + (yy - y) ** 2) / s**2)


def test_shifted_image_integer_moves_are_exact():
    img = np.random.default_rng(3).random((21, 25)).astype(np.float32)
    np.testing.assert_array_equal(shifted_image(img, 0, 0), img)
    np.testing.assert_array_equal(shifted_image(img, 2, 0)[:, 2:], img[:, :-2])
    np.testing.assert_array_equal(shifted_image(img, 0, -1)[:-1, :], img[1:, :])
    np.testing.assert_array_equal(shifted_image(img, -7, 5)[5:, :-7], img[:-5, 7:])


def _lanczos3_first_moment(d):
    """Where a Lanczos3 resampling by ``d`` px moves a smooth image's centroid: the first
    moment of its normalised taps, sinc(t) sinc(t/3) at t = m − d (not d itself: Lanczos3
    does not reproduce a linear ramp exactly, e.g. 0.2302 px for d = 0.25)."""
    m = np.arange(-8, 9)
    w = np.sinc(m - d) * np.sinc((m - d) / 3) * (np.abs(m - d) < 3)
    return float((m * w).sum() / w.sum())


@pytest.mark.parametrize("dx,dy", [(0.5, 0.0), (0.0, -0.5), (0.25, 0.35)])
def test_shifted_image_is_a_lanczos3_move(dx, dy):
    """A smooth Gaussian's centroid moves by the Lanczos3 kernel's own first moment (from
    its formula) to 1e-5 px, and its sum stays within 0.1 %."""
    img = _gaussian((41, 41), 20.2, 19.7)
    out = shifted_image(img, dx, dy).astype(float)
    yy, xx = np.mgrid[0:41, 0:41]
    cx, cy = (out * xx).sum() / out.sum(), (out * yy).sum() / out.sum()
    np.testing.assert_allclose([cx - 20.2, cy - 19.7],
                               [_lanczos3_first_moment(dx), _lanczos3_first_moment(dy)],
                               atol=1e-5)
    assert abs(out.sum() / img.sum() - 1) < 1e-3


def test_contaminated_image_adds_the_neighbour_and_the_hits():
    """The neighbour is the star (less the border's median), FACTOR times fainter, moved
    by whole pixels (exact, 0 beyond the border); the hits land at least 15 px from the
    star within 0.3–10 % of its peak (plus a track's second pixel); NaN stays NaN; the
    input is unchanged."""
    img = 5.0 + 100.0 * _gaussian((61, 61), 30.0, 30.0)
    img[0, 0] = np.nan
    before = img.copy()
    calm = contaminated_image(img, neighbour=(12, -7, 20.0), hits=0)
    np.testing.assert_array_equal(img, before)
    star = np.nan_to_num(img - 5.0)
    want = np.zeros_like(star)
    want[:-7, 12:] = star[7:, :-12] / 20.0  # out[r, c] = star[r + 7, c − 12] / 20
    assert np.isnan(calm[0, 0])
    np.testing.assert_allclose(np.nan_to_num(calm - img), want, rtol=0, atol=1e-12)
    hit = contaminated_image(img, neighbour=(12, -7, 20.0), hits=8, seed=4) - calm
    hit = np.nan_to_num(hit)
    rr, cc = np.nonzero(hit > 1e-9)
    assert 8 <= len(rr) <= 16
    assert np.hypot(rr - 30, cc - 30).min() >= 15 - 1.5  # a track's second pixel: ≤ 1.5 px on
    levels = np.sort(hit[rr, cc])[::-1]  # the star's peak is 100
    assert levels[0] <= 2 * 10.0  # at most 10 % each (two hits could share a pixel)
    assert levels[7] >= 0.3 and levels[-1] >= 0.3 * 0.3  # 0.3 % each; a track's 2nd ≥ 30 %


def test_contaminated_image_refuses_what_it_cannot_place():
    """Hot pixels need a pixel at least ``clear`` px from the star (else the search would
    never end); a neighbour moves by whole pixels and is fainter than the star."""
    img = 100.0 * _gaussian((19, 19), 9.0, 9.0)
    with pytest.raises(FitInputError, match="15 px or more"):
        contaminated_image(img, neighbour=(3, 3, 10.0), hits=1)
    assert contaminated_image(img, neighbour=(3, 3, 10.0), hits=0).shape == (19, 19)
    assert np.isfinite(contaminated_image(img, neighbour=(3, 3, 10.0), hits=2, clear=5)).all()
    for bad in ((0.5, 0, 10.0), (1, 1, 0.5)):
        with pytest.raises(FitInputError, match="whole pixels"):
            contaminated_image(img, neighbour=bad, hits=0)


def test_load_manifest_transform_changes_the_whole_frame_rows_down(tmp_path):
    """``transform`` sees the file's whole frame as the fitter reads it (a FITS file's
    rows reversed: rows down), before the window is cut; what it makes NaN is masked."""
    from astropy.io import fits

    frame = 1.0 + np.random.default_rng(1).random((30, 34))
    frame[14, 16] = 50.0  # some signal above the border
    fits.PrimaryHDU(frame[::-1].copy()).writeto(tmp_path / "star.fits")  # FITS: rows up
    man = _manifest("t", {"path": "star.fits", "sigma": 0.1, "roi": [4, 26, 5, 29]},
                    [{"free": "all", "max_steps": 2}])
    (tmp_path / "m.json").write_text(json.dumps(man))
    seen = []

    def change(im):
        seen.append(im.copy())
        out = np.zeros_like(im)
        out[2:, 3:] = im[:-2, :-3]  # whole pixels: 3 columns right, 2 rows down
        out[0, :] = np.nan
        return out

    _, data, _ = load_manifest(tmp_path / "m.json", transform=change)
    np.testing.assert_array_equal(seen[0], frame)
    np.testing.assert_array_equal(data.image, frame[2:24, 2:26])
    _, plain, _ = load_manifest(tmp_path / "m.json")
    np.testing.assert_array_equal(plain.image, frame[4:26, 5:29])
    man["data"]["roi"] = [0, 20, 0, 20]
    (tmp_path / "m.json").write_text(json.dumps(man))
    with pytest.warns(UserWarning, match="20 of 400 pixels of the window are NaN"):
        _, data, _ = load_manifest(tmp_path / "m.json", transform=change)
    assert not data.mask[0].any() and data.mask[1:].all()


def _bright_star(tmp_path, shape=(19, 19), *, free_rotation=True, stages=None):
    """A star of the NumPy generator with read and Poisson noise (gain 50) and its
    manifest (one capture; centre, flux, background and, if asked, the rotation free;
    by default one stage that estimates the noise from the residuals)."""
    lin = _numpy_star(shape, **dict(TRUE, background=0.0))
    gain, read = 50.0, 0.05
    rng = np.random.default_rng(7)
    img = lin + TRUE["background"] + rng.normal(0, 1, lin.shape) * np.sqrt(read**2 + lin / gain)
    np.save(tmp_path / "star.npy", img)
    stages = stages or [{"free": "all", "max_steps": 30, "noise_from_residuals": {"floor": 0.0}}]
    man = _manifest("one star", {"path": "star.npy", "noise": {"read": read, "gain": gain}},
                    stages)
    if free_rotation:
        man["params"]["rotation"] = {"value": TRUE["rotation"], "free": True,
                                     "bounds": [-10, 10]}
    path = tmp_path / "manifest.json"
    path.write_text(json.dumps(man))
    return path, img, read, gain


def _intensity(img, bg):
    """Each pixel's 3 × 3 mean (the image's edge: over the pixels inside) less ``bg``,
    clipped at 0: the I of σ² = read² + I / gain."""
    h, w = img.shape
    pad = np.pad(img, 1)
    ones = np.pad(np.ones_like(img), 1)
    tot = sum(pad[i:i + h, j:j + w] for i in range(3) for j in range(3))
    cnt = sum(ones[i:i + h, j:j + w] for i in range(3) for j in range(3))
    return np.maximum(tot / cnt - bg, 0.0)


def test_noise_limit_is_the_fisher_bound_of_flux_and_background(tmp_path):
    """With only the flux and the background free the model is linear, ∂I/∂flux = the
    generator's PSF and ∂I/∂background = 1, so the Cramér–Rao bound is the 2 × 2 Fisher
    matrix inverted by hand: for σ² = (f·read)² + f·I/gain and for σ = f·read, with the
    other parameter free and held, and the chance two such stars agree, from erf."""
    path, img, read, gain = _bright_star(tmp_path, (31, 31), free_rotation=False)
    man = json.loads(path.read_text())
    for k in ("x0", "y0"):
        man["params"][k] = TRUE[k]
    path.write_text(json.dumps(man))
    psf = _numpy_star((31, 31), **dict(TRUE, flux=1.0, background=0.0))
    bg = TRUE["background"]
    summary = {"values": {"flux": TRUE["flux"], "background": bg},
               "noise": {"read": read, "gain": gain}}
    study = noise_limit(path, summary, (1, 4), param="flux", within=5.0)
    inten = _intensity(img, bg)

    def bound(var):  # σ(flux) with the background free, with it held; σ(background)
        f = np.array([[np.sum(psf * psf / var), np.sum(psf / var)],
                      [np.sum(psf / var), np.sum(1 / var)]])
        cov = np.linalg.inv(f)
        return math.sqrt(cov[0, 0]), 1 / math.sqrt(f[0, 0]), math.sqrt(cov[1, 1])

    s1, rows = bound(read**2 + inten / gain)[0], study["rows"]
    assert [r["factor"] for r in rows] == [1.0, 4.0]
    for r in rows:
        f = r["factor"]
        free, held, bg_err = bound((f * read) ** 2 + f * inten / gain)
        assert r["error"] == pytest.approx(free, rel=0.01)
        assert r["error_others_held"] == pytest.approx(held, rel=0.01)
        assert r["errors"]["background"] == pytest.approx(bg_err, rel=0.01)
        assert r["error_read_only"] == pytest.approx(
            bound(np.full_like(img, (f * read) ** 2))[0], rel=0.01)
        pair = math.sqrt(s1**2 + free**2)
        assert r["p_agree"] == pytest.approx(math.erf(5.0 / (math.sqrt(2) * pair)), rel=0.02)
    assert rows[1]["error"] > rows[0]["error"] and 0 < rows[1]["p_agree"] < rows[0]["p_agree"]
    with pytest.raises(FitInputError, match="holds rotation fixed"):
        noise_limit(path, summary, (1,))
    with pytest.raises(FitInputError, match="noise_from_residuals"):
        noise_limit(path, {"values": summary["values"]}, (1,), param="flux")
    with pytest.raises(FitInputError, match=">= 1"):
        noise_limit(path, summary, (0.5,), param="flux")


def test_copy_row_deviations_in_standard_errors():
    """A copy's deviations are against the expected value, in the star's standard errors;
    parameters the star did not fit, or without an error, are left out."""
    from types import SimpleNamespace

    from difstar.fitting._studies import _copy_row

    star = {"values": {"rotation": 0.5, "x0": 0.25, "flux": 10.0, "z9": 1.0},
            "errors": {"rotation": 0.1, "x0": 0.05, "flux": 2.0, "z9": None}}
    res = SimpleNamespace(values={"rotation": 0.45, "x0": 0.8, "flux": 11.0, "z9": 3.0},
                          errors={}, free=["rotation", "x0", "flux", "z9"], status="converged",
                          residual_rms_peak=0.01, chi2_dof=1.2)
    row = _copy_row(res, star, 3.0, lambda k, v: v + 0.5 if k == "x0" else v)
    assert row["deviation_in_standard_errors"] == pytest.approx(
        {"rotation": -0.5, "x0": 1.0, "flux": 0.5})
    assert row["max_deviation"] == pytest.approx(1.0)
    assert row["max_deviation_parameter"] == "x0"


@pytest.fixture(scope="module")
def copies(tmp_path_factory):
    """One ``difstar fit-image`` run with the star moved by (+1, −1) px and with itself
    4 times fainter added in place (a "neighbour" at (0, 0)), no hot pixels."""
    d = tmp_path_factory.mktemp("copies")
    path, *_ = _bright_star(d, free_rotation=False, stages=[{"free": "all", "max_steps": 30}])
    out = d / "out"
    assert main([str(path), "--out", str(out), "--quiet", "--shifted=1,-1",
                 "--contaminated", "0,0,4", "--hits", "0"]) == 0
    return out, json.loads((out / "result.json").read_text()), np.load(d / "star.npy")


@pytest.mark.slow
def test_shifted_copy_moves_the_centre_by_the_shift(copies):
    """A whole-pixel move is exact, so the moved star's fit is the star's fit one column
    right (+x0) and one row up (rows down: −y0), the flux the same (the row and column it
    loses at the edge hold 10⁻³ of the light)."""
    out, res, _ = copies
    (one,) = json.loads((out / "shifted.json").read_text())["copies"]
    v = res["values"]
    assert one["shift"] == [1.0, -1.0]
    assert one["values"]["x0"] - v["x0"] == pytest.approx(1.0, abs=0.01)
    assert one["values"]["y0"] - v["y0"] == pytest.approx(-1.0, abs=0.01)
    assert one["values"]["flux"] == pytest.approx(v["flux"], rel=3e-3)
    dev = one["deviation_in_standard_errors"]  # against the star's x0, y0 plus the move
    assert abs(dev["x0"]) < 1.0 and abs(dev["y0"]) < 1.0
    md = (out / "shifted.md").read_text()
    assert "| (1, -1) |" in md and "| the star |" in md


@pytest.mark.slow
def test_contaminated_copy_adds_the_neighbour(copies):
    """The neighbour is the star itself less the median m of the image's 4-px border, F
    times fainter: put at (0, 0) with F = 4 the copy is 1.25 × the star − m / 4, whose
    fit (linear in the flux and the background) is the star's with 1.25 times its flux
    and 1.25 × its background − m / 4, at the same place (up to σ, which the noise
    model takes from the copy's own pixels)."""
    out, res, img = copies
    (near,) = json.loads((out / "contaminated.json").read_text())["copies"]
    v, got = res["values"], near["values"]
    m = np.median(np.concatenate([img[:4].ravel(), img[-4:].ravel(), img[:, :4].ravel(),
                                  img[:, -4:].ravel()]))
    assert near["neighbour"] == [0, 0, 4.0] and near["hits"] == 0 and near["seed"] == 0
    assert got["flux"] / v["flux"] == pytest.approx(1.25, rel=3e-3)
    assert got["background"] == pytest.approx(1.25 * v["background"] - m / 4, abs=3e-3)
    assert got["x0"] == pytest.approx(v["x0"], abs=3e-3)
    assert got["y0"] == pytest.approx(v["y0"], abs=3e-3)
    assert "| (0, 0), × 1/4; 0 (0) |" in (out / "contaminated.md").read_text()


@pytest.mark.slow
def test_noise_limit_option(tmp_path):
    """--noise-limit 1,4 writes noise_limit.json/.md: the read-noise-alone bound scales
    with the read noise exactly (σ × 4 gives errors × 4); the fainter star's bound is
    wider; the chance that another star as bright agrees is erf(0.05 / (√2 · √2 σ))."""
    path, *_ = _bright_star(tmp_path)
    out = tmp_path / "out"
    assert main([str(path), "--out", str(out), "--quiet", "--noise-limit", "1,4"]) == 0
    res = json.loads((out / "result.json").read_text())
    study = json.loads((out / "noise_limit.json").read_text())
    one, four = study["rows"]
    assert study["param"] == "rotation"
    assert study["noise"] == pytest.approx({k: res["noise"][k] for k in ("read", "gain")})
    assert four["error_read_only"] == pytest.approx(4 * one["error_read_only"], rel=1e-6)
    assert four["error"] > one["error"] >= one["error_others_held"] > 0
    assert one["p_agree"] == pytest.approx(math.erf(0.05 / (2 * one["error"])), rel=1e-9)
    assert "| 4 × fainter |" in (out / "noise_limit.md").read_text()


def test_studies_are_refused_before_the_main_fit(tmp_path, capsys):
    """What a manifest cannot run is refused with exit 2 and a message before any
    fitting, nothing written: a noise limit of a rotation held fixed or without a noise
    estimate, hot pixels with no room for them, malformed options."""
    path, *_ = _bright_star(tmp_path, free_rotation=False)
    out = tmp_path / "o"
    assert main([str(path), "--out", str(out), "--quiet", "--noise-limit", "1"]) == 2
    assert "rotation fixed" in capsys.readouterr().err
    path, *_ = _bright_star(tmp_path, stages=[{"free": "all", "max_steps": 30}])
    assert main([str(path), "--out", str(out), "--quiet", "--noise-limit", "1"]) == 2
    assert "noise_from_residuals" in capsys.readouterr().err
    assert main([str(path), "--out", str(out), "--quiet", "--contaminated", "3,3,10"]) == 2
    assert "15 px or more" in capsys.readouterr().err
    assert main([str(path), "--out", str(out), "--quiet", "--joint"]) == 2  # no copies
    assert "--joint" in capsys.readouterr().err
    fixed, *_ = _bright_star(tmp_path, free_rotation=False)
    assert main([str(fixed), "--out", str(out), "--quiet", "--joint", "--shifted=1,0"]) == 2
    assert "rotation fixed" in capsys.readouterr().err
    assert not out.exists()
    for bad in (["--shifted", "1"], ["--contaminated", "1.5,0,3"], ["--contaminated", "1,0,0.5"],
                ["--hits", "-1"], ["--noise-limit", "0.5"]):
        with pytest.raises(SystemExit) as e:
            main([str(path), "--out", str(out), *bad])
        assert e.value.code == 2


@pytest.mark.slow
def test_joint_fit_of_the_star_and_its_moved_copies(tmp_path):
    """--joint fits the star and a whole-pixel move of it together: one rotation for
    both, each its own centre (a whole-pixel move is exact: x0@1 − x0@0 = 1,
    y0@1 − y0@0 = −1) and flux. The copy carries the star's information again, so the
    joint rotation's standard error is about the star's / √2 (the Fisher information of
    two like captures; the move loses an edge row and column), smaller than either
    star's alone, and the joint rotation is the star's within its error."""
    path, *_ = _bright_star(tmp_path, stages=[{"free": "all", "max_steps": 30}])
    out = tmp_path / "out"
    assert main([str(path), "--out", str(out), "--quiet", "--shifted=1,-1", "--joint"]) == 0
    res = json.loads((out / "result.json").read_text())
    j = json.loads((out / "joint.json").read_text())
    v = j["values"]
    assert j["captures"][0] == "the star" and len(j["alone"]) == 2
    assert v["x0@1"] - v["x0@0"] == pytest.approx(1.0, abs=0.01)
    assert v["y0@1"] - v["y0@0"] == pytest.approx(-1.0, abs=0.01)
    assert v["flux@1"] == pytest.approx(v["flux@0"], rel=3e-3)
    star = res["errors"]["rotation"]
    assert j["smaller_error_than_any_alone"] is True
    assert j["rotation_error"] < min(a["rotation_error"] for a in j["alone"])
    assert 0.6 < j["rotation_error"] / star < 0.8, j["rotation_error"] / star
    assert abs(j["rotation"] - res["values"]["rotation"]) < star
    assert "| the 2 stars together |" in (out / "joint.md").read_text()
