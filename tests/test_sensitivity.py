"""Spectral sensitivities → white balance, camera→sRGB matrix, peak wavelengths.

Independent truths: colour-science's own copy of the same NPL measurement
("Nikon 5100 (NPL)"), and colour-science's spectral rendering of a colour checker."""

import json
from pathlib import Path

import colour
import numpy as np
import pytest

from difstar.io._sensitivity import (
    camera_to_srgb_matrix_from_sensitivities,
    load_spectral_sensitivity,
    peak_wavelengths,
    white_balance_from_sensitivities,
)

PATH = "/work/shared/data/raw/spectral_sensitivity/Nikon_D5100_380_780_5.json"


@pytest.fixture(scope="module")
def sens():
    return load_spectral_sensitivity(PATH)


@pytest.fixture(scope="module")
def matrix_d65(sens):
    return camera_to_srgb_matrix_from_sensitivities(sens, illuminant="D65")


def test_load_matches_colours_copy(sens):
    assert sens.name == "Nikon D5100"
    assert sens.shape == colour.SpectralShape(380, 780, 5)
    ref = colour.MSDS_CAMERA_SENSITIVITIES["Nikon 5100 (NPL)"].copy().align(sens.shape)
    # same NPL data, stored with different rounding
    np.testing.assert_allclose(sens.values, ref.values, rtol=0, atol=1e-8)


def test_peak_wavelengths(sens):
    r, g, b = peak_wavelengths(sens)
    assert 580e-9 <= r <= 620e-9
    assert 510e-9 <= g <= 550e-9
    assert 440e-9 <= b <= 470e-9


def _camera_rgb(sens, sd_values):
    return sd_values @ sens.values


@pytest.mark.parametrize("illuminant", ["D65", "E"])
def test_illuminant_renders_neutral(sens, matrix_d65, illuminant):
    m = camera_to_srgb_matrix_from_sensitivities(sens, illuminant=illuminant)
    if illuminant == "D65":  # the default
        np.testing.assert_array_equal(m, matrix_d65)
    gains = white_balance_from_sensitivities(sens, illuminant=illuminant)
    assert gains[1] == 1.0 and np.all(gains > 0)
    sd = colour.SDS_ILLUMINANTS[illuminant].copy().align(sens.shape).values
    srgb = m @ (gains * _camera_rgb(sens, sd))
    # R ≈ G ≈ B within 1 % (observed: 2e-4, the sRGB standard's matrix rounding)
    np.testing.assert_allclose(srgb / srgb.mean(), 1.0, rtol=0, atol=1e-2)
    np.testing.assert_allclose(m.sum(axis=1), 1.0, rtol=0, atol=1e-3)  # white → white


def test_colour_checker_accuracy(sens, matrix_d65):
    """24 ColorChecker patches under D65: camera RGB → matrix vs colour-science's
    spectral → XYZ → linear sRGB. A 3×3 matrix cannot be exact (the camera is not
    colorimetric): mean CIEDE2000 < 4 and max < 10 (observed about 2.4 and 6.6)."""
    gains = white_balance_from_sensitivities(sens)
    ill = colour.SDS_ILLUMINANTS["D65"].copy().align(sens.shape).values
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"].copy().align(sens.shape)
    refl = np.array([sd.copy().align(sens.shape).values
                     for sd in colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"].values()])
    cam = _camera_rgb(sens, refl * ill) * gains / (gains * _camera_rgb(sens, ill))[1]
    pred = cam @ matrix_d65.T
    xyz = (refl * ill) @ cmfs.values / (ill @ cmfs.values[:, 1])
    space = colour.RGB_COLOURSPACES["sRGB"]
    ref = xyz @ np.asarray(space.matrix_XYZ_to_RGB).T

    def lab(rgb):
        return colour.XYZ_to_Lab(colour.RGB_to_XYZ(rgb, space), space.whitepoint)

    de = colour.delta_E(lab(pred), lab(ref), method="CIE 2000")
    assert de.mean() < 4.0 and de.max() < 10.0


def test_bad_files(tmp_path, sens):
    with pytest.raises(FileNotFoundError, match="nope.json"):
        load_spectral_sensitivity(tmp_path / "nope.json")
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(ValueError, match=r"bad\.json.*cannot parse JSON"):
        load_spectral_sensitivity(bad)
    doc = json.loads(Path(PATH).read_text())

    def with_data(main):
        return {**doc, "spectral_data": {**doc["spectral_data"], "data": {"main": main}}}

    cases = {
        "nokeys.json": ({"header": {}}, "expected keys"),
        "channels.json": ({**doc, "spectral_data": {**doc["spectral_data"],
                                                    "index": {"main": ["G", "R", "B"]}}},
                          "index.main must be"),
        "values.json": (with_data({"380": [1, 2], "385": [1, 2]}), "exactly 3 values"),
        "text.json": (with_data({"380": ["x", 1, 2], "385": [1, 2, 3]}), "must be numbers"),
        "uneven.json": (with_data({"380": [1, 2, 3], "385": [1, 2, 3], "395": [1, 2, 3]}),
                        "evenly spaced"),
    }
    for name, (content, msg) in cases.items():
        p = tmp_path / name
        p.write_text(json.dumps(content))
        with pytest.raises(ValueError, match=f"{name}.*{msg}"):
            load_spectral_sensitivity(p)
    with pytest.raises(ValueError, match="illuminant 'D99'"):
        white_balance_from_sensitivities(sens, illuminant="D99")
