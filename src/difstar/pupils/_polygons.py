"""Polygons and circles: a free polygon, a regular n-gon (an iris of straight blades)
and a circle."""

from __future__ import annotations

import math

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from .._custom_types import Array, Float
from ._base import (
    AbstractPupil,
    _check_build_count,
    _check_ccw_simple,
    _concrete,
    _float,
    _is_origin,
    _rigid,
)
from ._raster import _safe_norm, disc_coverage, polygon_coverage


class Polygon(AbstractPupil):
    """Simple polygon (convex or not) with ``vertices`` an (n, 2) array of (x, y) in
    metres, counter-clockwise."""

    vertices: Float[Array, "n 2"]

    def __init__(self, vertices):
        try:
            v = jnp.asarray(vertices)
        except (TypeError, ValueError):
            v = None
        if v is None or not jnp.issubdtype(v.dtype, jnp.number):
            raise ValueError("Polygon.vertices must be an (n, 2) array of numbers (x, y in "
                             f"metres, counter-clockwise); got {type(vertices).__name__} "
                             f"{str(vertices)[:40]!r}.")
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
    """Vertices (n, 2), counter-clockwise, the first at angle ``rotation`` (radians).
    A rotation of more than a turn is taken modulo whole turns first (exactly, by
    ``fmod``): added as it is to the vertices' angles, 1e12 rad in float32 gave every
    vertex the same angle and a polygon of zero area."""
    k = jnp.arange(n)
    rotation = jnp.asarray(rotation)
    turns = jnp.remainder(rotation + math.pi, 2 * math.pi) - math.pi
    rotation = jnp.where(jnp.abs(rotation) > 2 * math.pi, turns, rotation)
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
    """Circular pupil of ``radius`` metres centred on the axis (or at ``centre``).

    ``on_axis`` (static) is true for a circle built without a centre (or with a literal
    ``(0, 0)``): :meth:`transformed` then only shifts it, and a rotation's derivative is
    not traced through it. To move such a circle, build ``Circle(radius, centre)``
    rather than replacing its ``centre`` leaf (``eqx.tree_at``), which keeps the flag."""

    radius: Float[Array, ""]
    centre: Float[Array, "2"]
    #: the centre is the origin by construction (not a value that may move): rotations
    #: about the axis leave the circle as it is
    on_axis: bool = eqx.field(static=True, default=False)

    def __init__(self, radius, centre=(0.0, 0.0)):
        self.radius = jnp.asarray(radius, dtype=jnp.result_type(float))
        self.centre = jnp.asarray(centre, dtype=jnp.result_type(float))
        self.on_axis = _is_origin(centre)
        try:
            r = float(self.radius)
        except Exception:
            r = None
        if r is not None and not r > 0:
            raise ValueError(f"Circle.radius must be > 0 metres; got {r}.")

    def coverage(self, x, y, cell):
        return disc_coverage(self.radius, self.centre[0], self.centre[1], x, y, cell)

    def max_radius(self):
        if self.on_axis:
            return self.radius
        return self.radius + _safe_norm(self.centre[0], self.centre[1])

    def transformed(self, rotation=0.0, centre=(0.0, 0.0)) -> "Circle":
        """The circle with its centre moved (exact: a disc is rotation invariant). A
        circle built on the axis is only shifted: its derivative in the rotation, zero,
        is then not traced at all."""
        if self.on_axis:
            return Circle(self.radius, centre)
        return Circle(self.radius, _rigid(self.centre, _float(rotation), _float(centre)))
