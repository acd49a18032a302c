"""The rotation the spike stage settles at, with the weights of fainter stars.

    python fit/jwst-nircam/spike_weights.py fit/jwst-nircam/manifest.json \
        fit/jwst-nircam/result [--factors 1 4 16] [--relative 3e-4]

Holds every parameter at a `difstar fit-image` result's values and re-runs only the
manifest's spikes stage (the rotation), on the same data, with σ as the noise of the
star itself (read noise and gain from the result's noise estimate, 3 % floor, the data's
intensity) and as the noise of stars ``factors`` times fainter would weigh the same
pixels (read noise × f, gain / f), and, with ``--relative``, with weights that scale with
the star (σ² = (r·peak)² + (floor·I)²). Prints one row per weighting. If the rotation
moves with the weights while the data stay the same, it is the model's mismatch, not
the noise, that the rotation follows. Writes nothing. About 1 minute per row on 2 cores.
"""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

import numpy as np
from _weights_args import parse


def main(argv=None) -> int:
    a = parse(__doc__, argv, factors=[1.0, 4.0, 16.0], relative=[])

    import jax

    jax.config.update("jax_enable_x64", True)
    from difstar import FitInputError, data_intensity, fit_image, load_fit_manifest

    try:
        ref = json.loads((Path(a.result) / "result.json").read_text())
        model, data, opts = load_fit_manifest(a.manifest)
        spike = next(dict(st) for st in opts["stages"] or () if st.get("spikes"))
    except (OSError, json.JSONDecodeError, FitInputError, StopIteration) as e:
        print(f"spike_weights: {e or 'the manifest has no spikes stage'}", file=sys.stderr)
        return 2
    floor = float((spike.pop("noise_from_residuals", None) or {}).get("floor", 0.03))
    v, noise = ref["values"], ref["noise"]
    inten = data_intensity(data, v["background"])
    rows = [(f"noise of a star {f:g} × fainter" if f != 1 else "the star's own noise",
             (noise["read"] * f) ** 2 + inten * f / noise["gain"]) for f in a.factors]
    rows += [(f"relative {r:g} of the peak", (r * inten[data.mask].max()) ** 2)
             for r in a.relative]
    model = model.with_values(v)
    print(f"start: rotation {v['rotation']:.4f}° (the result's); spike stage frees "
          f"{spike['free']}")
    print("| weights | rotation (°) | ± |\n|---|---|---|")
    for label, var in rows:
        sigma = np.sqrt(var + (floor * inten) ** 2)
        d = dataclasses.replace(data, sigma=np.where(data.mask, sigma, 1.0))
        res = fit_image(model, d, stages=[spike])
        print(f"| {label} | {res.values['rotation']:.4f} | "
              f"{res.errors.get('rotation', float('nan')):.4f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
