"""An iris of curved blades: circular arcs between the vertices of a (perturbed) polygon.

Real iris blades are cut as arcs so that the stopped-down opening is rounder than a
polygon. ``CurvedIris`` models ``n`` blades whose edges are circular arcs through
consecutive vertices of a polygon. The vertices sit near a regular ``n``-gon of
circumradius ``R``: vertex k at radius R (1 + radial[k]) and angle
rotation + 2πk/n + angular[k].

Curvature is relative to the circumradius: arc k has signed curvature
κ_k = curvature[k] / R (1/metres). ``curvature = 0`` is the straight polygon,
``curvature > 0`` bulges outwards, and ``curvature = 1`` on a regular polygon puts every
arc on the circumscribed circle (the shape is then exactly the disc of radius R).
Negative curvature (inward, concave blades) is allowed but not convex.

Rasterising. Each arc is replaced by ``segments`` straight pieces and the resulting
polygon is rasterised exactly with the edge terms of ``_pupil.polygon_coverage`` (area
coverage by Green's theorem), summed by a scan over the edges. The arc samples are equally
spaced in angle along the arc and their offsets from the chord are scaled by a factor
γ = 1 + O(1/segments²) chosen so that each cap's area equals the true circular segment's
exactly. The rasterised shape therefore has exactly the analytic :meth:`CurvedIris.area`
(to rounding, as long as the grid holds the pupil), and the sampled outline lies within
ρ (α / segments)² of the true arc (ρ the arc's radius, 2α the angle it subtends; in
practice about half that): for ``segments = 16`` and a 9-blade iris at curvature 1 the
samples sit 2.4e-4 R outside the circle, a fortieth of a cell when the pupil is 100 cells
across. All formulas are smooth through curvature 0
(written with sinc), so gradients with respect to the curvature, the vertices, the
rotation and the circumradius are finite there.

Lengths in metres in the exit-pupil plane, angles in radians.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._custom_types import Array, Float
from ._base import AbstractPupil, _check_build_count
from ._raster import _safe_norm, outline_coverage, tiled_outline_coverage


def _sinc(a: Array) -> Array:
    """sin(a)/a, smooth (and with a correct derivative) at a = 0."""
    return jnp.sinc(a / math.pi)


def _x_minus_sin_over_cube(x: Array) -> Array:
    """(x − sin x) / x³, by its series where x is small (no cancellation, smooth at 0)."""
    small = jnp.abs(x) < 0.1
    xs = jnp.where(small, x, 0.0)
    x2 = xs * xs
    series = 1 / 6 - x2 / 120 + x2 * x2 / 5040 - x2 * x2 * x2 / 362880
    xd = jnp.where(small, 1.0, x)
    direct = (xd - jnp.sin(xd)) / (xd * xd * xd)
    return jnp.where(small, series, direct)


def segment_area(chord: Array, half_angle: Array) -> Array:
    """Signed area between a chord of length ``chord`` and a circular arc subtending
    2 ``half_angle`` (positive angle: the arc bulges outwards).

    ρ²(2α − sin 2α)/2 with ρ = L / (2 sin α), written smoothly through α = 0 as
    (L²/4) α · 4 h(2α) / sinc²(α), h(x) = (x − sin x)/x³.
    """
    return chord * chord * half_angle * _x_minus_sin_over_cube(2 * half_angle) / _sinc(
        half_angle
    ) ** 2


class CurvedIris(AbstractPupil):
    """``n`` blades with circular-arc edges (see the module docstring).

    n: blade count (static). circumradius: R, metres. curvature: (n,) relative
    curvature of each blade's edge (κ = curvature / R); a scalar is broadcast.
    radial: (n,) relative radial deviation of each vertex (0 = regular).
    angular: (n,) angular deviation of each vertex, radians. rotation: angle of vertex 0
    from the +x axis, radians. segments: straight pieces per arc (static).

    Arc k joins vertex k to vertex k + 1 (counter-clockwise).
    """

    n: int = eqx.field(static=True)
    segments: int = eqx.field(static=True)
    circumradius: Float[Array, ""]
    curvature: Float[Array, " blades"]
    radial: Float[Array, " blades"]
    angular: Float[Array, " blades"]
    rotation: Float[Array, ""]

    def __init__(
        self,
        n: int,
        circumradius,
        curvature=0.0,
        *,
        radial=0.0,
        angular=0.0,
        rotation=0.0,
        segments: int = 16,
    ):
        if not isinstance(n, (int, np.integer)) or n < 3:
            raise ValueError(f"CurvedIris.n must be an integer >= 3 (blade count); got {n!r}.")
        if not isinstance(segments, (int, np.integer)) or segments < 2:
            raise ValueError(f"CurvedIris.segments must be an integer >= 2; got {segments!r}.")
        _check_build_count(n, "CurvedIris.n", "blades")
        _check_build_count(int(n) * int(segments), "CurvedIris.n x segments",
                           "edges (blades x segments)")
        self.n = int(n)
        self.segments = int(segments)
        dt = jnp.result_type(float)
        self.circumradius = jnp.asarray(circumradius, dtype=dt)
        self.rotation = jnp.asarray(rotation, dtype=dt)
        for name, v in (("curvature", curvature), ("radial", radial), ("angular", angular)):
            a = jnp.asarray(v, dtype=dt)
            if a.ndim == 0:
                a = jnp.broadcast_to(a, (self.n,))
            if a.shape != (self.n,):
                raise ValueError(
                    f"CurvedIris.{name} must be a scalar or have one value per blade "
                    f"({self.n}); got shape {a.shape}."
                )
            setattr(self, name, a)
        self._check_concrete()

    def _check_concrete(self) -> None:
        try:
            r = float(self.circumradius)
            c = np.asarray(self.curvature)
            rad = np.asarray(self.radial)
        except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError,
                TypeError):
            return  # built inside jit/grad: the caller checks once outside
        if not r > 0:
            raise ValueError(f"CurvedIris.circumradius must be > 0 metres; got {r}.")
        if np.any(rad <= -1):
            raise ValueError("CurvedIris.radial must be > -1 (a vertex radius must stay > 0).")
        z = np.asarray(self._sin_half_angles())
        if not np.all(np.abs(z) < 1):
            raise ValueError(
                "CurvedIris: an arc would subtend more than a half circle (|curvature| · "
                "chord / (2 R) >= 1); reduce the curvature."
            )
        if not np.all(np.isfinite(np.asarray(self.vertices))):
            raise ValueError("CurvedIris: non-finite vertices.")

    # --- geometry ----------------------------------------------------------------------

    @property
    def vertices(self) -> Float[Array, "blades 2"]:
        """The polygon's vertices (n, 2), metres, counter-clockwise."""
        k = jnp.arange(self.n)
        theta = self.rotation + 2 * math.pi * k / self.n + self.angular
        r = self.circumradius * (1 + self.radial)
        return jnp.stack([r * jnp.cos(theta), r * jnp.sin(theta)], axis=-1)

    def _chords(self):
        v0 = self.vertices
        v1 = jnp.roll(v0, -1, axis=0)
        d = v1 - v0
        length = _safe_norm(d[:, 0], d[:, 1])
        return v0, v1, d, length

    def _sin_half_angles(self) -> Array:
        _, _, _, length = self._chords()
        return self.curvature * length / (2 * self.circumradius)

    def half_angles(self) -> Float[Array, " blades"]:
        """α_k: half the angle each arc subtends (radians, signed; 0 for straight)."""
        z = self._sin_half_angles()
        return jnp.arcsin(jnp.clip(z, -1 + 1e-12, 1 - 1e-12))

    def chord_normal_angles(self) -> Float[Array, " blades"]:
        """Direction of each blade's outward chord normal (radians). A straight edge
        diffracts light into spikes along ± this direction in the image; an arc fans
        them over ± its half-angle around it."""
        _, _, d, _ = self._chords()
        return jnp.arctan2(-d[:, 0], d[:, 1])

    def spike_directions(self) -> Float[Array, " spikes"]:
        """Directions (radians, (2n,)) of the boundary's normals on either side of each
        vertex: arc k leaves vertex k with its outward normal at (chord normal − α_k)
        and reaches vertex k + 1 at (chord normal + α_k). A corner diffracts light into
        spikes along (± of) both normals that meet there; along an arc the light fans out
        between them instead of forming a spike. For straight blades the pairs coincide
        with the chord normals."""
        phi = self.chord_normal_angles()
        alpha = self.half_angles()
        return jnp.concatenate([phi - alpha, phi + alpha])

    def arc_points(self) -> Float[Array, "blades m 2"]:
        """Samples of each arc (n, segments + 1, 2), from vertex k to vertex k + 1, with the
        offsets area-matched (see the module docstring)."""
        v0, v1, d, length = self._chords()
        safe_len = jnp.where(length > 0, length, 1.0)
        tx = d[:, 0] / safe_len
        ty = d[:, 1] / safe_len
        nx, ny = ty, -tx  # outward normal of a counter-clockwise polygon's edge
        alpha = self.half_angles()[:, None]
        ell = length[:, None]
        u = jnp.linspace(-1.0, 1.0, self.segments + 1)[None, :]
        along = 0.5 * ell * u * _sinc(u * alpha) / _sinc(alpha)
        # offset / α, smooth at α = 0: (L/4)(1 − u²) sinc((1+u)α/2) sinc((1−u)α/2) / sinc α
        off = (0.25 * ell * (1 - u * u) * _sinc(0.5 * (1 + u) * alpha)
               * _sinc(0.5 * (1 - u) * alpha) / _sinc(alpha))
        trap = jnp.sum((along[:, 1:] - along[:, :-1]) * (off[:, 1:] + off[:, :-1]), axis=1) / 2
        exact = ell[:, 0] ** 2 * _x_minus_sin_over_cube(2 * alpha[:, 0]) / _sinc(alpha[:, 0]) ** 2
        gamma = exact / trap  # area matching: the cap polygon has the segment's exact area
        s = alpha * gamma[:, None] * off
        mid = 0.5 * (v0 + v1)
        px = mid[:, 0:1] + along * tx[:, None] + s * nx[:, None]
        py = mid[:, 1:2] + along * ty[:, None] + s * ny[:, None]
        # Pin the end points to the vertices exactly (so that neighbouring arcs meet).
        px = px.at[:, 0].set(v0[:, 0]).at[:, -1].set(v1[:, 0])
        py = py.at[:, 0].set(v0[:, 1]).at[:, -1].set(v1[:, 1])
        return jnp.stack([px, py], axis=-1)

    def outline(self) -> Float[Array, "points 2"]:
        """The sampled boundary (n · segments, 2), counter-clockwise (for plotting)."""
        return self.arc_points()[:, :-1, :].reshape(-1, 2)

    def polygon_area(self) -> Float[Array, ""]:
        v0, v1, _, _ = self._chords()
        return 0.5 * jnp.sum(v0[:, 0] * v1[:, 1] - v1[:, 0] * v0[:, 1])

    def segment_areas(self) -> Float[Array, " blades"]:
        """Signed area of each circular segment between chord and arc (m²)."""
        _, _, _, length = self._chords()
        return segment_area(length, self.half_angles())

    def area(self) -> Float[Array, ""]:
        """Open area (m²), analytic: polygon area plus the arcs' circular segments."""
        return self.polygon_area() + jnp.sum(self.segment_areas())

    def convexity_margin(self) -> Float[Array, ""]:
        """Smallest turning of the boundary (radians): at each vertex the polygon's turn
        less the two arcs' half-angles, and along each arc 2α. The shape is convex when
        this is ≥ 0."""
        _, _, d, _ = self._chords()
        phi = jnp.arctan2(d[:, 1], d[:, 0])
        turn = jnp.mod(phi - jnp.roll(phi, 1) + math.pi, 2 * math.pi) - math.pi
        alpha = self.half_angles()
        at_vertex = turn - alpha - jnp.roll(alpha, 1)
        return jnp.minimum(jnp.min(at_vertex), 2 * jnp.min(alpha))

    # --- AbstractPupil -----------------------------------------------------------------

    def coverage(self, x: Array, y: Array, cell) -> Array:
        return outline_coverage(*self._edges(), x, y, cell)

    def tiled_coverage(self, x: Array, y: Array, cell) -> Array:
        return tiled_outline_coverage(*self._edges(), x, y, cell)

    def outline_edges(self):
        """The arc pieces' edges (v0, v1): a closed counter-clockwise outline (see
        :meth:`AbstractPupil.outline_edges`)."""
        return self._edges()

    def _edges(self):
        p = self.arc_points()
        return p[:, :-1, :].reshape(-1, 2), p[:, 1:, :].reshape(-1, 2)

    def max_radius(self) -> Array:
        p = self.arc_points()
        return jnp.max(_safe_norm(p[..., 0], p[..., 1]))


def curved_iris_from_area(
    n: int,
    area,
    curvature=0.0,
    *,
    radial=0.0,
    angular=0.0,
    rotation=0.0,
    segments: int = 16,
) -> CurvedIris:
    """The ``CurvedIris`` of open ``area`` (m²) with this shape: the circumradius is set
    analytically (area scales as R² at fixed relative curvature and deviations), so the
    area is exact and the map is differentiable. A reparametrisation, not a penalty."""
    unit = CurvedIris(
        n, 1.0, curvature, radial=radial, angular=angular, rotation=rotation, segments=segments
    )
    r = jnp.sqrt(area / unit.area())
    return CurvedIris(
        n, r, curvature, radial=radial, angular=angular, rotation=rotation, segments=segments
    )
