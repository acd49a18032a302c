"""One PSF for a whole solve where the optics stay as they are: a stage that frees only
what acts after the optics (the star's position, flux, background, the detector's blurs,
the source's disc, the response curve) computes the PSF once, at the window's centre,
and moves it by a phase ramp of its spectrum at every step. A step then costs a few
FFTs instead of the PSF engine (the JWST star's whole-image stages: the PSF of 18
segments in 3 wavelengths, and its tangent in each free direction).

The PSF is point-sampled q times finer than the data's pixels a side, with q odd and
above twice the intensity's bandwidth (:func:`fine_factor`): the intensity is
band-limited (its spectrum, the OTF, vanishes beyond 2R/(λ z)), so at that rate its
samples determine it and a shift, the pixels' squares (their transform, a sinc) and the
blurs are exact in the spectrum; each data pixel is then the sample at its centre. The
window is periodic, as the direct path's blurs already take it; a move of up to the
padding's width wraps only into the padding, which is cut away."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._custom_types import ScalarLike
from ._params import ARCSEC
from ._programs import _light_key, program

#: the parameters one PSF at the star's centre serves besides the layers' after the
#: optics (the jitter's, the halos', a disc source's radius): a move of the star is a
#: phase ramp of its spectrum, the rest act after the optics
AFTER_OPTICS = frozenset({"x0", "y0", "flux", "background", "white", "toe", "knee"})


def optics_fixed(model, free: Sequence[str]) -> bool:
    """Whether a solve of ``free`` (names, ``name@i`` as ``name``) leaves the optics as
    they are, so that :func:`centred_psf` serves all its steps: every name acts after
    the optics, and nothing after them is defined on the data's pixels alone (a
    co-add's resampling kernel, a source image)."""
    after = AFTER_OPTICS.union(*(layer.parameters for layer in model.layers))
    return (bool(free) and not model.has_data_grid_kernel
            and all(k.split("@")[0] in after for k in free))


def fine_factor(model, light=None) -> int:
    """q: the fewest odd samples a data pixel a side above the intensity's Nyquist rate,
    2 × its bandwidth 2R·θ/λ cycles per data pixel (R the pupil's largest radius, θ the
    largest angle a data pixel spans, λ the shortest wavelength)."""
    light = model.light if light is None else light
    ang = model._bound("pixel_scale", max) * ARCSEC
    band = 2.0 * float(model.pupil.max_radius) * ang / float(np.min(light.wavelengths))
    q = int(math.floor(2.0 * band)) + 1
    return q if q % 2 else q + 1


def centred_psf(model, v: Mapping[str, Any], shape, light=None) -> np.ndarray:
    """The star's PSF at the window's centre (``x0 = y0 = 0``) for the optics at values
    ``v``, the segments' incoherent part mixed in: point samples on the padded window,
    :func:`fine_factor` times finer than the data's pixels, scaled so that a data
    pixel's square holds the sum of its q × q samples (q² × the fraction of the power
    per fine sample's area)."""
    light = model.light if light is None else light
    hp, wp = model.padded_shape(shape)
    q = fine_factor(model, light)
    fine = (hp * q, wp * q)
    v = {k: float(x) for k, x in {**v, "x0": 0.0, "y0": 0.0}.items()}
    plans = model.point_plans(v, light, fine, q)  # on Python numbers: no eager operation
    v = {k: jnp.asarray(x, float) for k, x in v.items()}
    # one compiled program (kept), not the pupil's and the wavefront's operations one
    # at a time (about 20 small programs compiled on a first run) and then the PSF's
    run = program(("centred psf", model.trace_key(), fine, q, _light_key(light), plans),
                  lambda: jax.jit(lambda vals: model.optics(vals, light, fine, q,
                                                            plans=plans, shift=False)),
                  (model.plan_cache,))
    return np.asarray(run(v)) * q * q


def image_from_psf(model, img, v: Mapping[str, Any], shape, q: int,
                   exposure: ScalarLike = 1.0, *, move: bool = False):
    """The model image from ``model.optics``' PSF ``img`` on the padded window (q
    samples a data pixel a side): the detector's blurs (and where q > 1 the pixels'
    squares) in its spectrum, then read out (:meth:`ImageModel.image`'s last part).
    ``move``: ``img`` is the star's PSF at the window's centre (``optics(...,
    shift=False)``), moved here by (``x0``, ``y0``) by a phase ramp of that spectrum,
    which the intensity's band limit makes exact (sampled above its Nyquist rate; the
    window taken as periodic, as the blurs take it): one PSF then serves every star of
    a field whose optics are shared."""
    hp, wp = model.padded_shape(shape)
    if q > 1:  # the data undersample the intensity: pixels and blurs in its spectrum
        img = pixels_from_fine(model, v, (hp, wp), img * (q * q), q, move=move)
    else:  # pixel-integrated samples of a band-limited image: blurs on them exact
        kern = model.detector_kernel(v, (hp, wp))
        if move:
            kern = kern * shift_ramp(v, hp, wp, 1)
        img = jnp.fft.irfft2(jnp.fft.rfft2(img) * kern, s=(hp, wp))
    return model.read_out(img, v, shape, exposure)


def image_from_centred(model, v: Mapping[str, Any], shape, centred, q: int,
                       exposure: ScalarLike = 1.0):
    """The model image (H, W) at values ``v`` from ``centred`` (:func:`centred_psf` at
    the optics of ``v``): moved by (``x0`` columns right, ``y0`` rows down), each data
    pixel's square integrated, the detector's blurs applied, all in the spectrum; then
    the sample at each data pixel's centre, read out as :meth:`ImageModel.image` does.
    Traceable in the values."""
    img = pixels_from_fine(model, v, model.padded_shape(shape), centred, q, move=True)
    return model.read_out(img, v, shape, exposure)


def shift_ramp(v: Mapping[str, Any], hp: int, wp: int, q: int):
    """The phase ramp on the half spectrum (``rfft2``) of an (hp q, wp q) window, q
    samples a data pixel a side, that moves its image by (``x0`` columns right, ``y0``
    rows down) data pixels."""
    fy = np.fft.fftfreq(hp * q)[:, None] * q  # cycles per data pixel
    fx = np.fft.rfftfreq(wp * q)[None, :] * q
    return jnp.exp(-2j * math.pi * (fx * v["x0"] + fy * v["y0"]))


def pixels_from_fine(model, v: Mapping[str, Any], padded, fine, q: int, *,
                     move: bool = False):
    """The padded window's data pixels (``padded``) from ``fine``, the intensity's point
    samples q times finer a side (× q²): each data pixel's square integrated (its
    transform, a sinc), the detector's blurs applied and, with ``move``, the star moved
    by (``x0``, ``y0``) data pixels, all in the spectrum; then the sample at each data
    pixel's centre, and what acts on the data's pixels themselves (a resampling kernel,
    a source image). Exact where ``fine`` samples the intensity above its Nyquist rate,
    the window taken as periodic."""
    hp, wp = padded
    fy = np.fft.fftfreq(hp * q)[:, None] * q  # cycles per data pixel
    fx = np.fft.rfftfreq(wp * q)[None, :] * q
    kern = model.detector_kernel(v, (hp, wp), q, data_grid=q == 1) * jnp.asarray(
        np.sinc(fx) * np.sinc(fy))
    if move:
        kern = kern * shift_ramp(v, hp, wp, q)
    img = jnp.fft.irfft2(jnp.fft.rfft2(fine) * kern, s=(hp * q, wp * q))
    # data pixel k's centre is fine sample k q + c (the axis: data pixel hp // 2, fine
    # sample hp q // 2)
    cy, cx = (hp * q) // 2 - (hp // 2) * q, (wp * q) // 2 - (wp // 2) * q
    img = img[cy::q, cx::q][:hp, :wp]
    if q > 1 and model.has_data_grid_kernel:
        img = jnp.fft.irfft2(jnp.fft.rfft2(img) * model.data_grid_kernel((hp, wp)),
                             s=(hp, wp))
    return img


__all__ = ["AFTER_OPTICS", "centred_psf", "fine_factor", "image_from_centred", "image_from_psf",
           "optics_fixed", "pixels_from_fine", "shift_ramp"]
