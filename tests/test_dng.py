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
