"""Reading intensity images (FITS, TIFF, PNG, NumPy): the shared real PSFs and round
trips of small generated files."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest
import tifffile
from astropy.io import fits
from PIL import Image

from difstar.io import ImageData, ImageReadError, read_image

# The CI clones the repository with ../shared beside it.
SHARED = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "measured_psf"
FILES = {
    "psf_f090w_star0.fits": "0dede92fcb90e711d07e581809f38a9a00be2a86ecd048eb6bf6d648b1fc92dc",
    "irac_ch1_flight.fits": "883afac151a1b4385a16251d943f30345e3e5e11796ba68fa1e4ffcc5eac14b9",
}


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _shared(name: str) -> Path:
    p = SHARED / name
    if not p.is_file():
        pytest.fail(f"real measured PSF missing: {p} (expected ../shared/data/measured_psf/ "
                    "beside the repository; see its README.md)")
    return p


def test_jwst_nircam_star():
    p = _shared("psf_f090w_star0.fits")
    im = read_image(p)
    assert isinstance(im, ImageData) and im.format == "fits" and im.hdu == 0
    assert im.shape == (91, 91) and im.data.dtype == np.float64
    assert not im.has_invalid and im.valid.all()
    # README: 0.03123″ per pixel from CD1_1 = −8.675e-6 deg
    assert im.pixel_scale == pytest.approx(0.03123, rel=1e-3)
    assert im.pixel_scale_keyword == "CD1_1..CD2_2"
    assert im.header["CD1_1"] == pytest.approx(-8.675e-6, rel=1e-3)
    stored = fits.getdata(p).astype(np.float64)
    # FITS row 0 is the bottom of the sky image: difstar's row 0 is the top
    assert im.flipped and np.array_equal(im.data, stored[::-1])
    raw = read_image(p, flip_fits=False)
    assert not raw.flipped and np.array_equal(raw.data, stored)
    peak = np.unravel_index(np.argmax(im.data), im.shape)
    assert peak[0] == 90 - np.unravel_index(np.argmax(stored), stored.shape)[0]
    with pytest.raises(ValueError):
        im.data[0, 0] = 1.0  # read-only
    assert _sha256(p) == FILES[p.name]


def test_spitzer_irac_psf():
    p = _shared("irac_ch1_flight.fits")
    im = read_image(p)
    assert im.shape == (81, 81)
    assert im.pixel_scale == pytest.approx(0.30525, rel=1e-9)  # README: header SECPIX
    assert im.pixel_scale_keyword == "SECPIX"
    np.testing.assert_array_equal(im.data, fits.getdata(p).astype(np.float64)[::-1])
    assert _sha256(p) == FILES[p.name]


def _image(h=12, w=17, seed=0):
    return np.random.default_rng(seed).uniform(0, 100, (h, w))


def test_fits_round_trips_hdus_cubes_and_nan(tmp_path):
    a = _image()
    a[3, 4] = np.nan
    p = tmp_path / "img.fits"
    hdr = fits.Header({"PIXSCALE": 0.11, "OBJECT": "star"})
    hdr["HISTORY"] = "made for a test"
    fits.PrimaryHDU(a.astype(np.float32), header=hdr).writeto(p)
    im = read_image(p)
    assert im.pixel_scale == pytest.approx(0.11) and im.header["OBJECT"] == "star"
    assert im.header["HISTORY"] == ["made for a test"]
    assert im.has_invalid and not im.valid[::-1][3, 4] and im.valid.sum() == a.size - 1
    assert im.data[::-1][3, 4] == 0.0
    good = np.isfinite(a)
    np.testing.assert_allclose(im.data[::-1][good], a.astype(np.float32)[good], rtol=0)

    # multi-extension: empty primary, a table, an image extension found by default
    m = tmp_path / "multi.fits"
    table = fits.BinTableHDU.from_columns([fits.Column(name="x", format="E", array=[1.0])])
    fits.HDUList([fits.PrimaryHDU(), table, fits.ImageHDU(a, name="SCI")]).writeto(m)
    im = read_image(m)
    assert im.hdu == 2
    assert read_image(m, hdu="SCI").hdu == 2
    with pytest.raises(ImageReadError, match=r"multi\.fits: HDU 1 is a BinTableHDU, not an image"):
        read_image(m, hdu=1)
    with pytest.raises(ImageReadError, match=r"multi\.fits: no HDU 'ERR'"):
        read_image(m, hdu="ERR")
    with pytest.raises(ImageReadError, match="HDU 0 holds no data"):
        read_image(m, hdu=0)
    t = tmp_path / "table.fits"
    fits.HDUList([fits.PrimaryHDU(), table]).writeto(t)
    with pytest.raises(ImageReadError, match=r"table\.fits: no image HDU with 2-D data"):
        read_image(t)

    # a cube needs plane=; leading length-1 axes are dropped
    c = tmp_path / "cube.fits"
    cube = np.stack([_image(seed=s) for s in range(3)])
    fits.PrimaryHDU(cube).writeto(c)
    with pytest.raises(ImageReadError,
                       match=r"cube\.fits: a cube of shape \(3, 12, 17\): pass plane="):
        read_image(c)
    np.testing.assert_array_equal(read_image(c, plane=1).data, cube[1][::-1])
    with pytest.raises(ImageReadError, match=r"plane must be an integer in \[0, 3\)"):
        read_image(c, plane=3)
    d = tmp_path / "deg.fits"
    fits.PrimaryHDU(a[None, None]).writeto(d)
    assert read_image(d).shape == (12, 17)
    one = tmp_path / "line.fits"
    fits.PrimaryHDU(np.arange(5.0)).writeto(one)
    with pytest.raises(ImageReadError, match=r"line\.fits: no image HDU with 2-D data"):
        read_image(one)
    with pytest.raises(ImageReadError, match=r"data of shape \(5,\) is not a 2-D image"):
        read_image(one, hdu=0)
    # CDELT in degrees
    w = tmp_path / "wcs.fits"
    fits.PrimaryHDU(a, header=fits.Header({"CDELT1": -1e-4, "CDELT2": 1e-4})).writeto(w)
    assert read_image(w).pixel_scale == pytest.approx(0.36)


def test_tiff_png_npy_round_trips(tmp_path):
    a = _image()
    for dtype in (np.float32, np.float64, np.uint16):
        p = tmp_path / f"img_{np.dtype(dtype).name}.tif"
        tifffile.imwrite(p, a.astype(dtype))
        im = read_image(p)
        assert im.format == "tiff" and not im.flipped and im.pixel_scale is None
        np.testing.assert_array_equal(im.data, a.astype(dtype).astype(np.float64))
    stack = tmp_path / "stack.tif"
    tifffile.imwrite(stack, np.stack([a, 2 * a]).astype(np.float32))
    with pytest.raises(ImageReadError, match=r"stack\.tif: a cube .* pass plane="):
        read_image(stack)
    np.testing.assert_allclose(read_image(stack, plane=1).data, (2 * a).astype(np.float32))
    rgb = tmp_path / "rgb.tif"
    tifffile.imwrite(rgb, np.stack([a, 2 * a, 3 * a], axis=-1).astype(np.uint16), photometric="rgb")
    np.testing.assert_array_equal(read_image(rgb, plane=2).data, (3 * a).astype(np.uint16))

    p8 = tmp_path / "img8.png"
    Image.fromarray(a.astype(np.uint8), mode="L").save(p8)
    np.testing.assert_array_equal(read_image(p8).data, a.astype(np.uint8))
    p16 = tmp_path / "img16.png"
    v16 = (a * 600).astype(np.uint16)
    Image.fromarray(v16).save(p16)
    im16 = read_image(p16)
    assert im16.format == "png" and im16.data.max() > 255
    np.testing.assert_array_equal(im16.data, v16)
    prgb = tmp_path / "rgb.png"
    Image.fromarray(np.stack([a, a, a], -1).astype(np.uint8), mode="RGB").save(prgb)
    with pytest.raises(ImageReadError, match=r"rgb\.png: a cube of shape \(3, 12, 17\)"):
        read_image(prgb)
    np.testing.assert_array_equal(read_image(prgb, plane=0).data, a.astype(np.uint8))

    n = tmp_path / "img.npy"
    b = a.copy()
    b[0, 0] = np.inf
    np.save(n, b)
    imn = read_image(n)
    assert imn.format == "npy" and not imn.valid[0, 0] and imn.data[0, 0] == 0
    np.testing.assert_array_equal(imn.data[1:], a[1:])
    bad = tmp_path / "obj.npy"
    np.save(bad, np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(ImageReadError, match=r"obj\.npy: not a plain numeric \.npy"):
        read_image(bad)
    v = tmp_path / "vec.npy"
    np.save(v, np.arange(4.0))
    with pytest.raises(ImageReadError, match=r"vec\.npy: data of shape \(4,\) is not a 2-D image"):
        read_image(v)
    allnan = tmp_path / "nan.npy"
    np.save(allnan, np.full((3, 3), np.nan))
    with pytest.raises(ImageReadError, match="no finite pixel values"):
        read_image(allnan)
    # a known format under another name is recognised by its content
    renamed = tmp_path / "star.dat"
    renamed.write_bytes(p16.read_bytes())
    np.testing.assert_array_equal(read_image(renamed).data, v16)


def test_unsupported_and_missing_files(tmp_path):
    with pytest.raises(ImageReadError, match=r"nope\.fits: file not found"):
        read_image(tmp_path / "nope.fits")
    with pytest.raises(ImageReadError, match="not a regular file"):
        read_image(tmp_path)
    t = tmp_path / "notes.txt"
    t.write_text("hello\n")
    with pytest.raises(ImageReadError,
                       match=r"notes\.txt: unsupported image format; difstar reads FITS"):
        read_image(t)
    j = tmp_path / "photo.jpg"
    j.write_bytes(b"\xff\xd8\xff\xe0" + bytes(100))
    with pytest.raises(ImageReadError, match="unsupported image format"):
        read_image(j)
    broken = tmp_path / "broken.fits"
    broken.write_bytes(b"SIMPLE  =                    T" + b" " * 50)
    with pytest.raises(ImageReadError, match=r"broken\.fits: cannot be read as FITS"):
        read_image(broken)
    npy = tmp_path / "a.npy"
    np.save(npy, np.ones((3, 3)))
    with pytest.raises(ImageReadError, match="hdu= applies to FITS files only"):
        read_image(npy, hdu=1)
