"""Area-coverage rasters against exact areas; gradients at edges and grid lines."""

import equinox as eqx
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


def test_vertices_that_are_not_numbers_are_a_clear_error():
    with pytest.raises(ValueError, match="Polygon.vertices must be an .n, 2. array of numbers"):
        difstar.Polygon("abc")
    # the message of difstar.psf, or the type checker's that the tests run under: both
    # name the parameter
    with pytest.raises(TypeError, match="pupil"):
        difstar.psf(None, wavelength=530e-9, z_image=0.05, pixel_pitch=3.9e-6, shape=(8, 8))


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_rotation_of_many_turns_keeps_the_polygon(dtype):
    """A rotation of many turns is the same polygon: its exact area (n/2) r² sin(2π/n)
    whatever the turns (1e12 rad in float32 gave every vertex one angle: zero area),
    and in float64 the vertices of 0.3 rad plus 10⁶ whole turns equal those of 0.3 rad."""
    from difstar.pupils._polygons import regular_polygon_vertices

    r, n, cell = 1.0, 7, 0.05
    x, y = _grid(64, cell)
    exact = 0.5 * n * r**2 * np.sin(2 * np.pi / n)
    for rot in (1e12, -3.7e5, 40.0):
        pup = difstar.RegularPolygon(n, jnp.asarray(r, dtype), jnp.asarray(rot, dtype))
        area = float(jnp.sum(pup.coverage(x, y, cell))) * cell**2
        assert area == pytest.approx(exact, rel=1e-5 if dtype == "float32" else 1e-12)
    if dtype == "float64":
        a = regular_polygon_vertices(n, 1.0, jnp.asarray(0.3, "float64"))
        b = regular_polygon_vertices(n, 1.0, jnp.asarray(0.3 + 2e6 * np.pi, "float64"))
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), atol=1e-9)


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


# --- tiled coverage: the same raster, its derivative from the outline only -------------


def _tiled_case(trial: int):
    """A perturbed polygon on an off-centre grid; odd trials have y descending (as on the
    frequency grid); trial 3 has an exactly vertical edge and a vertex on grid lines."""
    rng = np.random.default_rng(trial)
    h, w = 40, 48
    cell = 0.05 + 0.01 * trial
    xs = (np.arange(w) - w // 2 + 0.3 * trial) * cell
    ys = (np.arange(h) - h // 2) * cell * (-1 if trial % 2 else 1)
    n = 7 if trial < 4 else 12
    v = np.asarray(difstar.RegularPolygon(n, 0.8, 0.1 * trial).vertices)
    v = v + rng.normal(0, 0.05, (n, 2))
    if trial == 3:
        v[2, 0] = v[3, 0]
        v[1] = [xs[20] + 0.5 * cell, ys[10] + 0.5 * cell]
    return jnp.asarray(v), jnp.asarray(xs)[None, :], jnp.asarray(ys)[:, None], cell, rng


@pytest.mark.parametrize("trial", range(6))
def test_tiled_coverage_derivatives_equal_autodiff_of_green_terms(trial):
    # Truth: autodiff of the edge-by-edge Green's-theorem raster (outline_coverage), an
    # independent computation from the shape derivative on the outline's cell pieces.
    from difstar._pupil import outline_coverage, tiled_outline_coverage

    v, x, y, cell, rng = _tiled_case(trial)

    def of(fn):
        return lambda v, x, y, c: fn(v, jnp.roll(v, -1, axis=0), x, y, c)

    args = (v, x, y, jnp.asarray(cell))
    tangents = tuple(jnp.asarray(rng.normal(size=np.shape(a))) for a in args)
    # compiled, not op by op (the same numbers; a test run 5× shorter)
    out_t, jvp_t = jax.jit(lambda a, t: jax.jvp(of(tiled_outline_coverage), a, t))(args,
                                                                                  tangents)
    out_p, jvp_p = jax.jit(lambda a, t: jax.jvp(of(outline_coverage), a, t))(args, tangents)
    # the same Green's terms, summed in another order (the tiled raster: by cell pieces
    # and a cumulative sum over the rows): equal to float64 round-off
    np.testing.assert_allclose(out_t, out_p, rtol=0, atol=1e-13)
    scale = float(jnp.max(jnp.abs(jvp_p)))
    np.testing.assert_allclose(jvp_t, jvp_p, rtol=0, atol=1e-10 * scale)
    g = jnp.asarray(rng.normal(size=out_p.shape))
    grads = [jax.jit(jax.grad(lambda *a: jnp.sum(of(fn)(*a) * g), argnums=(0, 1, 2, 3)))(*args)
             for fn in (tiled_outline_coverage, outline_coverage)]
    for got, want in zip(*grads):
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-10 * float(jnp.max(jnp.abs(want))))


def _clipped_area(poly, x0, x1, y0, y1):
    """Area of a polygon clipped to the box [x0, x1] × [y0, y1] (Sutherland–Hodgman,
    then the shoelace formula): an independent truth for one cell's coverage."""
    pts = [tuple(p) for p in poly]
    for axis, bound, keep_above in ((0, x0, True), (0, x1, False), (1, y0, True),
                                    (1, y1, False)):
        out = []
        for i, cur in enumerate(pts):
            prev = pts[i - 1]
            cin = (cur[axis] >= bound) if keep_above else (cur[axis] <= bound)
            pin = (prev[axis] >= bound) if keep_above else (prev[axis] <= bound)
            if cin != pin:
                t = (bound - prev[axis]) / (cur[axis] - prev[axis])
                out.append(tuple(prev[k] + t * (cur[k] - prev[k]) for k in range(2)))
            if cin:
                out.append(cur)
        pts = out
        if not pts:
            return 0.0
    a = np.asarray(pts)
    return 0.5 * abs(np.sum(a[:, 0] * np.roll(a[:, 1], -1) - np.roll(a[:, 0], -1) * a[:, 1]))


@pytest.mark.parametrize("trial", [0, 1, 3])
def test_tiled_coverage_equals_clipped_areas(trial):
    # Truth: each cell's area inside the polygon by clipping the polygon to the cell
    # (Sutherland–Hodgman), on the perturbed polygons (convex or not) of _tiled_case, y
    # rising and falling, a vertical edge and a vertex on grid lines (trial 3).
    v, x, y, cell, _ = _tiled_case(trial)
    # compiled, the polygon made (and checked) outside and the cell a static number as
    # before: run op by op, the raster's many small operations took 6x as long
    tiled = eqx.filter_jit(lambda pupil, x, y, cell: pupil.tiled_coverage(x, y, cell))
    got = np.asarray(tiled(difstar.Polygon(v), x, y, cell))
    poly = np.asarray(v)
    want = np.array([[_clipped_area(poly, xc - cell / 2, xc + cell / 2, yc - cell / 2,
                                    yc + cell / 2) / cell**2
                      for xc in np.asarray(x).ravel()] for yc in np.asarray(y).ravel()])
    assert want.max() == pytest.approx(1.0) and want.min() == 0.0
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)


def test_tiled_coverage_gradient_matches_finite_differences():
    v, x, y, cell, rng = _tiled_case(4)
    g = jnp.asarray(rng.normal(size=(y.shape[0], x.shape[1])))
    f = lambda v, c: jnp.sum(difstar.Polygon(v).tiled_coverage(x * c, y * c, cell * c) * g)
    gv, gc = jax.jit(jax.grad(f, argnums=(0, 1)))(v, 1.0)
    f = jax.jit(f)  # the differences: compiled, not op by op
    eps = 1e-7
    for i, j in [(0, 0), (3, 1), (11, 0)]:
        dv = jnp.zeros_like(v).at[i, j].set(eps)
        fd = (f(v + dv, 1.0) - f(v - dv, 1.0)) / (2 * eps)
        assert float(gv[i, j]) == pytest.approx(float(fd), rel=1e-6, abs=1e-9)
    fd = (f(v, 1.0 + eps) - f(v, 1.0 - eps)) / (2 * eps)
    assert float(gc) == pytest.approx(float(fd), rel=1e-6)


def test_tiled_coverage_gradient_in_float32_on_a_large_grid():
    # On a 2000² grid of 1 µm cells 1 mm from the origin, float32 coordinates keep only
    # ~1e-4 cell of resolution: the grid's step must come from its ends, not from the
    # difference of two neighbours (which misplaces the far lines by a tenth of a cell).
    m, r = 2000, 0.9e-3
    cell = 2.2 * r / m
    g64 = jax.random.normal(jax.random.PRNGKey(0), (m, m), jnp.float32).astype(jnp.float64)

    def grad(dtype):
        x = ((jnp.arange(m) - m // 2) * cell)[None, :].astype(dtype)
        g = g64.astype(dtype)
        f = lambda p: jnp.sum(difstar.RegularPolygon(7, p[0], p[1]).tiled_coverage(
            x, -x.T, jnp.asarray(cell, dtype)) * g)
        return np.asarray(jax.jit(jax.grad(f))(jnp.asarray([r, 0.1], dtype)), np.float64)

    np.testing.assert_allclose(grad(jnp.float32), grad(jnp.float64), rtol=2e-3)


@pytest.mark.parametrize("descending", [False, True])
def test_tiled_coverage_on_a_plane_large_enough_for_the_parallel_scan(descending):
    # Planes of SCAN_CELLS or more take their cumulative sum by a parallel scan, and the
    # rows above a piece as the column's total less the rows below it. Truth: the
    # edge-by-edge Green's-theorem raster. The polygon overhangs the grid's top and
    # bottom (pieces off the grid reach every row or none; column totals are not 0).
    from difstar._pupil import outline_coverage
    from difstar.pupils._raster import SCAN_CELLS

    h, w = 520, 512
    assert h * w >= SCAN_CELLS
    cell = 2.0 / w
    xs = (np.arange(w) - w // 2 + 0.37) * cell
    ys = (np.arange(h) - h // 2 + 0.21) * cell * (-1 if descending else 1)
    rng = np.random.default_rng(5)
    v = np.asarray(difstar.RegularPolygon(9, 1.2, 0.3).vertices) * [0.7, 1.0]
    v = v + rng.normal(0, 0.02, v.shape)
    want = np.asarray(jax.jit(outline_coverage)(jnp.asarray(v), jnp.roll(jnp.asarray(v), -1, 0),
                                                jnp.asarray(xs)[None, :],
                                                jnp.asarray(ys)[:, None], cell))
    assert want[0].max() > 0.5 and want[-1].max() > 0.5  # it overhangs both ends
    # float32: its coordinates' round-off (the edge-by-edge raster in float32 is off by
    # up to 2.2e-5 here, the tiled one by 3.6e-5, with either cumulative sum)
    for dtype, atol in ((jnp.float64, 1e-12), (jnp.float32, 5e-5)):
        got = np.asarray(jax.jit(lambda v, x, y, c: difstar.Polygon(v).tiled_coverage(x, y, c))(
            jnp.asarray(v, dtype), jnp.asarray(xs, dtype)[None, :],
            jnp.asarray(ys, dtype)[:, None], jnp.asarray(cell, dtype)))
        np.testing.assert_allclose(got, want, rtol=0, atol=atol, err_msg=str(dtype))
