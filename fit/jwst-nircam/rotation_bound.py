"""How precisely the pixels of a star can tell the pupil's rotation: the noise limit.

    python fit/jwst-nircam/rotation_bound.py fit/jwst-nircam/manifest.json \
        fit/jwst-nircam/result [--factors 1 2 4 8 16 32]

At a `difstar fit-image` result's values, with every parameter the manifest frees
still free, prints the Cramér–Rao standard error of the rotation
(`difstar.noise_limited_errors`) for this star and for stars ``factors`` times fainter
(σ² = (f · read)² + f · I / gain, the read noise and gain the result estimated from its
own residual, no floor: the noise alone; the gain so estimated takes in some of the
model's mismatch, so a second column leaves out the photon noise: a lower limit). No fit of any kind, however good its model,
can be more precise on average; the model's mismatch only adds to it. For two stars
of one kind fitted independently, each with its own noise, the table gives the chance
that their rotations agree within ``--within`` degrees if each fit reached its bound
and had no bias: P = erf(within / (√2 σ_pair)), σ_pair² = σ_star² + σ_other². Writes
nothing; about 2 minutes on 2 cores (one Jacobian).
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
from _weights_args import parse


def main(argv=None) -> int:
    a = parse(__doc__, argv, factors=[1.0, 2.0, 4.0, 8.0, 16.0, 32.0], relative=[],
              extra=[(("--within",), {"type": float, "default": 0.05})])

    import jax

    jax.config.update("jax_enable_x64", True)
    from difstar import FitInputError, data_intensity, load_fit_manifest, noise_limited_errors

    try:
        ref = json.loads((Path(a.result) / "result.json").read_text())
        model, data, _ = load_fit_manifest(a.manifest)
        v, noise = ref["values"], ref["noise"]
        read, gain = float(noise["read"]), float(noise["gain"])
    except (OSError, json.JSONDecodeError, KeyError, TypeError, FitInputError) as e:
        print(f"rotation_bound: {e}", file=sys.stderr)
        return 2
    if "rotation" not in model.free:
        print("rotation_bound: the manifest holds the rotation fixed.", file=sys.stderr)
        return 2
    inten = np.maximum(data_intensity(data, v["background"]), 0.0)
    peak = float(inten[data.mask].max())
    sigmas = [np.sqrt((f * read) ** 2 + f * inten / gain) for f in a.factors]
    reads = [np.full(data.image.shape, f * read) for f in a.factors]
    both = noise_limited_errors(model.with_values(v), data, v, sigmas + reads)
    errs, errs_read = both[:len(sigmas)], both[len(sigmas):]
    s1 = errs[a.factors.index(1.0)]["rotation"] if 1.0 in a.factors else None
    print(f"rotation {v['rotation']:.4f}°; noise read {read:.3g}, gain {gain:.4g} (the "
          f"result's estimate, file units); {len(model.free)} free parameters")
    head = ("| star | peak S/N | σ(rotation), noise alone (°) | read noise alone, no photon "
            "noise (°) |")
    line = "|---|---|---|---|"
    if s1 is not None:
        head += f" P(its rotation and this star's agree within {a.within:g}°) |"
        line += "---|"
    print(head + "\n" + line)
    for f, e, er, sig in zip(a.factors, errs, errs_read, sigmas):
        snr = peak / f / (float(sig[data.mask][np.argmax(inten[data.mask])]) / f)
        row = (f"| {'another as bright' if f == 1 else f'{f:g} × fainter'} | {snr:.0f} | "
               f"{e['rotation']:.4f} | {er['rotation']:.4f} |")
        if s1 is not None:
            pair = math.sqrt(s1**2 + e["rotation"] ** 2) if f != 1 else math.sqrt(2) * s1
            row += f" {math.erf(a.within / (math.sqrt(2) * pair)):.2f} |"
        print(row, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
