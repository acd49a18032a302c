"""``difstar fit-image``: the command line of the image fitter (it parses, calls
:func:`difstar.fitting.run_fit_image` and reports).

    python -m difstar.cli._fit_image fit/jwst-nircam/manifest.json --out fit/jwst-nircam/result
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from ..fitting._run import run


def _add_arguments(ap) -> None:
    ap.add_argument("manifest", help="image-fit manifest (data_schemas/"
                    "image_fit_manifest.schema.json)")
    ap.add_argument("--out", required=True, help="folder for result.json, fit.png, model.npy "
                    "(created by difstar; never an existing folder of yours)")
    ap.add_argument("--overwrite", action="store_true",
                    help="replace an --out folder difstar itself wrote before")
    ap.add_argument("--max-steps", type=_positive_int, default=None,
                    help="Levenberg–Marquardt steps per stage (default: the manifest's)")
    ap.add_argument("--quiet", action="store_true", help="no progress or summary")
    ap.add_argument("--robustness", type=_nonnegative_int, default=0, metavar="N",
                    help="also refit from N rough starts (every free parameter within "
                    "± 20 %% of its start) and write robustness.json/.md (default 0)")
    ap.add_argument("--rough-about", choices=("start", "result"), default="start",
                    help="the rough starts are ± 20 %% about the manifest's starts "
                    "(default; a start at 0 moves by 20 %% of half its bounds) or about the "
                    "main fit's result (the issue's 'started 20 %% off' the answer)")
    ap.add_argument("--seed", type=_nonnegative_int, default=0,
                    help="seed of the rough starts, of the fainter copies' noise and of the "
                    "contaminated copies' hot pixels (default 0)")
    ap.add_argument("--fainter", type=_factors, default=(), metavar="F1,F2,...",
                    help="also fit copies of the star F times fainter (stand-ins for other "
                    "stars; needs a noise_from_residuals stage) and write fainter.json/.md")
    ap.add_argument("--shifted", type=_shift, action="append", default=[], metavar="DX,DY",
                    help="also fit the star moved by DX columns (right) and DY rows (down) "
                    "px with Lanczos3 resampling (another star elsewhere on the pixel "
                    "grid) and write shifted.json/.md; repeat for several moves; write "
                    "--shifted=-0.5,0 when DX is negative")
    ap.add_argument("--contaminated", type=_neighbour, action="append", default=[],
                    metavar="DX,DY,F",
                    help="also fit the star with a neighbour added (the star itself F times "
                    "fainter, moved by DX, DY whole px) and --hits hot pixels, and write "
                    "contaminated.json/.md; repeat for several; e.g. 26,15,30")
    ap.add_argument("--hits", type=_nonnegative_int, default=6, metavar="N",
                    help="hot pixels and two-pixel tracks in each --contaminated copy, at "
                    "least 15 px from the star (default 6)")
    ap.add_argument("--noise-limit", type=_factors, default=(), metavar="F1,F2,...",
                    help="also write noise_limit.json/.md: the rotation's Cramér–Rao bound "
                    "for the star and for stars F times fainter (1 for another as bright; "
                    "needs a noise_from_residuals stage), e.g. 1,2,4,8,16,32")
    ap.add_argument("--joint", action="store_true",
                    help="also fit the star and its --shifted and --contaminated copies "
                    "together, as the stars of one field (one pupil, rotation and wavefront; "
                    "each its own centre, flux and background), and write joint.json/.md")


def _positive_int(text: str) -> int:
    v = int(text)
    if v < 1:
        raise argparse.ArgumentTypeError(f"--max-steps must be >= 1; got {v}")
    return v


def _factors(text: str) -> tuple[float, ...]:
    try:
        v = tuple(float(t) for t in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"takes factors like 4,16; got {text!r}")
    if not v or not all(np.isfinite(x) and x >= 1 for x in v):
        raise argparse.ArgumentTypeError(f"factors must be finite and >= 1; got {text!r}")
    return v


def _numbers(text: str, n: int, like: str) -> tuple[float, ...]:
    try:
        v = tuple(float(t) for t in text.split(","))
    except ValueError:
        v = ()
    if len(v) != n or not all(np.isfinite(x) for x in v):
        raise argparse.ArgumentTypeError(f"takes {n} numbers like {like}; got {text!r}")
    return v


def _shift(text: str) -> tuple[float, float]:
    return _numbers(text, 2, "0.5,-0.25")


def _neighbour(text: str) -> tuple[int, int, float]:
    dx, dy, f = _numbers(text, 3, "26,15,30")
    if not (dx.is_integer() and dy.is_integer() and f >= 1):
        raise argparse.ArgumentTypeError(f"DX and DY must be whole pixels and F >= 1; got "
                                         f"{text!r}")
    return int(dx), int(dy), f


def _nonnegative_int(text: str) -> int:
    v = int(text)
    if v < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0; got {v}")
    return v


def register(sub, name: str) -> None:
    """``difstar fit-image`` in the command line."""
    p = sub.add_parser(name, help="fit a PSF model (pupil, wavefront, band, detector) to a "
                       "star image (FITS, TIFF, PNG, NumPy)")
    _add_arguments(p)
    p.set_defaults(func=_cmd)


def _cmd(a) -> int:
    from ..fitting._params import FitInputError

    try:
        run(a.manifest, a.out, verbose=not a.quiet, max_steps=a.max_steps,
            overwrite=a.overwrite, robustness=a.robustness, seed=a.seed,
            fainter=a.fainter, rough_about=a.rough_about, shifted=tuple(a.shifted),
            contaminated=tuple(a.contaminated), hits=a.hits, noise_limit=a.noise_limit,
            joint=a.joint)
    except FitInputError as e:
        raise ValueError(f"difstar fit-image: {e}") from None
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m difstar.cli._fit_image",
                                 description="Fit a PSF model to a star image (manifest).")
    _add_arguments(ap)
    a = ap.parse_args(argv)
    try:
        return _cmd(a)
    except ValueError as e:
        print(str(e), file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
