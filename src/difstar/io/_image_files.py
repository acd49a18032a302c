"""Image files other tools open: sRGB PNG and 16-bit TIFF (tagged sRGB) and the Bayer
DNG that ``predict`` writes (docs/outputs.md). Each writes one file at ``path``; the
caller writes into a folder from :func:`difstar.io._output.output_dir`, so a result
appears whole or not at all."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ._dng import dng_colour_matrix, write_dng


def _srgb_icc() -> bytes:
    """An ICC profile of sRGB (IEC 61966-2-1, D65), LittleCMS's built-in one via Pillow."""
    from PIL import ImageCms

    return ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes()


def _srgb_quantised(srgb, levels: int) -> np.ndarray:
    """(3, h, w) encoded sRGB in [0, 1] → (h, w, 3) integers round(v · levels) (clipped)."""
    a = np.asarray(srgb, float)
    if a.ndim != 3 or a.shape[0] != 3:
        raise ValueError(f"srgb must be (3, h, w); got shape {a.shape}")
    return np.round(np.moveaxis(np.clip(a, 0.0, 1.0), 0, -1) * levels)


def write_png_srgb(path: str | Path, srgb) -> None:
    """(3, h, w) sRGB in [0, 1] → 8-bit RGB PNG, tagged sRGB (an ``sRGB`` chunk, rendering
    intent perceptual, with the ``gAMA`` 1/2.2 the PNG specification asks to go with it)."""
    from PIL import Image, PngImagePlugin

    a = _srgb_quantised(srgb, 255).astype(np.uint8)
    info = PngImagePlugin.PngInfo()
    info.add(b"sRGB", b"\x00")
    info.add(b"gAMA", (45455).to_bytes(4, "big"))
    Image.fromarray(a, mode="RGB").save(path, pnginfo=info)


def write_tiff_srgb16(path: str | Path, srgb) -> None:
    """(3, h, w) sRGB in [0, 1] → 16-bit RGB TIFF, round(v · 65535), tagged sRGB by an
    embedded ICC profile (TIFF tag 34675); uncompressed, so any TIFF reader opens it."""
    import tifffile

    a = _srgb_quantised(srgb, 65535).astype(np.uint16)
    # no Software = difstar: that tag marks the DNGs difstar wrote (``written_by_difstar``)
    tifffile.imwrite(path, a, photometric="rgb", compression=None, metadata=None,
                     iccprofile=_srgb_icc())


#: the levels (DN) of the 16-bit mosaic ``predict`` writes: ζ = 0 ↔ black, ζ = 1 ↔ white
RAW_BLACK_LEVEL = 0
RAW_WHITE_LEVEL = 65535


def write_raw_dng(path: str | Path, cfa, *, pattern: str, white_balance, colour_matrix,
                  black_level: int = RAW_BLACK_LEVEL, white_level: int = RAW_WHITE_LEVEL,
                  exposure_time=None, focal_length=None) -> None:
    """(h, w) normalised mosaic ζ in [0, 1] → a Bayer DNG that raw converters develop:
    the values black + round(ζ · (white − black)) (uint16), the CFA layout ``pattern``,
    the black and white levels, ColorMatrix1 from difstar's camera RGB → linear sRGB
    ``colour_matrix`` and ``white_balance`` (:func:`difstar.io._dng.dng_colour_matrix`),
    AsShotNeutral = 1/``white_balance`` (G = 1), and ``Software`` = difstar.
    ``exposure_time`` (s) and ``focal_length`` (m) go to EXIF when given. Any even size is
    written; LibRaw (rawpy, darktable, RawTherapee) opens only ≥ 22 × 22 pixels."""
    z = np.clip(np.asarray(cfa, float), 0.0, 1.0)
    raw = (black_level + np.round(z * (white_level - black_level))).astype(np.uint16)
    write_dng(path, raw, pattern=pattern, black_level=black_level, white_level=white_level,
              exposure_time=exposure_time, focal_length=focal_length,
              camera_white_balance=np.asarray(white_balance, float),
              color_matrix=dng_colour_matrix(colour_matrix, white_balance),
              camera_model="difstar prediction", min_side=2)
