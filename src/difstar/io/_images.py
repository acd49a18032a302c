"""Reading intensity images (measured PSFs, star images): FITS, TIFF, PNG, NumPy.

``read_image(path)`` returns an ``ImageData``: a (h, w) float64 array in difstar's
convention (row 0 at the top, rows running down, y up), a mask of the valid (finite)
pixels, the file's header as a dict and, for FITS, the pixel scale its keywords give.
FITS stores row 0 at the bottom of the image, so FITS data are flipped vertically
(``flip_fits=False`` keeps the stored order). Every problem raises ``ImageReadError``
naming the file. The file is only opened for reading.

Outside the jitted core; astropy, tifffile and Pillow are imported lazily.
"""

from __future__ import annotations

import dataclasses
import math
import os
import warnings
from pathlib import Path

import numpy as np

from ._files import readable_file

_FITS = (".fits", ".fit", ".fts", ".fits.gz", ".fit.gz", ".fts.gz", ".fz")
_TIFF = (".tif", ".tiff")
_PNG = (".png",)
_NPY = (".npy",)
SUPPORTED = "FITS (.fits, .fit, .fts, .fits.gz, .fz), TIFF (.tif, .tiff), PNG (.png), NumPy (.npy)"
#: the most values (pixels × planes) an image file may hold: its size is read from the
#: header first and a larger file is refused before its data are read (a 10000 × 10000
#: image is 0.8 GB as float64; a star's window is a few hundred pixels wide)
MAX_VALUES = 100_000_000


class ImageReadError(ValueError):
    """An image file that cannot be used: missing, unreadable, an unsupported format, no
    image data, or data that is not one 2-D image. The message names the file."""


@dataclasses.dataclass(frozen=True, eq=False)
class ImageData:
    """One intensity image.

    Attributes
    ----------
    path : the file read.
    data : (h, w) float64, row 0 at the top (y up). Invalid pixels (NaN, ±inf, FITS
        BLANK) are set to 0 here and marked False in ``valid``.
    valid : (h, w) bool, True where the file holds a finite value.
    header : the header as a dict: FITS keywords of the HDU read (COMMENT and HISTORY as
        lists of strings), TIFF tags by name, PNG text chunks, {} for NumPy.
    pixel_scale : arcseconds per pixel from FITS keywords (the CD matrix, CDELT1/2 in
        degrees, or PIXSCALE / PIXELSCL / SECPIX / PIXSCAL1 in arcseconds), else None.
    pixel_scale_keyword : the keyword(s) ``pixel_scale`` came from, else None.
    format : "fits", "tiff", "png" or "npy".
    hdu : the FITS HDU index read (None for other formats).
    flipped : whether the rows were reversed on reading (FITS with ``flip_fits``).
    """

    path: Path
    data: np.ndarray
    valid: np.ndarray
    header: dict
    pixel_scale: float | None
    pixel_scale_keyword: str | None
    format: str
    hdu: int | None
    flipped: bool

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.data.shape)  # type: ignore[return-value]

    @property
    def has_invalid(self) -> bool:
        return not bool(np.all(self.valid))


def _err(path: Path, problem: str) -> ImageReadError:
    return ImageReadError(f"{path}: {problem}")


def _check_size(path: Path, shape) -> None:
    """Refuse, from its header's ``shape``, an image too large to read (a decompression
    bomb, a whole mosaic): before any of its data are read."""
    shape = tuple(int(n) for n in shape)
    total = math.prod(shape)
    if total > MAX_VALUES:
        raise _err(path, f"an image of shape {' × '.join(map(str, shape))} ({total} values) is "
                         f"larger than difstar reads (at most {MAX_VALUES} values, e.g. "
                         "10000 × 10000 pixels); cut out the star's region first")


def _kind(path: Path) -> str | None:
    name = path.name.lower()
    for kind, suffixes in (("fits", _FITS), ("tiff", _TIFF), ("png", _PNG), ("npy", _NPY)):
        if name.endswith(suffixes):
            return kind
    with path.open("rb") as fh:  # by content, for a file named otherwise
        head = fh.read(16)
    if head.startswith(b"SIMPLE  ="):
        return "fits"
    if head[:4] in (b"II*\0", b"MM\0*", b"II+\0", b"MM\0+"):
        return "tiff"
    if head.startswith(b"\x89PNG\r\n\x1a\n"):
        return "png"
    if head.startswith(b"\x93NUMPY"):
        return "npy"
    return None


def read_image(path: str | os.PathLike, *, hdu: int | str | None = None,
               plane: int | None = None, flip_fits: bool = True) -> ImageData:
    """Read one 2-D intensity image from a FITS, TIFF, PNG or NumPy ``.npy`` file.

    hdu : FITS only: the HDU to read (index or EXTNAME); by default the first HDU that
        holds image data (a multi-extension file whose primary HDU is empty works).
    plane : for data with one extra axis (a FITS or NumPy cube, a multi-page TIFF, an
        RGB TIFF/PNG): the index of the 2-D plane to read along it. Required for such
        data; leading axes of length 1 are dropped first.
    flip_fits : reverse the rows of FITS data (FITS row 0 is the bottom of the image;
        difstar's row 0 is the top).

    Values are returned as stored (FITS BSCALE/BZERO applied; 8/16-bit PNG and integer
    TIFF as their integer values), as float64. Raises ``ImageReadError`` naming the file.
    """
    path = readable_file(path, _err)
    try:
        kind = _kind(path)
    except OSError as e:
        raise _err(path, f"cannot be opened for reading ({e.strerror or e})") from e
    if kind is None:
        raise _err(path, f"unsupported image format; difstar reads {SUPPORTED}")
    if hdu is not None and kind != "fits":
        raise _err(path, f"hdu= applies to FITS files only; this is a {kind.upper()} file")
    try:
        if kind == "fits":
            arr, header, index = _read_fits(path, hdu)
        elif kind == "tiff":
            (arr, header), index = _read_tiff(path), None
        elif kind == "png":
            (arr, header), index = _read_png(path), None
        else:
            arr, header, index = _read_npy(path), {}, None
    except ImageReadError:
        raise
    except (OSError, ValueError, TypeError, KeyError, IndexError, EOFError) as e:
        raise _err(path, f"cannot be read as {kind.upper()} ({type(e).__name__}: {e})") from e

    arr = _one_plane(path, arr, plane)
    flipped = kind == "fits" and flip_fits
    if flipped:
        arr = arr[::-1]
    data = np.array(arr, dtype=np.float64, copy=True)
    valid = np.isfinite(data)
    if kind == "fits" and "BLANK" in header and np.issubdtype(np.asarray(arr).dtype, np.integer):
        valid &= np.asarray(arr) != header["BLANK"]
    if not np.any(valid):
        raise _err(path, "no finite pixel values (all NaN or infinite)")
    data[~valid] = 0.0
    scale, key = _pixel_scale(header) if kind == "fits" else (None, None)
    data.setflags(write=False)
    valid.setflags(write=False)
    return ImageData(path=path, data=data, valid=valid, header=header, pixel_scale=scale,
                     pixel_scale_keyword=key, format=kind, hdu=index, flipped=flipped)


def _one_plane(path: Path, arr: np.ndarray, plane: int | None) -> np.ndarray:
    arr = np.asarray(arr)
    if not (np.issubdtype(arr.dtype, np.number) or arr.dtype == np.bool_):
        raise _err(path, f"data of type {arr.dtype} is not numeric")
    if np.iscomplexobj(arr):
        raise _err(path, "complex data is not an intensity image")
    while arr.ndim > 2 and arr.shape[0] == 1:
        arr = arr[0]
    if arr.ndim == 3:
        if plane is None:
            raise _err(path, f"a cube of shape {arr.shape}: pass plane= (0 to "
                             f"{arr.shape[0] - 1}) to read one 2-D image")
        if not isinstance(plane, (int, np.integer)) or not 0 <= plane < arr.shape[0]:
            raise _err(path, f"plane must be an integer in [0, {arr.shape[0]}); got {plane!r}")
        arr = arr[int(plane)]
    elif plane is not None and arr.ndim == 2:
        raise _err(path, f"plane={plane!r} given but the data is one 2-D image {arr.shape}")
    if arr.ndim != 2:
        raise _err(path, f"data of shape {arr.shape} is not a 2-D image")
    if min(arr.shape) < 1:
        raise _err(path, f"empty image of shape {arr.shape}")
    return arr


def _read_fits(path: Path, hdu):
    from astropy.io import fits
    from astropy.utils.exceptions import AstropyWarning

    with warnings.catch_warnings(), path.open("rb") as fh:
        # a damaged header is an error here, not a warning and a partial read
        warnings.simplefilter("error", AstropyWarning)
        try:
            return _fits_hdus(path, fits.open(fh, memmap=False, lazy_load_hdus=False), hdu)
        except AstropyWarning as e:
            raise _err(path, f"cannot be read as FITS (damaged: {str(e).splitlines()[0]})") from e


def _fits_hdus(path: Path, hdul, hdu):
    from astropy.io import fits

    with hdul:
        names = [f"{i}:{h.name or '-'}({type(h).__name__})" for i, h in enumerate(hdul)]

        def is_image(h):
            return isinstance(h, (fits.PrimaryHDU, fits.ImageHDU, fits.CompImageHDU))

        if hdu is None:  # by the headers' shapes: no data read before the size check
            index = next((i for i, h in enumerate(hdul)
                          if is_image(h) and len(h.shape) >= 2), None)
            if index is None:
                raise _err(path, f"no image HDU with 2-D data (HDUs: {', '.join(names)}); "
                                 "pass hdu= if the image is elsewhere")
        else:
            try:
                index = hdul.index_of(hdu)
            except (KeyError, IndexError) as e:
                raise _err(path, f"no HDU {hdu!r} (HDUs: {', '.join(names)})") from e
            if not is_image(hdul[index]):
                raise _err(path, f"HDU {hdu!r} is a {type(hdul[index]).__name__}, not an "
                                 f"image (HDUs: {', '.join(names)})")
            _check_size(path, hdul[index].shape)
            if hdul[index].data is None:
                raise _err(path, f"HDU {hdu!r} holds no data (HDUs: {', '.join(names)})")
        h = hdul[index]
        _check_size(path, h.shape)
        data = np.array(h.data, copy=True)
        header = _fits_header(h.header)
    return data, header, index


def _fits_header(hdr) -> dict:
    out: dict = {}
    for card in hdr.cards:
        key = card.keyword
        if key in ("COMMENT", "HISTORY", ""):
            out.setdefault(key or "BLANKCARD", []).append(str(card.value))
        else:
            out[key] = card.value
    return out


def _num(header: dict, key: str) -> float | None:
    v = header.get(key)
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return None
    v = float(v)
    return v if math.isfinite(v) and v != 0 else None


def _pixel_scale(header: dict) -> tuple[float | None, str | None]:
    """Arcseconds per pixel (the square root of the pixel's area on the sky)."""
    cd = [_num(header, k) for k in ("CD1_1", "CD1_2", "CD2_1", "CD2_2")]
    if cd[0] is not None or cd[3] is not None:
        m = np.array([[c or 0.0 for c in cd[:2]], [c or 0.0 for c in cd[2:]]])
        det = abs(float(np.linalg.det(m)))
        if det > 0 and str(header.get("CUNIT1", "deg")).strip().lower() in ("deg", ""):
            return math.sqrt(det) * 3600.0, "CD1_1..CD2_2"
    c1, c2 = _num(header, "CDELT1"), _num(header, "CDELT2")
    if c1 is not None and str(header.get("CUNIT1", "deg")).strip().lower() in ("deg", ""):
        return math.sqrt(abs(c1 * (c2 if c2 is not None else c1))) * 3600.0, "CDELT1/CDELT2"
    for key in ("PIXSCALE", "PIXELSCL", "SECPIX", "SECPIX1", "PIXSCAL1", "PIXSCAL"):
        v = _num(header, key)
        if v is not None:
            return abs(v), key
    return None, None


def _read_tiff(path: Path):
    import tifffile

    with tifffile.TiffFile(path) as tif:
        if not tif.series:
            raise _err(path, "a TIFF file without image data")
        s = tif.series[0]
        _check_size(path, s.shape)
        arr = s.asarray()
        axes = s.axes
        header = {}
        for tag in tif.pages.first.tags.values():
            v = tag.value
            if isinstance(v, (bytes, bytearray)) and len(v) > 256:
                continue
            if isinstance(v, (tuple, list)) and len(v) > 256:
                continue
            header[tag.name] = v
    if arr.ndim == 3 and axes.endswith("S"):  # samples (RGB) last: planes first
        arr = np.moveaxis(arr, -1, 0)
    return arr, header


_PNG_SAMPLES = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}  # IHDR colour type → samples per pixel


def _read_png(path: Path):
    from PIL import Image

    with path.open("rb") as fh:  # IHDR, the first chunk: width, height, depth, colour
        head = fh.read(26)
    if len(head) == 26 and head[12:16] == b"IHDR":
        w, h = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
        n = _PNG_SAMPLES.get(head[25], 1)
        _check_size(path, (h, w) if n == 1 else (n, h, w))
    with warnings.catch_warnings():
        # the size was checked above (Pillow's own bomb check would end in a traceback)
        warnings.simplefilter("ignore", Image.DecompressionBombWarning)
        try:
            im = Image.open(path)
        except Image.DecompressionBombError as e:
            raise _err(path, f"too large to read ({e}); cut out the star's region "
                             "first") from e
    with im:
        im.load()
        mode = im.mode
        header = {k: v for k, v in im.info.items() if isinstance(v, (str, int, float, tuple))}
        header["mode"] = mode
        if mode == "P":
            raise _err(path, "a palette PNG holds colour indices, not intensities; save it "
                             "as greyscale (8 or 16 bits)")
        if mode in ("1", "L", "I", "I;16", "I;16B", "I;16L", "F"):
            arr = np.asarray(im)
        elif mode in ("LA", "RGB", "RGBA"):
            arr = np.moveaxis(np.asarray(im), -1, 0)  # channels as planes
        else:
            raise _err(path, f"unsupported PNG mode {mode!r}; use greyscale (8 or 16 bits)")
    return arr, header


def _read_npy(path: Path):
    fmt = np.lib.format
    with path.open("rb") as fh:  # the header's shape first: no data read before the check
        try:
            version = fmt.read_magic(fh)
            header = {(1, 0): fmt.read_array_header_1_0,
                      (2, 0): fmt.read_array_header_2_0}.get(version)
            shape = header(fh)[0] if header is not None else None
        except ValueError as e:
            raise _err(path, f"not a plain numeric .npy array ({e})") from e
    if shape is not None:
        _check_size(path, shape)
    try:
        return np.load(path, allow_pickle=False)
    except ValueError as e:
        raise _err(path, f"not a plain numeric .npy array ({e})") from e


def write_fits_like(path: str | os.PathLike, image, *, source: str | os.PathLike | None,
                    roi=None, keywords=(), flipped: bool = False, hdu: int | None = None
                    ) -> None:
    """Write ``image`` (as difstar holds it: rows down, cut to ``roi`` = (row0, row1, col0,
    col1) of the source image) as a float64 FITS file laid out like the file it came from,
    so that ``fits.getdata(source) - fits.getdata(path)`` subtracts pixel by pixel.

    ``source``: the image file read (None: the array is written as it is). A FITS source
    gives its header (WCS and all; the data-format keywords are remade) and its stored
    row order (``flipped``: the rows were reversed on reading, as :func:`read_image`
    does). The image goes to its place in the source's full frame; pixels outside
    ``roi`` are NaN. ``keywords``: (name, value, comment) cards added (long names as
    HIERARCH cards)."""
    from astropy.io import fits

    img = np.asarray(image, dtype=float)
    header = fits.Header()
    full = img
    if source is not None:
        src = Path(source)
        kind = _kind(src)
        if kind == "fits":
            header = fits.getheader(src, 0 if hdu is None else hdu).copy()
            shape = (int(header["NAXIS2"]), int(header["NAXIS1"]))
        else:
            shape = read_image(src).shape
        if roi is not None:
            r0, r1, c0, c1 = (int(v) for v in roi)
            full = np.full(shape, np.nan)
            full[r0:r1, c0:c1] = img
        if flipped:
            full = full[::-1]
    for k in ("BSCALE", "BZERO", "BLANK", "BUNIT_DN", "CHECKSUM", "DATASUM", "EXTEND",
              "XTENSION", "PCOUNT", "GCOUNT", "SIMPLE", "BITPIX"):
        header.remove(k, ignore_missing=True, remove_all=True)
    for name, value, comment in keywords:
        key = name.upper() if len(name) <= 8 and name.replace("_", "").isalnum() \
            else f"HIERARCH {name}"
        room = max(0, 80 - len(key) - 28)  # a card is 80 characters: cut the comment
        header[key] = (value, comment[:room])
    fits.PrimaryHDU(np.ascontiguousarray(full), header=header).writeto(path)
