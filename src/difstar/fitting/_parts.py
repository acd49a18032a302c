"""The model's parts: pupil builders (functions of the named parameters returning a
difstar pupil) and the light (one wavelength or a band)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from typing import Any

import jax.numpy as jnp
import numpy as np

from .._pupil import Circle, Obstructed, Struts, hex_segments
from .._pupil_curved import CurvedIris
from .._validate import MAX_WAVELENGTHS
from ._params import FitInputError


@dataclasses.dataclass(frozen=True)
class PupilBuilder:
    """A pupil as a function of named parameters. ``build(values)`` returns the pupil
    before the overall rotation; ``defaults`` name its parameters and their defaults (SI
    units, angles in degrees); ``max_radius`` bounds its radius over the fit (metres).

    A segmented pupil may also give ``segment(values)``, one of its segments centred on
    the origin (same orientation), and ``segment_radius``, that segment's outermost
    radius: the model then has the parameter ``incoherent``, the fraction of the light
    that falls as the segments' own diffraction patterns added incoherently (see
    :class:`ImageModel`)."""

    name: str
    build: Callable[[Mapping[str, Any]], Any]
    defaults: Mapping[str, float]
    max_radius: float
    segment: Callable[[Mapping[str, Any]], Any] | None = None
    segment_radius: float | None = None

def jwst_pupil(flat_to_flat: float = 1.32, gap: float = 0.007) -> PupilBuilder:
    """JWST-like: 18 hexagonal segments (two rings, no centre; flat top and bottom at
    rotation 0, so the six big spikes are at 90° ± k 60°), a circular central
    obstruction and three struts from the centre at 90° (up) and 270° ± ``strut_spread``
    (30° by default: their spikes lie on the hexagons' at 30° and 150°).
    Parameters: ``flat_to_flat``, ``gap``, ``obstruction`` (radius), ``strut_width``
    (metres), ``strut_spread`` and ``strut_tilt`` (the upper strut's angle from 90°),
    degrees."""

    def build(v):
        segs = hex_segments(2, v["flat_to_flat"], v["gap"])
        s = jnp.deg2rad(v["strut_spread"])
        up = 0.5 * math.pi + jnp.deg2rad(v["strut_tilt"])
        angles = jnp.stack([up, 1.5 * math.pi - s, 1.5 * math.pi + s])
        struts = Struts(angles, v["strut_width"])
        return Obstructed(segs, Circle(v["obstruction"]), struts)

    def segment(v):
        return hex_segments(0, v["flat_to_flat"], v["gap"], include_centre=True)

    r = 2 * (flat_to_flat + gap) + flat_to_flat / math.sqrt(3)  # outermost vertex
    return PupilBuilder("jwst", build, {"flat_to_flat": flat_to_flat, "gap": gap,
                                        "obstruction": 0.37, "strut_width": 0.1,
                                        "strut_spread": 30.0, "strut_tilt": 0.0,
                                        "incoherent": 0.0},
                        max_radius=1.05 * r, segment=segment,
                        segment_radius=1.05 * flat_to_flat / math.sqrt(3))

def obstructed_circle_pupil(radius: float = 0.425) -> PupilBuilder:
    """A circular primary of ``radius`` with a circular obstruction (``obstruction``,
    radius in metres) and three struts at 90° + k·120° + ``strut_offsets`` (degrees),
    ``strut_width`` metres wide (Spitzer-like)."""

    def build(v):
        angles = jnp.deg2rad(jnp.asarray([90.0, 210.0, 330.0]))
        struts = Struts(angles, v["strut_width"])
        return Obstructed(Circle(v["radius"]), Circle(v["obstruction"]), struts)

    return PupilBuilder("circle", build, {"radius": radius, "obstruction": 0.16,
                                          "strut_width": 0.03}, max_radius=1.1 * radius)

def iris_pupil(blades: int = 7, radius: float = 1.2e-3) -> PupilBuilder:
    """A camera's iris: ``blades`` blades with circular-arc edges (a regular polygon when
    ``curvature`` is 0; difstar's ``CurvedIris``), its first vertex on +x at rotation 0.
    Parameters: ``iris_radius`` (circumradius, metres; the aperture's radius is focal
    length / (2 N)) and ``curvature`` (each edge's relative curvature, R·κ: 0 straight,
    1 an arc of the circle through the vertices)."""
    if not isinstance(blades, (int, np.integer)) or blades < 3:
        raise FitInputError(f"iris_pupil: blades must be an integer >= 3; got {blades!r}.")

    def build(v):
        return CurvedIris(int(blades), v["iris_radius"], v["curvature"])

    return PupilBuilder("iris", build, {"iris_radius": radius, "curvature": 0.0},
                        max_radius=1.2 * radius)

BUILDERS = {"jwst": jwst_pupil, "circle": obstructed_circle_pupil, "iris": iris_pupil}

@dataclasses.dataclass(frozen=True)
class Light:
    """Wavelengths (metres) and weights (summing to 1)."""

    wavelengths: Any
    weights: Any

    def __post_init__(self):
        lam = np.asarray(self.wavelengths, float)
        if lam.ndim != 1 or lam.size < 1 or not np.all(np.isfinite(lam)):
            raise FitInputError(f"Light: wavelengths must be finite numbers; got {lam}.")
        if lam.size > MAX_WAVELENGTHS:
            raise FitInputError(f"Light: {lam.size} wavelengths, each a PSF per model image; "
                                f"at most {MAX_WAVELENGTHS}: sample the band with fewer "
                                "(Light.band's Gauss–Legendre nodes need few).")
        if np.any(lam > 100e-6) or np.any(lam < 10e-9):
            raise FitInputError(
                f"Light: wavelengths {lam.tolist()} are not in metres (a wavelength above "
                "100 µm or below 10 nm): give e.g. 0.9e-6 for 0.9 µm.")
        w = np.asarray(self.weights, float)
        if w.shape != lam.shape or not np.all(np.isfinite(w)) or np.any(w < 0) \
                or not w.sum() > 0:
            raise FitInputError(f"Light: weights must be one finite number >= 0 per "
                                f"wavelength, not all 0; got {w.tolist()}.")

    @staticmethod
    def monochromatic(wavelength: Any) -> Light:
        return Light((float(wavelength),), (1.0,))

    @staticmethod
    def band(lo: Any, hi: Any, n: Any = 4, source: Any = "flat") -> Light:
        """``n`` Gauss–Legendre nodes over [lo, hi] (metres), weighted by a flat
        photon spectrum (``"flat"``) or a blackbody of temperature ``source`` kelvin
        (photon counts)."""
        if not (lo < hi):
            raise FitInputError(f"Light.band: need lo < hi; got {lo}, {hi}.")
        Light((lo, hi), (0.5, 0.5))  # unit check
        try:
            whole = (isinstance(n, (int, float, np.integer, np.floating))
                     and not isinstance(n, bool) and float(n) == int(n))
        except (TypeError, ValueError, OverflowError):
            whole = False
        if not (whole and 1 <= int(n) <= MAX_WAVELENGTHS):
            raise FitInputError(f"Light.band: n must be a whole number from 1 to "
                                f"{MAX_WAVELENGTHS}; got {n!r}.")
        if source != "flat" and not (isinstance(source, (int, float))
                                     and not isinstance(source, bool)
                                     and math.isfinite(source) and source > 0):
            raise FitInputError(f"Light.band: source must be 'flat' or a blackbody "
                                f"temperature in kelvin > 0; got {source!r}.")
        x, w = np.polynomial.legendre.leggauss(int(n))
        lam = 0.5 * (lo + hi) + 0.5 * (hi - lo) * x
        if source != "flat":
            t = float(source)
            h, c, k = 6.62607015e-34, 2.99792458e8, 1.380649e-23
            with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
                w = w * lam ** -4 / np.expm1(h * c / (lam * k * t))  # photons ∝ B_λ λ
            if not (np.all(np.isfinite(w)) and w.sum() > 0):
                raise FitInputError(f"Light.band: source: a blackbody of {t:g} K gives no "
                                    f"light over the band [{lo}, {hi}] m (the weights "
                                    "underflow); give a temperature in kelvin (e.g. 5000) "
                                    "or 'flat'.")
        w = w / w.sum()
        return Light(tuple(lam.tolist()), tuple(w.tolist()))
