"""Unions of pupils that do not overlap (checked when built), and segmented mirrors of
hexagonal segments."""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from .._custom_types import Array, Float
from ._base import AbstractPupil, _concrete, _float, _rigid, _segments_cross
from ._polygons import Polygon, regular_polygon_vertices
from ._raster import outline_coverage, tiled_outline_coverage


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
