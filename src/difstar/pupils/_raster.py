"""Rasterising outlines by area coverage: the fraction of each square sample cell inside
a half-plane, an edge, a polygon's outline (exact, by Green's theorem on each edge) or a
disc; differentiable in the vertices, radius and rotation."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .._custom_types import Array, Float

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
    consecutive breaks the edge lies in one cell. Returns (s_lo, s_hi, row, col), each
    (e, W + H + 3): the pieces and their cells' indices, off the grid (below 0, or W or H
    and beyond) where a piece lies beyond it; a piece with s_hi = s_lo has no length.
    Primal-only work, O(e (W + H) log(W + H)).
    """
    w, h = x.shape[-1], y.shape[0]
    x0, sx = _axis(x)
    y0, sy = _axis(y)
    d = v1 - v0

    def breaks(c0, step, count, a, da):  # ascending: the lines in the edge's direction
        lines = c0 + (jnp.arange(count + 1, dtype=a.dtype) - 0.5) * step
        ok = (da != 0)[:, None]
        s = (lines[None, :] - a[:, None]) / jnp.where(ok, da[:, None], 1.0)
        s = jnp.where(ok, jnp.clip(s, 0.0, 1.0), 0.0)
        return jnp.where((step * da < 0)[:, None], s[:, ::-1], s)

    def merge(a, b):  # two ascending rows into one (a sort of them costs 10× more)
        at = jnp.arange(a.shape[0]) + jnp.searchsorted(b, a, side="left")
        bt = jnp.arange(b.shape[0]) + jnp.searchsorted(a, b, side="right")
        return jnp.zeros(a.shape[0] + b.shape[0], a.dtype).at[at].set(a).at[bt].set(b)

    e = v0.shape[0]
    s = jnp.concatenate(
        [jnp.zeros((e, 1), d.dtype),
         jax.vmap(merge)(breaks(x0, sx, w, v0[:, 0], d[:, 0]),
                         breaks(y0, sy, h, v0[:, 1], d[:, 1])),
         jnp.ones((e, 1), d.dtype)], axis=1)
    lo, hi = s[:, :-1], s[:, 1:]
    mid = 0.5 * (lo + hi)
    col = jnp.floor((v0[:, :1] + mid * d[:, :1] - x0) / sx + 0.5).astype(jnp.int32)
    row = jnp.floor((v0[:, 1:] + mid * d[:, 1:] - y0) / sy + 0.5).astype(jnp.int32)
    return lo, hi, row, col

def _on_grid(lo, hi, row, col, h: int, w: int):
    """(on, row, col) of :func:`_cell_pieces`' pieces: whether each has length and lies
    on the H × W grid, and its cell's indices clipped to the grid."""
    on = (hi > lo) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
    return on, jnp.clip(row, 0, h - 1), jnp.clip(col, 0, w - 1)

#: Planes of at least this many cells take their cumulative sums as a parallel scan.
#: On 2 CPU cores, on the paper's defocused 1250² window (987 × 986 cells) XLA's cumsum
#: (a reduce-window) took 2.4 ms and the scan 0.45 ms; on the JWST fit's 253 × 252
#: planes, inside its model image, the scan made the image slower (18 → 30 ms).
SCAN_CELLS = 2**18


def _cumulative_rows(a: Array) -> Array:
    """Cumulative sum of ``a`` down its rows (axis 0), by the faster way for its size."""
    if a.size >= SCAN_CELLS:
        return jax.lax.associative_scan(jnp.add, a, axis=0)
    return jnp.cumsum(a, axis=0)

def _tiled_primal(v0, v1, x, y, cell, pieces=None):
    """:func:`outline_coverage` on cells that tile the plane, from the edges' cell pieces
    (:func:`_cell_pieces`) instead of every edge over every cell: O(e (W + H)) work and
    a cumulative sum over the rows, where the edge-by-edge raster costs e passes over
    the W × H plane (the 18 hexagons of a segmented pupil: 108 passes).

    Green's term of a piece in cell (row, col), ∫ clamp(y − y_bottom, 0, cell) dx over
    the piece, is its mean height above the bottom of its own cell times its run in x,
    the whole cell side for every cell of its column below it, and nothing above it.
    ``pieces``: :func:`_cell_pieces`' result where the caller has it already."""
    h, w = y.shape[0], x.shape[-1]
    _, sy = _axis(y)
    lo, hi, row, col = _cell_pieces(v0, v1, x, y) if pieces is None else pieces
    d = v1 - v0
    dtype = jnp.result_type(x, y, v0)
    cell = jnp.asarray(cell, dtype)
    run = (hi - lo) * d[:, :1]  # each piece's signed run in x
    on, rows, cols = _on_grid(lo, hi, row, col, h, w)
    height = v0[:, 1:] + 0.5 * (lo + hi) * d[:, 1:] - (y.reshape(-1)[rows] - 0.5 * cell)
    # the pieces' own cells
    own = jnp.where(on, -run * height / (cell * cell), 0.0)
    total = jnp.zeros(h * w, dtype).at[(rows * w + cols).reshape(-1)].add(
        own.reshape(-1)).reshape(h, w)
    # the cells below each piece in its column (y lower: rows before it where y rises
    # with the row, after it where y falls), by a cumulative sum over the rows: a piece
    # above the grid reaches every row, one below it none
    full = jnp.where((hi > lo) & (col >= 0) & (col < w), -run / cell, 0.0).reshape(-1)
    rising = sy > 0
    k = jnp.where(rising, jnp.clip(row, 0, h), jnp.clip(row, -1, h - 1) + 1)
    steps = jnp.zeros((h + 1) * w, dtype).at[(k * w + cols).reshape(-1)].add(full)
    steps = steps.reshape(h + 1, w)
    # one cumulative sum: rows before r, Σ over k ≤ r; rows after r, Σ over k > r, the
    # column's total less that
    down = _cumulative_rows(steps)
    return total + jnp.where(rising, down[h] - down[:h], down[:h])

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
    return _tiled_primal(v0, v1, x, y, cell)

@tiled_outline_coverage.defjvp
def _tiled_outline_jvp(primals, tangents):
    v0, v1, x, y, cell = primals
    dv0, dv1, dx, dy, dcell = tangents
    pieces = _cell_pieces(v0, v1, x, y)  # one computation for the value and its tangent
    out = _tiled_primal(v0, v1, x, y, cell, pieces)
    h, w = out.shape
    lo, hi, row, col = pieces
    inside, row, col = _on_grid(lo, hi, row, col, h, w)
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
