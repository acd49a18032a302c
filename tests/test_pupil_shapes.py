"""Unions of polygons, hexagonal segments, struts, rotated/shifted pupils and masks:
coverage sums against analytic areas, gradients against finite differences (float64)."""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import difstar
from difstar import Mask, Obstructed, Polygon, RegularPolygon, Struts, Transformed, Union


def _grid(n, cell, x0=0.0, y0=0.0):
    c = (jnp.arange(n) - n // 2) * cell
    return (c + x0)[None, :], (c + y0)[:, None]


def _square(x0, y0, side):
    return np.array([[x0, y0], [x0 + side, y0], [x0 + side, y0 + side], [x0, y0 + side]])


# --- hexagons, unions, segments ------------------------------------------------------


def test_hexagon_coverage_is_its_analytic_area():
    s = 0.7  # side = circumradius
    cell = 0.031
    x, y = _grid(64, cell, 0.013, -0.007)
    hexagon = Polygon(np.asarray(RegularPolygon(6, s, 0.21).vertices) + [0.05, -0.03])
    area = float(jnp.sum(hexagon.coverage(x, y, cell))) * cell**2
    assert area == pytest.approx(1.5 * math.sqrt(3) * s * s, rel=1e-12)


def test_jwst_like_segments_union_is_the_sum_of_its_segments():
    f2f, gap = 1.32, 0.007
    u = difstar.hex_segments(2, f2f, gap, rotation=0.1, centre=(0.02, -0.03))
    assert isinstance(u, Union) and len(u.members) == 18
    s = f2f / math.sqrt(3)
    seg_area = 1.5 * math.sqrt(3) * s * s
    cell = 0.06
    x, y = _grid(128, cell)
    cov = u.coverage(x, y, cell)
    assert float(jnp.sum(cov)) * cell**2 == pytest.approx(18 * seg_area, rel=1e-12)
    assert float(u.area()) == pytest.approx(18 * seg_area, rel=1e-12)
    # the union's single scan over all edges equals the sum of the members' rasters
    each = sum(m.coverage(x, y, cell) for m in u.members)
    np.testing.assert_allclose(cov, each, rtol=0, atol=1e-13)
    assert float(jnp.max(cov)) <= 1 + 1e-12 and float(jnp.min(cov)) >= -1e-12
    # every segment is counter-clockwise, centres one pitch from their nearest neighbour
    for m in u.members:
        assert float(m.area()) == pytest.approx(seg_area, rel=1e-12)
    c = np.asarray(difstar.hex_segment_centres(2, f2f + gap, rotation=0.1, centre=(0.02, -0.03)))
    d = np.hypot(*(c[:, None, :] - c[None, :, :]).T)
    np.fill_diagonal(d, np.inf)
    np.testing.assert_allclose(d.min(axis=1), f2f + gap, rtol=1e-12)
    assert np.ptp(np.hypot(*(c[:6] - [0.02, -0.03]).T)) < 1e-12  # ring 1 first
    # the outer segments reach 2 pitches + a circumradius ... along a corner direction
    assert float(u.max_radius()) == pytest.approx(
        float(np.max(np.hypot(*(np.concatenate([np.asarray(m.vertices) for m in u.members])
                                 ).T))), rel=1e-12)


def test_hex_segments_options_and_errors():
    assert len(difstar.hex_segments(2, 1.0, 0.01, include_centre=True).members) == 19
    assert len(difstar.hex_segments(0, 1.0, 0.0, include_centre=True).members) == 1
    u = difstar.hex_segments(2, 1.0, 0.01, missing=(0, 17))
    assert len(u.members) == 16
    full = np.asarray(difstar.hex_segment_centres(2, 1.01))
    kept = np.stack([np.mean(np.asarray(m.vertices), axis=0) for m in u.members])
    np.testing.assert_allclose(kept, full[1:17], atol=1e-12)
    with pytest.raises(ValueError, match="gap must be >= 0"):
        difstar.hex_segments(2, 1.0, -0.1)
    with pytest.raises(ValueError, match="flat_to_flat must be > 0"):
        difstar.hex_segments(2, 0.0, 0.1)
    with pytest.raises(ValueError, match=r"missing indices must be in \[0, 18\)"):
        difstar.hex_segments(2, 1.0, 0.1, missing=(18,))
    with pytest.raises(ValueError, match="rings must be an integer >= 1"):
        difstar.hex_segments(0, 1.0, 0.1)


def test_union_refuses_overlapping_members_and_accepts_touching_ones():
    a = Polygon(_square(0, 0, 1))
    Union([a, Polygon(_square(1, 0, 1)), Polygon(_square(0, 1, 1))])  # touching: fine
    with pytest.raises(ValueError, match="members 0 and 1 overlap"):
        Union([a, Polygon(_square(0.5, 0.5, 1))])
    with pytest.raises(ValueError, match="overlap"):
        Union([a, Polygon(_square(0, 0, 1))])  # identical
    with pytest.raises(ValueError, match="overlap"):
        Union([a, Polygon(_square(0.25, 0.25, 0.5))])  # one inside the other
    ell = Polygon(np.array([[0, 0], [2, 0], [2, 1], [1, 1], [1, 2], [0, 2]], float))
    Union([ell, Polygon(_square(1, 1, 1))])  # fills the L's notch: touching, non-convex
    with pytest.raises(ValueError, match="overlap"):
        Union([ell, Polygon(_square(0.9, 0.9, 1))])
    with pytest.raises(ValueError, match="overlap"):  # overlapping hexagons (gap < 0)
        Union([Polygon(c + np.asarray(RegularPolygon(6, 0.6, 0.0).vertices))
               for c in np.asarray(difstar.hex_segment_centres(1, 1.0))])
    Union([a, Polygon(_square(0.5, 0.5, 1))], check_overlap=False)
    with pytest.raises(TypeError, match="difstar pupils"):
        Union([a, "square"])
    # nested unions flatten; mixed members (a circle) add their own coverage
    u = Union([Union([a]), difstar.Circle(0.3, (-1.0, -1.0))])
    assert len(u.members) == 2 and u.outline_edges() is None
    cell = 0.02
    x, y = _grid(200, cell)
    area = float(jnp.sum(u.coverage(x, y, cell))) * cell**2
    assert area == pytest.approx(1 + math.pi * 0.09, rel=1e-3)


def test_union_gradients_finite_and_match_finite_differences():
    cell = 0.08
    x, y = _grid(48, cell)
    g = jax.random.normal(jax.random.PRNGKey(0), (48, 48), jnp.float64)

    def f(p):  # f2f, gap, rotation, centre x
        u = difstar.hex_segments(1, p[0], p[1], p[2], (p[3], 0.01), include_centre=True)
        return jnp.sum(u.coverage(x, y, cell) * g)

    p = jnp.asarray([0.9, 0.05, 0.13, 0.02])
    gr = jax.jit(jax.grad(f))(p)
    f = jax.jit(f)
    assert np.all(np.isfinite(gr))
    jf = jax.jacfwd(f)(p)
    np.testing.assert_allclose(jf, gr, rtol=1e-9)
    eps = 1e-6
    for i in range(4):
        dp = jnp.zeros(4).at[i].set(eps)
        fd = (f(p + dp) - f(p - dp)) / (2 * eps)
        assert float(gr[i]) == pytest.approx(float(fd), rel=1e-5, abs=1e-8)
    # with respect to the vertices of a union's member directly
    va = jnp.asarray(_square(-0.9, -0.5, 0.8))

    def fv(v):
        return jnp.sum(Union([Polygon(v), Polygon(_square(0.1, -0.5, 0.8))],
                             check_overlap=False).coverage(x, y, cell) * g)

    gv = jax.grad(fv)(va)
    assert np.all(np.isfinite(gv))
    fv = jax.jit(fv)
    dv = jnp.zeros_like(va).at[2, 1].set(eps)
    assert float(gv[2, 1]) == pytest.approx(float((fv(va + dv) - fv(va - dv)) / (2 * eps)),
                                            rel=1e-5)


def test_union_tiled_coverage_derivative_equals_autodiff():
    cell = 0.07
    x, y = _grid(48, cell, 0.011, 0.0)
    y = -y  # descending, as on the frequency grid
    g = jax.random.normal(jax.random.PRNGKey(2), (48, 48), jnp.float64)

    def f(p, method):
        u = difstar.hex_segments(1, p[0], p[1], p[2])
        pupil = Obstructed(u, difstar.Circle(0.3), Struts(p[3:6], p[6], offsets=0.02))
        return jnp.sum(getattr(pupil, method)(x, y, cell) * g)

    p = jnp.asarray([0.7, 0.03, 0.05, 0.3, 2.4, 4.5, 0.04])
    vt, gt = jax.jit(jax.value_and_grad(lambda p: f(p, "tiled_coverage")))(p)
    vp, gp = jax.jit(jax.value_and_grad(lambda p: f(p, "coverage")))(p)
    assert float(vt) == pytest.approx(float(vp), rel=1e-12)
    np.testing.assert_allclose(gt, gp, rtol=1e-8, atol=1e-10 * float(jnp.max(jnp.abs(gp))))


# --- struts --------------------------------------------------------------------------


def test_strut_areas_are_width_times_length():
    cell = 0.025
    x, y = _grid(160, cell, 0.0031, -0.0017)
    widths = np.array([0.05, 0.08, 0.031])
    lengths = np.array([1.2, 0.9, 1.4])
    s = Struts([0.3, 2.2, 4.4], widths, offsets=[0.0, 0.07, -0.11], length=lengths,
               start=0.4)
    area = float(jnp.sum(s.occlusion(x, y, cell))) * cell**2
    # the struts do not meet (they start 0.4 from the centre): exact to rounding
    assert area == pytest.approx(float(np.sum(widths * lengths)), rel=1e-12)


def test_struts_inside_a_pupil_remove_width_times_length_inside():
    # A square pupil [-1, 1]², struts from 0.3 out to beyond the grid: inside the pupil
    # strut k covers w (chord to the square's edge) = w ((1 + o sin θ) / cos θ − start)
    # for a strut leaving through x = 1 (|θ| < 45°), and likewise for the other sides.
    cell = 0.02
    x, y = _grid(128, cell, 0.0037, 0.0011)
    square = Polygon(_square(-1, -1, 2))
    th = np.array([0.2, math.pi / 2 + 0.1, math.pi - 0.3])
    w = np.array([0.04, 0.06, 0.03])
    o = np.array([0.05, -0.02, 0.0])
    start = 0.3
    p = Obstructed(square, None, Struts(th, w, o, start=start))
    area = float(jnp.sum(p.coverage(x, y, cell))) * cell**2

    def chord(t, off):  # distance along the strut from the centre line's foot to the edge
        u = np.array([np.cos(t), np.sin(t)])
        n = np.array([-u[1], u[0]])
        c = off * n
        ts = [(np.sign(u[i]) - c[i]) / u[i] for i in range(2) if abs(u[i]) > 1e-12]
        return min(t_ for t_ in ts if t_ > 0)

    removed = sum(w[k] * (chord(th[k], o[k]) - start) for k in range(3))
    # the cells where a strut crosses the square's slanted-to-it edge multiply two
    # fractions instead of intersecting the shapes: a few cells' worth at most
    assert area == pytest.approx(4 - removed, abs=4 * cell**2)
    assert area == pytest.approx(4 - removed, rel=2e-4)


def test_struts_match_evenly_spaced_spiders():
    cell = 0.01
    x, y = _grid(256, cell)
    spid = Obstructed(difstar.Circle(1.0), difstar.Circle(0.3), difstar.Spiders(4, 0.05, 0.1, 1.5))
    angles = 0.1 + np.pi / 2 * np.arange(4)
    strut = Obstructed(difstar.Circle(1.0), difstar.Circle(0.3), Struts(angles, 0.05))
    a1 = jnp.sum(spid.coverage(x, y, cell))
    a2 = jnp.sum(strut.coverage(x, y, cell))
    assert float(a2) * cell**2 == pytest.approx(np.pi * (1 - 0.09) - 4 * 0.05 * 0.7, rel=2e-3)
    assert float(a1) == pytest.approx(float(a2), rel=1e-4)
    # a transformed Spiders is the equivalent Struts
    moved = difstar.Spiders(4, 0.05, 0.1, 1.5).transformed(0.2, (0.1, 0.0))
    assert isinstance(moved, Struts)
    np.testing.assert_allclose(moved.angles, angles + 0.2, atol=1e-15)


def test_strut_gradients_angle_width_offset():
    cell = 0.05
    x, y = _grid(64, cell)
    g = jax.random.normal(jax.random.PRNGKey(3), (64, 64), jnp.float64)
    outer = RegularPolygon(6, 1.4, 0.05)

    def f(p):
        s = Struts(jnp.stack([p[0], p[0] + 2.1]), jnp.stack([p[1], 0.07]),
                   jnp.stack([p[2], -0.03]), start=0.2)
        return jnp.sum(Obstructed(outer, difstar.Circle(0.25), s).coverage(x, y, cell) * g)

    p = jnp.asarray([0.37, 0.06, 0.021])
    gr = jax.jit(jax.grad(f))(p)
    f = jax.jit(f)
    assert np.all(np.isfinite(gr)) and np.all(gr != 0)
    np.testing.assert_allclose(jax.jacfwd(f)(p), gr, rtol=1e-9)
    eps = 1e-6
    for i in range(3):
        dp = jnp.zeros(3).at[i].set(eps)
        fd = (f(p + dp) - f(p - dp)) / (2 * eps)
        assert float(gr[i]) == pytest.approx(float(fd), rel=1e-5)
    # the area's derivative in width is the strut's length (finite strut, in the grid)
    area = lambda w: jnp.sum(Struts([0.4], w, 0.01, 1.1, start=0.2).occlusion(x, y, cell))
    assert float(jax.grad(area)(0.05)) * cell**2 == pytest.approx(1.1, rel=1e-10)


def test_struts_validation():
    with pytest.raises(ValueError, match="widths must be > 0"):
        Struts([0.0, 1.0], [0.1, -0.1])
    with pytest.raises(ValueError, match=r"one value per strut \(2\)"):
        Struts([0.0, 1.0], [0.1, 0.1, 0.1])
    with pytest.raises(ValueError, match="NaN or infinity"):
        Struts([0.0, np.nan], 0.1)
    with pytest.raises(ValueError, match="1-D array"):
        Struts(0.3, 0.1)


# --- rotated and shifted pupils ------------------------------------------------------


def test_transformed_polygons_are_exact():
    cell = 0.04
    x, y = _grid(96, cell)
    rp = RegularPolygon(7, 1.1, 0.05)
    np.testing.assert_allclose(Transformed(rp, 0.2).coverage(x, y, cell),
                               RegularPolygon(7, 1.1, 0.25).coverage(x, y, cell), atol=1e-12)
    r2 = rp.transformed(0.2)
    assert isinstance(r2, RegularPolygon) and float(r2.rotation) == pytest.approx(0.25)
    moved = rp.transformed(0.2, (0.3, -0.2))
    assert isinstance(moved, Polygon)
    v = np.asarray(rp.vertices)
    c, s = np.cos(0.2), np.sin(0.2)
    want = v @ np.array([[c, s], [-s, c]]) + [0.3, -0.2]
    np.testing.assert_allclose(moved.vertices, want, atol=1e-14)
    np.testing.assert_allclose(Transformed(rp, 0.2, (0.3, -0.2)).coverage(x, y, cell),
                               moved.coverage(x, y, cell), atol=1e-12)
    # areas are kept exactly; max_radius follows the vertices
    iris = difstar.CurvedIris(9, 1.0, 0.4)
    t = Transformed(iris, 0.3, (0.1, 0.2))
    assert float(jnp.sum(t.coverage(x, y, cell))) * cell**2 == pytest.approx(
        float(iris.area()), rel=1e-9)
    assert float(t.max_radius()) <= float(iris.max_radius()) + math.hypot(0.1, 0.2)
    u = difstar.hex_segments(1, 0.5, 0.01).transformed(0.4, (0.2, 0.0))
    assert isinstance(u, Union)
    assert float(jnp.sum(u.coverage(x, y, cell))) * cell**2 == pytest.approx(
        6 * 1.5 * math.sqrt(3) * (0.5 / math.sqrt(3)) ** 2, rel=1e-12)
    ob = Obstructed(rp, difstar.Circle(0.3), Struts([0.0, 2.0], 0.05)).transformed(0.2, (0.1, 0.1))
    assert isinstance(ob.outer, Polygon) and isinstance(ob.spiders, Struts)
    np.testing.assert_allclose(ob.obstruction.centre, [0.1, 0.1], atol=1e-15)
    np.testing.assert_allclose(ob.spiders.centre, [0.1, 0.1], atol=1e-15)


def test_transformed_gradient_rotation_and_centre():
    cell = 0.06
    x, y = _grid(48, cell)
    g = jax.random.normal(jax.random.PRNGKey(4), (48, 48), jnp.float64)
    base = difstar.hex_segments(1, 0.5, 0.02)

    def f(p):
        return jnp.sum(Transformed(base, p[0], p[1:]).tiled_coverage(x, y, cell) * g)

    p = jnp.asarray([0.3, 0.05, -0.02])
    gr = jax.jit(jax.grad(f))(p)
    f = jax.jit(f)
    eps = 1e-6
    for i in range(3):
        dp = jnp.zeros(3).at[i].set(eps)
        assert float(gr[i]) == pytest.approx(float((f(p + dp) - f(p - dp)) / (2 * eps)),
                                             rel=1e-5)


def test_a_circle_on_the_axis_is_only_shifted_by_a_rotation():
    """A circle built on the axis ignores the rotation (a disc about its own centre); one
    built off the axis still has its centre rotated; a circle whose centre is a value
    (not a built-in origin) rotates it too, even when that value is zero. The derivative
    in the rotation of the obstructed pupil is its struts' alone: the same as with the
    circles rotated, by finite differences."""
    assert difstar.Circle(0.3).on_axis and not difstar.Circle(0.3, (0.1, 0.0)).on_axis
    assert not difstar.Circle(0.3, jnp.zeros(2)).on_axis
    assert float(difstar.Circle(0.3).max_radius()) == pytest.approx(0.3, rel=1e-15)
    assert float(difstar.Circle(0.3, (0.1, 0.0)).max_radius()) == pytest.approx(0.4, rel=1e-15)
    moved = difstar.Circle(0.3).transformed(0.7, (0.1, -0.2))
    np.testing.assert_allclose(moved.centre, [0.1, -0.2], atol=0)
    assert not moved.on_axis
    c, s = math.cos(0.7), math.sin(0.7)
    off = difstar.Circle(0.3, (0.1, 0.0)).transformed(0.7)
    np.testing.assert_allclose(off.centre, [0.1 * c, 0.1 * s], atol=1e-15)
    np.testing.assert_allclose(moved.transformed(0.7).centre,
                               [0.1 * c + 0.2 * s, 0.1 * s - 0.2 * c], atol=1e-15)
    cell = 0.05
    x, y = _grid(64, cell)
    g = jax.random.normal(jax.random.PRNGKey(5), (64, 64), jnp.float64)

    def f(rot):
        pupil = Obstructed(difstar.Circle(1.2), difstar.Circle(0.4),
                           Struts([0.3, 2.4, 4.5], 0.06))
        return jnp.sum(pupil.transformed(rot).tiled_coverage(x, y, cell) * g)

    rot = 0.2
    slope = float(jax.jit(jax.grad(f))(rot))
    fd = float((jax.jit(f)(rot + 1e-6) - jax.jit(f)(rot - 1e-6)) / 2e-6)
    assert slope == pytest.approx(fd, rel=1e-5)


# --- masks ---------------------------------------------------------------------------


def _disc_mask(radius, pitch, n):
    c = (np.arange(n) - (n - 1) / 2) * pitch
    xx, yy = np.meshgrid(c, -c)
    return np.hypot(xx, yy) < radius


def test_boolean_mask_of_a_disc_against_the_analytic_disc():
    r, pitch, cell = 1.0, 0.004, 0.04  # ten mask pixels per grid cell
    m = _disc_mask(r, pitch, 560)
    x, y = _grid(64, cell, 0.5 * cell, 0.5 * cell)  # cell edges on pixel edges
    got = Mask(m, pitch).coverage(x, y, cell)
    want = difstar.Circle(r).coverage(x, y, cell)
    # per cell: the boolean staircase is off by at most about a pixel row of the cell
    assert float(jnp.max(jnp.abs(got - want))) < 2 * pitch / cell
    # in total: the boolean disc's own area (exact), within 0.1 % of π r²
    assert float(jnp.sum(got)) * cell**2 == pytest.approx(m.sum() * pitch**2, rel=1e-12)
    assert float(jnp.sum(got)) * cell**2 == pytest.approx(math.pi * r * r, rel=1e-3)
    # full cells are 1, empty 0, edge cells fractional (not rounded up to 1)
    interior = np.asarray(want) == 1
    assert np.all(np.asarray(got)[interior] == pytest.approx(1.0, abs=1e-12))
    edge = (np.asarray(want) > 0.2) & (np.asarray(want) < 0.8)
    assert edge.sum() > 20
    assert np.max(np.abs(np.asarray(got)[edge] - np.asarray(want)[edge])) < 0.05


def test_mask_resampling_by_area_is_exact():
    # A float mask that is a polygon's coverage at pitch p, resampled to cells of 2p on
    # aligned cell edges, is the polygon's coverage at 2p (averages of coverages).
    import equinox as eqx

    # each coverage compiled (the cell a static number, the paths chosen by the arrays'
    # shapes as before): run op by op, the rasters took 2.5x as long
    cov = eqx.filter_jit(lambda shape, x, y, cell: shape.coverage(x, y, cell))
    pitch = 0.02
    poly = RegularPolygon(5, 0.7, 0.3)
    xf, yf = _grid(100, pitch, 0.5 * pitch, 0.5 * pitch)
    fine = np.asarray(cov(poly, xf, yf, pitch))[::-1]  # rows down for the mask
    mask = Mask(fine, pitch, centre=(0.0, 0.0))
    # the fine grid's centres run from −50 p + p/2: its pixel edges at multiples of p
    x, y = _grid(50, 2 * pitch, pitch, pitch)
    np.testing.assert_allclose(cov(mask, x, y, 2 * pitch), cov(poly, x, y, 2 * pitch),
                               atol=1e-12)
    # the same cells as the mask's pixels give the pixel values back
    np.testing.assert_allclose(cov(mask, xf, yf, pitch), fine[::-1], atol=1e-12)
    # arbitrary cell centres (the 2-D summed-area path) agree with the separable path
    xo, yo = _grid(52, 0.033, 0.011, -0.017)
    sep = cov(mask, xo, yo, 0.033)
    gen = cov(mask, jnp.broadcast_to(xo, (52, 52)), jnp.broadcast_to(yo, (52, 52)), 0.033)
    np.testing.assert_allclose(gen, sep, atol=1e-12)
    assert float(jnp.sum(sep)) * 0.033**2 == pytest.approx(float(mask.area()), rel=1e-12)
    # differentiable in the values (linear)
    gv = jax.jit(jax.grad(lambda v: jnp.sum(Mask(v, pitch).coverage(xo, yo, 0.033))))(
        jnp.asarray(fine))
    c = (np.arange(100) - 49.5) * pitch  # pixel centres; the grid spans about ±0.84
    inside = (np.abs(c)[:, None] < 0.8) & (np.abs(c)[None, :] < 0.8)
    outside = (np.abs(c)[:, None] > 0.9) | (np.abs(c)[None, :] > 0.9)
    np.testing.assert_allclose(np.asarray(gv)[inside] * 0.033**2, pitch**2, rtol=1e-10)
    np.testing.assert_allclose(np.asarray(gv)[outside] * 0.033**2, 0.0, atol=1e-15)


def test_mask_max_radius_is_tight_and_values_validated():
    pitch = 0.01
    v = np.zeros((40, 60), bool)
    v[5, 50] = True  # row 5 from the top, column 50: one open pixel
    m = Mask(v, pitch)
    x_far = (51 - 30) * pitch  # the pixel's outer edges
    y_far = (20 - 5) * pitch
    assert float(m.max_radius()) == pytest.approx(math.hypot(x_far, y_far), rel=1e-12)
    assert float(m.max_radius()) < 0.5 * pitch * math.hypot(40, 60)
    d = _disc_mask(0.3, pitch, 100)
    # farthest open pixel corner: within a pixel diagonal beyond the radius
    assert 0.3 < float(Mask(d, pitch).max_radius()) <= 0.3 + pitch * math.sqrt(2)
    assert float(Mask(d, pitch, centre=(0.1, 0.0)).max_radius()) > 0.39
    with pytest.raises(ValueError, match=r"in \[0, 1\]"):
        Mask(np.full((4, 4), 1.5), pitch)
    with pytest.raises(ValueError, match="NaN or infinity"):
        Mask(np.full((4, 4), np.nan), pitch)
    with pytest.raises(ValueError, match="zero everywhere"):
        Mask(np.zeros((4, 4)), pitch)
    with pytest.raises(ValueError, match="2-D"):
        Mask(np.ones(4), pitch)
    with pytest.raises(ValueError, match="pitch must be > 0"):
        Mask(np.ones((4, 4)), -1.0)
    with pytest.raises(ValueError, match="only 0 and 1"):
        Mask(np.full((4, 4), 2), pitch)
    Mask(np.ones((4, 4), np.uint8), pitch)


def test_rotated_mask_approximates_the_rotated_shape():
    pitch, cell = 0.01, 0.04
    poly = RegularPolygon(6, 0.6, 0.0)
    xf, yf = _grid(160, pitch, 0.5 * pitch, 0.5 * pitch)
    mask = Mask(np.asarray(poly.coverage(xf, yf, pitch))[::-1], pitch)
    x, y = _grid(48, cell)
    got = mask.transformed(0.25, (0.05, 0.0)).coverage(x, y, cell)
    want = poly.transformed(0.25, (0.05, 0.0)).coverage(x, y, cell)
    assert float(jnp.sum(got)) == pytest.approx(float(jnp.sum(want)), rel=2e-3)
    assert float(jnp.max(jnp.abs(got - want))) < 0.1
    shifted = mask.transformed(0.0, (0.05, 0.0))
    assert isinstance(shifted, Mask)
    # the rotated, shifted mask's max_radius: its farthest open pixel corner, moved
    moved = mask.transformed(0.25, (0.05, 0.0))
    rm = float(moved.max_radius())
    assert float(poly.transformed(0.25, (0.05, 0.0)).max_radius()) < rm
    assert rm < float(poly.transformed(0.25, (0.05, 0.0)).max_radius()) + 1.5 * pitch


def test_boolean_mask_psf_matches_the_analytic_pupil():
    # Issue 15: a boolean Mask made the PSF 4.3 % off (half-covered edge cells became 1).
    # A 100-pixel boolean hexagon (pixel centres inside) now gives the hexagon's PSF
    # within its staircase's own error, and its max_radius does not inflate the grid.
    r = 1e-3
    poly = RegularPolygon(6, r, 0.1)
    n = 100
    pitch = 2 * r / n
    c = (np.arange(n + 20) - (n + 19) / 2) * pitch
    xx, yy = np.meshgrid(c, -c)
    v = np.asarray(poly.vertices)
    inside = np.ones(xx.shape, bool)
    for k in range(6):  # inside every edge's half-plane (convex, counter-clockwise)
        a, b = v[k], v[(k + 1) % 6]
        inside &= (b[0] - a[0]) * (yy - a[1]) - (b[1] - a[1]) * (xx - a[0]) > 0
    mask = Mask(inside, pitch)
    assert 1.0 < float(mask.max_radius()) / r < 1 + 1.5 * pitch / r
    kw = dict(wavelength=0.55e-6, z_image=0.05, pixel_pitch=4e-6, shape=(48, 48), accuracy=0.01)
    want = difstar.psf(poly, **kw)
    got = difstar.psf(mask, **kw)
    assert float(jnp.max(jnp.abs(got - want)) / jnp.max(want)) < 2e-3
    assert float(jnp.sum(got)) == pytest.approx(float(jnp.sum(want)), rel=2e-3)


def test_polygon_checks_self_intersection_before_orientation():
    eight = np.array([[0, 0], [1, 1], [1, 0], [0, 1]], float)  # a bow tie: zero area
    with pytest.raises(ValueError, match="edges 0 and 2 cross"):
        Polygon(eight)
    lopsided = np.array([[0, 0], [2, 2], [2, 0], [0, 1]], float)  # negative net area
    with pytest.raises(ValueError, match="cross; the polygon must be simple"):
        Polygon(lopsided)
    with pytest.raises(ValueError, match="clockwise"):
        Polygon(_square(0, 0, 1)[::-1])
    # a many-vertex simple polygon is checked quickly (vectorised)
    import time

    t = time.perf_counter()
    Polygon(np.asarray(RegularPolygon(2000, 1.0).vertices))
    assert time.perf_counter() - t < 10.0


# --- linear maps of the pupil (image-plane distortion) ---------------------------------


def test_distorted_hexagon_psf_is_the_image_seen_through_the_map():
    """Transforming the pupil by M = D^(−T) transforms the far field by D: the PSF of the
    distorted hexagon equals the independent Lee–Mittra intensity of the original at
    D⁻¹x, divided by det D (float64, point sampling, pixel centres)."""
    from references import pixel_centres, polygon_intensity_focus, regular_polygon_vertices

    from difstar._pupil import distorted

    d = np.array([[1.0, 0.0], [0.04, 1.03]])  # shear and y stretch of the image
    hexagon = regular_polygon_vertices(6, 1.0e-3, 0.1)
    pup = distorted(Polygon(hexagon), np.linalg.inv(d).T)
    lam, z, p, shape = 550e-9, 0.05, 4e-6, (48, 48)
    got = np.asarray(difstar.psf(pup, wavelength=lam, z_image=z, pixel_pitch=p, shape=shape,
                                 sampling="point"))
    xs, ys = pixel_centres(shape, p)
    xx, yy = np.broadcast_arrays(xs[None, :], ys[:, None])
    u = np.linalg.solve(d, np.stack([xx.ravel(), yy.ravel()]))
    ref = polygon_intensity_focus(hexagon, wavelength=lam, z=z)(u[0], u[1]).reshape(shape)
    ref = ref * p**2 / np.linalg.det(d)
    assert np.max(np.abs(got - ref)) < 1e-9 * ref.max()


def test_distorted_struts_and_union_keep_area_ratios():
    """A linear map scales every area by its determinant: segments with struts across
    them, a circle (mapped to the circle of equal area) and the union, on a fine grid."""
    from difstar._pupil import distorted

    m = jnp.array([[1.02, -0.03], [0.01, 0.97]])
    det = float(jnp.linalg.det(m))
    segs = difstar.hex_segments(1, 0.3, 0.01)
    struts = Struts(jnp.deg2rad(jnp.array([90.0, 200.0, 340.0])), 0.02, offsets=0.01)
    pupil = Obstructed(segs, difstar.Circle(0.08), struts)
    x, y = _grid(512, 0.0025)
    a0 = float(jnp.sum(pupil.coverage(x, y, 0.0025)))
    a1 = float(jnp.sum(distorted(pupil, m).coverage(x, y, 0.0025)))
    assert abs(a1 / (det * a0) - 1) < 2e-3
    # the strut direction follows the map: a strut along u goes along M u
    s1 = distorted(struts, m)
    u = np.asarray(m) @ np.array([np.cos(np.deg2rad(200.0)), np.sin(np.deg2rad(200.0))])
    assert abs(float(s1.angles[1]) - math.atan2(u[1], u[0])) < 1e-12
    with pytest.raises(ValueError, match="determinant"):
        distorted(segs, jnp.array([[1.0, 0.0], [0.0, -1.0]]))
    with pytest.raises(TypeError, match="not supported"):
        distorted(Mask(np.ones((4, 4)), 0.1), m)


def test_distortion_gradient_matches_finite_differences():
    from difstar._pupil import distorted

    segs = difstar.hex_segments(1, 0.3, 0.01)
    x, y = _grid(96, 0.012)

    def f(s):
        m = jnp.array([[1.0, -s], [0.0, 1.0]])
        return jnp.sum(jnp.sin(37 * x) * distorted(segs, m).coverage(x, y, 0.012))

    g = jax.jit(jax.grad(f))(0.01)
    h = 1e-6
    ff = jax.jit(f)  # the differences: compiled, not op by op
    fd = (ff(0.01 + h) - ff(0.01 - h)) / (2 * h)
    assert np.isfinite(g) and abs(g - fd) < 1e-5 * max(1.0, abs(fd))
    assert abs(jax.jit(jax.jacfwd(f))(0.01) - g) < 1e-9 * max(1.0, abs(g))
