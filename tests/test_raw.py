"""Reading real camera RAW files with ``read_raw``, checked against rawpy's own values."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest
import rawpy
import tifffile

from difstar.io._raw import RawCapture, RawReadError, read_raw

# The CI clones the repository with ../shared beside it.
SHARED = Path(__file__).resolve().parents[1].parent / "shared"
BLACKMAGIC = SHARED / "data" / "raw" / "camera_raw" / "Blackmagic.dng"
BLACKMAGIC_SHA256 = "adb7beb2753978d8e2bb1a868057ce373f103957908a6d36b2c4da714e211e25"


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def blackmagic() -> Path:
    if not BLACKMAGIC.is_file():
        pytest.fail(
            f"real RAW test file missing: {BLACKMAGIC} (expected ../shared/data/raw/camera_raw/"
            "Blackmagic.dng beside the repository; see shared/data/raw/README.md)"
        )
    return BLACKMAGIC


@pytest.fixture(scope="module")
def capture(blackmagic) -> RawCapture:
    return read_raw(blackmagic)


def test_blackmagic_is_the_documented_file(blackmagic):
    assert _sha256(blackmagic) == BLACKMAGIC_SHA256


def test_blackmagic_agrees_with_rawpy(blackmagic, capture):
    with rawpy.imread(str(blackmagic)) as r:
        raw = r.raw_image_visible.copy()
        colors = r.raw_colors_visible.copy()
        desc = r.color_desc.decode()
        pattern = "".join(desc[i] for i in r.raw_pattern.ravel())
        black = np.asarray(r.black_level_per_channel, float)
        white = float(r.white_level)
        wb = np.asarray(r.camera_whitebalance, float)
        cam_srgb = np.asarray(r.color_matrix, float)[:3, :3]
    # rawpy's values, and those the README states
    assert pattern == "RGGB"
    assert black.tolist() == [512.0] * 4 and white == 65535.0
    assert raw.shape == (2176, 4128)

    c = capture
    assert c.pattern == pattern
    assert c.raw.dtype == np.uint16 and c.shape == raw.shape
    assert np.array_equal(c.raw, raw)
    assert np.array_equal(c.raw_colors, colors)
    assert np.array_equal(c.black_level, black) and c.white_level == white
    assert np.array_equal(c.black_level_tile, np.full((2, 2), 512.0))
    assert c.cfa.dtype == np.float64
    np.testing.assert_allclose(c.cfa, (raw - 512.0) / (65535.0 - 512.0), rtol=0, atol=1e-15)
    assert np.array_equal(c.saturated, raw >= 65535)
    np.testing.assert_allclose(c.camera_white_balance, [wb[0] / wb[1], 1.0, wb[2] / wb[1]])
    np.testing.assert_allclose(c.camera_to_srgb, cam_srgb)


def test_blackmagic_colour_and_metadata(blackmagic, capture):
    with tifffile.TiffFile(blackmagic) as t:
        tags = t.pages.first.tags
        # AsShotNeutral 0.4533, 1, 0.53 → multipliers 1/neutral
        neutral = np.asarray(tags[50728].value, float)
        cm2 = np.asarray(tags[50722].value, float)  # ColorMatrix2, calibrated for D65 (21)
        assert tags[50779].value == 21
        has_exif = any(k in tags for k in (33434, 33437, 37386, 34665))
    gains = neutral[1::2] / neutral[0::2]  # 1 / AsShotNeutral
    np.testing.assert_allclose(capture.camera_white_balance, gains / gains[1], rtol=1e-6)
    np.testing.assert_allclose(capture.rgb_xyz_matrix, (cm2[0::2] / cm2[1::2]).reshape(3, 3))
    np.testing.assert_allclose(
        capture.camera_to_xyz @ capture.rgb_xyz_matrix, np.eye(3), atol=1e-12
    )
    # this file carries no exposure metadata: the fields say so rather than guess
    assert not has_exif
    assert capture.exposure_time is None and capture.f_number is None
    assert capture.focal_length is None


def test_capture_is_read_only_and_input_untouched(blackmagic, capture):
    assert _sha256(blackmagic) == BLACKMAGIC_SHA256
    with pytest.raises(ValueError):
        capture.cfa[0, 0] = 1.0
    with pytest.raises(AttributeError):
        capture.pattern = "BGGR"  # type: ignore[misc]


def test_missing_file():
    p = Path("/nonexistent/dir/photo.dng")
    with pytest.raises(RawReadError, match=r"photo\.dng: file not found"):
        read_raw(p)


def test_truncated_file(blackmagic, tmp_path):
    data = blackmagic.read_bytes()
    p = tmp_path / "truncated.dng"
    p.write_bytes(data[: len(data) // 2])
    with pytest.raises(RawReadError, match=r"truncated\.dng: truncated"):
        read_raw(p)
    assert _sha256(blackmagic) == BLACKMAGIC_SHA256


def test_text_file_renamed_dng(tmp_path):
    p = tmp_path / "notes.dng"
    p.write_text("this is not a raw file\n" * 10)
    with pytest.raises(RawReadError, match=r"notes\.dng: .*not a RAW file"):
        read_raw(p)


def test_empty_file_and_directory(tmp_path):
    p = tmp_path / "empty.nef"
    p.write_bytes(b"")
    with pytest.raises(RawReadError, match=r"empty\.nef: .*(empty|not a RAW)"):
        read_raw(p)
    with pytest.raises(RawReadError, match="not a regular file"):
        read_raw(tmp_path)


def _dng(path, data, photometric, tags, white=4000):
    base = [
        (50706, 1, 4, bytes((1, 4, 0, 0)), True),
        (50708, 2, 0, "test", True),
        (50717, 4, 1, white, True),
    ]
    tifffile.imwrite(
        path, data, photometric=photometric, subfiletype=0, metadata=None, extratags=base + tags
    )
    return path


XTRANS = [
    [1, 1, 0, 1, 1, 2],
    [1, 1, 2, 1, 1, 0],
    [2, 0, 1, 0, 2, 1],
    [1, 1, 2, 1, 1, 0],
    [1, 1, 0, 1, 1, 2],
    [0, 2, 1, 2, 0, 1],
]


@pytest.mark.parametrize(
    "name, shape, photometric, tags, match",
    [
        (
            "xtrans.dng",
            (36, 48),
            32803,
            [(33421, 3, 2, (6, 6), True), (33422, 1, 36, bytes(np.ravel(XTRANS).tolist()), True)],
            r"xtrans\.dng: not a Bayer sensor: X-Trans",
        ),
        ("linear.dng", (32, 48, 3), 34892, [], r"linear\.dng: not a Bayer sensor: .*linear"),
        (
            "cmyg.dng",
            (32, 48),
            32803,
            [
                (33421, 3, 2, (2, 2), True),
                (33422, 1, 4, bytes([3, 4, 5, 1]), True),
                (50710, 1, 4, bytes([3, 4, 5, 1]), True),
            ],
            r"cmyg\.dng: not a Bayer sensor: .*4 colours",
        ),
        (
            "nowb.dng",
            (32, 48),
            32803,
            [(33421, 3, 2, (2, 2), True), (33422, 1, 4, bytes([0, 1, 1, 2]), True)],
            r"nowb\.dng: missing camera white balance",
        ),
    ],
)
def test_non_bayer_and_missing_values(tmp_path, name, shape, photometric, tags, match):
    data = np.random.default_rng(0).integers(0, 4000, shape).astype(np.uint16)
    p = _dng(tmp_path / name, data, photometric, tags)
    with pytest.raises(RawReadError, match=match):
        read_raw(p)


# --- truncation (issue 16), missing colour matrix and non-Bayer files (issue 15) --------

SYNTHETIC = Path(__file__).resolve().parents[1] / "fit" / "synthetic-paper-camera" / "captures"


@pytest.mark.parametrize("keep", [8, 9, 300, 500, 10_000, 1_000_000, 3_359_557])
def test_truncated_copies_of_the_real_dng_are_refused(blackmagic, tmp_path, keep):
    # LibRaw alone decodes a copy cut to its first 10 KB "successfully" (zeros or
    # uninitialised memory); the file's own TIFF tags say how long it must be.
    p = tmp_path / f"cut{keep}.dng"
    p.write_bytes(blackmagic.read_bytes()[:keep])
    with pytest.raises(RawReadError, match=rf"cut{keep}\.dng: truncated: .*{keep} bytes"):
        read_raw(p)
    assert _sha256(blackmagic) == BLACKMAGIC_SHA256


def test_truncated_copies_of_the_synthetic_dngs_are_refused(tmp_path):
    files = sorted(SYNTHETIC.glob("*.dng"))
    if not files:
        pytest.fail(f"synthetic captures missing: {SYNTHETIC}")
    for src in files[:3]:
        data = src.read_bytes()
        before = _sha256(src)
        read_raw(src)  # the whole file reads
        for keep in (10_000, len(data) // 2, len(data) - 1):
            p = tmp_path / f"{src.stem}_{keep}.dng"
            p.write_bytes(data[:keep])
            with pytest.raises(RawReadError, match=r"truncated: its TIFF tags declare image data"):
                read_raw(p)
        assert _sha256(src) == before and src.stat().st_size == len(data)


def test_truncation_message_names_the_file_and_sizes(blackmagic, tmp_path):
    p = tmp_path / "first10k.dng"
    p.write_bytes(blackmagic.read_bytes()[:10_000])
    with pytest.raises(RawReadError) as e:
        read_raw(p)
    msg = str(e.value)
    assert msg.startswith(str(p)) and "3359558" in msg and "10000 bytes" in msg


def test_missing_colour_matrix_warns_and_reads_the_mosaic(tmp_path):
    from difstar.io import MissingColourMatrixWarning

    data = np.random.default_rng(1).integers(0, 4000, (32, 48)).astype(np.uint16)
    p = _dng(tmp_path / "nomatrix.dng", data, 32803,
             [(33421, 3, 2, (2, 2), True), (33422, 1, 4, bytes([0, 1, 1, 2]), True),
              (50728, 5, 3, (1, 2, 1, 1, 1, 2), True)])  # AsShotNeutral, no ColorMatrix
    with pytest.warns(MissingColourMatrixWarning, match=r"nomatrix\.dng: no colour matrix.*sRGB"):
        c = read_raw(p)
    assert c.rgb_xyz_matrix is None and c.camera_to_srgb is None
    assert c.pattern == "RGGB" and np.array_equal(c.raw, data)
    np.testing.assert_allclose(c.camera_white_balance, [2.0, 1.0, 2.0])
    with pytest.raises(RawReadError, match=r"nomatrix\.dng: no colour matrix.*XYZ"):
        c.camera_to_xyz


def test_monochrome_dng_is_a_clear_error(tmp_path):
    data = np.random.default_rng(2).integers(0, 4000, (32, 48)).astype(np.uint16)
    p = _dng(tmp_path / "mono.dng", data, "minisblack", [])
    with pytest.raises(RawReadError,
                       match=r"mono\.dng: not a Bayer sensor: monochrome.*difstar reads Bayer"):
        read_raw(p)
