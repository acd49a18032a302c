"""The campaign on the star with a neighbouring star and hot pixels added.

    python fit/jwst-nircam/contaminated.py fit/jwst-nircam/manifest.json \
        fit/jwst-nircam/result --out DIR [--neighbour 26 -15 30] [--hits 6] [--seed 0]

Other stars' cut-outs are rarely clean: a fainter neighbour, a cosmic ray or a hot
pixel the pipeline left. None of them is in the model, and one lying on a spike pulls
the rotation toward it. This adds to the star's own file

- a neighbour: the star itself (its image less the border's median), ``FACTOR`` times
  fainter, moved by whole pixels (``DX`` along the columns, ``DY`` along the rows of
  the FITS array, the file's own order; no resampling), so it has real spikes and real
  noise; the default puts its core on the star's spike at 150° (counter-clockwise from
  +x, y up), 30 px out;
- ``--hits`` hot pixels and two-pixel cosmic-ray tracks at random places at least 15 px
  from the star, each between 0.3 % and 10 % of the star's peak (``--seed``),

writes it as a new FITS file (the header kept: the star has not moved) and fits it with
the manifest given, only the file swapped. The rotation against the star's, with a
manifest that masks what the model cannot explain (``reject`` stages) and with one that
does not, is what the masking is for.

Writes into the new folder ``DIR`` (refused if it exists; removed again if the fit
fails): ``contaminated.fits``, ``manifest.json``, ``fit/`` (``difstar fit-image``'s
result) and ``contaminated.md`` (each free parameter: the star's fit, the fit of the
contaminated copy, the difference in the star's standard errors). About as long as the
main fit (9 min).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

_HIT_R_MIN = 15.0  # hot pixels and tracks land at least this far from the star (pixels)


def moved_whole(img: np.ndarray, dx: int, dy: int) -> np.ndarray:
    """``img`` moved by ``dx`` columns and ``dy`` rows, whole pixels: out[r, c] =
    img[r − dy, c − dx], 0 where that falls outside."""
    h, w = img.shape
    out = np.zeros_like(img)
    rs, cs = slice(max(dy, 0), h + min(dy, 0)), slice(max(dx, 0), w + min(dx, 0))
    out[rs, cs] = img[max(-dy, 0):h - max(dy, 0), max(-dx, 0):w - max(dx, 0)]
    return out


def contaminated_image(img: np.ndarray, *, neighbour=(26, -15, 30.0), hits=6,
                       seed=0) -> np.ndarray:
    """``img`` (the star, its brightest pixel its centre) plus a neighbour (``neighbour``
    = (dx, dy, factor): the star less the border's median, ``factor`` times fainter,
    moved by whole pixels) and ``hits`` hot pixels or two-pixel tracks (random, at least
    15 px from the brightest pixel, 0.3–10 % of its height above the border). NaN pixels
    stay NaN; the input is not changed."""
    a = np.asarray(img, float)
    h, w = a.shape
    finite = np.where(np.isfinite(a), a, np.nan)
    border = np.concatenate([finite[:4].ravel(), finite[-4:].ravel(),
                             finite[:, :4].ravel(), finite[:, -4:].ravel()])
    bg = float(np.nanmedian(border))
    star = np.nan_to_num(finite - bg)
    dx, dy, factor = neighbour
    out = a + moved_whole(star, int(dx), int(dy)) / float(factor)
    peak = float(star.max())
    r0, c0 = np.unravel_index(np.argmax(star), star.shape)
    rng = np.random.default_rng(seed)
    placed = 0
    while placed < hits:
        r, c = int(rng.integers(1, h - 1)), int(rng.integers(1, w - 1))
        if math.hypot(r - r0, c - c0) < _HIT_R_MIN:
            continue
        level = peak * 10 ** rng.uniform(math.log10(3e-3), -1)
        out[r, c] += level
        if rng.random() < 0.5:  # a two-pixel track: the next pixel along a random axis
            dr, dc = ((0, 1), (1, 0), (1, 1))[int(rng.integers(3))]
            out[r + dr, c + dc] += level * rng.uniform(0.3, 1.0)
        placed += 1
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("manifest")
    ap.add_argument("result", help="the star's `difstar fit-image` result folder")
    ap.add_argument("--out", required=True, help="a new folder")
    ap.add_argument("--neighbour", nargs=3, type=float, default=[26, -15, 30],
                    metavar=("DX", "DY", "FACTOR"),
                    help="the neighbour's place (whole pixels along the columns and rows) "
                    "and how many times fainter than the star it is (default 26 -15 30)")
    ap.add_argument("--hits", type=int, default=6, help="hot pixels and tracks (default 6)")
    ap.add_argument("--seed", type=int, default=0, help="where the hits land (default 0)")
    a = ap.parse_args(argv)
    dx, dy, factor = a.neighbour
    if not (dx == int(dx) and dy == int(dy) and math.isfinite(factor) and factor >= 1
            and a.hits >= 0):
        ap.error("--neighbour: DX and DY whole numbers of pixels, FACTOR >= 1; --hits >= 0.")
    from _copy_fit import fit_copy, write_comparison

    star = json.loads((Path(a.result) / "result.json").read_text())

    def change(data, head):
        return contaminated_image(data, neighbour=(int(dx), int(dy), factor), hits=a.hits,
                                  seed=a.seed), head

    what = (f"a neighbour {factor:g} times fainter at ({dx:+g}, {dy:+g}) px and {a.hits} hot "
            f"pixels (seed {a.seed})")
    got = fit_copy(Path(a.manifest), Path(a.out), "contaminated.fits", change,
                   f"The star with {what}.")
    if got is None:
        return 2
    write_comparison(Path(a.out) / "contaminated.md", f"The star's fit and the fit of the star "
                     f"with {what}, manifest {a.manifest}.", star, got, "contaminated")
    return 0


if __name__ == "__main__":
    sys.exit(main())
