"""The layers after the optics: what acts on a star's image as a factor of its
spectrum, each a class with its named parameters (defaults and units) and its transfer
function (frequencies in cycles per data pixel) — the detector's, and the source's
extent (a disc, an image) where the source is not a point.

:class:`ImageModel` composes them: a :class:`Jitter`, a list of :class:`Halo` layers
(each named by its user), a :class:`NativePixel` for oversampled data, and a
:class:`Resampling` kernel for a co-add. A blur's transfer is a product, so the order of
the layers does not change the image. :class:`Jitter` and :class:`Halo`, which the
camera chain applies too (:class:`difstar.Blur`), live in :mod:`difstar._detector`. A new
layer is a class here (or there, for both) with its test (see docs/design.md, "Where to
add")."""

from __future__ import annotations

import dataclasses
import math
from typing import ClassVar

import jax.numpy as jnp
import numpy as np

from .._detector import DetectorLayer as DetectorLayer
from .._detector import Halo as Halo
from .._detector import Jitter as Jitter
from .._detector import halos_of as halos_of
from ._params import FitInputError


@dataclasses.dataclass(frozen=True)
class NativePixel(DetectorLayer):
    """A native detector pixel's box, ``size`` data pixels wide (drizzled or
    oversampled data): its transfer sinc(size fx) sinc(size fy)."""

    size: float

    def transfer(self, v, fx, fy):
        return jnp.asarray(np.sinc(self.size * fx) * np.sinc(self.size * fy))


def lanczos_kernel(x, a: int):
    """The Lanczos-``a`` interpolation kernel sinc(x)·sinc(x/a) for |x| < a, else 0."""
    x = np.asarray(x, float)
    return np.where(np.abs(x) < a, np.sinc(x) * np.sinc(x / a), 0.0)


def lanczos_transfer(f, a: int, n: int = 4001):
    """The transfer function (Fourier transform, unit at f = 0) of the continuous
    Lanczos-``a`` kernel at frequencies ``f`` (cycles per data pixel).

    Why a resampled image sees it: a frame sampled at an offset u and interpolated
    onto the output grid with kernel L gives out(x) = Σ_k g(k + u) L(x − k − u); averaged
    over offsets u spread evenly over a pixel this is ∫ g(t) L(x − t) dt, the
    convolution of the pixel-integrated PSF g with L. A co-add of many frames at
    random sub-pixel offsets (SWarp's RESAMPT = LANCZOS3, combined by mean or median)
    is blurred by L on average; the separable 2-D kernel is L(x) L(y).
    Composite Simpson's rule over [−a, a] with ``n`` (odd) nodes: the kernel is smooth
    and compact, so 4001 nodes give the transfer to about 1e-12."""
    x = np.linspace(-a, a, n)
    w = np.ones(n)
    w[1:-1:2], w[2:-1:2] = 4.0, 2.0
    w *= (x[1] - x[0]) / 3.0
    k = lanczos_kernel(x, a) * w
    f = np.asarray(f, float)
    h = np.cos(2 * np.pi * f[..., None] * x) @ k
    return h / k.sum()


@dataclasses.dataclass(frozen=True)
class Resampling(DetectorLayer):
    """The Lanczos-``order`` kernel a co-add was resampled with (SWarp's RESAMPT =
    LANCZOS3: ``order`` 3), on the data's pixels: :func:`lanczos_transfer` in x and y."""

    order: int
    on_data_grid: ClassVar[bool] = True

    def __post_init__(self):
        if isinstance(self.order, bool) or self.order not in (2, 3, 4, 5):
            raise FitInputError(f"Resampling: order {self.order!r} must be 2, 3, 4 or 5 "
                                "(Lanczos2 … Lanczos5; SWarp's LANCZOS3 is 3).")

    def transfer(self, v, fx, fy):
        return lanczos_transfer(fx, self.order) * lanczos_transfer(fy, self.order)


def disc_transform(x):
    """2 J1(x) / x, the Fourier transform of a uniform disc of unit area at
    x = 2π f R (f cycles per pixel, R the radius in pixels); 1 at x = 0. J1 by the
    rational and asymptotic approximations of Hart (Numerical Recipes' bessj1), to
    about 1e-8, smooth in x for gradients."""
    x = jnp.abs(jnp.asarray(x, float))
    y = x * x
    p = 72362614232.0 + y * (-7895059235.0 + y * (242396853.1 + y * (
        -2972611.439 + y * (15704.48260 + y * (-30.16036606)))))
    q = 144725228442.0 + y * (2300535178.0 + y * (18583304.74 + y * (
        99447.43394 + y * (376.9991397 + y))))
    small = 2.0 * p / q  # 2 J1(x)/x for x < 8 (J1 = x p/q)
    xb = jnp.maximum(x, 8.0)
    z = 8.0 / xb
    y2 = z * z
    xx = xb - 2.356194491
    a1 = 1.0 + y2 * (0.183105e-2 + y2 * (-0.3516396496e-4 + y2 * (
        0.2457520174e-5 + y2 * (-0.240337019e-6))))
    a2 = 0.04687499995 + y2 * (-0.2002690873e-3 + y2 * (0.8449199096e-5 + y2 * (
        -0.88228987e-6 + y2 * 0.105787412e-6)))
    big = 2.0 * jnp.sqrt(0.636619772 / xb) * (jnp.cos(xx) * a1 - z * jnp.sin(xx) * a2) / xb
    return jnp.where(x < 8.0, small, big)


@dataclasses.dataclass(frozen=True)
class DiscSource(DetectorLayer):
    """The source a uniform disc of radius ``source_radius`` data pixels (a resolved
    star, a lamp behind a pinhole) instead of a point: its transform, 2 J1(x)/x at
    x = 2π f R (:func:`disc_transform`), multiplies the image's spectrum."""

    @property
    def parameters(self) -> dict[str, float]:
        return {"source_radius": 1.0}

    @property
    def units(self) -> dict[str, str]:
        return {"source_radius": "data px"}

    def transfer(self, v, fx, fy):
        return disc_transform(2 * math.pi * np.sqrt(fx**2 + fy**2) * v["source_radius"])


class SourceImage(DetectorLayer):
    """The source as the data's pixels would see it: a 2-D array of finite, non-negative
    values with a positive sum (any size up to the padded window), its centre pixel
    (shape // 2) at the star's position. Acts on the data's pixels: its transfer is the
    array's discrete transform (unit sum) at the data grid's frequencies, by two matrix
    products (the same numbers as a periodic FFT of the window), kept per grid."""

    on_data_grid: ClassVar[bool] = True

    def __init__(self, image):
        a = np.asarray(image, dtype=float)
        if a.ndim != 2 or not np.all(np.isfinite(a)) or np.any(a < 0) or not a.sum() > 0:
            raise FitInputError("ImageModel: a source image must be a 2-D array of finite, "
                                "non-negative values with a positive sum.")
        self.image = a / a.sum()  # a copy: the caller's array is never changed
        self._spectra: dict = {}

    @property
    def shape(self) -> tuple[int, int]:
        return self.image.shape

    def transfer(self, v, fx, fy):
        fy = np.ravel(np.asarray(fy, float))
        fx = np.ravel(np.asarray(fx, float))
        key = (fy.tobytes(), fx.tobytes())
        if key not in self._spectra:
            sh, sw = self.image.shape
            dy = np.arange(sh) - sh // 2  # offsets from the centre pixel
            dx = np.arange(sw) - sw // 2
            ey = np.exp(-2j * np.pi * np.outer(fy, dy))
            ex = np.exp(-2j * np.pi * np.outer(dx, fx))
            self._spectra[key] = ey @ self.image @ ex  # NumPy: a constant in any trace
        return self._spectra[key]


def source_of(source):
    """The source layer for ``source``: None for "point"; :class:`DiscSource` for
    "disc"; a :class:`SourceImage` for a 2-D array; a layer as it is."""
    if isinstance(source, (DiscSource, SourceImage)) or source is None:
        return source
    if isinstance(source, str):
        if source not in ("point", "disc"):
            raise FitInputError(f"ImageModel: source must be 'point', 'disc' or an image "
                                f"(2-D array); got {source!r}.")
        return DiscSource() if source == "disc" else None
    return SourceImage(source)


__all__ = ["DetectorLayer", "DiscSource", "Halo", "Jitter", "NativePixel", "Resampling",
           "SourceImage", "disc_transform", "halos_of", "lanczos_kernel", "lanczos_transfer",
           "source_of"]
