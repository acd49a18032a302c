"""The command line shared by spike_weights.py and alternation.py: a manifest, a
`difstar fit-image` result folder, brightness factors and relative weights."""

from __future__ import annotations

import argparse
import math


def parse(doc: str, argv, *, factors, relative, extra=()) -> argparse.Namespace:
    """The parsed arguments; exits with status 2 and a message when a factor is not a
    finite number >= 1 or a relative weight not in (0, 1). ``extra``: (args, kwargs) pairs for
    ``add_argument``."""
    ap = argparse.ArgumentParser(description=doc.split("\n")[0])
    ap.add_argument("manifest")
    ap.add_argument("result", help="a difstar fit-image --out folder")
    ap.add_argument("--factors", nargs="+", type=float, default=list(factors))
    ap.add_argument("--relative", nargs="*", type=float, default=list(relative))
    for args, kwargs in extra:
        ap.add_argument(*args, **kwargs)
    a = ap.parse_args(argv)
    if not all(math.isfinite(f) and f >= 1 for f in a.factors) or not all(
            math.isfinite(r) and 0 < r < 1 for r in a.relative):
        ap.error("--factors must be >= 1 and --relative in (0, 1).")
    return a
