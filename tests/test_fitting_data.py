"""FitData and Noise (difstar.fitting._data) refuse what cannot be fitted, naming the
field and what to give: each case below was once accepted silently (a complex image
lost its imaginary part, a negative pixel scale or read noise went on) or failed with
NumPy's own words (a ragged list, a σ or mask of another shape, a short roi)."""

from __future__ import annotations

import numpy as np
import pytest

from difstar.fitting import FitData, FitInputError, Noise

IMG = np.random.default_rng(0).normal(size=(32, 32)) + 10.0

CASES = [
    ("complex", lambda: FitData.from_array(IMG.astype(complex)), "complex numbers"),
    ("text", lambda: FitData.from_array([["a"] * 8] * 8), "real numbers"),
    ("ragged", lambda: FitData.from_array([[1, 2, 3], [1, 2]]), "ragged"),
    ("a mask as the image", lambda: FitData.from_array(IMG > 10), "mask="),
    ("σ of another shape", lambda: FitData.from_array(IMG, sigma=np.ones((3, 3))),
     r"sigma has shape \(3, 3\)"),
    ("mask of another shape", lambda: FitData.from_array(IMG, mask=np.ones((3, 3), bool)),
     r"mask has shape \(3, 3\)"),
    ("roi outside", lambda: FitData.from_array(IMG, roi=(40, 50, 0, 10)), "inside the 32"),
    ("roi reversed", lambda: FitData.from_array(IMG, roi=(20, 10, 0, 10)), "inside the 32"),
    ("roi of two numbers", lambda: FitData.from_array(IMG, roi=(0, 10)), "4 whole numbers"),
    ("roi of fractions", lambda: FitData.from_array(IMG, roi=(0.5, 10, 0, 10)),
     "4 whole numbers"),
    ("negative pixel scale", lambda: FitData.from_array(IMG, pixel_scale=-1), "pixel_scale"),
    ("NaN pixel scale", lambda: FitData.from_array(IMG, pixel_scale=float("nan")),
     "pixel_scale"),
    ("exposure as text", lambda: FitData.from_array(IMG, exposure="x"), "exposure"),
    ("saturation as text", lambda: FitData.from_array(IMG, saturation="x"), "saturation"),
    ("an image of zeros", lambda: FitData.from_array(np.zeros((32, 32))), "0 on every used"),
    ("negative read noise", lambda: Noise(read=-1.0), "Noise.read"),
    ("zero gain", lambda: Noise(read=1.0, gain=0.0), "Noise.gain"),
    ("NaN floor", lambda: Noise(floor=float("nan")), "Noise.floor"),
]


@pytest.mark.parametrize("make,match", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_what_cannot_be_fitted_is_refused_by_name(make, match):
    with pytest.raises(FitInputError, match=match):
        make()


def test_what_can_be_fitted_is_kept():
    """The checks let through what was fitted before: an integer image, a roi of whole
    numbers given as floats, a scalar σ, no shot noise (gain inf, as the noise estimated
    from residuals may find) — and never change the caller's arrays."""
    img = np.arange(64 * 64).reshape(64, 64) % 97 + 1
    before = img.copy()
    d = FitData.from_array(img, roi=(8.0, 40, 4, 36), sigma=2.0, pixel_scale=0.03)
    assert d.image.shape == (32, 32) and np.all(d.sigma == 2.0)
    assert np.array_equal(img, before)
    assert Noise(None, float("inf"), 0.0).gain == float("inf")
    sig = np.full(img.shape, 3.0)
    d = FitData.from_array(img, sigma=sig, roi=(0, 16, 0, 16))
    assert d.sigma.shape == (16, 16)
