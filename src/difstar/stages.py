"""The steps of :func:`difstar.simulate` one at a time, and the sampling rules that size
its grid: for whoever times, checks or recombines them (``benchmarks/`` does). Most users
need only ``simulate``, ``psf`` and ``choose_grid`` from the top-level package.

The chain, in the order data flows: the geometric image of the sources
(:func:`geometric_image`) and its spectrum (:func:`image_spectrum`); one colour channel's
PSF on the grid (:func:`channel_psf`), its OTF (:func:`otf`), their product back to an
image (:func:`convolve`) cut to the capture (:func:`crop`); the sensor's response
(:func:`sensor`), the colour filter mosaic (:func:`mosaic`) and the rendering to sRGB
(:func:`render_srgb`).
"""

from ._atf import defocus_phase_coefficient as defocus_phase_coefficient
from ._cfa import mosaic as mosaic
from ._chain import _crop as crop
from ._chain import channel_psf as channel_psf
from ._chain import geometry_of as geometry_of
from ._colour import render_srgb as render_srgb
from ._fft_size import fast_length as fast_length
from ._image import convolve as convolve
from ._image import geometric_image as geometric_image
from ._image import image_spectrum as image_spectrum
from ._mft import conv_size as conv_size
from ._mft import window_rfft2 as window_rfft2
from ._otf import otf as otf
from ._sampling import DEFAULT_ACCURACY as DEFAULT_ACCURACY
from ._sampling import choose_grid as choose_grid
from ._sampling import padding_for_accuracy as padding_for_accuracy
from ._sampling import scene_extent as scene_extent
from ._sensor import sensor as sensor

__all__ = [
    "DEFAULT_ACCURACY", "channel_psf", "choose_grid", "conv_size", "convolve", "crop",
    "defocus_phase_coefficient", "fast_length", "geometric_image", "geometry_of",
    "image_spectrum", "mosaic", "otf", "padding_for_accuracy",
    "render_srgb", "scene_extent", "sensor", "window_rfft2",
]
