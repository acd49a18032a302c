"""Area-coverage rasters against exact areas; gradients at edges and grid lines."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import difstar
from difstar._pupil import halfplane_coverage


def _grid(n, cell):
    c = (jnp.arange(n) - n // 2) * cell
    return c[None, :], c[:, None]


@pytest.mark.parametrize("n_blades", [3, 5, 7, 9])
def test_polygon_coverage_area_exact(n_blades):
    r, cell = 1.0, 0.05
    pup = difstar.RegularPolygon(n_blades, r, 0.1234)
    x, y = _grid(64, cell)
    area = float(jnp.sum(pup.coverage(x, y, cell))) * cell**2
    exact = 0.5 * n_blades * r**2 * np.sin(2 * np.pi / n_blades)
    # Green's-theorem coverage is exact: only rounding remains
    assert area == pytest.approx(exact, rel=1e-12)


def test_circle_coverage_area():
    cell = 0.02
    x, y = _grid(128, cell)
    area = float(jnp.sum(difstar.Circle(1.0).coverage(x, y, cell))) * cell**2
    assert area == pytest.approx(np.pi, rel=5e-5)  # local straight-edge approximation


def test_halfplane_coverage_matches_brute_force():
    rng = np.random.default_rng(0)
    m = 400  # sub-samples per side for the brute-force truth
    sub = (np.arange(m) + 0.5) / m - 0.5
    sx, sy = np.meshgrid(sub, sub)
    for _ in range(20):
        th = rng.uniform(0, 2 * np.pi)
        s = rng.uniform(-0.8, 0.8)
        nx, ny = np.cos(th), np.sin(th)
        truth = np.mean(nx * sx + ny * sy <= s)
        got = float(halfplane_coverage(jnp.asarray(s), jnp.asarray(nx), jnp.asarray(ny), 1.0))
        assert got == pytest.approx(truth, abs=3e-3)  # brute force resolves 1/400


def test_gradient_wrt_vertex_on_grid_line_is_finite_and_matches_fd():
    cell = 0.1
    x, y = _grid(32, cell)
    base = np.array([[0.0, -1.0], [1.0, 0.0], [0.0, 1.0], [-1.0, 0.0]])  # vertices on lines

    def area(t):
        v = jnp.asarray(base).at[1, 0].set(t)
        return jnp.sum(difstar.Polygon(v).coverage(x, y, cell))

    g = jax.grad(area)(1.0)
    assert np.isfinite(g)
    eps = 1e-5
    fd = (area(1.0 + eps) - area(1.0 - eps)) / (2 * eps)
    assert float(g) == pytest.approx(float(fd), rel=1e-4)
    # the exact area derivative of this rhombus wrt the vertex x is 1 (height 2 / 2) / cell²
    assert float(g) * cell**2 == pytest.approx(1.0, rel=1e-9)


def test_rotation_and_radius_gradients_finite():
    cell = 0.05
    x, y = _grid(64, cell)
    f = lambda r, rot: jnp.sum(difstar.RegularPolygon(7, r, rot).coverage(x, y, cell) ** 2)
    gr, grot = jax.grad(f, argnums=(0, 1))(1.0, 0.0)
    assert np.isfinite(gr) and np.isfinite(grot)
    gc = jax.grad(lambda r: jnp.sum(difstar.Circle(r).coverage(x, y, cell)))(1.0)
    assert float(gc) * cell**2 == pytest.approx(2 * np.pi, rel=3e-3)  # d(πr²)/dr


def test_obstructed_and_spiders_area():
    cell = 0.01
    x, y = _grid(256, cell)
    p = difstar.Obstructed(difstar.Circle(1.0), difstar.Circle(0.3),
                           difstar.Spiders(4, 0.05, 0.0, 1.5))
    area = float(jnp.sum(p.coverage(x, y, cell))) * cell**2
    # annulus minus four vanes over r in [0.3, 1]; vanes overlap only inside the obstruction
    exact = np.pi * (1 - 0.09) - 4 * 0.05 * 0.7
    assert area == pytest.approx(exact, rel=2e-3)


def test_bad_pupils_are_clear_errors():
    with pytest.raises(ValueError, match="clockwise"):
        difstar.Polygon(np.array([[0, 0], [0, 1], [1, 1], [1, 0]], float))
    star = np.array([[np.cos(t), np.sin(t)] for t in np.pi / 2 + 4 * np.pi / 5 * np.arange(5)])
    with pytest.raises(ValueError, match="edges .* cross"):
        difstar.Polygon(star)  # a pentagram: self-intersecting


def test_nonconvex_polygon_area_exact():
    # an L shape, area 3, placed off-grid; Green's-theorem coverage is exact for it too
    v = np.array([[0, 0], [2, 0], [2, 1], [1, 1], [1, 2], [0, 2]], float) - 0.937
    cell = 0.07
    x, y = _grid(96, cell)
    area = float(jnp.sum(difstar.Polygon(v).coverage(x, y, cell))) * cell**2
    assert area == pytest.approx(3.0, rel=1e-12)
    with pytest.raises(ValueError, match=r"\(n, 2\)"):
        difstar.Polygon(np.zeros((4, 3)))
    with pytest.raises(ValueError, match="n must be an integer >= 3"):
        difstar.RegularPolygon(2, 1.0)
    with pytest.raises(ValueError, match="circumradius must be > 0"):
        difstar.RegularPolygon(6, -1.0)


def test_vertical_edge_keeps_its_gradient():
    # A 7-gon at rotation 0 has an exactly vertical edge (x = −r cos(π/7)); tilting it by
    # moving one of its vertices in x changes the area by (edge height)/2 per unit.
    cell = 0.05
    x, y = _grid(64, cell)
    v0 = np.asarray(difstar.RegularPolygon(7, 1.0, 0.0).vertices)
    k = 3  # vertex 3 → 4 is the vertical edge
    assert v0[k, 0] == pytest.approx(v0[k + 1, 0], abs=1e-12)

    def area(t):
        v = jnp.asarray(v0).at[k, 0].add(t)
        return jnp.sum(difstar.Polygon(v).coverage(x, y, cell)) * cell**2

    g = float(jax.grad(area)(0.0))
    # shoelace: ∂A/∂x_k = (y_{k+1} − y_{k−1}) / 2
    expect = 0.5 * (v0[k + 1, 1] - v0[k - 1, 1])
    assert g == pytest.approx(expect, rel=1e-9)
