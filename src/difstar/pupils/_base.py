"""What every pupil is (:class:`AbstractPupil`), the generic wrapper that moves one
(:class:`Transformed`: rotation, shift, a linear map), and the checks pupils make when
built (counter-clockwise, simple, not too many edges)."""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._custom_types import Array, Float
from .._limits import MAX_BUILD_EDGES, check_edge_count
from ._raster import _safe_norm, outline_coverage, tiled_outline_coverage


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
