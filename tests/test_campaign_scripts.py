"""The JWST campaign's check scripts (fit/jwst-nircam/*.py): the images they make from the
star, against exact moves and an analytic centroid."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pytest

HERE = Path(__file__).resolve().parents[1] / "fit" / "jwst-nircam"


def _script(name):
    sys.path.insert(0, str(HERE))  # the scripts import their shared _copy_fit
    try:
        spec = importlib.util.spec_from_file_location(name, HERE / f"{name}.py")
        mod = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(mod)
    finally:
        sys.path.remove(str(HERE))
    return mod


def _gaussian(shape, x, y, s=2.0):
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]]
    return np.exp(-0.5 * ((xx - x) ** 2 + (yy - y) ** 2) / s**2)


def test_shifted_image_integer_moves_are_exact():
    shifted_image = _script("shifted").shifted_image
    img = np.random.default_rng(3).random((21, 25)).astype(np.float32)
    np.testing.assert_array_equal(shifted_image(img, 0, 0), img)
    np.testing.assert_array_equal(shifted_image(img, 2, 0)[:, 2:], img[:, :-2])
    np.testing.assert_array_equal(shifted_image(img, 0, -1)[:-1, :], img[1:, :])


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
    shifted_image = _script("shifted").shifted_image
    img = _gaussian((41, 41), 20.2, 19.7)
    out = shifted_image(img, dx, dy).astype(float)
    yy, xx = np.mgrid[0:41, 0:41]
    cx, cy = (out * xx).sum() / out.sum(), (out * yy).sum() / out.sum()
    np.testing.assert_allclose([cx - 20.2, cy - 19.7],
                               [_lanczos3_first_moment(dx), _lanczos3_first_moment(dy)],
                               atol=1e-5)
    assert abs(out.sum() / img.sum() - 1) < 1e-3


def test_shifted_and_mirrored_fits_keep_the_wcs(tmp_path):
    """Each pixel keeps its sky position: the star's peak in the written file and the
    CRPIX-based pixel of the same sky point move together."""
    from astropy.io import fits
    from astropy.wcs import WCS

    img = _gaussian((31, 31), 12.0, 14.0).astype(np.float32)
    head = fits.Header({"CTYPE1": "RA---TAN", "CTYPE2": "DEC--TAN", "CRVAL1": 10.0,
                        "CRVAL2": 20.0, "CRPIX1": 16.0, "CRPIX2": 15.0,
                        "CD1_1": -1e-5, "CD1_2": 0.0, "CD2_1": 0.0, "CD2_2": 1e-5})
    src = tmp_path / "star.fits"
    fits.PrimaryHDU(img, head).writeto(src)
    before = src.read_bytes()
    sky = WCS(head).pixel_to_world(12.0, 14.0)  # the star's sky position (x, y, 0-based)
    write_changed_fits = _script("_copy_fit").write_changed_fits
    for name, change, want in (("shifted", _script("shifted").shifted(2.0, -1.0), (14, 13)),
                               ("mirrored", _script("mirrored").mirrored, (18, 14))):
        dst = tmp_path / f"{name}.fits"
        write_changed_fits(src, dst, change)
        with fits.open(dst) as h:
            data, w = h[0].data, WCS(h[0].header)
        r, c = np.unravel_index(np.argmax(data), data.shape)
        assert (c, r) == want
        np.testing.assert_allclose(w.world_to_pixel(sky), want, atol=1e-6)
    assert src.read_bytes() == before  # the star's file is not touched


def test_write_comparison_rows(tmp_path, capsys):
    """The comparison table's differences are against the expected value, in the star's
    standard errors; parameters the copy did not fit are left out."""
    write_comparison = _script("_copy_fit").write_comparison
    star = {"free": ["rotation", "flux", "z9"], "values": {"rotation": 0.5, "flux": 10.0,
            "z9": 1.0}, "errors": {"rotation": 0.1, "flux": 2.0, "z9": 1.0},
            "residual_rms_over_peak": 0.004, "chi2_dof": 2.5}
    got = {"values": {"rotation": -0.45, "flux": 11.0}, "residual_rms_over_peak": 0.005,
           "chi2_dof": 2.6}
    path = tmp_path / "c.md"
    write_comparison(path, "T", star, got, "copy", lambda k, v: -v if k == "rotation" else v,
                     "expected")
    rows = [r.split(" | ") for r in path.read_text().splitlines() if r.startswith("| ")][1:]
    assert [r[0] for r in rows] == ["| rotation", "| flux"]
    assert rows[0][2:] == ["-0.5", "-0.45", "+0.05", "+0.500 |"]
    assert rows[1][2:] == ["10", "11", "+1", "+0.500 |"]
    assert "0.400 %, copy 0.500 %" in path.read_text() and "| rotation" in capsys.readouterr().out


def test_contaminated_image_adds_the_neighbour_and_the_hits():
    """The neighbour is the star (less the border's median), FACTOR times fainter, moved
    by whole pixels (exact, 0 beyond the border); the hits land at least 15 px from the
    star within 0.3–10 % of its peak (plus a track's second pixel); NaN stays NaN; the
    input is unchanged."""
    mod = _script("contaminated")
    img = 5.0 + 100.0 * _gaussian((61, 61), 30.0, 30.0)
    img[0, 0] = np.nan
    before = img.copy()
    calm = mod.contaminated_image(img, neighbour=(12, -7, 20.0), hits=0)
    np.testing.assert_array_equal(img, before)
    star = np.nan_to_num(img - 5.0)
    want = np.zeros_like(star)
    want[:-7, 12:] = star[7:, :-12] / 20.0  # out[r, c] = star[r + 7, c − 12] / 20
    assert np.isnan(calm[0, 0])
    np.testing.assert_allclose(np.nan_to_num(calm - img), want, rtol=0, atol=1e-12)
    hit = mod.contaminated_image(img, neighbour=(12, -7, 20.0), hits=8, seed=4) - calm
    hit = np.nan_to_num(hit)
    rr, cc = np.nonzero(hit > 1e-9)
    assert 8 <= len(rr) <= 16
    assert np.hypot(rr - 30, cc - 30).min() >= 15 - 1.5  # a track's second pixel: ≤ 1.5 px on
    levels = np.sort(hit[rr, cc])[::-1]  # the star's peak is 100
    assert levels[0] <= 2 * 10.0  # at most 10 % each (two hits could share a pixel)
    assert levels[7] >= 0.3 and levels[-1] >= 0.3 * 0.3  # 0.3 % each; a track's 2nd ≥ 30 %


def test_rotation_bound_and_resampling_refuse_bad_input(tmp_path, capsys):
    """The noise-limit and resampling scripts name what is wrong and exit with 2 before
    any computation: a result folder without result.json, a factor below 1, an unknown
    kernel."""
    manifest = str(HERE / "manifest.json")
    bound = _script("rotation_bound")
    assert bound.main([manifest, str(tmp_path)]) == 2
    assert "result.json" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:
        bound.main([manifest, str(tmp_path), "--factors", "0.5"])
    assert e.value.code == 2
    (tmp_path / "result.json").write_text('{"values": {}}')
    assert _script("resampling").main([manifest, str(tmp_path), "--kernel", "cubic"]) == 2
    assert "resampling" in capsys.readouterr().err
