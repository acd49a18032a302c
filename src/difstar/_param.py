"""The one parameter type of difstar, :class:`Param`, and the one bound map.

Every quantity a fit or a design adjusts is a :class:`Param`: its ``value`` (the start,
when it is free), whether it is ``free``, its ``bounds`` and, for a free parameter
without bounds, the ``scale`` of one unit step. The RAW camera fit, the image fit and
the design study all use it; only the value's form differs (a number for an image-fit
parameter, an array such as a per-vertex deviation for the RAW fit, a PyTree of arrays
such as :class:`difstar.IrisParams` for a design).

Solvers never move a value directly: they move unconstrained numbers ``u`` (all O(1), so
the isotropic Levenberg–Marquardt damping and Adam's step treat parameters of different
units alike), mapped element by element by the one bound map:

- bounded (lo < hi): ``x = lo + (hi − lo)·σ(u)`` — every value tried lies inside;
- fixed by its bounds (lo == hi, design boxes): ``x = lo`` with ``u = 0`` and no gradient;
- unbounded: ``x = value + scale·u`` (scale default 10 % of |value|, at least 1e-3).

A start on a bound is moved inside by ``margin`` × the range (the logistic map never
reaches its ends): :data:`START_MARGIN` unless the caller says otherwise.
"""

from __future__ import annotations

import abc
import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

#: A start on a bound is moved this fraction of the range inside it.
START_MARGIN = 1e-4


class FitInputError(ValueError):
    """A fitting input that cannot be right (a unit, a bound, NaN data, nothing free)."""


def bound_map(u, lo, hi):
    """Unconstrained ``u`` → its value in [lo, hi] (``lo`` where lo == hi)."""
    return lo + (hi - lo) * jax.nn.sigmoid(u)


def bound_map_slope(u: float, lo: float, hi: float) -> float:
    """d :func:`bound_map` / du at a concrete ``u``, in NumPy (no program to compile):
    (hi − lo) σ(u) (1 − σ(u)), written with e^(−|u|) so that no exponential overflows."""
    e = math.exp(-abs(float(u)))
    return (hi - lo) * e / (1.0 + e) ** 2


def step_map(u, start, scale):
    """Unconstrained ``u`` → the value of an unbounded parameter: ``start + scale·u``."""
    return start + scale * u


def bound_map_inverse(x, lo, hi, margin: float = START_MARGIN):
    """Value ``x`` in [lo, hi] → unconstrained ``u`` (0 where lo == hi); a value within
    ``margin`` × the range of a bound is moved to that distance first."""
    xp = jnp if any(isinstance(a, jax.Array) for a in (x, lo, hi)) else np  # NumPy: f64
    span = hi - lo
    fixed = span == 0
    t = xp.clip((x - lo) / xp.where(fixed, 1.0, span), margin, 1 - margin)
    return xp.where(fixed, 0.0, xp.log(t) - xp.log1p(-t))


def _number(x) -> bool:
    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(
        x, (bool, np.bool_))


def _array_like(x) -> bool:
    return isinstance(x, (list, np.ndarray)) or (
        isinstance(x, jax.Array) and not isinstance(x, jax.core.Tracer))


def _leaves_finite(tree) -> bool:
    return all(bool(np.all(np.isfinite(np.asarray(v)))) for v in jax.tree.leaves(tree))


@dataclasses.dataclass
class Param:
    """One named quantity to fit or design.

    value: the value (the start when free): a number, an array, or a PyTree of arrays.
    free: whether the solver moves it.
    bounds: ``(lo, hi)``, each a number, an array broadcast to the value's shape, or a
        PyTree shaped like the value; lo ≤ hi everywhere (a number's range must be wider
        than zero; for arrays and PyTrees lo == hi fixes that element). A free value
        must lie within its bounds.
    scale: for a free parameter without bounds, the value's change per unit of ``u``
        (default 10 % of |value|, at least 1e-3).
    """

    value: Any
    free: Any = False
    bounds: Any = None
    scale: Any = None

    def __post_init__(self):
        self.free = bool(self.free)
        if _number(self.value) or (isinstance(self.value, np.ndarray)
                                   and self.value.ndim == 0):
            self.value = float(self.value)
        elif _array_like(self.value):
            self.value = np.array(self.value, float)
        if not _leaves_finite(self.value):
            raise FitInputError(f"Param value must be finite; got {self.value}.")
        if self.bounds is None:
            return
        try:
            lo, hi = self.bounds
        except (TypeError, ValueError):
            raise FitInputError(f"Param bounds must be a pair (lo, hi); got {self.bounds}.")
        if isinstance(self.value, float):
            lo, hi = float(lo), float(hi)
            if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                raise FitInputError(f"Param bounds must be finite with lo < hi; got "
                                    f"{self.bounds}.")
        else:
            if isinstance(self.value, np.ndarray):
                lo, hi = (np.broadcast_to(np.asarray(b, float), self.value.shape).copy()
                          for b in (lo, hi))
            if not (_leaves_finite(lo) and _leaves_finite(hi)):
                raise FitInputError(f"Param bounds must be finite; got {self.bounds}.")
            if not all(bool(np.all(np.asarray(a) <= np.asarray(b))) for a, b in
                       zip(jax.tree.leaves(lo), jax.tree.leaves(hi), strict=True)):
                raise FitInputError(f"Param bounds need lo ≤ hi everywhere; got {lo}, {hi}.")
        self.bounds = (lo, hi)
        if self.free and not self.contains(self.value):
            raise FitInputError(f"Param start {self.value} lies outside its bounds "
                                f"{self.bounds}.")

    @property
    def shape(self) -> tuple[int, ...]:
        """The value's shape (a number: ``()``; not defined for PyTrees)."""
        return np.shape(self.value)

    @property
    def size(self) -> int:
        """How many numbers the value holds (all leaves of a PyTree)."""
        return sum(int(np.size(v)) for v in jax.tree.leaves(self.value))

    @property
    def lo(self):
        return None if self.bounds is None else self.bounds[0]

    @property
    def hi(self):
        return None if self.bounds is None else self.bounds[1]

    def contains(self, x) -> bool:
        """Whether ``x`` (shaped like the value) lies within the bounds (always, without)."""
        if self.bounds is None:
            return True
        return all(bool(np.all((np.asarray(lo) <= np.asarray(v)) & (np.asarray(v)
                                                                   <= np.asarray(hi))))
                   for v, lo, hi in zip(jax.tree.leaves(x), jax.tree.leaves(self.bounds[0]),
                                        jax.tree.leaves(self.bounds[1]), strict=True))

    def with_value(self, value) -> Param:
        """A copy at a new value (start), bounds and freedom unchanged."""
        return dataclasses.replace(self, value=value)

    def step_scale(self):
        """The unbounded map's scale: ``scale``, or 10 % of |value| (at least 1e-3)."""
        if self.scale:
            return self.scale
        return jax.tree.map(lambda v: np.maximum(0.1 * np.abs(v), 1e-3), self.value)

    def to_unconstrained(self, x=None, *, margin: float = START_MARGIN):
        """Unconstrained ``u`` (shaped like the value) for ``x`` (default: the value)."""
        x = self.value if x is None else x
        if self.bounds is not None:
            return jax.tree.map(lambda v, lo, hi: bound_map_inverse(v, lo, hi, margin),
                                x, self.bounds[0], self.bounds[1])
        return jax.tree.map(lambda v, v0, s: (v - v0) / s, x, self.value,
                            _tree_like(self.step_scale(), self.value))

    def from_unconstrained(self, u):
        """The value (shaped like the value) for unconstrained ``u``; jittable in ``u``."""
        if self.bounds is not None:
            return jax.tree.map(bound_map, u, self.bounds[0], self.bounds[1])
        return jax.tree.map(step_map, u, self.value, _tree_like(self.step_scale(), self.value))


def _tree_like(s, value):
    """A scale given as one number broadcast over a PyTree value's leaves."""
    if _number(s):
        return jax.tree.map(lambda _: s, value)
    return s


class ForwardModel(abc.ABC):
    """What every fit model shares, whatever data it predicts: named parameters, each a
    :class:`Param` (``params``, in the solver's order), that the model turns into a
    prediction of its data. Its two kinds: :class:`difstar.raw_fit.FitModel` (RAW
    mosaics through ``difstar.simulate``) and :class:`difstar.fitting.ImageModel` (a
    star's intensity image). Both give their parameters' values and units and a copy at
    other values the same way."""

    params: dict[str, Param]

    @property
    def free(self) -> Sequence[str]:
        """The free parameters' names, in the order of the solver's vector."""
        return [k for k, p in self.params.items() if p.free]

    def values(self) -> dict[str, Any]:
        """Every parameter's value (its start, where it is free)."""
        return {k: p.value for k, p in self.params.items()}

    @abc.abstractmethod
    def unit(self, name: str) -> str:
        """The unit of parameter ``name``."""

    @property
    def units(self) -> dict[str, str]:
        """Every parameter's unit."""
        return {k: self.unit(k) for k in self.params}

    @abc.abstractmethod
    def with_values(self, values: Mapping[str, Any], free: Sequence[str] | None = None):
        """A copy with ``values`` (name → value; the others as they are, bounds kept)
        and, given ``free``, only those of the free parameters left free."""


__all__ = ["Param", "FitInputError", "ForwardModel", "bound_map", "bound_map_inverse",
           "bound_map_slope", "step_map", "START_MARGIN"]
