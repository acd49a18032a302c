"""Parameters: :class:`Param` (a value, fixed or free, with bounds) and its map to the
solver's unconstrained numbers; the fitter's error type and constants."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

import jax
import numpy as np

ARCSEC = math.pi / (180 * 3600)

PERTURB = 0.2  # rough starts: each free parameter within ± 20 % (perturbed_starts)

_PITCH = 1e-5  # metres: the detector pitch the model uses (only pitch / z_image matters)

class FitInputError(ValueError):
    """A fitting input that cannot be right (a unit, a bound, NaN data, nothing free)."""

@dataclasses.dataclass
class Param:
    """One named parameter: ``value`` (the start when free), ``free``, ``bounds``
    (lo, hi) for a free parameter (a logistic map keeps it inside), ``scale`` (the
    step of O(1) in the fitted variable for an unbounded parameter; default 10 % of
    |value| or 1e-3)."""

    value: Any
    free: Any = False
    bounds: Any = None
    scale: Any = None

    def __post_init__(self):
        self.value = float(self.value)
        if not math.isfinite(self.value):
            raise FitInputError(f"Param value must be finite; got {self.value}.")
        if self.bounds is not None:
            lo, hi = (float(b) for b in self.bounds)
            if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                raise FitInputError(f"Param bounds must be finite with lo < hi; got {self.bounds}.")
            self.bounds = (lo, hi)
            if self.free and not lo <= self.value <= hi:
                raise FitInputError(f"Param start {self.value} lies outside its bounds "
                                    f"{self.bounds}.")

def _as_param(p: Any) -> Param:
    if isinstance(p, Param):
        return dataclasses.replace(p)
    if isinstance(p, Mapping):
        return Param(p["value"], bool(p.get("free", False)),
                     None if p.get("bounds") is None else tuple(p["bounds"]), p.get("scale"))
    return Param(float(p))

def _to_u(p: Param) -> float:
    if p.bounds is not None:
        lo, hi = p.bounds
        t = min(max((p.value - lo) / (hi - lo), 1e-4), 1 - 1e-4)
        return math.log(t / (1 - t))
    return 0.0

def _from_u(p: Param, u):
    if p.bounds is not None:
        lo, hi = p.bounds
        return lo + (hi - lo) * jax.nn.sigmoid(u)
    s = p.scale if p.scale else max(0.1 * abs(p.value), 1e-3)
    return p.value + s * u

def _whole(x) -> bool:
    """A whole number (an int, or a float such as JSON's 2.0), not a bool."""
    if isinstance(x, (bool, np.bool_)):
        return False
    if isinstance(x, (int, np.integer)):
        return True
    return isinstance(x, (float, np.floating)) and math.isfinite(x) and float(x).is_integer()

def _finite(x) -> bool:
    """A finite real number, not a bool."""
    return (isinstance(x, (int, float, np.integer, np.floating))
            and not isinstance(x, (bool, np.bool_)) and math.isfinite(x))
