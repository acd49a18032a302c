"""The image fit's use of :class:`difstar._param.Param` (one number per name), its
map to the solver's unconstrained numbers, and the fitter's constants."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from .._param import FitInputError as FitInputError  # the fitter's error type
from .._param import Param as Param

ARCSEC = math.pi / (180 * 3600)

PERTURB = 0.2  # rough starts: each free parameter within ± 20 % (perturbed_starts)

_PITCH = 1e-5  # metres: the detector pitch the model uses (only pitch / z_image matters)

def _as_param(p: Any) -> Param:
    if isinstance(p, Param):
        return dataclasses.replace(p)
    if isinstance(p, Mapping):
        return Param(p["value"], bool(p.get("free", False)),
                     None if p.get("bounds") is None else tuple(p["bounds"]), p.get("scale"))
    return Param(float(p))

def _to_u(p: Param) -> float:
    """The start's unconstrained number (the one bound map, :mod:`difstar._param`)."""
    return float(p.to_unconstrained()) if p.bounds is not None else 0.0

def _from_u(p: Param, u):
    return p.from_unconstrained(u)

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
