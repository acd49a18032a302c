"""The units and axes of docs/conventions.md, checked at each boundary where a layer
differs from the Python API, both ways:

- the Python API: rows run down, y up, rotations counter-clockwise (radians), Zernike
  coefficients in metres RMS over the unit disc (Noll);
- image-fit manifests and results: x0 right and y0 *down* in data pixels from the
  window's centre pixel, rotation in degrees counter-clockwise as the picture is shown,
  Zernike in nm RMS;
- RAW-fit manifests: source positions and offsets as (row, col) pixels, rows down;
- FITS: row 0 stored at the bottom, flipped once on reading (``io.read_image``) and once
  back on writing (``io.write_fits_like``).

The truths are independent of difstar: a rectangle's far field is brightest across its
long edges (the streak of an edge of length L carries L²), the centroid of a point
source's image is where its position says, a disc's RMS is an integral done here with
NumPy, and astropy's own reading of the FITS files.
"""

from __future__ import annotations

import json
import math

import jax.numpy as jnp
import numpy as np
import pytest

import difstar

LAM = 0.9e-6
PIXEL_SCALE = 0.1  # arcsec per data pixel: λ/D = 2.2 px for a 0.85 m primary


def _rectangle(half_long: float, half_short: float, angle: float) -> np.ndarray:
    """Vertices (x, y up), counter-clockwise, of a rectangle whose long side makes
    ``angle`` (radians, counter-clockwise) with +x."""
    c, s = math.cos(angle), math.sin(angle)
    corners = [(-half_long, -half_short), (half_long, -half_short),
               (half_long, half_short), (-half_long, half_short)]
    return np.array([(c * x - s * y, s * x + c * y) for x, y in corners])


def _brightest_direction(img: np.ndarray, radius: float) -> float:
    """Direction (degrees in [0, 180), counter-clockwise from +x with y UP) of the
    brightest streak on a ring of ``radius`` px about the centre pixel (H//2, W//2) of an
    array whose rows run down."""
    h, w = img.shape
    phis = np.deg2rad(np.arange(0.0, 360.0, 0.25))
    rows = h // 2 - radius * np.sin(phis)  # y up: a positive y is a smaller row
    cols = w // 2 + radius * np.cos(phis)
    r0, c0 = np.floor(rows).astype(int), np.floor(cols).astype(int)
    fr, fc = rows - r0, cols - c0
    vals = ((1 - fr) * (1 - fc) * img[r0, c0] + (1 - fr) * fc * img[r0, c0 + 1]
            + fr * (1 - fc) * img[r0 + 1, c0] + fr * fc * img[r0 + 1, c0 + 1])
    return float(np.rad2deg(phis[np.argmax(vals)]) % 180.0)


def _angle_error(a: float, b: float) -> float:
    d = (a - b) % 180.0
    return min(d, 180.0 - d)


# ------------------------------------------------------------------ the Python API


@pytest.mark.parametrize("angle_deg", [0.0, 30.0, 75.0])
def test_psf_rows_down_y_up_rotation_counter_clockwise(angle_deg):
    """A rectangle 3 times longer than wide, its long side at ``angle`` (CCW from +x,
    y up): its long edges' streak, the brightest, runs across them, at angle + 90°.
    Read with y up from the rows-down array it is there; read with y down it would be
    at −(angle + 90°), which differs for every angle here but 0 and 90 (mod 180)."""
    h = w = 96
    z, p = 50e-3, 2e-6
    pupil = difstar.Polygon(_rectangle(3e-3, 1e-3, math.radians(angle_deg)))
    img = np.asarray(difstar.psf(pupil, wavelength=500e-9, z_image=z, pixel_pitch=p,
                                 shape=(h, w), sampling="point"))
    got = _brightest_direction(img, radius=30.0)
    want = (angle_deg + 90.0) % 180.0
    assert _angle_error(got, want) < 1.0, (got, want)
    # and the pupil's own rotation (radians, CCW) agrees with rotating the vertices
    turned = difstar.Polygon(_rectangle(3e-3, 1e-3, 0.0)).transformed(math.radians(angle_deg))
    img2 = np.asarray(difstar.psf(turned, wavelength=500e-9, z_image=z, pixel_pitch=p,
                                  shape=(h, w), sampling="point"))
    assert _angle_error(_brightest_direction(img2, radius=30.0), want) < 1.0


def test_zernike_coefficients_are_metres_rms_over_the_disc_with_noll_indices():
    """Zernike({j: c}, R): c is the RMS of the OPD over the disc of radius R (NumPy
    quadrature here), in the OPD's own unit (metres); Noll 4 is defocus √3 (2ρ² − 1),
    Noll 2 the tilt in x (2 ρ cos θ), Noll 3 in y (y up)."""
    R, c = 2e-3, 50e-9
    n = 801
    x = np.linspace(-R, R, n)
    xx, yy = np.meshgrid(x, x)
    inside = xx**2 + yy**2 <= R**2
    for j, analytic in ((4, lambda x, y: math.sqrt(3) * (2 * (x**2 + y**2) / R**2 - 1)),
                        (2, lambda x, y: 2 * x / R), (3, lambda x, y: 2 * y / R)):
        opd = np.asarray(difstar.Zernike({j: c}, R).opd(jnp.asarray(xx), jnp.asarray(yy)))
        rms = math.sqrt(np.mean(opd[inside] ** 2))
        assert abs(rms / c - 1) < 2e-3, (j, rms)
        np.testing.assert_allclose(opd[inside], c * analytic(xx, yy)[inside], atol=1e-6 * c)


# ------------------------------------------------------------------ image-fit layer


def _rectangle_builder(angle_deg: float = 0.0) -> difstar.PupilBuilder:
    def build(v):
        return difstar.Polygon(_rectangle(0.6, 0.2, math.radians(angle_deg)))

    return difstar.PupilBuilder("rectangle", build, {}, max_radius=0.7)


def _disc_builder() -> difstar.PupilBuilder:
    """A clear 0.85 m disc; the image fitter's Zernike terms are normalised over its
    ``max_radius``."""
    return difstar.PupilBuilder("disc", lambda v: difstar.Circle(0.425), {}, max_radius=0.425)


def _image(model: difstar.ImageModel, shape, **values) -> np.ndarray:
    v = {k: p.value for k, p in model.params.items()} | values
    return np.asarray(model.image(v, shape))


@pytest.mark.parametrize("x0,y0", [(3.0, 2.0), (-1.3, 2.6)])
def test_image_fit_position_is_data_pixels_right_and_down(x0, y0):
    """x0 right and y0 DOWN in data pixels from the window's centre pixel (w//2, h//2):
    a point star's centroid lands at column w//2 + x0, row h//2 + y0."""
    model = difstar.ImageModel(
        _disc_builder(), {"pixel_scale": PIXEL_SCALE, "flux": 1.0},
        light=difstar.Light.monochromatic(LAM), pad=8, accuracy=3e-3)
    h, w = 41, 45
    img = _image(model, (h, w), x0=x0, y0=y0)
    rows, cols = np.mgrid[:h, :w]
    near = (rows - (h // 2 + y0)) ** 2 + (cols - (w // 2 + x0)) ** 2 < 8**2  # the core
    r = np.sum(img * rows * near) / np.sum(img * near)
    c = np.sum(img * cols * near) / np.sum(img * near)
    assert abs(r - (h // 2 + y0)) < 0.05 and abs(c - (w // 2 + x0)) < 0.05, (r, c)


@pytest.mark.parametrize("rotation_deg", [0.0, 30.0, -50.0])
def test_image_fit_rotation_is_degrees_counter_clockwise_in_the_picture(rotation_deg):
    """``rotation`` (degrees) turns the pupil counter-clockwise as the picture is shown
    (rows down, y up on the screen): the rectangle's brightest streak moves from 90° to
    90° + rotation, read with y up; the same as rotating the vertices by hand."""
    light = difstar.Light.monochromatic(LAM)
    model = difstar.ImageModel(_rectangle_builder(), {"pixel_scale": 0.02, "flux": 1.0},
                               light=light, pad=8, accuracy=3e-3)
    img = _image(model, (81, 81), rotation=rotation_deg)
    want = (90.0 + rotation_deg) % 180.0
    assert _angle_error(_brightest_direction(img, radius=25.0), want) < 1.0
    by_hand = difstar.ImageModel(_rectangle_builder(rotation_deg),
                                 {"pixel_scale": 0.02, "flux": 1.0}, light=light, pad=8,
                                 accuracy=3e-3)
    np.testing.assert_allclose(img, _image(by_hand, (81, 81)), rtol=0,
                               atol=1e-6 * img.max())


def test_image_fit_zernike_is_nm_rms():
    """z<j> of the image fitter is nm RMS: z4 = 80 gives the image of a lens whose
    wavefront is Zernike({4: 80e-9}) in the Python API, and not that of 80e-9 nm or
    80 m (a different image: defocus of 0.09 waves RMS broadens the core by a lot)."""
    light = difstar.Light.monochromatic(LAM)
    builder = _disc_builder()
    fixed = {"pixel_scale": PIXEL_SCALE, "flux": 1.0}
    model = difstar.ImageModel(builder, fixed, light=light, zernike=(4,), pad=8,
                               accuracy=1e-3)
    img = _image(model, (33, 33), z4=80.0)
    plain = _image(model, (33, 33), z4=0.0)
    # the same through the Python API: the pupil at pitch p, z from the pixel scale
    pitch = 1e-5
    z = pitch / (PIXEL_SCALE * math.pi / (180 * 3600))
    pupil = builder.build({})
    api = np.asarray(difstar.psf(pupil, wavelength=LAM, z_image=z, pixel_pitch=pitch,
                                 shape=(33 + 16, 33 + 16), accuracy=1e-3,
                                 wavefront=difstar.Zernike({4: 80e-9}, builder.max_radius)))
    api = api[8:-8, 8:-8]
    assert np.abs(img - plain).max() > 0.02 * plain.max()  # the term matters
    np.testing.assert_allclose(img, api, rtol=0, atol=3e-3 * plain.max())


def test_image_fit_manifest_on_a_fits_file_rows_up(tmp_path):
    """The whole boundary: a FITS file stores its first row at the BOTTOM. A star
    stored at FITS row 9 of 31 (0-based, counted up from the bottom; astropy's y) and
    column 20 is 31 − 1 − 9 = 21 rows from the top, so the manifest's y0 ("auto": the
    brightest pixels' centroid, data pixels down from the centre row 15) is +6 and x0
    is 20 − 15 = +5."""
    from astropy.io import fits

    h = w = 31
    stored = np.zeros((h, w))
    stored[9, 20] = 100.0
    stored[8:11, 19:22] += 10.0
    stored += 1.0
    fits.PrimaryHDU(stored).writeto(tmp_path / "star.fits")
    man = {"data": {"path": "star.fits", "sigma": 0.1},
           "pupil": {"builder": "circle", "radius": 0.425},
           "light": {"wavelength": LAM},
           "params": {"pixel_scale": PIXEL_SCALE, "obstruction": 0.1, "strut_width": 0.0,
                      "x0": {"value": "auto", "free": True, "bounds_about": [-2, 2]},
                      "y0": {"value": "auto", "free": True, "bounds_about": [-2, 2]}}}
    (tmp_path / "m.json").write_text(json.dumps(man))
    model, data, _ = difstar.load_fit_manifest(tmp_path / "m.json")
    assert abs(model.params["x0"].value - 5.0) < 0.05
    assert abs(model.params["y0"].value - 6.0) < 0.05
    # and the data difstar holds are the FITS rows reversed (astropy's reading)
    assert np.array_equal(np.asarray(data.image), fits.getdata(tmp_path / "star.fits")[::-1])


# ------------------------------------------------------------------ RAW-fit layer


def test_raw_fit_source_offset_is_row_col_pixels_rows_down():
    """A RAW-fit source offset (row, col) in pixels becomes an object-plane position
    (x, y up) such that the disc's image lands (row, col) pixels from the window's
    centre pixel: +row down, +col right."""
    from difstar import _fit as F

    cc = F.CameraConstants(
        focal_length=51.5e-3, principal_separation=-3e-3, pupil_magnification=1.0,
        pixel_pitch=3.917e-6, pattern="RGGB", wavelengths=(600e-9, 530e-9, 450e-9),
        n_blades=7)
    truth = {"circumradius": 51.5e-3 / 44, "rotation": 0.0, "source_radius": 0.2e-3,
             "source_offset/c": np.array([6.0, -4.0]), "phi0": np.full(3, 0.01),
             "toe": np.full(3, 0.02), "knee": np.full(3, 40.0), "defocus/c": 0.0}
    params = {k: F.Param(np.broadcast_to(v, F.param_shape(k, 7))) for k, v in truth.items()}
    grid = difstar.Grid(n=96, crop=(48, 48), use_defocus=False, raw_only=True)
    model = F.FitModel(cc, (F.ConfigSpec("c", 1.0, 1.0, grid),),
                       (F.CaptureSpec("a", "c", 0.1, (0.0, 0.0)),), params)
    camera, scene, _, _ = F.camera_scene(model, {k: jnp.asarray(v) for k, v in truth.items()},
                                         "c")
    m = difstar.geometry_of(camera, scene).magnification
    img = np.asarray(difstar.geometric_image(scene.sources, magnification=m,
                                             pixel_pitch=cc.pixel_pitch, shape=(48, 48)))[1]
    rows, cols = np.mgrid[:48, :48]
    r, c = np.sum(img * rows) / img.sum(), np.sum(img * cols) / img.sum()
    assert abs(r - (24 + 6.0)) < 0.05 and abs(c - (24 - 4.0)) < 0.05, (r, c)


# ------------------------------------------------------------------ FITS files


def test_fits_rows_up_round_trip(tmp_path):
    """FITS → read_image (rows reversed once: difstar's rows run down) → a window of
    it → write_fits_like (reversed back): astropy reads the written file as the
    original pixel for pixel inside the window, NaN outside, with the header's WCS kept;
    and without the flip on reading nothing is flipped on writing."""
    from astropy.io import fits

    from difstar.io import read_image
    from difstar.io._images import write_fits_like

    h, w = 12, 9
    stored = np.arange(h * w, dtype=float).reshape(h, w)
    hdr = fits.Header()
    hdr["CRPIX1"], hdr["CRPIX2"], hdr["CTYPE1"], hdr["CTYPE2"] = 3.0, 4.0, "RA---TAN", "DEC--TAN"
    src = tmp_path / "in.fits"
    fits.PrimaryHDU(stored, header=hdr).writeto(src)

    im = read_image(src)
    assert im.flipped
    assert np.array_equal(im.data[0], stored[-1])  # the top row is FITS's last (highest y)
    roi = (2, 7, 1, 6)  # rows 2..6, columns 1..5 as difstar holds them (rows down)
    window = im.data[roi[0]:roi[1], roi[2]:roi[3]]
    write_fits_like(tmp_path / "out.fits", window, source=src, roi=roi, flipped=im.flipped)
    back = fits.getdata(tmp_path / "out.fits")
    inside = np.zeros((h, w), bool)
    inside[h - roi[1]:h - roi[0], roi[2]:roi[3]] = True  # the same pixels, FITS rows up
    assert np.array_equal(back[inside], stored[inside])
    assert np.all(np.isnan(back[~inside]))
    out_hdr = fits.getheader(tmp_path / "out.fits")
    assert (out_hdr["CRPIX1"], out_hdr["CRPIX2"], out_hdr["CTYPE2"]) == (3.0, 4.0, "DEC--TAN")

    raw = read_image(src, flip_fits=False)
    write_fits_like(tmp_path / "raw.fits", raw.data, source=src, flipped=raw.flipped)
    assert np.array_equal(fits.getdata(tmp_path / "raw.fits"), stored)
