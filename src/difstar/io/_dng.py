"""Synthetic captures written as minimal Bayer CFA DNG files.

``write_dng`` stores a uint16 Bayer mosaic as an uncompressed DNG 1.4 (one IFD, CFA
photometric) that LibRaw (``rawpy.imread``) reads back with the same raw values, Bayer
layout, black and white levels, white balance and exposure metadata. ``synthesize_capture``
turns noiseless normalised values ζ into a noisy uint16 mosaic with the Poisson–Gaussian
model of a real sensor, clipped at the white level so saturation is real.

These helpers run outside the jitted core (NumPy and tifffile only). tifffile is imported
lazily so that ``import difstar`` stays cheap.
"""

from __future__ import annotations

import contextlib
import os
import secrets
from fractions import Fraction
from pathlib import Path

import numpy as np

from .._colour import xyz_to_srgb_linear_matrix

Real = float | int | np.integer | np.floating  # a real scalar (Python or NumPy)

BAYER_PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")
_CFA_CODE = {"R": 0, "G": 1, "B": 2}  # TIFF/EP CFAPattern colour codes

# TIFF field types
_BYTE, _ASCII, _SHORT, _LONG, _RATIONAL, _SRATIONAL = 1, 2, 3, 4, 5, 10

_D65 = 21  # EXIF LightSource code of CIE D65
_MIN_SIDE = 22  # LibRaw refuses images narrower or shorter than 22 pixels


class DngWriteError(ValueError):
    """Bad input to ``write_dng`` (or an existing output without ``overwrite``)."""


def _rational(x: float, *, signed: bool, name: str) -> tuple[int, int]:
    """float → (numerator, denominator) fitting in 32 bits (exact for simple fractions)."""
    x = float(x)
    if not np.isfinite(x) or (not signed and x < 0):
        raise DngWriteError(f"{name} = {x!r} cannot be stored as a {'S' if signed else ''}RATIONAL")
    lim = 2**31 - 1 if signed else 2**32 - 1
    if abs(x) > lim:
        raise DngWriteError(f"{name} = {x!r} is too large for a TIFF rational")
    f = Fraction(x).limit_denominator(1_000_000)
    while abs(f.numerator) > lim or f.denominator > lim:  # pragma: no cover - huge values
        f = Fraction(x).limit_denominator(max(1, f.denominator // 10))
    return f.numerator, f.denominator


def _rationals(values, *, signed: bool, name: str) -> tuple[int, ...]:
    out: list[int] = []
    for v in np.ravel(np.asarray(values, float)):
        out.extend(_rational(v, signed=signed, name=name))
    return tuple(out)


def _black_tile(black_level, pattern: str) -> np.ndarray:
    """Black level at each position of the 2×2 Bayer tile, (2, 2) float (DN)."""
    b = np.asarray(black_level, float)
    if b.ndim == 0:
        return np.full((2, 2), float(b))
    if b.size == 4:
        return b.reshape(2, 2)
    raise DngWriteError(
        "black_level must be a scalar or 4 values (DN), one per position of the 2×2 Bayer tile "
        f"in row-major order (top-left, top-right, bottom-left, bottom-right of {pattern!r}); "
        f"got shape {b.shape}"
    )


def write_dng(
    path: str | os.PathLike,
    raw: np.ndarray,
    *,
    pattern: str,
    black_level,
    white_level: Real,
    exposure_time: Real | None = None,
    f_number: Real | None = None,
    focal_length: Real | None = None,
    camera_white_balance=None,
    color_matrix=None,
    camera_model: str = "difstar synthetic",
    overwrite: bool = False,
    min_side: int = _MIN_SIDE,
) -> Path:
    """Write a Bayer mosaic as a minimal valid DNG that LibRaw reads back exactly.

    Parameters
    ----------
    path : destination file. Written atomically (a temporary file in the same directory,
        then ``os.replace``), so the output appears whole or not at all. An existing file
        is refused unless ``overwrite=True``.
    raw : (h, w) uint16 mosaic in DN (h, w even and ≥ 22), stored uncompressed, 16 bits/sample.
    pattern : Bayer layout of the top-left 2×2 tile, one of "RGGB", "BGGR", "GRBG", "GBRG".
    black_level : DN; a scalar, or 4 values for the 2×2 tile positions in row-major order
        (for "RGGB": R, G(top-right), G(bottom-left), B). ``RawCapture.black_level_tile``
        gives this form.
    white_level : DN, the saturation level (≤ 65535, > every black level).
    exposure_time : seconds (EXIF ExposureTime), or None to omit.
    f_number : dimensionless (EXIF FNumber), or None.
    focal_length : metres (stored as EXIF FocalLength in millimetres), or None.
    camera_white_balance : (3,) R, G, B multipliers (any scale; stored as AsShotNeutral =
        1/multiplier normalised to G = 1); None writes (1, 1, 1).
    color_matrix : (3, 3) XYZ → camera RGB matrix under D65 (DNG ColorMatrix1, the same
        meaning as LibRaw's ``rgb_xyz_matrix``), or None for the identity.
    camera_model : UniqueCameraModel string.
    min_side : the least height and width accepted: by default 22, the least LibRaw opens;
        a smaller one (≥ 2) writes a valid DNG that LibRaw (rawpy, darktable, RawTherapee)
        refuses but other readers open.

    Returns the path written.
    """
    import tifffile

    path = Path(path)
    raw = np.asarray(raw)
    if raw.ndim != 2 or raw.dtype != np.uint16:
        raise DngWriteError(f"raw must be a 2-D uint16 array; got {raw.dtype} {raw.shape}")
    h, w = raw.shape
    side = max(2, int(min_side))
    if h < side or w < side or h % 2 or w % 2:
        raise DngWriteError(
            f"raw must have even height and width ≥ {side}"
            + (" (LibRaw rejects smaller images)" if side == _MIN_SIDE else "")
            + f"; got {raw.shape}"
        )
    pattern = str(pattern).upper()
    if pattern not in BAYER_PATTERNS:
        raise DngWriteError(f"pattern must be one of {BAYER_PATTERNS}; got {pattern!r}")
    white = int(white_level)
    if white != white_level or not 0 < white <= 65535:
        raise DngWriteError(f"white_level must be an integer in (0, 65535]; got {white_level!r}")
    if raw.size and int(raw.max()) > white:
        raise DngWriteError(f"raw values up to {int(raw.max())} exceed white_level {white}")
    black = _black_tile(black_level, pattern)
    if np.any(black < 0) or np.any(black >= white):
        raise DngWriteError(f"black levels {black.ravel().tolist()} must lie in [0, white_level)")
    if path.exists() and not overwrite:
        raise DngWriteError(f"{path} already exists; pass overwrite=True to replace it")

    tags: list[tuple] = [
        (33421, _SHORT, 2, (2, 2), True),  # CFARepeatPatternDim
        (33422, _BYTE, 4, bytes(_CFA_CODE[c] for c in pattern), True),  # CFAPattern
        (50706, _BYTE, 4, bytes((1, 4, 0, 0)), True),  # DNGVersion
        (50707, _BYTE, 4, bytes((1, 1, 0, 0)), True),  # DNGBackwardVersion
        (50708, _ASCII, 0, camera_model, True),  # UniqueCameraModel
        (50710, _BYTE, 3, bytes((0, 1, 2)), True),  # CFAPlaneColor
        (50711, _SHORT, 1, 1, True),  # CFALayout: rectangular
        (50713, _SHORT, 2, (2, 2), True),  # BlackLevelRepeatDim
        (50714, _RATIONAL, 4, _rationals(black, signed=False, name="black_level"), True),
        (50717, _LONG, 1, white, True),  # WhiteLevel
        (50778, _SHORT, 1, _D65, True),  # CalibrationIlluminant1
    ]
    cm = np.eye(3) if color_matrix is None else np.asarray(color_matrix, float)
    if cm.shape != (3, 3) or not np.all(np.isfinite(cm)):
        raise DngWriteError(f"color_matrix must be a finite (3, 3) array; got shape {cm.shape}")
    tags.append((50721, _SRATIONAL, 9, _rationals(cm, signed=True, name="color_matrix"), True))
    wb = np.ones(3) if camera_white_balance is None else np.asarray(camera_white_balance, float)
    wb = wb.ravel()
    if wb.shape != (3,) or not np.all(np.isfinite(wb)) or np.any(wb <= 0):
        raise DngWriteError(
            f"camera_white_balance must be 3 positive R, G, B multipliers; got {wb.tolist()}"
        )
    neutral = wb[1] / wb
    tags.append((50728, _RATIONAL, 3, _rationals(neutral, signed=False, name="wb"), True))
    if exposure_time is not None:
        if not exposure_time > 0:
            raise DngWriteError(f"exposure_time must be > 0 s; got {exposure_time!r}")
        tags.append((33434, _RATIONAL, 1, _rational(exposure_time, signed=False, name="t"), True))
    if f_number is not None:
        if not f_number > 0:
            raise DngWriteError(f"f_number must be > 0; got {f_number!r}")
        tags.append((33437, _RATIONAL, 1, _rational(f_number, signed=False, name="N"), True))
    if focal_length is not None:
        if not focal_length > 0:
            raise DngWriteError(f"focal_length must be > 0 m; got {focal_length!r}")
        mm = _rational(float(focal_length) * 1e3, signed=False, name="focal_length")
        tags.append((37386, _RATIONAL, 1, mm, True))

    path.parent.mkdir(parents=True, exist_ok=True)
    # A fresh name beside the destination, created with open(..., "xb") so the usual
    # umask permissions apply (mkstemp would make it private).
    tmp = path.parent / f".{path.name}.{os.getpid()}.{secrets.token_hex(6)}.tmp"
    try:
        open(tmp, "xb").close()
        with tifffile.TiffWriter(tmp, bigtiff=False, byteorder="<") as tif:
            tif.write(
                raw,
                photometric=tifffile.PHOTOMETRIC.CFA,
                subfiletype=0,
                compression=None,
                rowsperstrip=h,
                metadata=None,
                software=SOFTWARE,
                extratags=tags,
            )
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        if path.exists() and not overwrite:  # appeared meanwhile
            raise DngWriteError(f"{path} already exists; pass overwrite=True to replace it")
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    return path


def dng_colour_matrix(colour_matrix, white_balance) -> np.ndarray:
    """DNG ColorMatrix1 (XYZ → camera RGB under D65, LibRaw's ``rgb_xyz_matrix``) of a
    camera whose white-balanced RGB difstar renders with ``colour_matrix``.

    difstar renders linear sRGB = M · diag(wb) · camera RGB (M = ``colour_matrix``, wb the
    R, G, B ``white_balance`` gains), and linear sRGB = X · CIE XYZ with X the XYZ → sRGB
    matrix difstar uses everywhere (colour-science's, D65:
    :func:`difstar._colour.xyz_to_srgb_linear_matrix`). So camera RGB = diag(1/wb) · M⁻¹ ·
    X · XYZ: that matrix, scaled so that D65 white (CIE 1931 xy, Y = 1) gives a camera
    neutral whose largest component is 1 (the DNG convention). Its neutral is then ∝ 1/wb,
    the AsShotNeutral :func:`write_dng` stores for the same gains, so a DNG reader's white
    balance and matrix give difstar's colours. Raw converters (LibRaw, Adobe) map the
    camera neutral to white; difstar's own rendering does so too exactly when M's rows
    sum to 1 (M · (1, 1, 1) = (1, 1, 1)), as colour matrices are normalised.
    """
    import colour  # noqa: PLC0415  (lazy: keep `import difstar` cheap)

    m = np.asarray(colour_matrix, float)
    wb = np.ravel(np.asarray(white_balance, float))
    if m.shape != (3, 3) or not np.all(np.isfinite(m)):
        raise DngWriteError(f"colour_matrix must be a finite (3, 3) array; got shape {m.shape}")
    if wb.shape != (3,) or not np.all(np.isfinite(wb)) or np.any(wb <= 0):
        raise DngWriteError(f"white_balance must be 3 positive gains R, G, B; got {wb.tolist()}")
    if abs(np.linalg.det(m)) < 1e-12 * max(np.abs(m).max(), 1e-300) ** 3:
        raise DngWriteError(f"colour_matrix {m.tolist()} is singular: no camera RGB → sRGB "
                            "mapping can be stored in a DNG; give an invertible matrix.")
    cm = np.diag(1.0 / wb) @ np.linalg.inv(m) @ xyz_to_srgb_linear_matrix()
    xy = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]
    neutral = cm @ np.asarray(colour.xy_to_XYZ(xy), float)
    return cm / np.max(np.abs(neutral))


def synthesize_capture(
    zeta: np.ndarray,
    *,
    black_level,
    white_level: Real,
    gain_e_per_dn: Real,
    read_noise_dn: Real,
    rng: np.random.Generator,
) -> np.ndarray:
    """Noisy uint16 mosaic (DN) from noiseless normalised values ζ with Poisson–Gaussian noise.

    Model, per pixel: electrons ~ Poisson(ζ·(white − black)·gain); signal (DN) =
    electrons / gain + Normal(0, read_noise_dn); raw = round(clip(signal + black, 0, white)).
    So E[raw − black] = ζ·(white − black) and Var = ζ·(white − black)/gain + read_noise_dn²
    away from the clip; values at or above white are clipped to white (real saturation).

    Parameters
    ----------
    zeta : (h, w) float, expected normalised values ζ (≥ 0; values above 1 saturate).
    black_level : DN; a scalar, a (2, 2) tile repeated over the mosaic, or an (h, w) array.
    white_level : DN, the saturation level.
    gain_e_per_dn : electrons per DN (> 0).
    read_noise_dn : standard deviation of the Gaussian read noise in DN (≥ 0).
    rng : numpy Generator (the only source of randomness).
    """
    z = np.asarray(zeta, float)
    if z.ndim != 2:
        raise ValueError(f"zeta must be 2-D (h, w); got shape {z.shape}")
    if not np.all(np.isfinite(z)) or np.any(z < 0):
        raise ValueError("zeta must be finite and ≥ 0")
    if not gain_e_per_dn > 0 or not read_noise_dn >= 0:
        raise ValueError(
            f"need gain_e_per_dn > 0 and read_noise_dn ≥ 0; got {gain_e_per_dn}, {read_noise_dn}"
        )
    h, w = z.shape
    b = np.asarray(black_level, float)
    if b.shape == (2, 2):
        b = np.tile(b, ((h + 1) // 2, (w + 1) // 2))[:h, :w]
    b = np.broadcast_to(b, z.shape)
    white = float(white_level)
    if np.any(b >= white):
        raise ValueError("black level must be below the white level")
    electrons = rng.poisson(z * (white - b) * gain_e_per_dn)
    dn = electrons / gain_e_per_dn + rng.normal(0.0, read_noise_dn, size=z.shape) + b
    return np.round(np.clip(dn, 0.0, min(white, 65535.0))).astype(np.uint16)


#: the TIFF Software tag :func:`write_dng` writes, by which difstar knows its own DNGs
SOFTWARE = "difstar"


def written_by_difstar(path: str | Path) -> bool:
    """True only for a regular file that is a TIFF/DNG whose first image's ``Software``
    tag reads ``difstar`` (a DNG :func:`write_dng` wrote). Reads the header only; any
    other file, or one that cannot be read, is False (a camera's own RAW file is never
    taken for difstar's)."""
    import tifffile

    p = Path(path)
    if p.is_symlink() or not p.is_file():
        return False
    try:
        with tifffile.TiffFile(p) as tif:
            tag = tif.pages[0].tags.get("Software")
            return tag is not None and str(tag.value).strip("\x00 ") == SOFTWARE
    except Exception:  # noqa: BLE001 - not a TIFF difstar can read: not difstar's
        return False
