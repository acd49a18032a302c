"""The detector's blur: layers that act on the linear image as a factor of its spectrum
(:class:`DetectorLayer`: :class:`Jitter`, :class:`Halo`), each with its named
parameters (defaults and units) and its transfer function at frequencies in cycles per
pixel of the data (the sensor's pixels, for a camera).

The camera chain applies them to each channel's linear image (:class:`Blur`, a
:class:`difstar.Sensor`'s ``blur``), the image fit to the star's image
(:class:`difstar.fitting.ImageModel`): one implementation for both. A blur's transfer
is a product, so the order of the layers does not change the image."""

from __future__ import annotations

import dataclasses
import math
import re
from collections.abc import Mapping, Sequence
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._param import FitInputError


class DetectorLayer:
    """One layer of the detector. ``parameters``: its named parameters with their
    defaults; ``units``: theirs; :meth:`transfer`: its factor on the image's spectrum
    at frequencies ``fx`` (columns) and ``fy`` (rows), cycles per data pixel, for the
    values ``v`` (traceable). ``on_data_grid``: it acts on the data's pixels themselves,
    after they sample the image (computed on the data's grid only)."""

    on_data_grid: ClassVar[bool] = False

    @property
    def parameters(self) -> dict[str, float]:
        return {}

    @property
    def units(self) -> dict[str, str]:
        return {}

    def transfer(self, v: Mapping[str, Any], fx, fy):
        raise NotImplementedError


def _gaussian(sigma, fx, fy):
    """The transfer of a unit Gaussian of σ ``sigma`` data pixels."""
    return jnp.exp(-2 * math.pi**2 * sigma**2 * (fx**2 + fy**2))


@dataclasses.dataclass(frozen=True)
class Jitter(DetectorLayer):
    """A Gaussian blur of σ ``jitter`` data pixels (pointing jitter, charge diffusion)."""

    @property
    def parameters(self) -> dict[str, float]:
        return {"jitter": 0.0}

    @property
    def units(self) -> dict[str, str]:
        return {"jitter": "data px, Gaussian sigma"}

    def transfer(self, v, fx, fy):
        return _gaussian(v["jitter"], fx, fy)


#: a halo's name: a parameter name of its own (letters, digits, underscores)
_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


@dataclasses.dataclass(frozen=True)
class Halo(DetectorLayer):
    """A fraction of the light moved into a Gaussian: parameters ``<name>`` (the
    fraction, 0 … 1; default 0, off) and ``<name>_width`` (its σ in data pixels;
    default ``width``). Scattered light; a segmented mirror's phasing errors, which
    spread light over about one segment's diffraction pattern; a co-add's
    misregistration. A model may have any number, each under its own name."""

    name: str = "halo"
    width: float = 4.0

    def __post_init__(self):
        if not isinstance(self.name, str) or not _NAME.fullmatch(self.name) or (
                re.fullmatch(r"z\d+", self.name)):
            raise FitInputError(f"Halo: name {self.name!r} must be letters, digits and "
                                "underscores, starting with a letter (and not z<j>, a "
                                "Zernike term), e.g. 'halo' or 'scatter'.")
        w = self.width
        if isinstance(w, bool) or not isinstance(w, (int, float)) or not (
                math.isfinite(w) and w > 0):
            raise FitInputError(f"Halo {self.name!r}: width {w!r} must be a finite number "
                                "of data pixels > 0.")

    @property
    def parameters(self) -> dict[str, float]:
        return {self.name: 0.0, f"{self.name}_width": float(self.width)}

    @property
    def units(self) -> dict[str, str]:
        return {self.name: "1, fraction of the light",
                f"{self.name}_width": "data px, Gaussian sigma"}

    def transfer(self, v, fx, fy):
        a = v[self.name]
        return (1.0 - a) + a * _gaussian(v[f"{self.name}_width"], fx, fy)


def halos_of(given) -> tuple[Halo, ...]:
    """The halos a model is given: None (one, ``halo``), or a list of :class:`Halo`,
    names, or ``{"name": ..., "width": ...}`` (as a manifest's ``detector.halos``
    writes them); the names must differ."""
    if given is None:
        return (Halo(),)
    if isinstance(given, (str, Mapping, Halo)) or not hasattr(given, "__iter__"):
        raise FitInputError(f"halos: a list of halos (Halo, a name, or {{name, width}}); "
                            f"got {given!r}.")
    out = []
    for i, h in enumerate(given):
        try:
            if isinstance(h, str):
                h = Halo(h)
            elif isinstance(h, Mapping):
                if set(h) - {"name", "width"} or "name" not in h:
                    raise FitInputError(f"a halo is {{name, width}}; got {dict(h)}.")
                h = Halo(**h)
            elif not isinstance(h, Halo):
                raise FitInputError(f"a Halo, a name or {{name, width}}; got {h!r}.")
        except FitInputError as e:
            raise FitInputError(f"halos/{i}: {e}") from None
        out.append(h)
    names = [h.name for h in out]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise FitInputError(f"halos: the names {dup} are given twice; each halo needs a name "
                            "of its own (e.g. 'halo' and 'halo2').")
    return tuple(out)


#: how far a blur reaches, in its widest Gaussian's σ: beyond it a Gaussian's kernel is
#: exp(−6²/2) ≈ 1.5e-8 of its peak
REACH_SIGMAS = 6.0


def widths(layers: Sequence[DetectorLayer], values: Mapping[str, Any]) -> list[float]:
    """The Gaussian σ (pixels) of each blurring layer at ``values`` (concrete numbers;
    a halo with fraction 0 blurs nothing)."""
    out = []
    for layer in layers:
        if isinstance(layer, Jitter):
            out.append(abs(float(values["jitter"])))
        elif isinstance(layer, Halo) and float(values[layer.name]) != 0:
            out.append(abs(float(values[f"{layer.name}_width"])))
    return out


def reach_of(layers: Sequence[DetectorLayer], values: Mapping[str, Any]) -> int:
    """The pixels the blur of ``layers`` reaches at ``values`` (concrete):
    :data:`REACH_SIGMAS` × its widest Gaussian σ (:func:`widths`)."""
    return math.ceil(REACH_SIGMAS * max(widths(layers, values), default=0.0))


class Blur(eqx.Module):
    """The detector's blur of a camera's linear image (:class:`difstar.Sensor`'s
    ``blur``): its ``layers`` (static) with their named ``values`` (traceable arrays),
    and ``reach``, the pixels beyond which its light is negligible (static: the chain
    computes the image that far beyond the crop, so that the blurred crop is whole).

    ``reach`` defaults to :data:`REACH_SIGMAS` × the widest Gaussian σ of ``values``
    (which must then be concrete); a fit whose widths move gives the reach of their
    upper bounds. Every layer's parameters need a value: the layer's default where
    ``values`` leaves one out."""

    layers: tuple = eqx.field(static=True)
    values: dict
    reach: int = eqx.field(static=True)

    def __init__(self, layers: Sequence[DetectorLayer], values: Mapping[str, Any] | None = None,
                 *, reach: int | None = None):
        layers = tuple(layers)
        for i, layer in enumerate(layers):
            if not isinstance(layer, (Jitter, Halo)):
                raise FitInputError(f"Blur: layers[{i}] is {layer!r}; a camera's blur takes "
                                    "Jitter and Halo layers.")
        names = [k for layer in layers for k in layer.parameters]
        dup = sorted({k for k in names if names.count(k) > 1})
        if dup:
            raise FitInputError(f"Blur: the parameters {dup} belong to two layers; give each "
                                "layer its own (one Jitter, halos of different names).")
        defaults = {k: v for layer in layers for k, v in layer.parameters.items()}
        values = dict(values or {})
        unknown = sorted(set(values) - set(defaults))
        if unknown:
            raise FitInputError(f"Blur: values {unknown} belong to no layer; the layers' "
                                f"parameters are {sorted(defaults)}.")
        self.layers = layers
        self.values = {k: jnp.asarray(values.get(k, d), dtype=float)
                       for k, d in defaults.items()}
        if reach is None:
            try:
                reach = reach_of(layers, defaults | values)
            except (TypeError, jax.errors.ConcretizationTypeError,
                    jax.errors.TracerArrayConversionError) as e:
                raise FitInputError("Blur: give reach (pixels) where the widths are traced "
                                    f"({e.__class__.__name__}).") from None
        if isinstance(reach, bool) or not isinstance(reach, (int, np.integer)) or reach < 0:
            raise FitInputError(f"Blur: reach must be a whole number of pixels >= 0; got "
                                f"{reach!r}.")
        self.reach = int(reach)

    def transfer(self, fx, fy):
        """The product of the layers' transfers at ``fx``, ``fy`` (cycles per pixel)."""
        out = jnp.ones(jnp.broadcast_shapes(jnp.shape(fx), jnp.shape(fy)))
        for layer in self.layers:
            out = out * layer.transfer(self.values, fx, fy)
        return out


__all__ = ["Blur", "DetectorLayer", "Halo", "Jitter", "REACH_SIGMAS", "halos_of", "reach_of",
           "widths"]
