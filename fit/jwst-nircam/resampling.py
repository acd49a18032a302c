"""The campaign's last stages with and without the co-add's Lanczos3 blur in the model.

    python fit/jwst-nircam/resampling.py fit/jwst-nircam/manifest.json \
        fit/jwst-nircam/result [--kernel lanczos3]

The file was made by SWarp, resampling each exposure onto the sky grid with Lanczos3
(RESAMPT1/2) before taking the median. Averaged over the exposures' sub-pixel offsets
that is a convolution with the kernel (``ImageModel(resampling=...)``). From a
`difstar fit-image` result's values, runs the manifest's last whole-image stage (σ
re-estimated as its last spike stage says), its last spike stage (the rotation) and the
whole-image stage again, once with the manifest's model and once with the kernel added,
and prints a row for each: χ², residual RMS / peak, the rotation and the parameters the
blur competes with (jitter, halo, Z4, Z11). Writes nothing; about 2 minutes a row on
2 cores.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("manifest")
    ap.add_argument("result", help="a difstar fit-image --out folder")
    ap.add_argument("--kernel", default="lanczos3")
    a = ap.parse_args(argv)

    import jax

    jax.config.update("jax_enable_x64", True)
    from difstar import FitInputError, fit_image, load_fit_manifest

    try:
        v = json.loads((Path(a.result) / "result.json").read_text())["values"]
        model, data, opts = load_fit_manifest(a.manifest)
        stages = opts["stages"] or []
        spike = next(dict(st) for st in reversed(stages) if st.get("spikes"))
        whole = next(dict(st) for st in reversed(stages)
                     if st.get("free") and not st.get("spikes"))
        with_kernel = model.with_resampling(a.kernel)
    except (OSError, json.JSONDecodeError, KeyError, FitInputError, StopIteration) as e:
        print(f"resampling: {e or 'the manifest needs a spikes stage and a whole-image stage'}",
              file=sys.stderr)
        return 2
    nfr = spike.get("noise_from_residuals")
    run = [dict(whole, noise_from_residuals=nfr) if nfr else whole, spike, whole]
    print(f"from the result's values (rotation {v['rotation']:.4f}°); stages: whole image "
          "(σ re-estimated), spikes (rotation), whole image")
    print("| model | χ² | residual RMS / peak | rotation (°) | jitter (px) | halo | Z4, Z11 "
          "(nm) |\n|---|---|---|---|---|---|---|")
    for label, m in [("the manifest's", model), (f"+ {a.kernel} co-add blur", with_kernel)]:
        res = fit_image(m.with_values(v), data, stages=run)
        r = res.values
        print(f"| {label} | {res.chi2:.1f} | {100 * res.residual_rms_peak:.3f} % | "
              f"{r['rotation']:.4f} ± {res.errors.get('rotation', float('nan')):.3f} | "
              f"{r['jitter']:.3f} | {r['halo']:.3f} | {r.get('z4', 0):+.1f}, "
              f"{r.get('z11', 0):+.1f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
