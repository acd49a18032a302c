"""A pupil from a measured transmission map (an aperture photo), sampled by area."""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._custom_types import Array, Float
from ._base import AbstractPupil, Transformed, _concrete, _float, _rigid


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
