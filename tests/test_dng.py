"""Synthetic captures written as DNG and read back by rawpy and by ``read_raw``."""

from __future__ import annotations

import os

import numpy as np
import pytest
import rawpy

from difstar.io._dng import DngWriteError, synthesize_capture, write_dng
from difstar.io._raw import read_raw

PATTERNS = ["RGGB", "BGGR", "GRBG", "GBRG"]
XYZ_TO_CAM = np.array([[0.9, -0.4, 0.03], [-0.35, 1.3, 0.2], [-0.05, 0.2, 0.6]])


def _raw(shape=(32, 48), white=16383, seed=0):
    rng = np.random.default_rng(seed)
    a = rng.integers(0, white + 1, shape).astype(np.uint16)
    a[0, 0] = white  # one saturated pixel, one at 0
    a[1, 1] = 0
    return a


def _write(path, raw, pattern, black=(500, 510, 520, 530), white=16383, **kw):
    args = dict(
        exposure_time=1 / 125,
        f_number=22.0,
        focal_length=0.05,
        camera_white_balance=[2.0, 1.0, 1.5],
        color_matrix=XYZ_TO_CAM,
    )
    args.update(kw)
    return write_dng(path, raw, pattern=pattern, black_level=black, white_level=white, **args)


@pytest.mark.parametrize("pattern", PATTERNS)
def test_roundtrip_rawpy_and_read_raw(tmp_path, pattern):
    raw = _raw()
    black = np.array([500.0, 510.0, 520.0, 530.0])  # per tile position, row-major
    path = _write(tmp_path / f"{pattern}.dng", raw, pattern, black=black)

    # rawpy's own view of the file
    with rawpy.imread(str(path)) as r:
        assert np.array_equal(r.raw_image_visible, raw)
        desc = r.color_desc.decode()
        assert "".join(desc[i] for i in r.raw_pattern.ravel()) == pattern
        per_channel = np.asarray(r.black_level_per_channel, float)
        assert np.array_equal(per_channel[r.raw_pattern].ravel(), black)
        assert r.white_level == 16383
        wb = np.asarray(r.camera_whitebalance[:3])
        np.testing.assert_allclose(wb / wb[1], [2.0, 1.0, 1.5], rtol=1e-6)

    cap = read_raw(path)
    assert cap.pattern == pattern
    assert np.array_equal(cap.raw, raw) and cap.raw.dtype == np.uint16
    assert np.array_equal(cap.black_level_tile.ravel(), black)
    assert cap.white_level == 16383
    blk = np.tile(black.reshape(2, 2), (16, 24))
    np.testing.assert_array_equal(cap.cfa, (raw - blk) / (16383 - blk))
    assert np.array_equal(cap.saturated, raw >= 16383) and cap.saturated[0, 0]
    np.testing.assert_allclose(cap.camera_white_balance, [2.0, 1.0, 1.5], rtol=1e-6)
    np.testing.assert_allclose(cap.rgb_xyz_matrix, XYZ_TO_CAM, atol=1e-6)
    assert cap.exposure_time == pytest.approx(1 / 125, rel=1e-12)
    assert cap.f_number == pytest.approx(22.0, rel=1e-12)
    assert cap.focal_length == pytest.approx(0.05, rel=1e-12)


def test_metadata_absent_gives_none(tmp_path):
    path = write_dng(tmp_path / "a.dng", _raw(), pattern="RGGB", black_level=64, white_level=16383)
    cap = read_raw(path)
    assert cap.exposure_time is None and cap.f_number is None and cap.focal_length is None
    np.testing.assert_array_equal(cap.black_level, [64.0] * 4)
    np.testing.assert_allclose(cap.rgb_xyz_matrix, np.eye(3), atol=1e-12)


def test_no_overwrite_and_atomic(tmp_path, monkeypatch):
    path = tmp_path / "c.dng"
    _write(path, _raw(seed=1), "RGGB")
    before = path.read_bytes()
    with pytest.raises(DngWriteError, match="already exists"):
        _write(path, _raw(seed=2), "RGGB")
    assert path.read_bytes() == before
    _write(path, _raw(seed=2), "RGGB", overwrite=True)
    assert np.array_equal(read_raw(path).raw, _raw(seed=2))
    assert sorted(os.listdir(tmp_path)) == ["c.dng"]  # no temporary files left

    # A failure while writing leaves neither a partial output nor a temporary file.
    import tifffile

    def boom(*a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(tifffile.TiffWriter, "write", boom)
    with pytest.raises(OSError, match="disk full"):
        _write(tmp_path / "d.dng", _raw(), "RGGB")
    with pytest.raises(OSError, match="disk full"):
        _write(path, _raw(seed=3), "RGGB", overwrite=True)
    assert sorted(os.listdir(tmp_path)) == ["c.dng"]
    assert np.array_equal(read_raw(path).raw, _raw(seed=2))


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(pattern="RGBG"), "pattern"),
        (dict(white_level=1000), "exceed white_level"),
        (dict(black_level=20000, white_level=16383), "black levels"),
        (dict(raw=np.zeros((20, 48), np.uint16)), "≥ 22"),
        (dict(raw=np.zeros((32, 48), np.float32)), "uint16"),
        (dict(exposure_time=-1.0), "exposure_time"),
    ],
)
def test_write_dng_rejects_bad_input(tmp_path, kw, match):
    args = dict(raw=_raw(), pattern="RGGB", black_level=512, white_level=16383)
    args.update(kw)
    raw = args.pop("raw")
    with pytest.raises(DngWriteError, match=match):
        write_dng(tmp_path / "x.dng", raw, **args)
    assert not os.listdir(tmp_path)


def test_noise_statistics_match_poisson_gaussian():
    """Flat fields: mean and variance against E = ζ(W−B), Var = E/g + σ_r² + 1/12.

    N = 65 536 pixels per field. Tolerances: mean within 5 standard errors
    (SE = sqrt(Var/N) ≤ 0.2 DN), variance within 4 % (its relative SE is sqrt(2/N) ≈ 0.55 %,
    so 4 % is > 7 SE; the +1/12 DN² is the rounding to integers).
    """
    rng = np.random.default_rng(1234)
    black, white, gain, rn = 512.0, 16383.0, 2.0, 3.0
    for zeta in (0.0, 0.02, 0.3, 0.8):
        z = np.full((256, 256), zeta)
        raw = synthesize_capture(
            z, black_level=black, white_level=white, gain_e_per_dn=gain, read_noise_dn=rn, rng=rng
        )
        assert raw.dtype == np.uint16
        x = raw.astype(float) - black
        mean_th = zeta * (white - black)
        var_th = mean_th / gain + rn**2 + 1 / 12
        assert abs(x.mean() - mean_th) < 5 * np.sqrt(var_th / x.size), zeta
        assert x.var() == pytest.approx(var_th, rel=0.04), zeta


def test_saturation_is_clipped_at_white(tmp_path):
    rng = np.random.default_rng(7)
    z = np.concatenate([np.full((32, 24), 1.3), np.full((32, 24), 0.5)], axis=1)
    raw = synthesize_capture(
        z,
        black_level=np.array([[500, 510], [520, 530]]),
        white_level=4095,
        gain_e_per_dn=1.0,
        read_noise_dn=2.0,
        rng=rng,
    )
    assert raw.max() == 4095
    assert np.all(raw[:, :24] == 4095)
    assert np.all(raw[:, 24:] < 4095)
    cap = read_raw(
        write_dng(
            tmp_path / "s.dng",
            raw,
            pattern="GRBG",
            black_level=[500, 510, 520, 530],
            white_level=4095,
        )
    )
    assert np.array_equal(cap.saturated, z > 1.0)
    # the unsaturated half reads back ζ ≈ 0.5 on average per channel
    for i in range(2):
        for j in range(2):
            assert cap.cfa[i::2, 24 + j :: 2].mean() == pytest.approx(0.5, abs=2e-3)


def test_synthesize_is_reproducible_and_checks_input():
    z = np.full((4, 4), 0.5)
    kw = dict(black_level=0, white_level=1023, gain_e_per_dn=4.0, read_noise_dn=1.0)
    a = synthesize_capture(z, rng=np.random.default_rng(3), **kw)
    b = synthesize_capture(z, rng=np.random.default_rng(3), **kw)
    assert np.array_equal(a, b)
    with pytest.raises(ValueError):
        synthesize_capture(-z, rng=np.random.default_rng(3), **kw)
    with pytest.raises(ValueError):
        synthesize_capture(z, rng=np.random.default_rng(3), **{**kw, "gain_e_per_dn": 0.0})


# ------------------------------------------------ what `difstar predict` writes (issue 34)

#: the paper's camera RGB → linear sRGB matrix (rows sum to 1 within 2e-4) and gains
WB = np.array([2.0, 1.0, 2.0])


def _paper_matrix():
    from difstar._examples import PAPER_COLOUR_MATRIX

    return np.asarray(PAPER_COLOUR_MATRIX, float)


def test_dng_colour_matrix_of_srgb_itself_is_colour_science_xyz_to_srgb():
    """A camera whose RGB is linear sRGB (identity matrix, unit gains): ColorMatrix1 must
    be colour-science's XYZ → sRGB matrix, which maps D65 white to (1, 1, 1) (to the 4
    digits IEC 61966-2-1 gives it)."""
    import colour

    from difstar.io._dng import dng_colour_matrix

    x2s = np.asarray(colour.RGB_COLOURSPACES["sRGB"].matrix_XYZ_to_RGB)
    d65 = colour.xy_to_XYZ(colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"])
    np.testing.assert_allclose(x2s @ d65, 1.0, atol=2e-4)
    np.testing.assert_allclose(dng_colour_matrix(np.eye(3), np.ones(3)), x2s, rtol=2e-4)
    # with gains, D65 white gives the camera neutral 1/wb (largest component 1): the
    # AsShotNeutral that write_dng stores for the same gains
    neutral = dng_colour_matrix(_paper_matrix(), WB) @ d65
    np.testing.assert_allclose(neutral, (1 / WB) / np.max(1 / WB), rtol=5e-4)  # rows: 2e-4
    with pytest.raises(DngWriteError, match="singular"):
        dng_colour_matrix(np.ones((3, 3)), WB)


def _smooth_zeta(h=96, w=128):
    """Normalised values ζ that vary slowly (periods ≥ 3.7 pixels × 2π) and stay well
    below saturation: any two demosaics agree there to second order."""
    y, x = np.mgrid[0:h, 0:w] / 64.0
    return np.stack([0.2 + 0.15 * np.sin(1.3 * x + y), 0.3 + 0.1 * np.cos(1.7 * y),
                     0.15 + 0.1 * np.sin(x + 0.5 * y)])


@pytest.mark.parametrize("pattern", PATTERNS)
def test_predicted_dng_develops_in_libraw_as_difstar_renders(tmp_path, pattern):
    """write_raw_dng (what `predict` writes as raw.dng): LibRaw reads back the layout,
    levels, values and white balance written, and its development (camera white balance,
    the embedded colour matrix, sRGB curve, no auto-brightening, 16 bits) equals difstar's
    render_srgb of the same mosaic: bilinear against LibRaw's LINEAR, Malvar 2004 against
    AHD.

    Tolerance 2e-3 of the encoded sRGB range, away from a 4-pixel border (LibRaw fills its
    border differently). Measured: 4.2e-4 (bilinear/LINEAR), 6.8e-4 (Malvar/AHD). What
    remains: LibRaw's 16-bit integer pipeline (1.5e-5 linear, up to 2e-4 encoded in the
    steep dark part of the curve), its sRGB curve solved for continuity from (1/2.4,
    12.92) rather than IEC 61966-2-1's constants, its normalisation of the matrix rows
    (2e-4 for this matrix), and the demosaics' second-order differences."""
    import jax.numpy as jnp
    import rawpy

    from difstar._cfa import mosaic
    from difstar._colour import render_srgb
    from difstar.io._image_files import write_raw_dng

    zeta = _smooth_zeta()
    cfa = np.asarray(mosaic(jnp.asarray(zeta), pattern))
    black, white = 1024, 60000
    path = tmp_path / "raw.dng"
    write_raw_dng(path, cfa, pattern=pattern, white_balance=WB, colour_matrix=_paper_matrix(),
                  black_level=black, white_level=white, exposure_time=0.5)
    want_raw = (black + np.round(cfa * (white - black))).astype(np.uint16)
    with rawpy.imread(str(path)) as r:
        assert np.array_equal(r.raw_image_visible, want_raw)
        desc = r.color_desc.decode()
        assert "".join(desc[i] for i in r.raw_pattern.ravel()) == pattern
        assert list(r.black_level_per_channel) == [black] * 4
        assert r.white_level == white
        cam_wb = np.asarray(r.camera_whitebalance[:3])
        np.testing.assert_allclose(cam_wb / cam_wb[1], WB, rtol=1e-6)
        developed = {}
        for alg in ("LINEAR", "AHD"):
            img = r.postprocess(use_camera_wb=True, no_auto_bright=True, gamma=(2.4, 12.92),
                                output_bps=16, user_flip=0,
                                demosaic_algorithm=getattr(rawpy.DemosaicAlgorithm, alg))
            developed[alg] = np.moveaxis(img.astype(float) / 65535, -1, 0)
    quantised = (want_raw.astype(float) - black) / (white - black)
    for method, alg in (("bilinear", "LINEAR"), ("malvar2004", "AHD")):
        ours = np.asarray(render_srgb(jnp.asarray(quantised), pattern, white_balance=WB,
                                      matrix=_paper_matrix(), demosaic_method=method))
        diff = (developed[alg] - ours)[:, 4:-4, 4:-4]
        assert np.abs(diff).max() < 2e-3, (method, np.abs(diff).max())


def test_small_dng_is_written_when_asked(tmp_path):
    """min_side=2 writes a 16 × 16 DNG (LibRaw refuses below 22, so predict's smallest
    crops still get their raw.dng); tifffile reads its values and CFA layout back."""
    import tifffile

    raw = _raw((16, 16))
    with pytest.raises(DngWriteError, match="≥ 22"):
        write_dng(tmp_path / "a.dng", raw, pattern="GBRG", black_level=0, white_level=16383)
    path = write_dng(tmp_path / "a.dng", raw, pattern="GBRG", black_level=0,
                     white_level=16383, min_side=2)
    with tifffile.TiffFile(path) as tif:
        page = tif.pages[0]
        assert np.array_equal(page.asarray(), raw)
        assert bytes(page.tags["CFAPattern"].value) == bytes((1, 2, 0, 1))
