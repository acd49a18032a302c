"""Pupil polygon from a (synthetic) photo of the aperture, scikit-image based."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage
from skimage.draw import polygon as draw_polygon

from difstar.io._pupil_photo import PupilPhotoError, estimate_pupil_polygon

SHAPE = (200, 220)
CENTRE = (97.3, 112.6)  # (row, col) of the polygon's centre, px


def render(n, radius, rotation, *, blur=1.2, noise=0.02, seed=0, bright=True, ss=4):
    """Photo of a regular n-gon: circumradius ``radius`` px, first vertex at angle
    ``rotation`` (x right, y up), drawn with skimage.draw.polygon on a ss× supersampled
    grid, box-averaged to pixels, Gaussian-blurred (σ = blur px), plus Gaussian noise.
    Returns the image and the true vertices (n, 2) in px about the centre (x, y up)."""
    h, w = SHAPE
    th = rotation + 2 * np.pi * np.arange(n) / n
    x, y = radius * np.cos(th), radius * np.sin(th)
    rows, cols = CENTRE[0] - y, CENTRE[1] + x
    big = np.zeros((h * ss, w * ss))
    # sub-pixel centres: pixel r spans [r − ½, r + ½]; sub-pixel j centre at (r+½)·ss − ½
    rr, cc = draw_polygon((rows + 0.5) * ss - 0.5, (cols + 0.5) * ss - 0.5, big.shape)
    big[rr, cc] = 1.0
    img = ndimage.gaussian_filter(big.reshape(h, ss, w, ss).mean(axis=(1, 3)), blur)
    img = 0.1 + 0.8 * img + noise * np.random.default_rng(seed).standard_normal(img.shape)
    return (img if bright else 1.0 - img), np.stack([x, y], axis=1)


def _rot_err_deg(est, true, n):
    """Rotation difference modulo the polygon's symmetry 2π/n, in degrees."""
    return abs(np.degrees(np.angle(np.exp(1j * n * (est - true))) / n))


def _max_vertex_err(est, true):
    d = np.hypot(*(est[:, None, :] - true[None, :, :]).transpose(2, 0, 1))
    return d.min(axis=1).max()


def _signed_area(v):
    x, y = v[:, 0], v[:, 1]
    return 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)


def test_seven_blades_known_count_accuracy():
    n, radius, rot = 7, 80.0, 0.37
    img, true = render(n, radius, rot)
    pix = 3.9e-6  # m/pixel
    p = estimate_pupil_polygon(img, n_blades=n, pixel_size=pix)
    assert p.n_blades == 7 and not p.n_blades_inferred
    assert p.vertices.shape == (7, 2)
    assert abs(p.circumradius / (radius * pix) - 1) < 0.005  # 0.5 %
    assert _rot_err_deg(p.rotation, rot, n) < 0.2  # degrees; y up (a flip would give −rot)
    assert 0 <= p.rotation < 2 * np.pi / n
    assert _max_vertex_err(p.vertices / pix, true) < 0.3  # px
    assert _signed_area(p.vertices) > 0  # counter-clockwise
    # first vertex at the angle ``rotation``; origin at the centroid
    first = np.arctan2(p.vertices[0, 1], p.vertices[0, 0])
    assert abs(np.angle(np.exp(1j * (first - p.rotation)))) < np.radians(0.5)
    assert np.hypot(*p.vertices.mean(axis=0)) < 0.05 * pix
    assert np.hypot(p.centroid_px[0] - CENTRE[0], p.centroid_px[1] - CENTRE[1]) < 0.1
    assert p.residual_rms_px < 0.2


@pytest.mark.parametrize("n", [5, 6, 7, 8, 9])
def test_blade_count_inferred(n):
    rot = 0.1 + 0.13 * n
    img, true = render(n, 70.0, rot, blur=1.5, noise=0.03, seed=n)
    p = estimate_pupil_polygon(img)
    assert p.n_blades == n and p.n_blades_inferred
    assert abs(p.circumradius / 70.0 - 1) < 0.005
    assert _rot_err_deg(p.rotation, rot, n) < 0.2
    # more blur and noise than above, shorter sides for large n: noise-limited ~0.35 px
    assert _max_vertex_err(p.vertices, true) < 0.4


def test_dark_aperture_on_bright_background():
    img, true = render(6, 60.0, 0.2, bright=False, seed=3)
    p = estimate_pupil_polygon(img)
    assert p.n_blades == 6
    assert abs(p.circumradius / 60.0 - 1) < 0.005
    assert _max_vertex_err(p.vertices, true) < 0.3


def test_errors():
    with pytest.raises(PupilPhotoError, match="uniform"):
        estimate_pupil_polygon(np.ones((50, 50)))
    touching = np.zeros((60, 60))
    touching[:40, :40] = 1.0
    with pytest.raises(PupilPhotoError, match="no aperture found"):
        estimate_pupil_polygon(touching)
    with pytest.raises(PupilPhotoError, match="no polygonal aperture"):
        estimate_pupil_polygon(np.random.default_rng(0).random((60, 60)))
    img, _ = render(7, 50.0, 0.0)
    with pytest.raises(PupilPhotoError, match="n_blades"):
        estimate_pupil_polygon(img, n_blades=2)
    with pytest.raises(PupilPhotoError, match="2-D"):
        estimate_pupil_polygon(np.ones(10))
    assert issubclass(PupilPhotoError, ValueError)
