"""Exit-pupil shapes, rasterised by area coverage.

Every shape gives, for a grid of square sample cells, the fraction of each cell that lies
inside the shape. Polygons are exact (Green's theorem on each edge, vertices included);
a circle's edge is treated locally as straight (the cell's projection onto the edge
normal is the convolution of two boxes, so the covered fraction is the trapezoid's CDF);
thin spider vanes multiply their edges' half-plane fractions. This makes the raster
differentiable with respect to vertices, radius and rotation, and removes the staircase
of a binary raster.

Lengths are in metres in the exit-pupil plane.
"""

from __future__ import annotations

import math
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._custom_types import Array, Float

_TINY = 1e-6  # fraction of a cell below which an edge's slant is treated as axis-aligned


def _safe_norm(x: Array, y: Array) -> Array:
    r2 = x * x + y * y
    ok = r2 > 0
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, r2, 1.0)), 0.0)


def halfplane_coverage(s: Array, nx: Array, ny: Array, cell: float | Array) -> Array:
    """Fraction of a square cell (side ``cell``) inside a half-plane.

    ``s`` is the signed distance from the cell centre to the edge, positive inside; ``(nx,
    ny)`` the edge's unit normal. The projection of a uniform square onto the normal is a
    trapezoid of widths ``a = cell |nx|`` and ``b = cell |ny|``; its CDF at ``s`` is the
    covered fraction (piecewise quadratic–linear–quadratic).
    """
    a0 = cell * jnp.abs(nx)
    b0 = cell * jnp.abs(ny)
    a = jnp.maximum(jnp.minimum(a0, b0), _TINY * cell)
    b = jnp.maximum(jnp.maximum(a0, b0), _TINY * cell)
    u = s + 0.5 * (a + b)
    r1 = u * u / (2 * a * b)
    r2 = (u - 0.5 * a) / b
    w = a + b - u
    r3 = 1.0 - w * w / (2 * a * b)
    out = jnp.where(u <= a, r1, jnp.where(u <= b, r2, r3))
    out = jnp.where(u <= 0, 0.0, out)
    return jnp.where(w <= 0, 1.0, out)


def _ramp_integral(t: Array, h) -> Array:
    """G(t) = ∫_{-∞}^t clamp(τ, 0, h) dτ."""
    tc = jnp.clip(t, 0.0, h)
    return 0.5 * tc * tc + h * jnp.maximum(t - h, 0.0)


def edge_coverage(x0, y0, x1, y1, x: Array, y: Array, cell) -> Array:
    """One straight edge's term of ``_pupil.polygon_coverage`` (Green's theorem): summed
    over a closed counter-clockwise outline it gives the exact covered fraction of each
    cell. ``x`` (1, W) and ``y`` (H, 1) are cell centres.

    By Green's theorem the area of P ∩ cell is −∮ F dx with
    F = 1[x in the cell's column] · clamp(y − y_bottom, 0, cell), whose integral along a
    straight edge has a closed form (the ramp's antiderivative G). The edge is
    parametrised along its length so the term stays differentiable when the edge is
    exactly vertical (its value is 0 there, its derivative in x is not).
    """
    xa = x - 0.5 * cell
    xb = x + 0.5 * cell
    ya = y - 0.5 * cell
    dxe = x1 - x0
    vertical = dxe == 0
    safe = jnp.where(vertical, 1.0, dxe)
    xc0 = jnp.clip(x0, xa, xb)  # the part of the edge inside each cell column
    xc1 = jnp.clip(x1, xa, xb)
    signed_length = xc1 - xc0  # (1, W), negative for an edge running towards −x
    s0 = jnp.where(vertical, 0.0, (xc0 - x0) / safe)
    s1 = jnp.where(vertical, 1.0, (xc1 - x0) / safe)
    t1 = y0 + (y1 - y0) * s0 - ya  # (H, W): heights above each cell's bottom
    t2 = y0 + (y1 - y0) * s1 - ya
    dt = t2 - t1
    small = jnp.abs(dt) < 1e-3 * cell
    # G's divided difference; G is piecewise quadratic, so where dt is tiny the
    # derivative at the midpoint is exact within one piece.
    dd = (_ramp_integral(t2, cell) - _ramp_integral(t1, cell)) / jnp.where(small, 1.0, dt)
    mid = jnp.clip(0.5 * (t1 + t2), 0.0, cell)
    return -signed_length * jnp.where(small, mid, dd) / (cell * cell)


def outline_coverage(
    v0: Float[Array, "e 2"], v1: Float[Array, "e 2"], x: Array, y: Array, cell
) -> Array:
    """Exact area coverage of the closed outline made of the edges v0[i] → v1[i].

    A scan over the edges, one edge's term per step (checkpointed): compile time and
    reverse-mode memory do not grow with the number of edges, unlike an unrolled loop.
    """
    shape = jnp.broadcast_shapes(x.shape, y.shape)
    dtype = jnp.result_type(x, y, v0)

    @jax.checkpoint
    def term(e):
        return edge_coverage(e[0], e[1], e[2], e[3], x, y, cell)

    def step(total, e):
        return total + term(e), None

    edges = jnp.concatenate([v0, v1], axis=1)
    total, _ = jax.lax.scan(step, jnp.zeros(shape, dtype), edges)
    return total


def _axis(c: Array) -> tuple[Array, Array]:
    """(first centre, signed step) of a uniform axis of cell centres (the step from the
    ends: the difference of neighbours cancels digits, in float32 enough to misplace the
    far grid lines by a tenth of a cell)."""
    c = c.reshape(-1)
    return c[0], (c[-1] - c[0]) / (c.shape[0] - 1)


def _cell_pieces(v0, v1, x, y):
    """The pieces into which the grid lines cut each edge v0[i] → v1[i], for cells that
    tile the plane (uniform ``x`` (1, W) and ``y`` (H, 1), spacing = cell side).

    Every grid line an edge crosses is a break in its parameter s ∈ [0, 1]; between
    consecutive breaks the edge lies in one cell. Returns (s_lo, s_hi, row, col, inside),
    each (e, W + H + 3): the pieces, their cells (clipped) and whether that cell is on the
    grid and the piece has length. Primal-only work, O(e (W + H) log(W + H)).
    """
    w, h = x.shape[-1], y.shape[0]
    x0, sx = _axis(x)
    y0, sy = _axis(y)
    d = v1 - v0

    def breaks(c0, step, count, a, da):
        lines = c0 + (jnp.arange(count + 1, dtype=a.dtype) - 0.5) * step
        ok = (da != 0)[:, None]
        s = (lines[None, :] - a[:, None]) / jnp.where(ok, da[:, None], 1.0)
        return jnp.where(ok, jnp.clip(s, 0.0, 1.0), 0.0)

    e = v0.shape[0]
    s = jnp.concatenate(
        [jnp.zeros((e, 1), d.dtype), jnp.ones((e, 1), d.dtype),
         breaks(x0, sx, w, v0[:, 0], d[:, 0]), breaks(y0, sy, h, v0[:, 1], d[:, 1])], axis=1)
    s = jnp.sort(s, axis=1)
    lo, hi = s[:, :-1], s[:, 1:]
    mid = 0.5 * (lo + hi)
    col = jnp.floor((v0[:, :1] + mid * d[:, :1] - x0) / sx + 0.5).astype(jnp.int32)
    row = jnp.floor((v0[:, 1:] + mid * d[:, 1:] - y0) / sy + 0.5).astype(jnp.int32)
    inside = (hi > lo) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
    return lo, hi, jnp.clip(row, 0, h - 1), jnp.clip(col, 0, w - 1), inside


@jax.custom_jvp
def tiled_outline_coverage(v0: Float[Array, "e 2"], v1: Float[Array, "e 2"], x: Array,
                           y: Array, cell) -> Array:
    """:func:`outline_coverage` on cells that tile the plane: ``x`` (1, W) and ``y`` (H, 1)
    uniform (ascending or descending, W, H ≥ 2) with spacing equal to ``cell``, as on a
    square frequency grid. The same values; the derivative is the shape derivative, which
    holds for closed outlines (every v1 is some edge's v0, as for a polygon's edges or a
    curved iris's arc pieces): pass v0 and v1 built from the same vertices.

    Moving the outline with velocity V changes the area of its intersection with a cell
    by ∫ V · n ds along the part of the outline inside that cell (n the outward normal),
    so the coverage's derivative lives on the O(W + H) pieces into which the grid lines
    cut the edges (:func:`_cell_pieces`), not on the whole plane: the tangent is a
    scatter of one value per piece, and reverse mode (its transpose) a gather. Moving
    the cell centres is moving the outline the other way; the cell side follows from
    the coverage's invariance under scaling everything. Forward and reverse mode both
    work, and both cost O(W + H) per edge on top of a zero plane, where autodiff of the
    edge terms costs several passes over the W × H plane per edge.
    """
    return outline_coverage(v0, v1, x, y, cell)


@tiled_outline_coverage.defjvp
def _tiled_outline_jvp(primals, tangents):
    v0, v1, x, y, cell = primals
    dv0, dv1, dx, dy, dcell = tangents
    out = tiled_outline_coverage(v0, v1, x, y, cell)
    h, w = out.shape
    lo, hi, row, col, inside = _cell_pieces(v0, v1, x, y)
    d = v1 - v0
    nx, ny = d[:, 1:], -d[:, :1]  # outward normal of a counter-clockwise outline, × length
    ds = hi - lo
    half_sq = 0.5 * (hi * hi - lo * lo)
    xs, ys = x.reshape(-1), y.reshape(-1)
    # ∫ (p(s) − c) · n ds over a piece: the cell-side term, by scale invariance
    lever = ((v0[:, :1] - xs[col]) * nx + (v0[:, 1:] - ys[row]) * ny) * ds
    cell = jnp.asarray(cell, out.dtype)
    dcell = jnp.asarray(dcell, out.dtype)
    speed = ((ds - half_sq) * (dv0[:, :1] * nx + dv0[:, 1:] * ny)
             + half_sq * (dv1[:, :1] * nx + dv1[:, 1:] * ny)
             - ds * (dx.reshape(-1)[col] * nx + dy.reshape(-1)[row] * ny)
             - lever * (dcell / cell))
    speed = jnp.where(inside, speed, 0.0) / (cell * cell)
    flat = jnp.zeros(h * w, out.dtype).at[(row * w + col).reshape(-1)].add(speed.reshape(-1))
    return out, flat.reshape(h, w)


def polygon_coverage(vertices: Float[Array, "n 2"], x: Array, y: Array, cell, *,
                     tiled: bool = False) -> Array:
    """Exact area coverage of a simple counter-clockwise polygon on square cells centred
    at ``x`` (1, W) and ``y`` (H, 1). Exact for convex and non-convex polygons;
    continuous and piecewise polynomial in the vertices, so it is differentiable with
    respect to them (finite gradients on grid lines and for vertical edges too).
    ``tiled=True``: the cells tile the plane (:func:`tiled_outline_coverage`)."""
    outline = tiled_outline_coverage if tiled else outline_coverage
    return outline(vertices, jnp.roll(vertices, -1, axis=0), x, y, cell)


def convex_polygon_coverage(vertices: Float[Array, "n 2"], x: Array, y: Array, cell) -> Array:
    """Approximate coverage of a convex polygon as the product of its edges' half-plane
    fractions (exact away from vertices; used for thin vanes where it is cheap)."""
    v0 = vertices
    v1 = jnp.roll(vertices, -1, axis=0)
    d = v1 - v0
    length = _safe_norm(d[:, 0], d[:, 1])
    length = jnp.where(length > 0, length, 1.0)
    nx = d[:, 1] / length  # outward normal of a CCW polygon
    ny = -d[:, 0] / length
    cov = jnp.ones(jnp.broadcast_shapes(x.shape, y.shape), dtype=x.dtype)
    for i in range(vertices.shape[0]):
        s = -(nx[i] * (x - v0[i, 0]) + ny[i] * (y - v0[i, 1]))
        cov = cov * halfplane_coverage(s, nx[i], ny[i], cell)
    return cov


def disc_coverage(radius, cx, cy, x: Array, y: Array, cell, *, subsamples: int = 1) -> Array:
    """Area coverage of a disc; the edge is treated locally as a straight line, with the
    normal along the radius. That overestimates the area of each edge cell by about
    ℓ³/(12 R) (ℓ the chord in the cell); ``subsamples`` s splits each cell into s × s
    sub-cells, which cuts that bias by s² — use it for discs only a few cells across."""
    if subsamples > 1:
        sub = cell / subsamples
        offs = (jnp.arange(subsamples) - (subsamples - 1) / 2) * sub
        oy, ox = jnp.meshgrid(offs, offs, indexing="ij")

        def add(total, o):
            return total + disc_coverage(radius, cx, cy, x + o[1], y + o[0], sub), None

        shape = jnp.broadcast_shapes(x.shape, y.shape)
        total0 = jnp.zeros(shape, dtype=jnp.result_type(x, y, radius))
        offsets = jnp.stack([oy.ravel(), ox.ravel()], axis=1)
        total, _ = jax.lax.scan(jax.checkpoint(add), total0, offsets)
        return total / subsamples**2
    dx = x - cx
    dy = y - cy
    r = _safe_norm(dx, dy)
    rs = jnp.where(r > 0, r, 1.0)
    nx = jnp.where(r > 0, dx / rs, 1.0)
    ny = jnp.where(r > 0, dy / rs, 0.0)
    return halfplane_coverage(radius - r, nx, ny, cell)


class AbstractPupil(eqx.Module):
    """A shape in the exit-pupil plane. Subclasses give ``coverage`` and ``max_radius``.

    ``area_coverage`` says the raster is the cell-averaged shape (so the PSF may divide
    out the cell's transform); a resampled mask is not.
    """

    area_coverage: ClassVar[bool] = True

    def coverage(self, x: Array, y: Array, cell) -> Array:
        raise NotImplementedError

    def tiled_coverage(self, x: Array, y: Array, cell) -> Array:
        """``coverage`` where the cells tile the plane (uniform axes, spacing = ``cell``,
        as on a square frequency grid): the same values; shapes with straight edges then
        differentiate along their outline only (:func:`tiled_outline_coverage`)."""
        return self.coverage(x, y, cell)

    def max_radius(self) -> Array:
        """Largest distance from the optical axis to the shape's boundary (metres)."""
        raise NotImplementedError

    def outline_edges(self) -> tuple[Array, Array] | None:
        """(v0, v1), each (e, 2): the edges v0[i] → v1[i] of a closed counter-clockwise
        outline whose Green's-theorem terms sum to this pupil's coverage, or None when
        the shape is not a straight-edged outline. Unions concatenate their members'
        edges into one scan (compile time independent of the member count); rotations
        and shifts transform them exactly."""
        return None

    def transformed(self, rotation=0.0, centre=(0.0, 0.0)) -> "AbstractPupil":
        """This pupil rotated by ``rotation`` (radians, counter-clockwise) about the
        optical axis, then shifted by ``centre`` (x, y metres): a point p goes to
        R(rotation) p + centre. Shapes that can, return their own type with transformed
        parameters (exact); the default wraps the pupil in :class:`Transformed`."""
        return Transformed(self, rotation, centre)


def _first_crossing(v: np.ndarray, w: np.ndarray) -> tuple[int, int] | None:
    """First pair (i, j), i < j, of non-adjacent edges v[k] → w[k] that cross properly;
    vectorised in blocks of rows (O(n²) work, O(n · block) memory)."""
    n = len(v)

    def orient(a, b, c):
        return np.sign((b[..., 0] - a[..., 0]) * (c[..., 1] - a[..., 1])
                       - (b[..., 1] - a[..., 1]) * (c[..., 0] - a[..., 0]))

    j = np.arange(n)[None, :]
    for lo in range(0, n, 256):
        i = np.arange(lo, min(n, lo + 256))[:, None]
        p1, p2 = v[i[:, 0]][:, None, :], w[i[:, 0]][:, None, :]
        p3, p4 = v[None, :, :], w[None, :, :]
        cross = ((orient(p1, p2, p3) * orient(p1, p2, p4) < 0)
                 & (orient(p3, p4, p1) * orient(p3, p4, p2) < 0))
        cross &= (j >= i + 2) & ~((i == 0) & (j == n - 1))
        hits = np.argwhere(cross)
        if len(hits):
            return int(hits[0][0] + lo), int(hits[0][1])
    return None


def _check_ccw_simple(v: np.ndarray, name: str) -> None:
    w = np.roll(v, -1, axis=0)
    # self-intersection first: a figure-8's orientation is meaningless
    hit = _first_crossing(v, w)
    if hit is not None:
        raise ValueError(
            f"{name}: edges {hit[0]} and {hit[1]} cross; the polygon must be simple "
            "(non-self-intersecting, e.g. not a figure-8)."
        )
    area = 0.5 * np.sum(v[:, 0] * w[:, 1] - w[:, 0] * v[:, 1])
    if area < 0:
        raise ValueError(
            f"{name}: vertices are in clockwise order; give them counter-clockwise "
            "(reverse the array, e.g. vertices[::-1])."
        )
    if area == 0:
        raise ValueError(f"{name}: the polygon has zero area.")


def _check_build_count(count, field: str, what: str) -> None:
    """At most ``MAX_BUILD_EDGES`` vertices / blades / vanes when a pupil is built (a
    static count; difstar.psf and simulate take at most ``MAX_EDGES`` per outline)."""
    from ._limits import MAX_BUILD_EDGES, check_edge_count

    check_edge_count(int(count), field, what, most=MAX_BUILD_EDGES)


def _segments_cross(p1, p2, p3, p4) -> bool:
    def orient(a, b, c):
        return np.sign((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]))

    return bool(orient(p1, p2, p3) * orient(p1, p2, p4) < 0) and bool(
        orient(p3, p4, p1) * orient(p3, p4, p2) < 0
    )


def _concrete(a) -> np.ndarray | None:
    """``a`` as a NumPy array, or None for a tracer (inside jit/grad the checks that need
    values are skipped: they ran when the pupil was built outside)."""
    try:
        return np.asarray(a)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError,
            TypeError):
        return None


def _float(a) -> Array:
    return jnp.asarray(a, dtype=jnp.result_type(float))


def _rigid(p: Array, rotation, centre) -> Array:
    """Points (..., 2) rotated by ``rotation`` (radians, counter-clockwise) about the
    origin, then shifted by ``centre``."""
    c, s = jnp.cos(rotation), jnp.sin(rotation)
    x, y = p[..., 0], p[..., 1]
    return jnp.stack([c * x - s * y + centre[0], s * x + c * y + centre[1]], axis=-1)


def _is_origin(centre) -> bool:
    """True when ``centre`` is statically the origin (None or a tuple/list of zeros)."""
    if centre is None:
        return True
    return isinstance(centre, (tuple, list)) and all(
        isinstance(c, (int, float)) and c == 0 for c in centre)


class Polygon(AbstractPupil):
    """Simple polygon (convex or not) with ``vertices`` an (n, 2) array of (x, y) in
    metres, counter-clockwise."""

    vertices: Float[Array, "n 2"]

    def __init__(self, vertices):
        v = jnp.asarray(vertices)
        if v.ndim != 2 or v.shape[1] != 2 or v.shape[0] < 3:
            raise ValueError(
                f"Polygon.vertices must be an (n, 2) array with n >= 3; got shape {v.shape}."
            )
        _check_build_count(v.shape[0], "Polygon.vertices", "vertices")
        if not jnp.issubdtype(v.dtype, jnp.floating):
            v = v.astype(float)
        concrete = _concrete(v)  # None for a tracer: checked when built outside jit
        if concrete is not None:
            if not np.all(np.isfinite(concrete)):
                raise ValueError("Polygon.vertices contains NaN or infinity.")
            _check_ccw_simple(concrete, "Polygon.vertices")
        self.vertices = v

    def coverage(self, x, y, cell):
        return polygon_coverage(self.vertices, x, y, cell)

    def tiled_coverage(self, x, y, cell):
        return polygon_coverage(self.vertices, x, y, cell, tiled=True)

    def max_radius(self):
        return jnp.max(_safe_norm(self.vertices[:, 0], self.vertices[:, 1]))

    def outline_edges(self):
        return self.vertices, jnp.roll(self.vertices, -1, axis=0)

    def area(self) -> Array:
        """Open area (m²), by the shoelace formula."""
        v, w = self.outline_edges()
        return 0.5 * jnp.sum(v[:, 0] * w[:, 1] - w[:, 0] * v[:, 1])

    def transformed(self, rotation=0.0, centre=(0.0, 0.0)) -> "Polygon":
        """The polygon with its vertices rotated by ``rotation`` (radians) about the
        axis, then shifted by ``centre`` (metres): exact."""
        return Polygon(_rigid(self.vertices, _float(rotation), _float(centre)))


def regular_polygon_vertices(n: int, circumradius, rotation) -> Array:
    """Vertices (n, 2), counter-clockwise, the first at angle ``rotation`` (radians)."""
    k = jnp.arange(n)
    theta = rotation + 2 * math.pi * k / n
    return jnp.stack([circumradius * jnp.cos(theta), circumradius * jnp.sin(theta)], axis=-1)


class RegularPolygon(AbstractPupil):
    """Regular ``n``-gon (an iris of ``n`` straight blades).

    ``circumradius`` in metres; ``rotation`` in radians, the angle of the first vertex
    from the +x axis.
    """

    n: int = eqx.field(static=True)
    circumradius: Float[Array, ""]
    rotation: Float[Array, ""]

    def __init__(self, n: int, circumradius, rotation=0.0):
        if not isinstance(n, (int, np.integer)) or n < 3:
            raise ValueError(f"RegularPolygon.n must be an integer >= 3 (blade count); got {n!r}.")
        _check_build_count(n, "RegularPolygon.n", "blades (edges)")
        self.n = int(n)
        self.circumradius = jnp.asarray(circumradius, dtype=jnp.result_type(float))
        self.rotation = jnp.asarray(rotation, dtype=jnp.result_type(float))
        try:
            r = float(self.circumradius)
        except Exception:
            r = None
        if r is not None and not r > 0:
            raise ValueError(f"RegularPolygon.circumradius must be > 0 metres; got {r}.")

    @property
    def vertices(self) -> Array:
        return regular_polygon_vertices(self.n, self.circumradius, self.rotation)

    def coverage(self, x, y, cell):
        return polygon_coverage(self.vertices, x, y, cell)

    def tiled_coverage(self, x, y, cell):
        return polygon_coverage(self.vertices, x, y, cell, tiled=True)

    def max_radius(self):
        return self.circumradius

    def outline_edges(self):
        v = self.vertices
        return v, jnp.roll(v, -1, axis=0)

    def area(self) -> Array:
        """Open area (m²): n R² sin(2π/n) / 2."""
        return 0.5 * self.n * self.circumradius**2 * math.sin(2 * math.pi / self.n)

    def transformed(self, rotation=0.0, centre=None) -> "RegularPolygon | Polygon":
        """Rotated by ``rotation`` (radians) about the axis, then shifted by ``centre``.
        Without a centre (None, or a literal tuple of zeros) a ``RegularPolygon`` with
        its rotation increased; with one, the :class:`Polygon` of the moved vertices
        (a regular polygon here is centred on the axis). Exact either way."""
        if _is_origin(centre):
            return RegularPolygon(self.n, self.circumradius, self.rotation + rotation)
        return Polygon(_rigid(self.vertices, _float(rotation), _float(centre)))


class Circle(AbstractPupil):
    """Circular pupil of ``radius`` metres centred on the axis (or at ``centre``)."""

    radius: Float[Array, ""]
    centre: Float[Array, "2"]

    def __init__(self, radius, centre=(0.0, 0.0)):
        self.radius = jnp.asarray(radius, dtype=jnp.result_type(float))
        self.centre = jnp.asarray(centre, dtype=jnp.result_type(float))
        try:
            r = float(self.radius)
        except Exception:
            r = None
        if r is not None and not r > 0:
            raise ValueError(f"Circle.radius must be > 0 metres; got {r}.")

    def coverage(self, x, y, cell):
        return disc_coverage(self.radius, self.centre[0], self.centre[1], x, y, cell)

    def max_radius(self):
        return self.radius + _safe_norm(self.centre[0], self.centre[1])

    def transformed(self, rotation=0.0, centre=(0.0, 0.0)) -> "Circle":
        """The circle with its centre moved (exact: a disc is rotation invariant)."""
        return Circle(self.radius, _rigid(self.centre, _float(rotation), _float(centre)))


class Spiders(eqx.Module):
    """``n`` straight vanes of ``width`` metres from the axis outwards, the first at
    angle ``rotation`` (radians), each ``length`` metres long, evenly spaced.

    Each vane's coverage is the product of its edges' half-plane fractions (approximate
    at the vane's corners). :class:`Struts` gives vanes at any angles, each with its own
    width and lateral offset, with exact area coverage."""

    n: int = eqx.field(static=True)
    width: Float[Array, ""]
    rotation: Float[Array, ""]
    length: Float[Array, ""]

    def __init__(self, n: int, width, rotation=0.0, length=1.0):
        if not isinstance(n, (int, np.integer)) or n < 1:
            raise ValueError(f"Spiders.n must be an integer >= 1; got {n!r}.")
        _check_build_count(n, "Spiders.n", "vanes")
        self.n = int(n)
        self.width = jnp.asarray(width, dtype=jnp.result_type(float))
        self.rotation = jnp.asarray(rotation, dtype=jnp.result_type(float))
        self.length = jnp.asarray(length, dtype=jnp.result_type(float))

    def transmission(self, x, y, cell):
        t = jnp.ones(jnp.broadcast_shapes(x.shape, y.shape), dtype=x.dtype)
        for k in range(self.n):
            th = self.rotation + 2 * math.pi * k / self.n
            c, s = jnp.cos(th), jnp.sin(th)
            w = 0.5 * self.width
            verts = jnp.stack(
                [
                    jnp.stack([w * s, -w * c]),
                    jnp.stack([self.length * c + w * s, self.length * s - w * c]),
                    jnp.stack([self.length * c - w * s, self.length * s + w * c]),
                    jnp.stack([-w * s, w * c]),
                ]
            )
            t = t * (1.0 - convex_polygon_coverage(verts, x, y, cell))
        return t

    def transformed(self, rotation=0.0, centre=(0.0, 0.0)) -> "Struts":
        """The same vanes rotated and moved, as :class:`Struts` (exact coverage)."""
        angles = self.rotation + rotation + 2 * math.pi * jnp.arange(self.n) / self.n
        return Struts(angles, self.width, 0.0, self.length,
                      centre=_rigid(jnp.zeros(2), _float(rotation), _float(centre)))


class Struts(eqx.Module):
    """Straight struts (spider vanes) at any angles, each with its own width and lateral
    offset: a transmission multiplier for :class:`Obstructed` (like :class:`Spiders`).

    Strut k is the rectangle of width ``widths[k]`` (metres) whose centre line runs from
    ``centre + offsets[k] n_k + start[k] u_k`` outwards along u_k = (cos a_k, sin a_k),
    a_k = ``angles[k]`` (radians, counter-clockwise from +x), for ``length[k]`` metres;
    n_k = (−sin a_k, cos a_k) is its left-hand normal, so a positive offset moves the
    strut counter-clockwise. ``length=None`` extends every strut beyond the edge of the
    grid it is evaluated on (beyond any pupil the grid holds). ``widths``, ``offsets``,
    ``start`` and ``length`` take a scalar (the same for every strut) or one value per
    strut. A strut through the whole pupil is a negative ``start``.

    Each rectangle's coverage of a cell is exact (the Green's-theorem edge terms of
    :func:`polygon_coverage`), so the raster is differentiable with respect to the
    angles, widths, offsets, start, length and centre. Struts combine as the product of
    their transmissions 1 − coverage: exact where a cell meets one strut; where two
    struts meet in one cell (near the centre, usually behind the obstruction) the
    product treats their coverages as independent.
    """

    angles: Float[Array, " k"]
    widths: Float[Array, " k"]
    offsets: Float[Array, " k"]
    start: Float[Array, " k"]
    length: Float[Array, " k"] | None
    centre: Float[Array, "2"]

    def __init__(self, angles, widths, offsets=0.0, length=None, *, start=0.0,
                 centre=(0.0, 0.0)):
        a = _float(angles)
        if a.ndim != 1 or a.shape[0] < 1:
            raise ValueError(
                f"Struts.angles must be a 1-D array of at least one angle (radians); got "
                f"shape {a.shape}.")
        k = a.shape[0]
        _check_build_count(k, "Struts.angles", "struts")

        def per_strut(name, v):
            v = _float(v)
            if v.ndim == 0:
                v = jnp.broadcast_to(v, (k,))
            if v.shape != (k,):
                raise ValueError(
                    f"Struts.{name} must be a scalar or have one value per strut ({k}); got "
                    f"shape {v.shape}.")
            return v

        self.angles = a
        self.widths = per_strut("widths", widths)
        self.offsets = per_strut("offsets", offsets)
        self.start = per_strut("start", start)
        self.length = None if length is None else per_strut("length", length)
        self.centre = _float(centre)
        if self.centre.shape != (2,):
            raise ValueError(f"Struts.centre must be (x, y); got shape {self.centre.shape}.")
        for name in ("angles", "widths", "offsets", "start", "length", "centre"):
            v = getattr(self, name)
            c = None if v is None else _concrete(v)
            if c is None:
                continue
            if not np.all(np.isfinite(c)):
                raise ValueError(f"Struts.{name} contains NaN or infinity: {c.tolist()}.")
            if name in ("widths", "length") and np.any(c <= 0):
                raise ValueError(f"Struts.{name} must be > 0 metres; got {c.tolist()}.")

    def rectangles(self, reach=None) -> Float[Array, "k 4 2"]:
        """Each strut's corners (k, 4, 2), counter-clockwise. ``reach`` (metres): for
        struts without a length, how far past ``|start|`` they run (beyond the grid)."""
        u = jnp.stack([jnp.cos(self.angles), jnp.sin(self.angles)], axis=-1)
        n = jnp.stack([-u[:, 1], u[:, 0]], axis=-1)
        t0 = self.start
        if self.length is not None:
            t1 = self.start + self.length
        else:
            if reach is None:
                raise ValueError("Struts without a length need a reach (the grid's extent).")
            t1 = jnp.abs(self.start) + reach
        base = self.centre + self.offsets[:, None] * n
        hw = 0.5 * self.widths[:, None] * n
        corners = [base + t0[:, None] * u - hw, base + t1[:, None] * u - hw,
                   base + t1[:, None] * u + hw, base + t0[:, None] * u + hw]
        return jnp.stack(corners, axis=1)

    def _reach(self, x, y, cell):
        if self.length is not None:
            return None
        ext = (jnp.max(jnp.abs(x - self.centre[0])) + jnp.max(jnp.abs(y - self.centre[1]))
               + 2 * jnp.abs(cell))
        return jax.lax.stop_gradient(ext)

    def transmission(self, x, y, cell, *, tiled: bool = False) -> Array:
        """Π_k (1 − coverage of strut k) on cells of side ``cell`` centred at (x, y).
        ``tiled=True``: the cells tile the plane (:func:`tiled_outline_coverage`)."""
        rect = self.rectangles(self._reach(x, y, cell))
        outline = tiled_outline_coverage if tiled else outline_coverage
        shape = jnp.broadcast_shapes(x.shape, y.shape)

        def step(t, r):
            return t * (1.0 - outline(r, jnp.roll(r, -1, axis=0), x, y, cell)), None

        t, _ = jax.lax.scan(step, jnp.ones(shape, jnp.result_type(x, y, rect)), rect)
        return t

    def occlusion(self, x, y, cell) -> Array:
        """1 − transmission: the fraction of each cell the struts block."""
        return 1.0 - self.transmission(x, y, cell)

    def transformed(self, rotation=0.0, centre=(0.0, 0.0)) -> "Struts":
        """The struts rotated by ``rotation`` about the axis, then shifted (exact)."""
        rotation = _float(rotation)
        return Struts(self.angles + rotation, self.widths, self.offsets, self.length,
                      start=self.start, centre=_rigid(self.centre, rotation, _float(centre)))


class Obstructed(AbstractPupil):
    """An outer pupil with an optional central obstruction (a :class:`Circle` or any
    pupil) and optional vanes (:class:`Spiders` or :class:`Struts`), each multiplying
    the outer pupil's coverage by its transmission."""

    outer: AbstractPupil
    obstruction: AbstractPupil | None = None
    spiders: Spiders | Struts | None = None

    def coverage(self, x, y, cell):
        return self._with_stops(self.outer.coverage(x, y, cell), x, y, cell, False)

    def tiled_coverage(self, x, y, cell):
        return self._with_stops(self.outer.tiled_coverage(x, y, cell), x, y, cell, True)

    def _with_stops(self, cov, x, y, cell, tiled):
        if self.obstruction is not None:
            ob = self.obstruction.tiled_coverage if tiled else self.obstruction.coverage
            cov = cov * (1.0 - ob(x, y, cell))
        if isinstance(self.spiders, Struts):
            cov = cov * self.spiders.transmission(x, y, cell, tiled=tiled)
        elif self.spiders is not None:
            cov = cov * self.spiders.transmission(x, y, cell)
        return cov

    def max_radius(self):
        return self.outer.max_radius()

    def transformed(self, rotation=0.0, centre=(0.0, 0.0)) -> "Obstructed":
        """Every part rotated about the axis, then shifted (exact for polygons, circles
        and struts; evenly spaced :class:`Spiders` become :class:`Struts`)."""
        c = (0.0, 0.0) if centre is None else centre
        return Obstructed(
            self.outer.transformed(rotation, c),
            None if self.obstruction is None else self.obstruction.transformed(rotation, c),
            None if self.spiders is None else self.spiders.transformed(rotation, c),
        )


# --- unions of polygons; hexagonal segments ------------------------------------------


def _is_convex(v: np.ndarray, tol: float) -> bool:
    d = np.roll(v, -1, axis=0) - v
    cross = d[:, 0] * np.roll(d[:, 1], -1) - d[:, 1] * np.roll(d[:, 0], -1)
    return bool(np.all(cross >= -tol))


def _convex_overlap(a: np.ndarray, b: np.ndarray, tol: float) -> bool:
    """Whether two convex polygons' interiors overlap by more than ``tol`` (metres),
    by the separating-axis theorem."""
    for p in (a, b):
        d = np.roll(p, -1, axis=0) - p
        n = np.stack([d[:, 1], -d[:, 0]], axis=1)
        n = n / np.maximum(np.hypot(n[:, 0], n[:, 1]), 1e-300)[:, None]
        pa, pb = a @ n.T, b @ n.T
        depth = np.minimum(pa.max(0), pb.max(0)) - np.maximum(pa.min(0), pb.min(0))
        if np.any(depth <= tol):
            return False
    return True


def _dist_to_outline(p: np.ndarray, v: np.ndarray) -> float:
    w = np.roll(v, -1, axis=0)
    d = w - v
    t = np.clip(np.sum((p - v) * d, axis=1) / np.maximum(np.sum(d * d, axis=1), 1e-300), 0, 1)
    q = v + t[:, None] * d
    return float(np.min(np.hypot(*(p - q).T)))


def _inside(p: np.ndarray, v: np.ndarray) -> bool:
    """Even–odd point-in-polygon test."""
    w = np.roll(v, -1, axis=0)
    cond = (v[:, 1] > p[1]) != (w[:, 1] > p[1])
    with np.errstate(divide="ignore", invalid="ignore"):
        xc = v[:, 0] + (p[1] - v[:, 1]) * (w[:, 0] - v[:, 0]) / (w[:, 1] - v[:, 1])
    return bool(np.sum(cond & (p[0] < xc)) % 2)


def _general_overlap(a: np.ndarray, b: np.ndarray, tol: float) -> bool:
    """Whether two simple polygons' interiors overlap: edges crossing properly, or a
    vertex or an inward-nudged edge midpoint of one strictly inside the other."""
    aw, bw = np.roll(a, -1, axis=0), np.roll(b, -1, axis=0)
    for i in range(len(a)):
        for j in range(len(b)):
            if _segments_cross(a[i], aw[i], b[j], bw[j]):
                return True
    for p, pw, q in ((a, aw, b), (b, bw, a)):
        d = pw - p
        inward = np.stack([-d[:, 1], d[:, 0]], axis=1)
        inward = inward / np.maximum(np.hypot(inward[:, 0], inward[:, 1]), 1e-300)[:, None]
        pts = np.concatenate([p, 0.5 * (p + pw) + 10 * tol * inward])
        for pt in pts:
            if _inside(pt, q) and _dist_to_outline(pt, q) > tol:
                return True
    return False


def _check_no_overlap(members, name: str = "Union") -> None:
    """Raise if two concrete straight-edged members overlap (more than a 1e-9 relative
    sliver: touching edges are allowed). Traced or curved members are not checked."""
    polys = []
    for i, m in enumerate(members):
        e = m.outline_edges()
        v = None if e is None else _concrete(e[0])
        if v is not None and np.all(np.isfinite(v)):
            polys.append((i, np.asarray(v, np.float64)))
    if len(polys) < 2:
        return
    allv = np.concatenate([v for _, v in polys])
    tol = 1e-9 * float(np.max(np.abs(allv)) or 1.0)
    boxes = [(v.min(0), v.max(0)) for _, v in polys]
    convex = [_is_convex(v, tol * tol) for _, v in polys]
    for a in range(len(polys)):
        for b in range(a + 1, len(polys)):
            lo = np.maximum(boxes[a][0], boxes[b][0])
            hi = np.minimum(boxes[a][1], boxes[b][1])
            if np.any(hi - lo <= tol):
                continue
            va, vb = polys[a][1], polys[b][1]
            hit = (_convex_overlap(va, vb, tol) if convex[a] and convex[b]
                   else _general_overlap(va, vb, tol))
            if hit:
                raise ValueError(
                    f"{name}: members {polys[a][0]} and {polys[b][0]} overlap; the members "
                    "of a union must not overlap (its coverage is the sum of theirs, which "
                    "would count the overlap twice).")


class Union(AbstractPupil):
    """The union of non-overlapping pupils (polygons, regular polygons, curved irises,
    or any pupil): its coverage is the sum of the members' coverages.

    The members must not overlap (they may touch): a sum counts an overlap twice and
    clipping it at 1 would not be the area coverage of the union either. Where the
    members' vertices are concrete (built outside jit) this is checked for straight-
    edged members and a ``ValueError`` names the pair; ``check_overlap=False`` skips the
    check. Straight-edged members (those with :meth:`AbstractPupil.outline_edges`)
    are rasterised together, all their edges in one scan, so compile time does not grow
    with the number of members; ``tiled_coverage`` goes through the members' own.
    Nested unions are flattened.
    """

    members: tuple[AbstractPupil, ...]

    def __init__(self, polygons, *, check_overlap: bool = True):
        flat: list[AbstractPupil] = []
        for m in polygons:
            if isinstance(m, Union):
                flat.extend(m.members)
            elif isinstance(m, AbstractPupil):
                flat.append(m)
            else:
                raise TypeError(
                    f"Union members must be difstar pupils (Polygon, RegularPolygon, ...); "
                    f"got {type(m).__name__}.")
        if not flat:
            raise ValueError("Union needs at least one member.")
        self.members = tuple(flat)
        if check_overlap:
            _check_no_overlap(self.members)

    def _split(self):
        edges, others = [], []
        for m in self.members:
            e = m.outline_edges()
            (others.append(m) if e is None else edges.append(e))
        return edges, others

    def _cover(self, x, y, cell, tiled):
        edges, others = self._split()
        total = None
        if edges:
            v0 = jnp.concatenate([e[0] for e in edges])
            v1 = jnp.concatenate([e[1] for e in edges])
            total = (tiled_outline_coverage if tiled else outline_coverage)(v0, v1, x, y, cell)
        for m in others:
            c = (m.tiled_coverage if tiled else m.coverage)(x, y, cell)
            total = c if total is None else total + c
        return total

    def coverage(self, x, y, cell):
        return self._cover(x, y, cell, False)

    def tiled_coverage(self, x, y, cell):
        return self._cover(x, y, cell, True)

    def max_radius(self):
        return jnp.max(jnp.stack([jnp.asarray(m.max_radius()) for m in self.members]))

    def outline_edges(self):
        edges, others = self._split()
        if others:
            return None
        return (jnp.concatenate([e[0] for e in edges]), jnp.concatenate([e[1] for e in edges]))

    def area(self) -> Array:
        """Open area (m²): the sum of the members' areas (members with an ``area``
        method or a straight outline)."""
        total = 0.0
        for m in self.members:
            if hasattr(m, "area"):
                total = total + m.area()
                continue
            e = m.outline_edges()
            if e is None:
                raise TypeError(f"Union.area: member {type(m).__name__} has no area.")
            total = total + 0.5 * jnp.sum(e[0][:, 0] * e[1][:, 1] - e[1][:, 0] * e[0][:, 1])
        return total

    def transformed(self, rotation=0.0, centre=(0.0, 0.0)) -> "Union":
        """Every member rotated about the axis, then shifted (exact for straight-edged
        members). Rigid motions keep non-overlapping members apart: not re-checked."""
        c = (0.0, 0.0) if centre is None else centre
        return Union([m.transformed(rotation, c) for m in self.members], check_overlap=False)


def _hex_lattice(rings: int, include_centre: bool) -> np.ndarray:
    """Integer axial coordinates (m, 2) of the cells of a hexagonal lattice, ring by
    ring (the centre first if included), each ring counter-clockwise from angle 30°."""
    out = []
    for k in range(0 if include_centre else 1, rings + 1):
        ring = [(q, r) for q in range(-k, k + 1) for r in range(-k, k + 1)
                if max(abs(q), abs(r), abs(q + r)) == k]
        # unit-pitch positions: q (cos 30°, sin 30°) + r (0, 1)
        ang = [math.atan2(0.5 * q + r, 0.5 * math.sqrt(3) * q) for q, r in ring]
        ang = [(a - math.pi / 6) % (2 * math.pi) for a in ang]
        out.extend(p for _, p in sorted(zip(np.round(ang, 9), ring)))
    return np.asarray(out, dtype=np.float64).reshape(-1, 2)


def hex_segment_centres(rings: int, pitch, *, rotation=0.0, centre=(0.0, 0.0),
                        include_centre: bool = False) -> Float[Array, "m 2"]:
    """Centres (m, 2) of the segments :func:`hex_segments` builds, in its order: ring by
    ring from the inside (the centre segment first when included), each ring counter-
    clockwise starting from the segment at angle ``rotation`` + 30° (ring 1; outer
    rings start at the first segment at or after that angle). Neighbouring centres are
    ``pitch`` apart along the segments' edge normals (at ``rotation`` + 30° + k 60°)."""
    q = _hex_lattice(rings, include_centre)
    unit = np.stack([0.5 * math.sqrt(3) * q[:, 0], 0.5 * q[:, 0] + q[:, 1]], axis=1)
    return _rigid(jnp.asarray(unit) * _float(pitch), _float(rotation), _float(centre))


def hex_segments(rings: int, flat_to_flat, gap, rotation=0.0, centre=(0.0, 0.0),
                 missing=(), *, include_centre: bool = False) -> Union:
    """A segmented aperture: a :class:`Union` of regular hexagonal :class:`Polygon`
    segments on a hexagonal lattice (JWST-like: ``rings=2`` without the centre gives 18
    segments).

    flat_to_flat: each segment's width across flats (metres). gap: the distance between
    the facing flat edges of neighbouring segments (metres, ≥ 0), so centres are
    ``flat_to_flat + gap`` apart. rotation: radians; at 0 each segment has a vertex on
    its +x axis (flat top and bottom) and the lattice is rotated with the segments.
    centre: (x, y) of the lattice's centre (metres). missing: indices (in the order of
    :func:`hex_segment_centres`) of segments to leave out. include_centre: whether the
    central segment is present (index 0 when it is). Vertices counter-clockwise;
    differentiable with respect to ``flat_to_flat``, ``gap``, ``rotation``, ``centre``.
    """
    if not isinstance(rings, (int, np.integer)) or rings < (0 if include_centre else 1):
        raise ValueError(
            f"hex_segments: rings must be an integer >= {0 if include_centre else 1}; got "
            f"{rings!r}.")
    f2f, g = _float(flat_to_flat), _float(gap)
    cf, cg = _concrete(f2f), _concrete(g)
    if cf is not None and not (np.isfinite(cf) and cf > 0):
        raise ValueError(f"hex_segments: flat_to_flat must be > 0 metres; got {cf}.")
    if cg is not None and not (np.isfinite(cg) and cg >= 0):
        raise ValueError(f"hex_segments: gap must be >= 0 metres; got {cg}.")
    rotation, centre_a = _float(rotation), _float(centre)
    centres = hex_segment_centres(rings, f2f + g, rotation=rotation, centre=centre_a,
                                  include_centre=include_centre)
    m = centres.shape[0]
    miss = sorted({int(i) for i in missing})
    if any(not 0 <= i < m for i in miss):
        raise ValueError(f"hex_segments: missing indices must be in [0, {m}); got {miss}.")
    keep = [i for i in range(m) if i not in miss]
    if not keep:
        raise ValueError("hex_segments: every segment is missing.")
    circ = f2f / math.sqrt(3)
    hexagon = regular_polygon_vertices(6, circ, rotation)
    segs = [Polygon(centres[i] + hexagon) for i in keep]
    return Union(segs, check_overlap=False)  # disjoint by construction when gap >= 0


# --- a linear map of the pupil plane (an image-plane distortion) ---------------------


def distorted(pupil, matrix):
    """``pupil`` with every point p mapped to ``matrix`` @ p (a 2 × 2 linear map with a
    positive determinant, traceable): the pupil that produces the image of the
    original pupil seen through the image-plane linear map D = matrix^(−T) (Fraunhofer:
    transforming the pupil by B transforms the far field by B^(−T)), e.g. a detector or
    resampling grid with a shear or unequal x and y scales.

    Exact for polygons, unions of them and :class:`Struts` (their centre lines and
    widths are mapped; their far ends, beyond the pupil, stay square). A :class:`Circle`
    becomes the circle of the same area (an ellipse with axes differing by the map's
    anisotropy would be exact: a first-order error in that anisotropy on the circle's
    own, round, contribution to the image). :class:`Obstructed` maps its parts. Other
    pupils raise ``TypeError``.
    """
    m = _float(matrix)
    if m.shape != (2, 2):
        raise ValueError(f"distorted: matrix must be 2 × 2; got shape {m.shape}.")
    det = m[0, 0] * m[1, 1] - m[0, 1] * m[1, 0]
    c = _concrete(det)
    if c is not None and not (np.isfinite(c) and c > 0):
        raise ValueError(f"distorted: the matrix's determinant must be > 0 (no "
                         f"reflection, not singular); got {float(c)}.")
    if isinstance(pupil, Polygon):
        return Polygon(pupil.vertices @ m.T)
    if isinstance(pupil, RegularPolygon):
        return distorted(Polygon(pupil.outline_edges()[0]), m)
    if isinstance(pupil, Union):
        return Union([distorted(q, m) for q in pupil.members], check_overlap=False)
    if isinstance(pupil, Circle):
        return Circle(pupil.radius * jnp.sqrt(det), m @ pupil.centre)
    if isinstance(pupil, Obstructed):
        return Obstructed(distorted(pupil.outer, m),
                          None if pupil.obstruction is None
                          else distorted(pupil.obstruction, m),
                          None if pupil.spiders is None else distorted(pupil.spiders, m))
    if isinstance(pupil, Spiders):
        return distorted(pupil.transformed(0.0), m)
    if isinstance(pupil, Struts):
        u = jnp.stack([jnp.cos(pupil.angles), jnp.sin(pupil.angles)], axis=-1) @ m.T
        stretch = _safe_norm(u[:, 0], u[:, 1])  # |M u|: lengths along the strut
        across = det / stretch  # widths and offsets across it
        return Struts(jnp.arctan2(u[:, 1], u[:, 0]), pupil.widths * across,
                      pupil.offsets * across,
                      None if pupil.length is None else pupil.length * stretch,
                      start=pupil.start * stretch, centre=m @ pupil.centre)
    raise TypeError(f"distorted: {type(pupil).__name__} is not supported (polygons, unions, "
                    "circles, struts and obstructed pupils are).")


# --- any pupil rotated and shifted --------------------------------------------------


class Transformed(AbstractPupil):
    """``pupil`` rotated by ``rotation`` (radians, counter-clockwise) about the optical
    axis, then shifted by ``centre`` (x, y metres): p → R p + centre.

    Straight-edged pupils (those with an outline: polygons, curved irises, unions of
    them) are transformed exactly, through their edges. Others (a :class:`Mask`, or a
    union or obstructed pupil holding one) are evaluated at the inversely transformed
    cell centres with the cell kept square in the pupil's own frame: a rotated square
    cell is not a square cell, so the coverage of edge cells is approximate (exact for
    shifts and for rotations by multiples of 90°); inside and outside the shape it is
    exact. Prefer ``pupil.transformed(rotation, centre)``, which returns the exact
    transformed shape of the pupil's own type where it can (Polygon, RegularPolygon,
    Circle, Union, Obstructed, Struts) and this wrapper otherwise.
    """

    pupil: AbstractPupil
    rotation: Float[Array, ""]
    centre: Float[Array, "2"]

    def __init__(self, pupil, rotation=0.0, centre=(0.0, 0.0)):
        if not isinstance(pupil, AbstractPupil):
            raise TypeError(
                f"Transformed.pupil must be a difstar pupil; got {type(pupil).__name__}.")
        self.pupil = pupil
        self.rotation = _float(rotation)
        self.centre = _float(centre)
        if self.rotation.shape != () or self.centre.shape != (2,):
            raise ValueError(
                f"Transformed: rotation must be a scalar and centre (x, y); got shapes "
                f"{self.rotation.shape} and {self.centre.shape}.")
        for name in ("rotation", "centre"):
            c = _concrete(getattr(self, name))
            if c is not None and not np.all(np.isfinite(c)):
                raise ValueError(f"Transformed.{name} contains NaN or infinity.")

    def outline_edges(self):
        e = self.pupil.outline_edges()
        if e is None:
            return None
        return (_rigid(e[0], self.rotation, self.centre), _rigid(e[1], self.rotation, self.centre))

    def _inverse(self, x, y):
        c, s = jnp.cos(self.rotation), jnp.sin(self.rotation)
        dx, dy = x - self.centre[0], y - self.centre[1]
        return c * dx + s * dy, -s * dx + c * dy

    def coverage(self, x, y, cell):
        e = self.outline_edges()
        if e is not None:
            return outline_coverage(*e, x, y, cell)
        return self.pupil.coverage(*self._inverse(x, y), cell)

    def tiled_coverage(self, x, y, cell):
        e = self.outline_edges()
        if e is not None:
            return tiled_outline_coverage(*e, x, y, cell)
        return self.coverage(x, y, cell)

    def max_radius(self):
        e = self.outline_edges()
        if e is not None:
            return jnp.max(_safe_norm(e[0][:, 0], e[0][:, 1]))
        return self.pupil.max_radius() + _safe_norm(self.centre[0], self.centre[1])

    def transformed(self, rotation=0.0, centre=(0.0, 0.0)) -> "Transformed":
        rotation = _float(rotation)
        c = (0.0, 0.0) if centre is None else centre
        return Transformed(self.pupil, self.rotation + rotation,
                           _rigid(self.centre, rotation, _float(c)))


# --- rasters -------------------------------------------------------------------------


def _cumulative(v: Array, axis: int) -> Array:
    """Cumulative sums at the pixel edges along ``axis`` (a zero prepended)."""
    pad = [(0, 0)] * v.ndim
    pad[axis] = (1, 0)
    return jnp.pad(jnp.cumsum(v, axis=axis), pad)


def _interp_edges(c: Array, u: Array, axis: int) -> Array:
    """The integral of a piecewise-constant row up to position ``u`` (pixel units,
    clamped to [0, n]): linear between the cumulative sums ``c`` at the pixel edges."""
    n = c.shape[axis] - 1
    u = jnp.clip(u, 0.0, n)
    k = jnp.clip(jnp.floor(u).astype(jnp.int32), 0, n - 1)
    lo = jnp.take(c, k, axis=axis)
    hi = jnp.take(c, k + 1, axis=axis)
    f = (u - k).reshape((1,) * axis + (-1,) + (1,) * (c.ndim - axis - 1))
    return lo + f * (hi - lo)


_OPEN = 1e-9  # a Mask pixel above this is open (for max_radius)


class Mask(AbstractPupil):
    """A pre-rasterised aperture: ``values`` (h, w) on square pixels of side ``pitch``
    metres, row 0 at the top (y up), the raster centred at ``centre`` (default the axis).

    Each value is the open fraction (area coverage) of its own pixel, in [0, 1] (rounding
    within 1e-9 is clipped): a
    boolean mask is read as 0/1 coverage (a True pixel is fully open, a False one fully
    closed); float masks must be finite and within [0, 1]. The mask is the piecewise-
    constant shape these pixels describe, and ``coverage`` resamples it by area to the
    requested cells: the open area inside each cell (the integral of the pixel values
    over the cell, from cumulative sums along each axis: exact for this piecewise-
    constant shape at any cell size and position) divided by the cell's area. The
    raster is therefore an area coverage like the analytic shapes' (a boolean mask's
    staircase edge is resolved at its own pitch, not at the grid's). Differentiable
    with respect to the values (and the cell positions), not the outline geometry. Cells
    on rows and columns (x (1, W), y (H, 1)) take two 1-D passes; arbitrary cell centres
    (a rotated mask, see :class:`Transformed`) use the 2-D summed-area table, whose
    large partial sums lose digits in float32 for big masks.

    ``max_radius`` is tight: the distance from the axis to the farthest corner of an
    open pixel (value above 1e-9: rounding noise of a computed coverage is closed).
    """

    values: Float[Array, "h w"]
    pitch: float = eqx.field(static=True)
    centre: Float[Array, "2"]

    def __init__(self, values, pitch, centre=(0.0, 0.0)):
        v = jnp.asarray(values)
        if v.ndim != 2 or min(v.shape) < 1:
            raise ValueError(f"Mask.values must be a 2-D (h, w) array; got shape {v.shape}.")
        if v.dtype == jnp.bool_ or jnp.issubdtype(v.dtype, jnp.integer):
            c = _concrete(v)
            if c is not None and v.dtype != jnp.bool_ and not np.all((c == 0) | (c == 1)):
                raise ValueError(
                    "Mask.values: an integer mask must hold only 0 and 1 (or give floats "
                    "in [0, 1], the open fraction of each pixel).")
            v = v.astype(jnp.result_type(float))
        else:
            c = _concrete(v)
            if c is not None:
                if not np.all(np.isfinite(c)):
                    raise ValueError("Mask.values contains NaN or infinity.")
                if c.min() < -1e-9 or c.max() > 1 + 1e-9:
                    raise ValueError(
                        f"Mask.values must be coverage fractions in [0, 1]; got the range "
                        f"[{c.min()}, {c.max()}].")
                if c.min() < 0 or c.max() > 1:  # rounding (e.g. a computed coverage)
                    v = jnp.clip(v, 0.0, 1.0)
        try:
            p = float(pitch)
        except (TypeError, jax.errors.ConcretizationTypeError) as e:
            raise ValueError("Mask.pitch must be a concrete number of metres.") from e
        if not (math.isfinite(p) and p > 0):
            raise ValueError(f"Mask.pitch must be > 0 metres; got {p}.")
        self.values = v
        self.pitch = p
        self.centre = _float(centre)
        if self.centre.shape != (2,):
            raise ValueError(f"Mask.centre must be (x, y); got shape {self.centre.shape}.")
        c = _concrete(v)
        if c is not None and not np.any(c > _OPEN):
            raise ValueError("Mask.values is zero everywhere: the aperture is closed.")

    def _pixel_units(self, x, y):
        h, w = self.values.shape
        u = (x - self.centre[0]) / self.pitch + 0.5 * w  # from the left edge
        v = (self.centre[1] - y) / self.pitch + 0.5 * h  # from the top edge, rows down
        return u, v

    def coverage(self, x, y, cell):
        vals = self.values.astype(jnp.result_type(self.values, x, y))
        half = 0.5 * cell / self.pitch
        u, v = self._pixel_units(x, y)
        scale = (self.pitch / cell) ** 2
        if x.ndim == 2 and y.ndim == 2 and x.shape[0] == 1 and y.shape[1] == 1:
            u, v = u.reshape(-1), v.reshape(-1)
            cx = _cumulative(vals, 1)  # (h, w + 1)
            rows = _interp_edges(cx, u + half, 1) - _interp_edges(cx, u - half, 1)  # (h, W)
            cy = _cumulative(rows, 0)  # (h + 1, W)
            return (_interp_edges(cy, v + half, 0) - _interp_edges(cy, v - half, 0)) * scale
        shape = jnp.broadcast_shapes(x.shape, y.shape)
        u, v = jnp.broadcast_to(u, shape), jnp.broadcast_to(v, shape)
        s = _cumulative(_cumulative(vals, 0), 1)  # (h + 1, w + 1) summed-area table
        h, w = vals.shape

        def table(uu, vv):  # bilinear in the table: exact for piecewise-constant pixels
            uu, vv = jnp.clip(uu, 0.0, w), jnp.clip(vv, 0.0, h)
            i = jnp.clip(jnp.floor(vv).astype(jnp.int32), 0, h - 1)
            j = jnp.clip(jnp.floor(uu).astype(jnp.int32), 0, w - 1)
            fv, fu = vv - i, uu - j
            return ((1 - fv) * ((1 - fu) * s[i, j] + fu * s[i, j + 1])
                    + fv * ((1 - fu) * s[i + 1, j] + fu * s[i + 1, j + 1]))

        area = (table(u + half, v + half) - table(u - half, v + half)
                - table(u + half, v - half) + table(u - half, v - half))
        return area * scale

    def max_radius(self):
        h, w = self.values.shape
        xe = self.centre[0] + (jnp.arange(w + 1) - 0.5 * w) * self.pitch
        ye = self.centre[1] + (0.5 * h - jnp.arange(h + 1)) * self.pitch
        fx = jnp.maximum(jnp.abs(xe[:-1]), jnp.abs(xe[1:]))
        fy = jnp.maximum(jnp.abs(ye[:-1]), jnp.abs(ye[1:]))
        r = jnp.sqrt(fy[:, None] ** 2 + fx[None, :] ** 2)
        return jnp.max(jnp.where(self.values > _OPEN, r, 0.0))

    def area(self) -> Array:
        """Open area (m²): Σ values × pitch²."""
        return jnp.sum(self.values) * self.pitch**2

    def transformed(self, rotation=0.0, centre=(0.0, 0.0)) -> AbstractPupil:
        """Shifted only (``rotation`` statically 0): the same mask with its centre moved,
        exact. Otherwise the :class:`Transformed` wrapper (approximate at edges)."""
        c = _float((0.0, 0.0) if centre is None else centre)
        if isinstance(rotation, (int, float)) and rotation == 0:
            return Mask(self.values, self.pitch, self.centre + c)
        # R p + c = R (p + R⁻¹ c): shift the mask itself, then rotate about the axis, so
        # that max_radius stays tight (a rotation about the axis keeps radii)
        rotation = _float(rotation)
        moved = Mask(self.values, self.pitch, self.centre + _rigid(c, -rotation, jnp.zeros(2)))
        return Transformed(moved, rotation, (0.0, 0.0))
