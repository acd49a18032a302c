"""CurvedIris: reduction to the straight polygon, exact area, circle limit, gradients."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from difstar._pupil import Polygon, RegularPolygon, polygon_coverage
from difstar._pupil_curved import CurvedIris, curved_iris_from_area, segment_area

R = 1.0
N = 96
CELL = 2.3 * R / N


def _grid(n=N, cell=CELL):
    x = ((jnp.arange(n) - n // 2) * cell)[None, :]
    y = (-(jnp.arange(n) - n // 2) * cell)[:, None]
    return x, y


def _inside_true_shape(iris: CurvedIris, px: np.ndarray, py: np.ndarray) -> np.ndarray:
    """Point-in-shape for the exact arcs (convex polygon with outward circular segments),
    NumPy, independent of the rasteriser."""
    v = np.asarray(iris.vertices)
    w = np.roll(v, -1, axis=0)
    kappa = np.asarray(iris.curvature) / float(iris.circumradius)
    inside_poly = np.ones(px.shape, bool)
    in_segment = np.zeros(px.shape, bool)
    for k in range(len(v)):
        d = w[k] - v[k]
        length = np.hypot(*d)
        nx, ny = d[1] / length, -d[0] / length
        beyond = (px - v[k, 0]) * nx + (py - v[k, 1]) * ny  # > 0 outside the chord
        inside_poly &= beyond <= 0
        if kappa[k] > 0:
            rho = 1 / kappa[k]
            h = math.sqrt(rho * rho - length * length / 4)
            cx, cy = (v[k] + w[k]) / 2 - h * np.array([nx, ny])
            in_segment |= (beyond > 0) & ((px - cx) ** 2 + (py - cy) ** 2 <= rho * rho)
    return inside_poly | in_segment


def _brute_coverage(iris, n=N, cell=CELL, sub=16):
    off = (np.arange(sub) - (sub - 1) / 2) * cell / sub
    xc = (np.arange(n) - n // 2) * cell
    yc = -(np.arange(n) - n // 2) * cell
    px = (xc[None, :, None, None] + off[None, None, None, :]).repeat(n, 0).repeat(sub, 2)
    py = (yc[:, None, None, None] + off[None, None, :, None]).repeat(n, 1).repeat(sub, 3)
    return _inside_true_shape(iris, px, py).mean(axis=(2, 3))


@pytest.mark.parametrize("n", [7, 9])
def test_curvature_zero_is_the_straight_polygon(n):
    x, y = _grid()
    got = CurvedIris(n, R, 0.0, rotation=0.3).coverage(x, y, CELL)
    want = jax.jit(lambda: RegularPolygon(n, R, 0.3).coverage(x, y, CELL))()
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)  # rounding only
    rng = np.random.default_rng(1)
    rad = 0.05 * rng.standard_normal(n)
    ang = 0.05 * rng.standard_normal(n)
    iris = CurvedIris(n, R, 0.0, radial=rad, angular=ang, rotation=0.3)
    poly = Polygon(np.asarray(iris.vertices))
    want = jax.jit(lambda p: p.coverage(x, y, CELL))(poly)
    np.testing.assert_allclose(iris.coverage(x, y, CELL), want, rtol=0, atol=1e-12)
    np.testing.assert_allclose(float(iris.area()), float(want.sum()) * CELL**2, rtol=1e-12)


@pytest.mark.parametrize("curvature", [0.2, 0.6, 1.0, -0.3])
def test_area_exact_and_against_brute_force(curvature):
    x, y = _grid()
    rng = np.random.default_rng(2)
    iris = CurvedIris(7, R, curvature, radial=0.02 * rng.standard_normal(7),
                      angular=0.02 * rng.standard_normal(7), rotation=0.1)
    cov = iris.coverage(x, y, CELL)
    # The rasterised outline has the analytic area exactly (area-matched arc samples).
    np.testing.assert_allclose(float(cov.sum()) * CELL**2, float(iris.area()), rtol=1e-10)
    if curvature > 0:  # the brute-force point test handles outward arcs
        brute = _brute_coverage(iris)
        # 16 x 16 points per cell: area to ~1e-4, per-cell to a few 1/16 on the edge
        np.testing.assert_allclose(brute.sum() * CELL**2, float(iris.area()), rtol=5e-4)
        assert np.max(np.abs(brute - np.asarray(cov))) < 0.1
        assert np.mean(np.abs(brute - np.asarray(cov))) < 2e-3


def test_segment_area_against_quadrature():
    from scipy.integrate import quad

    for chord, alpha in ((1.0, 0.05), (0.7, 0.8), (2.0, -0.4)):
        rho = chord / (2 * math.sin(alpha))
        h = math.sqrt(rho * rho - chord * chord / 4)
        val, _ = quad(lambda t: math.sqrt(rho * rho - t * t) - h, -chord / 2, chord / 2)
        val = math.copysign(val, alpha)  # rho < 0 for inward arcs: same magnitude
        np.testing.assert_allclose(float(segment_area(jnp.asarray(chord), jnp.asarray(alpha))),
                                   val, rtol=1e-9, atol=1e-18)
    # near straight: the parabola's area L² α / 6, smoothly through α = 0
    for alpha in (1e-9, 0.0, -1e-9):
        np.testing.assert_allclose(float(segment_area(jnp.asarray(1.0), jnp.asarray(alpha))),
                                   alpha / 6, rtol=1e-12, atol=1e-300)
    g = jax.grad(lambda a: segment_area(jnp.asarray(1.0), a))(0.0)
    np.testing.assert_allclose(float(g), 1 / 6, rtol=1e-12)


def test_circle_limit():
    iris = CurvedIris(9, R, 1.0, rotation=0.2)
    np.testing.assert_allclose(float(iris.area()), math.pi * R * R, rtol=1e-12)
    pts = np.asarray(iris.outline())
    r = np.hypot(pts[:, 0], pts[:, 1])
    # samples lie within ρ (α/m)² of the circle (docstring), α = π/9, m = 16
    assert np.max(np.abs(r - R)) < (math.pi / 9 / 16) ** 2 * R
    x, y = _grid()
    brute = _brute_coverage(iris)
    assert np.max(np.abs(brute - np.asarray(iris.coverage(x, y, CELL)))) < 0.1
    assert float(iris.convexity_margin()) == pytest.approx(0.0, abs=1e-9)


def test_from_area_is_exact():
    a = 3e-5
    for c in (0.0, 0.4, 0.9):
        iris = curved_iris_from_area(9, a, c, radial=0.01, angular=0.01)
        np.testing.assert_allclose(float(iris.area()), a, rtol=1e-13)


def test_convexity_margin_and_checks():
    assert float(CurvedIris(7, R, 0.5).convexity_margin()) > 0
    assert float(CurvedIris(7, R, -0.1).convexity_margin()) < 0
    with pytest.raises(ValueError, match="half circle"):
        CurvedIris(3, R, 2.0)
    with pytest.raises(ValueError, match="one value per blade"):
        CurvedIris(7, R, np.zeros(5))
    with pytest.raises(ValueError, match="circumradius"):
        CurvedIris(7, -1.0)


def _loss(c, rad, ang, rot):
    x, y = _grid(48, 2.3 * R / 48)
    iris = CurvedIris(7, R, c, radial=rad, angular=ang, rotation=rot)
    cov = iris.coverage(x, y, 2.3 * R / 48)
    w = jnp.cos(3 * x) * jnp.sin(2 * y + 0.3)  # a smooth, non-symmetric weighting
    return jnp.sum(cov * cov * (1 + w))


@pytest.mark.parametrize("c0", [0.0, 0.4])
def test_gradients_finite_and_match_finite_differences(c0):
    rng = np.random.default_rng(3)
    rad = jnp.asarray(0.03 * rng.standard_normal(7))
    ang = jnp.asarray(0.03 * rng.standard_normal(7))
    rot = jnp.asarray(0.15)
    grads = jax.jit(jax.grad(_loss, argnums=(0, 1, 2, 3)))(jnp.asarray(c0), rad, ang, rot)
    for g in grads:
        assert np.all(np.isfinite(np.asarray(g)))
    eps = 1e-6
    _loss_j = jax.jit(_loss)
    fd_c = (_loss_j(c0 + eps, rad, ang, rot) - _loss_j(c0 - eps, rad, ang, rot)) / (2 * eps)
    np.testing.assert_allclose(float(grads[0]), float(fd_c), rtol=1e-4)
    e = jnp.zeros(7).at[2].set(eps)
    fd_r = (_loss_j(c0, rad + e, ang, rot) - _loss_j(c0, rad - e, ang, rot)) / (2 * eps)
    np.testing.assert_allclose(float(grads[1][2]), float(fd_r), rtol=1e-4)
    fd_a = (_loss_j(c0, rad, ang + e, rot) - _loss_j(c0, rad, ang - e, rot)) / (2 * eps)
    np.testing.assert_allclose(float(grads[2][2]), float(fd_a), rtol=1e-4)


def test_area_gradient_with_a_vertical_edge():
    # 9-gon at rotation 0: edge 4 → 5 is exactly vertical. The raster's area must still
    # respond to each vertex equally (d area / d radial_k = R² sin(2π/n) for all k).
    x, y = _grid(48, 2.3 * R / 48)
    g = jax.jit(jax.grad(lambda r: CurvedIris(9, R, 0.0, radial=r).coverage(
        x, y, 2.3 * R / 48).sum() * (2.3 * R / 48) ** 2))(jnp.zeros(9))
    np.testing.assert_allclose(np.asarray(g), math.sin(2 * math.pi / 9), rtol=1e-9)
    # The area's analytic gradient agrees.
    ga = jax.grad(lambda r: CurvedIris(9, R, 0.0, radial=r).area())(jnp.zeros(9))
    np.testing.assert_allclose(np.asarray(ga), math.sin(2 * math.pi / 9), rtol=1e-12)


def test_jit_equals_no_jit():
    x, y = _grid(64, 2.3 * R / 64)

    def f(c, rad):
        return CurvedIris(9, R, c, radial=rad, rotation=0.05).coverage(x, y, 2.3 * R / 64)

    rad = jnp.linspace(-0.02, 0.02, 9)
    np.testing.assert_allclose(jax.jit(f)(0.7, rad), f(0.7, rad), rtol=0, atol=1e-13)


def test_outline_coverage_matches_polygon_coverage():
    # the scan over edge terms is the core's polygon coverage, edge by edge
    x, y = _grid(40, 0.06)
    v = jnp.asarray([[0.3, -0.7], [0.9, 0.1], [0.2, 0.8], [-0.8, 0.35], [-0.5, -0.6]])
    from difstar._pupil_curved import outline_coverage

    got = outline_coverage(v, jnp.roll(v, -1, axis=0), x, y, 0.06)
    np.testing.assert_allclose(got, polygon_coverage(v, x, y, 0.06), rtol=0, atol=1e-13)


def test_tiled_coverage_of_curved_iris_and_obstructed_pupil_matches_plain():
    # The tiled raster's shape derivative against autodiff of the plain raster (float64),
    # for a many-edged outline and for an outline under a central obstruction.
    from difstar._pupil import Circle, Obstructed

    x, y = _grid()
    g = jax.random.normal(jax.random.PRNGKey(1), (N, N), jnp.float64)

    def grads(method):
        def f(p):
            iris = CurvedIris(9, p[0], p[1], rotation=p[2])
            pupils = (iris, Obstructed(RegularPolygon(6, p[0], p[2]), Circle(0.3 * p[0])))
            return sum(jnp.sum(getattr(q, method)(x, y, CELL) * g) for q in pupils)

        p = jnp.asarray([R, 0.15, 0.05])
        return jax.jit(jax.value_and_grad(f))(p)  # compiled: not op by op

    v_t, g_t = grads("tiled_coverage")
    v_p, g_p = grads("coverage")
    assert float(v_t) == pytest.approx(float(v_p), rel=1e-12)
    np.testing.assert_allclose(g_t, g_p, rtol=1e-9)
