"""Reading camera RAW files (any Bayer camera LibRaw supports) with rawpy.

``read_raw(path)`` returns a ``RawCapture``: the visible Bayer mosaic, its layout, black
and white levels, the saturated pixels, the camera white balance and colour matrix, and
the exposure metadata. Non-Bayer sensors (X-Trans, Foveon, monochrome, linear DNG), files
LibRaw cannot read (unsupported, unreadable, truncated) and missing required values raise
``RawReadError`` naming the file and the problem. The input file is only ever opened for
reading.

This module runs outside the jitted core; rawpy and tifffile are imported lazily.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import os
import struct
import warnings
from pathlib import Path

import numpy as np

from ._files import readable_file

_EXPOSURE_TIME, _F_NUMBER, _FOCAL_LENGTH = 33434, 33437, 37386
_EXIF_IFD = 34665
_EXIF_NAMES = {"ExposureTime": _EXPOSURE_TIME, "FNumber": _F_NUMBER, "FocalLength": _FOCAL_LENGTH}
_COLOR_MATRIX_1, _COLOR_MATRIX_2 = 50721, 50722
_ILLUMINANT_1, _ILLUMINANT_2 = 50778, 50779
_D65 = 21


class RawReadError(ValueError):
    """A RAW file that cannot be used: missing, unreadable, truncated, non-Bayer, or
    lacking a required value. The message names the file and the problem."""


class MissingColourMatrixWarning(UserWarning):
    """A RAW file read without a colour matrix (LibRaw has none for the camera and the
    file carries none): the mosaic is usable (fitting needs only it), but rendering it
    to sRGB needs a camera → XYZ matrix supplied by the user."""


@dataclasses.dataclass(frozen=True, eq=False)
class RawCapture:
    """One RAW capture, visible area only.

    Attributes
    ----------
    path : the file read.
    cfa : (h, w) float64 normalised values ζ = (raw − black) / (white − black), with the
        black level of each pixel's CFA channel (not clipped: noise can make ζ < 0).
    raw : (h, w) uint16 visible mosaic in DN, as LibRaw decodes it (linearised).
    pattern : Bayer layout of the top-left 2×2 tile of the visible area, e.g. "RGGB".
    black_level : (4,) float64 DN, black level per CFA channel index as rawpy gives it
        (``black_level_per_channel``; index 3 is the second green). See
        ``black_level_tile`` for the level at each position of the 2×2 tile.
    white_level : float DN, the saturation level.
    saturated : (h, w) bool, raw ≥ white level or ≥ the camera's own per-channel
        saturation level where rawpy exposes one (``camera_white_level_per_channel``).
    camera_white_balance : (3,) R, G, B as-shot multipliers normalised to G = 1.
    rgb_xyz_matrix : (3, 3) XYZ → camera RGB matrix (LibRaw's ``rgb_xyz_matrix``; for DNG
        files, where LibRaw leaves it zero, the file's ColorMatrix for D65 if present,
        else ColorMatrix1). Rows: camera R, G, B; columns: X, Y, Z. None when neither
        LibRaw nor the file has one (a ``MissingColourMatrixWarning`` is issued): the
        mosaic can still be fitted; rendering to sRGB then needs a matrix.
    camera_to_srgb : (3, 3) camera RGB → linear sRGB matrix (LibRaw's ``color_matrix``,
        rows summing to 1); None when ``rgb_xyz_matrix`` is None.
    exposure_time : seconds, or None when the file does not say.
    f_number : dimensionless, or None.
    focal_length : metres, or None.
    raw_colors : (h, w) uint8 CFA channel index of each visible pixel (rawpy's
        ``raw_colors_visible``; indexes ``black_level``).
    """

    path: Path
    cfa: np.ndarray
    raw: np.ndarray
    pattern: str
    black_level: np.ndarray
    white_level: float
    saturated: np.ndarray
    camera_white_balance: np.ndarray
    rgb_xyz_matrix: np.ndarray | None
    camera_to_srgb: np.ndarray | None
    exposure_time: float | None
    f_number: float | None
    focal_length: float | None
    raw_colors: np.ndarray

    @property
    def shape(self) -> tuple[int, int]:
        """(h, w) of the visible mosaic in pixels."""
        return tuple(self.raw.shape)  # type: ignore[return-value]

    @property
    def black_level_tile(self) -> np.ndarray:
        """(2, 2) black level in DN at each position of the top-left Bayer tile (the
        form ``write_dng`` takes, flattened row-major)."""
        return self.black_level[self.raw_colors[:2, :2]]

    @property
    def camera_to_xyz(self) -> np.ndarray:
        """(3, 3) camera RGB → XYZ, the inverse of ``rgb_xyz_matrix``."""
        if self.rgb_xyz_matrix is None:
            raise RawReadError(
                f"{self.path}: no colour matrix (LibRaw has none for this camera and the "
                "file carries none); rendering to sRGB needs a camera → XYZ matrix: give "
                "one explicitly.")
        return np.linalg.inv(self.rgb_xyz_matrix)


def _err(path: Path, problem: str) -> RawReadError:
    return RawReadError(f"{path}: {problem}")


def read_raw(path: str | os.PathLike) -> RawCapture:
    """Read a Bayer RAW file (any format LibRaw supports) into a ``RawCapture``.

    Raises ``RawReadError`` (a ``ValueError``) naming the file when it is missing, not a
    RAW file LibRaw can read, unreadable or truncated, from a non-Bayer sensor (X-Trans,
    Foveon, monochrome, linear/demosaiced DNG, CMYG), or lacks a required value (levels,
    white balance). A file without a colour matrix is read (the mosaic is what a fit
    needs) with a ``MissingColourMatrixWarning`` and ``rgb_xyz_matrix = None``.

    Truncation: a TIFF-based RAW (DNG, NEF, CR2, ARW, PEF, ...) is checked before LibRaw
    decodes it against the sizes its own tags declare: every IFD, the strip/tile offset
    and byte-count arrays, and the strips/tiles themselves must lie inside the file
    (LibRaw would otherwise decode a cut file "successfully" from uninitialised memory).
    Other formats rely on LibRaw's own errors, reported with the file's name.
    """
    import rawpy

    path = readable_file(path, _err)

    size = path.stat().st_size
    if size == 0:
        raise _err(path, "empty file (0 bytes), not a RAW file")
    problem = _tiff_truncation(path, size)
    if problem is not None:
        raise _err(path, problem)

    try:
        rp = rawpy.imread(str(path))
    except rawpy.LibRawFileUnsupportedError as e:
        kind = _tiff_kind(path)
        if kind is not None:
            raise _err(path, f"not a Bayer sensor: {kind}; {_SUPPORTED}") from e
        raise _err(
            path, f"not a RAW file LibRaw can read (unsupported format); {_SUPPORTED}") from e
    except rawpy.LibRawError as e:
        raise _err(path, _diagnose(path, e)) from e
    except OSError as e:
        raise _err(path, f"cannot be read ({e})") from e

    with rp:
        try:
            return _capture(path, rp)
        except rawpy.LibRawError as e:
            raise _err(path, _diagnose(path, e)) from e


def _diagnose(path: Path, e: Exception) -> str:
    """A readable reason for a LibRaw failure (truncation detected from TIFF offsets)."""
    msg = e.args[0].decode(errors="replace") if e.args and isinstance(e.args[0], bytes) else str(e)
    size = path.stat().st_size
    if size == 0:
        return "empty file (0 bytes), not a RAW file"
    end = _tiff_data_end(path)
    if end is not None and end > size:
        return (
            f"truncated: the image data extends to byte {end} but the file has only {size} "
            f"bytes (LibRaw: {msg})"
        )
    with path.open("rb") as fh:
        head = fh.read(512)
    if head and all(32 <= b < 127 or b in (9, 10, 13) for b in head):
        return f"a text file, not a RAW file (LibRaw: {msg})"
    return (
        f"unreadable or truncated RAW data, or not a RAW file (LibRaw: {type(e).__name__}: {msg})"
    )


@contextlib.contextmanager
def _quiet_tifffile():
    """Silence tifffile's log messages about damaged tags while probing a file."""
    log = logging.getLogger("tifffile")
    old = log.level
    log.setLevel(logging.CRITICAL + 1)
    try:
        yield
    finally:
        log.setLevel(old)


def _tiff_data_end(path: Path) -> int | None:
    """Largest offset + byte count of the strips/tiles of a TIFF-based file, else None."""
    try:
        import tifffile

        end = 0
        with _quiet_tifffile(), tifffile.TiffFile(path) as tif:
            pages = list(tif.pages)
            for p in list(pages):
                pages.extend(getattr(p, "pages", []) or [])
            for p in pages:
                offs = getattr(p, "dataoffsets", ()) or ()
                cnts = getattr(p, "databytecounts", ()) or ()
                for o, c in zip(offs, cnts):
                    end = max(end, int(o) + int(c))
        return end or None
    except Exception:
        return None


# TIFF field type → bytes per value; struct codes of the integer types offsets use
_TIFF_TYPE_SIZE = {1: 1, 2: 1, 3: 2, 4: 4, 5: 8, 6: 1, 7: 1, 8: 2, 9: 4, 10: 8, 11: 4, 12: 8,
                   13: 4, 16: 8, 17: 8, 18: 8}
_TIFF_INT = {1: "B", 3: "H", 4: "I", 13: "I", 16: "Q", 18: "Q"}
_DATA_TAGS = ((273, 279, "strip"), (324, 325, "tile"))  # offsets, byte counts
_IFD_POINTERS = (330, 34665)  # SubIFDs (where DNGs keep the raw image), EXIF IFD


def _tiff_truncation(path: Path, size: int) -> str | None:
    """Why a TIFF-based file is cut short, or None (also for files that are not TIFF).

    Walks the IFD chain and the SubIFD/EXIF IFDs the file declares (classic and
    BigTIFF) and checks that every IFD, the strip/tile offset and byte-count arrays and
    the strips/tiles themselves lie inside the file; then the same data extents as
    ``tifffile`` parses them. Tag values other than these are not checked (a damaged
    private tag does not stop LibRaw)."""
    def cut(what: str, end: int) -> str:
        return (f"truncated: its TIFF tags declare {what} up to byte {end} but the file has "
                f"only {size} bytes (cut short or incompletely copied)")

    with path.open("rb") as fh:
        head = fh.read(16)
        if head[:4] in (b"II*\0", b"MM\0*"):
            big = False
        elif head[:4] in (b"II+\0", b"MM\0+"):
            big = True
        else:
            return None
        bo = "<" if head[:2] == b"II" else ">"
        ptr, cnt, entry = ("Q", "Q", 20) if big else ("I", "H", 12)
        psize = struct.calcsize(ptr)
        if len(head) < (16 if big else 8):
            return (f"truncated: {size} bytes, shorter than the TIFF header it starts "
                    f"({16 if big else 8} bytes)")
        first = struct.unpack(bo + ptr, head[8:16] if big else head[4:8])[0]

        def read_ints(typ: int, count: int, pos: int, inline_at: int | None):
            code = _TIFF_INT.get(typ)
            if code is None or count > 10_000_000:
                return []
            fh.seek(inline_at if inline_at is not None else pos)
            return list(struct.unpack(f"{bo}{count}{code}", fh.read(count * struct.calcsize(code))))

        queue, seen = [first], set()
        while queue and len(seen) < 10_000:
            off = queue.pop(0)
            if off == 0 or off in seen:
                continue
            seen.add(off)
            csize = struct.calcsize(cnt)
            if off + csize > size:
                return cut(f"an IFD at byte {off}", off + csize)
            fh.seek(off)
            n = struct.unpack(bo + cnt, fh.read(csize))[0]
            end = off + csize + n * entry + psize
            if end > size:
                return cut(f"an IFD of {n} entries at byte {off}", end)
            buf = fh.read(n * entry + psize)
            tags = {}
            for i in range(n):
                e = buf[i * entry:(i + 1) * entry]
                code, typ = struct.unpack(bo + "HH", e[:4])
                count = struct.unpack(bo + ptr, e[4:4 + psize])[0]
                nbytes = count * _TIFF_TYPE_SIZE.get(typ, 1)
                if nbytes <= psize:  # stored in the entry itself
                    tags[code] = (typ, count, off + csize + i * entry + 4 + psize, True, nbytes)
                else:
                    voff = struct.unpack(bo + ptr, e[4 + psize:4 + 2 * psize])[0]
                    tags[code] = (typ, count, voff, False, nbytes)
            queue.append(struct.unpack(bo + ptr, buf[n * entry:n * entry + psize])[0])

            def values(code):
                typ, count, pos, inline, nbytes = tags[code]
                return read_ints(typ, count, pos, pos if inline else None)

            for code in (*(c for o, b, _ in _DATA_TAGS for c in (o, b)), *_IFD_POINTERS):
                if code in tags and not tags[code][3]:
                    _, _, pos, _, nbytes = tags[code]
                    if pos + nbytes > size:
                        return cut(f"the values of tag {code} (an offset table)", pos + nbytes)
            for o_code, b_code, what in _DATA_TAGS:
                if o_code in tags and b_code in tags:
                    ends = [o + b for o, b in zip(values(o_code), values(b_code))]
                    if ends and max(ends) > size:
                        return cut(f"image data ({what}s)", max(ends))
            for code in _IFD_POINTERS:
                if code in tags:
                    queue.extend(values(code))
    end = _tiff_data_end(path)
    if end is not None and end > size:
        return cut("image data", end)
    return None


_SUPPORTED = (
    "difstar reads Bayer RAW mosaics only (a 2×2 RGB colour filter array: RGGB, BGGR, GRBG "
    "or GBRG, any camera LibRaw decodes)")


def _tiff_kind(path: Path) -> str | None:
    """What a TIFF/DNG image LibRaw refused holds, from its PhotometricInterpretation:
    "monochrome ...", "linear ...", "an RGB ..."; None when it cannot tell."""
    try:
        import tifffile

        with _quiet_tifffile(), tifffile.TiffFile(path) as tif:
            pages = list(tif.pages)
            for p in list(pages):
                pages.extend(getattr(p, "pages", []) or [])
            kinds = set()
            for p in pages:
                phot = int(getattr(p, "photometric", -1))
                if phot in (0, 1) and int(getattr(p, "samplesperpixel", 1)) == 1:
                    kinds.add("monochrome (no colour filter array)")
                elif phot == 34892:
                    kinds.add("a linear (already demosaiced) DNG")
                elif phot == 2:
                    kinds.add("an RGB image (already demosaiced), not a RAW mosaic")
                elif phot == 32803:
                    return None  # a CFA image: LibRaw's refusal has another reason
            return sorted(kinds)[0] if kinds else None
    except Exception:
        return None


def _sensor_check(path: Path, rp) -> None:
    import rawpy

    pat = rp.raw_pattern
    ncol = int(rp.num_colors)
    desc = bytes(rp.color_desc).decode(errors="replace")
    if rp.raw_type != rawpy.RawType.Flat or pat is None:
        kind = (
            "monochrome"
            if ncol == 1
            else "a non-mosaic sensor (Foveon/layered or linear/demosaiced DNG)"
        )
        raise _err(path, f"not a Bayer sensor: {kind}; {_SUPPORTED}")
    if pat.shape == (6, 6):
        raise _err(path, f"not a Bayer sensor: X-Trans (6×6 CFA); {_SUPPORTED}")
    if ncol == 1:
        raise _err(path, f"not a Bayer sensor: monochrome (no colour filter array); {_SUPPORTED}")
    if pat.shape != (2, 2) or ncol != 3:
        raise _err(
            path,
            f"not a Bayer sensor: CFA {pat.shape[0]}×{pat.shape[1]} with {ncol} colours "
            f"({desc}); {_SUPPORTED}",
        )


def _capture(path: Path, rp) -> RawCapture:
    _sensor_check(path, rp)
    desc = bytes(rp.color_desc).decode(errors="replace")
    raw = np.array(rp.raw_image_visible, dtype=np.uint16, copy=True)
    colors = np.array(rp.raw_colors_visible, dtype=np.uint8, copy=True)
    h, w = raw.shape
    if h < 2 or w < 2:
        raise _err(path, f"visible area {h}×{w} is too small for a 2×2 Bayer tile")
    tile = colors[:2, :2]
    try:
        letters = "".join(desc[int(c)] for c in tile.ravel())
    except IndexError:
        raise _err(path, f"CFA channel index out of range of colour description {desc!r}") from None
    if sorted(letters) != ["B", "G", "G", "R"]:
        raise _err(path, f"not an RGB Bayer layout: top-left tile {letters!r} ({desc})")
    expect = np.tile(tile, ((h + 1) // 2, (w + 1) // 2))[:h, :w]
    if not np.array_equal(colors, expect):
        raise _err(path, "CFA layout is not a repeating 2×2 Bayer tile over the visible area")

    black = np.asarray(rp.black_level_per_channel, dtype=np.float64)
    if black.shape != (4,) or not np.all(np.isfinite(black)):
        raise _err(path, f"missing or invalid black level per channel: {black.tolist()}")
    white = float(rp.white_level)
    if not np.isfinite(white) or white <= 0:
        raise _err(path, f"missing white level (LibRaw reports {white})")
    black_px = black[colors]
    if np.any(black[np.unique(tile)] >= white):
        raise _err(path, f"black level {black.tolist()} is not below the white level {white}")
    cfa = (raw.astype(np.float64) - black_px) / (white - black_px)

    sat_level = np.full(4, white)
    cam_white = rp.camera_white_level_per_channel
    if cam_white is not None:
        cw = np.asarray(cam_white, float)
        if cw.shape == (4,):
            sat_level = np.where(cw > 0, np.minimum(cw, white), white)
    saturated = raw >= sat_level[colors]

    wb = np.asarray(rp.camera_whitebalance, dtype=np.float64)[:4]
    wb3 = _rgb_from_channels(wb, desc)
    if wb3 is None or not np.all(np.isfinite(wb3)) or np.any(wb3 <= 0):
        raise _err(path, f"missing camera white balance (LibRaw reports {wb.tolist()})")
    wb3 = wb3 / wb3[1]

    tags = _tiff_tags(path)
    xyz_cam = np.asarray(rp.rgb_xyz_matrix, dtype=np.float64)[:3, :3]
    if not np.any(xyz_cam):
        xyz_cam = _dng_color_matrix(tags)
    if xyz_cam is None or not np.any(xyz_cam):
        warnings.warn(
            f"{path}: no colour matrix (LibRaw has none for this camera and the file "
            "carries none); the mosaic is read as is (fitting needs only it), but rendering "
            "it to sRGB will need a camera → XYZ matrix given explicitly.",
            MissingColourMatrixWarning, stacklevel=3)
        xyz_cam = cam_srgb = None
    else:
        if not np.all(np.isfinite(xyz_cam)) or abs(np.linalg.det(xyz_cam)) < 1e-12:
            raise _err(path, f"invalid colour matrix (singular or not finite): {xyz_cam.tolist()}")
        cam_srgb = np.asarray(rp.color_matrix, dtype=np.float64)[:3, :3].copy()

    other = getattr(rp, "other", None)
    t = _tag_float(tags, _EXPOSURE_TIME)
    n = _tag_float(tags, _F_NUMBER)
    f_mm = _tag_float(tags, _FOCAL_LENGTH)
    if t is None and other is not None and other.shutter_speed > 0:
        t = float(other.shutter_speed)
    if n is None and other is not None and other.aperture > 0:
        n = float(other.aperture)
    if f_mm is None and other is not None and other.focal_length > 0:
        f_mm = float(other.focal_length)

    for a in (cfa, raw, black, saturated, wb3, xyz_cam, cam_srgb, colors):
        if a is not None:
            a.setflags(write=False)
    return RawCapture(
        path=path,
        cfa=cfa,
        raw=raw,
        pattern=letters,
        black_level=black,
        white_level=white,
        saturated=saturated,
        camera_white_balance=wb3,
        rgb_xyz_matrix=xyz_cam,
        camera_to_srgb=cam_srgb,
        exposure_time=t,
        f_number=n,
        focal_length=None if f_mm is None else f_mm * 1e-3,
        raw_colors=colors,
    )


def _rgb_from_channels(v: np.ndarray, desc: str) -> np.ndarray | None:
    """(R, G, B) from per-channel values indexed like ``color_desc`` (first of each)."""
    out = []
    for c in "RGB":
        i = desc.find(c)
        if i < 0 or i >= v.size:
            return None
        out.append(v[i])
    return np.array(out, dtype=np.float64)


def _tiff_tags(path: Path) -> dict[int, object]:
    """Tags of IFD0 and its EXIF IFD by code (EXIF wins on clashes); {} if not TIFF-based."""
    try:
        import tifffile

        out: dict[int, object] = {}
        with _quiet_tifffile(), tifffile.TiffFile(path) as tif:
            page = tif.pages.first
            for tag in page.tags.values():
                out[tag.code] = tag.value
            exif = page.tags.get(_EXIF_IFD)
            if exif is not None and isinstance(exif.value, dict):
                for name, value in exif.value.items():
                    code = _EXIF_NAMES.get(name)
                    if code is not None:
                        out[code] = value
        return out
    except Exception:
        return {}


def _tag_float(tags: dict[int, object], code: int) -> float | None:
    """A RATIONAL/number tag as a positive float, else None."""
    v = tags.get(code)
    if v is None:
        return None
    try:
        a = np.asarray(v, dtype=np.float64).ravel()
        x = a[0] / a[1] if a.size == 2 else a[0] if a.size == 1 else np.nan
    except (TypeError, ValueError):
        return None
    return float(x) if np.isfinite(x) and x > 0 else None


def _dng_color_matrix(tags: dict[int, object]) -> np.ndarray | None:
    """XYZ → camera (3, 3) from DNG ColorMatrix1/2: the one calibrated for D65, else 1."""
    cands = [(tags.get(_ILLUMINANT_1), tags.get(_COLOR_MATRIX_1))]
    cands.append((tags.get(_ILLUMINANT_2), tags.get(_COLOR_MATRIX_2)))
    cands = [(ill, m) for ill, m in cands if m is not None]
    if not cands:
        return None
    cands.sort(key=lambda im: 0 if _as_int(im[0]) == _D65 else 1)
    a = np.asarray(cands[0][1], dtype=np.float64).ravel()
    if a.size == 18:
        a = a[0::2] / a[1::2]
    if a.size < 9:
        return None
    return a[:9].reshape(3, 3)


def _as_int(v) -> int | None:
    try:
        return int(np.asarray(v).ravel()[0])
    except (TypeError, ValueError, IndexError):
        return None
