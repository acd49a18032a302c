"""Fit one fainter copy of the star, from a result folder, with any manifest's stages.

    python fit/jwst-nircam/faint_copy.py fit/jwst-nircam/manifest.json \
        fit/jwst-nircam/result --factor 16 --seed 2

The copy is the one ``difstar fit-image MANIFEST --out DIR --seed S --fainter F1,F2,...``
fits as its k-th copy (factor Fk, noise draw S + k − 1), made from the result folder's
``result.json`` and ``model.npy`` (the fit of the star) instead of a fresh main fit: so
one copy, under one manifest or a variant of it, takes about 10 minutes instead of 20+.
Prints each stage as it ends, every alternative a hop tried (where it ended and its χ²
on all pixels) and each repeat round, then the copy's rotation.

The point: to see whether a copy that ends far from the star's rotation is a search that
missed the star's minimum (a hop reaching it would end lower) or a draw of the noise
that prefers another one (every hop ends higher).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("manifest", help="the manifest whose stages fit the copy")
    ap.add_argument("result", help="a `difstar fit-image` result folder of the star "
                    "(result.json, model.npy)")
    ap.add_argument("--factor", type=float, default=16.0, help="how many times fainter")
    ap.add_argument("--seed", type=int, default=0, help="the noise draw")
    a = ap.parse_args(argv)
    import jax

    jax.config.update("jax_enable_x64", True)  # as difstar fit-image runs
    from difstar.fitting import fit_fainter_copy

    res_dir = Path(a.result)
    summary = json.loads((res_dir / "result.json").read_text())
    mimg = np.load(res_dir / "model.npy")
    res = fit_fainter_copy(a.manifest, summary, mimg, a.factor, a.seed, verbose=True)
    print(f"\ncopy × 1/{a.factor:g}, noise draw {a.seed}: hops and repeats")
    print("| stage | alternative | ends at | χ² (all pixels) |\n|---|---|---|---|")
    for st in res.stages:
        for t in st.get("tried", ()):
            ends = ", ".join(f"{q} {x:.4g}" for q, x in t.get("ends_at", {}).items())
            print(f"| {st['stage']} | {t['change']} | {ends or 'as it was'} | {t['chi2']:.6g} |")
        for i, r in enumerate(st.get("rounds", ())):
            print(f"| {st['stage']} | repeat round {i + 1} | rotation "
                  f"{r['values'].get('rotation', float('nan')):.4g} | {r['chi2']:.6g} |")
    print(f"\nrotation {res.values['rotation']:.4f}° ± {res.errors.get('rotation', 0):.4f}° "
          f"(the star's: {summary['values']['rotation']:.4f}°), residual RMS / peak "
          f"{100 * res.residual_rms_peak:.3f} %, χ²/dof {res.chi2 / res.dof:.4g}, "
          f"{res.status}, {res.wall_time:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
