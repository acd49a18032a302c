"""The campaign on the star's exact left-right mirror image: does it find the mirror fit?

    python fit/jwst-nircam/mirrored.py fit/jwst-nircam/manifest.json \
        fit/jwst-nircam/result --out DIR

The JWST pupil is symmetric about its vertical axis, so the mirror image of the star is
what the same telescope would give with the pupil's rotation, the upper strut's tilt,
the centre's x and the Zernike terms odd in x negated (the model is exactly so:
``tests/test_fitting.py::test_jwst_model_mirrored_is_the_mirror_image``). Fitting the
mirrored data with the same manifest must therefore end at those negated values: any
difference is the search's own path (its starts, scans and hops), not the data. No
resampling: columns are reversed, the pixels and their noise are the star's.

Writes into the new folder ``DIR`` (refused if it exists; removed again if the fit
fails): ``mirrored.fits`` (the star, columns reversed, its WCS mirrored to match),
``manifest.json`` (the manifest with that file), ``fit/`` (``difstar fit-image``'s
result of it) and ``mirror.md`` (each free parameter: the star's fit, its mirror, the
mirrored star's fit, the difference in standard errors). About as long as the main fit.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def odd_in_x(values) -> list[str]:
    """The parameters that change sign under x → −x: the pupil's rotation, the upper
    strut's tilt, the centre's x and the Zernike terms odd in x (found numerically)."""
    from difstar import zernike_noll

    x, y = np.array([0.3, 0.5, -0.2, 0.7]), np.array([0.4, -0.1, 0.6, 0.2])
    odd = ["rotation", "strut_tilt", "x0"]
    for k in values:
        if k[0] == "z" and k[1:].isdigit():
            j = int(k[1:])
            if np.allclose(zernike_noll(j, -x, y, 1.0), -np.asarray(zernike_noll(j, x, y, 1.0))):
                odd.append(k)
    return odd


def mirrored(data, head):
    """The image with its columns reversed; CD1_1, CD2_1 negated and CRPIX1 moved so the
    WCS still names each pixel's sky position (the pixel scale stays). A ``change`` for
    ``_copy_fit.fit_copy``."""
    data = np.ascontiguousarray(data[:, ::-1])
    for k in ("CD1_1", "CD2_1", "CDELT1"):
        if k in head:
            head[k] = -head[k]
    if "CRPIX1" in head:
        head["CRPIX1"] = data.shape[1] + 1 - head["CRPIX1"]
    return data, head


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("manifest")
    ap.add_argument("result", help="the star's `difstar fit-image` result folder")
    ap.add_argument("--out", required=True, help="a new folder")
    a = ap.parse_args(argv)
    from _copy_fit import fit_copy, write_comparison

    star = json.loads((Path(a.result) / "result.json").read_text())
    got = fit_copy(Path(a.manifest), Path(a.out), "mirrored.fits", mirrored,
                   "The star's left-right mirror image.")
    if got is None:
        return 2
    odd = odd_in_x(star["values"])
    write_comparison(Path(a.out) / "mirror.md", "The star's fit, its mirror (the parameters "
                     "odd in x negated), and the fit of the mirrored star by the same manifest.",
                     star, got, "mirrored star", lambda k, v: -v if k in odd else v,
                     "mirror of the star's fit")
    return 0


if __name__ == "__main__":
    sys.exit(main())
