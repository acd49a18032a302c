"""The campaign on the star moved by a fraction of a pixel: does the rotation stay?

    python fit/jwst-nircam/shifted.py fit/jwst-nircam/manifest.json \
        fit/jwst-nircam/result --shift 0.5 0 --out DIR

Other stars of the same kind sit at other sub-pixel positions on the sky grid, and the
resampling onto that grid (SWarp, Lanczos3: the file's RESAMPT1/2) blurs each one a
little differently; the model describes neither. This moves the star by ``--shift DX DY``
pixels (DX along the array's columns, DY along its rows, the FITS file's own order) with
Pillow's Lanczos3 resampling, the kind of kernel SWarp used, and fits the moved star with
the same manifest. The rotation it gives against the star's is what a sub-pixel position
and one more resampling do to it; the centre's change against the shift checks the move.

Writes into the new folder ``DIR`` (refused if it exists; removed again if the fit
fails): ``shifted.fits`` (the moved star; CRPIX moved with it, so the WCS still names each
pixel's sky position), ``manifest.json``, ``fit/`` (``difstar fit-image``'s result) and
``shift.md`` (each free parameter: the star's fit, the moved star's fit, the difference in
the star's standard errors). About as long as the main fit (9 min, 7.5 GB).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

_PAD = 4  # Lanczos3 reaches 3 px; edge pixels are repeated beyond the border


def shifted_image(img: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """``img`` moved by ``dx`` columns and ``dy`` rows (out[r, c] = img[r − dy, c − dx]) by
    Pillow's Lanczos3 resampling, in float32 (Pillow's float mode). Integer shifts are exact
    moves; the border beyond the image repeats its edge pixels."""
    from PIL import Image

    h, w = img.shape
    a = np.pad(np.asarray(img, np.float32), _PAD, mode="edge")
    box = (_PAD - dx, _PAD - dy, _PAD - dx + w, _PAD - dy + h)
    return np.asarray(Image.fromarray(a).resize((w, h), Image.LANCZOS, box=box))


def shifted(dx: float, dy: float):
    """A ``change(data, header)`` for ``_copy_fit.fit_copy``: the image moved by
    ``shifted_image``, CRPIX1 and CRPIX2 moved by the same amounts."""
    def change(data, head):
        for k, d in (("CRPIX1", dx), ("CRPIX2", dy)):
            if k in head:
                head[k] = head[k] + d
        return shifted_image(data, dx, dy), head
    return change


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("manifest")
    ap.add_argument("result", help="the star's `difstar fit-image` result folder")
    ap.add_argument("--shift", nargs=2, type=float, required=True, metavar=("DX", "DY"),
                    help="pixels along the array's columns and rows, each within ±3")
    ap.add_argument("--out", required=True, help="a new folder")
    a = ap.parse_args(argv)
    dx, dy = a.shift
    if not all(math.isfinite(s) and abs(s) <= 3 for s in a.shift):
        ap.error("--shift: each of DX, DY must be a finite number of pixels within ±3 "
                 "(the manifest's centre bounds).")
    from _copy_fit import fit_copy, write_comparison

    star = json.loads((Path(a.result) / "result.json").read_text())
    got = fit_copy(Path(a.manifest), Path(a.out), "shifted.fits", shifted(dx, dy),
                   f"The star moved by ({dx:g}, {dy:g}) px (Lanczos3).")
    if got is None:
        return 2
    write_comparison(Path(a.out) / "shift.md", f"The star's fit and the fit of the star moved "
                     f"by {dx:g} px along the columns and {dy:g} px along the rows (Lanczos3), "
                     "same manifest.", star, got, "moved star")
    return 0


if __name__ == "__main__":
    sys.exit(main())
