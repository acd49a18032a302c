"""Telescope pupils: spider vanes through the centre, struts anywhere, and an outer
pupil with a central obstruction and vanes."""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._custom_types import Array, Float
from ._base import AbstractPupil, _check_build_count, _concrete, _float, _rigid
from ._raster import convex_polygon_coverage, outline_coverage, tiled_outline_coverage


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
