"""How precisely the pixels of a star can tell the pupil's rotation: the noise limit.

    python fit/jwst-nircam/rotation_bound.py fit/jwst-nircam/manifest.json \
        fit/jwst-nircam/result [--factors 1 2 4 8 16 32]

At a `difstar fit-image` result's values, with every parameter the manifest frees
still free, prints the Cramér–Rao standard error of the rotation
(`difstar.noise_limited_errors`) for this star and for stars ``factors`` times fainter
(σ² = (f · read)² + f · I / gain, the read noise and gain the result estimated from its
own residual, no floor: the noise alone; the gain so estimated takes in some of the
model's mismatch, so a second column leaves out the photon noise: a lower limit). No
unbiased fit, however good its model, can be more precise on average; the model's
mismatch only adds to it. For two stars
of one kind fitted independently, each with its own noise, the table gives the chance
that their rotations agree within ``--within`` degrees if each fit reached its bound
and had no bias: P = erf(within / (√2 σ_pair)), σ_pair² = σ_star² + σ_other². Writes
nothing; about 2 minutes on 2 cores (one Jacobian).

With ``--draws N`` it then checks how the campaign's own rotation estimate follows the
noise: N draws of the noise a star ``--copy-factor`` (4) times fainter would add (the
variance of that row less this star's, in this star's units), each added once to the
model image at the fit's values (where the model is exact) and once to the star, and
the manifest's last spike stage (the rotation; its ``reject`` left out) run on each
from the fit's values. An unbiased fit of an exact model moves by about the bound; if
the star's fits move much less, the rotation there is held by the model's mismatch
with the data more than by the spikes' information. About 45 s a fit.
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
              extra=[(("--within",), {"type": float, "default": 0.05}),
                     (("--draws",), {"type": int, "default": 0}),
                     (("--copy-factor",), {"type": float, "default": 4.0}),
                     (("--seed",), {"type": int, "default": 0})])
    if a.draws < 0 or not a.copy_factor > 1:
        print("rotation_bound: --draws must be >= 0 and --copy-factor > 1.", file=sys.stderr)
        return 2

    import jax

    jax.config.update("jax_enable_x64", True)
    from difstar import (
        FitInputError,
        data_intensity,
        fit_image,
        load_fit_manifest,
        noise_limited_errors,
    )

    try:
        ref = json.loads((Path(a.result) / "result.json").read_text())
        model, data, opts = load_fit_manifest(a.manifest)
        v, noise = ref["values"], ref["noise"]
        read, gain = float(noise["read"]), float(noise["gain"])
        spike = next(dict(st) for st in reversed(opts["stages"] or ()) if st.get("spikes"))
    except (OSError, json.JSONDecodeError, KeyError, TypeError, FitInputError,
            StopIteration) as e:
        print(f"rotation_bound: {e or 'the manifest has no spikes stage'}", file=sys.stderr)
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
    brightest = np.argmax(inten[data.mask])
    for f, e, er, sig in zip(a.factors, errs, errs_read, sigmas):
        snr = peak / float(sig[data.mask][brightest])  # the fainter star's, scaled alike
        row = (f"| {'another as bright' if f == 1 else f'{f:g} × fainter'} | {snr:.0f} | "
               f"{e['rotation']:.4f} | {er['rotation']:.4f} |")
        if s1 is not None:
            pair = math.sqrt(s1**2 + e["rotation"] ** 2) if f != 1 else math.sqrt(2) * s1
            row += f" {math.erf(a.within / (math.sqrt(2) * pair)):.2f} |"
        print(row, flush=True)
    alone = noise_limited_errors(model.with_values(v, free=["rotation"]), data, v,
                                 sigmas[:1])[0]["rotation"]
    print(f"with every other parameter held at the fit's values, {a.factors[0]:g} × "
          f"fainter: σ(rotation) = {alone:.4f}° (all free: {errs[0]['rotation']:.4f}°)")
    if a.draws:
        follow_noise(a, model, data, v, spike, read, gain, inten, fit_image)
    return 0


def follow_noise(a, model, data, v, spike, read, gain, inten, fit_image) -> None:
    """The spike stage on the model image and on the star, each with the same draws of
    the noise a star ``a.copy_factor`` times fainter adds; prints each fit's rotation
    and the RMS of their moves."""
    import dataclasses

    f = a.copy_factor
    spike.pop("reject", None)
    start = model.with_values(v)
    clean = start(data.image.shape)
    extra = np.sqrt((f * f - 1) * read**2 + (f - 1) * inten / gain)
    rng = np.random.default_rng(a.seed)
    moves = {"the model image": [], "the star": []}
    print(f"\nthe spike stage with the noise of a star {f:g} × fainter added ({a.draws} "
          f"draws, seed {a.seed}):\n| draw | on the model image (°) | on the star (°) |"
          "\n|---|---|---|")
    for k in range(a.draws):
        noise = rng.normal(size=data.image.shape) * extra
        row = []
        for label, base in (("the model image", clean), ("the star", data.image)):
            d = dataclasses.replace(data, image=np.where(data.mask, base + noise, 0.0))
            r = fit_image(start, d, stages=[spike]).values["rotation"]
            moves[label].append(r - v["rotation"])
            row.append(f"{r:.4f}")
        print(f"| {k} | {row[0]} | {row[1]} |", flush=True)
    rms = {k: math.sqrt(np.mean(np.square(m))) for k, m in moves.items()}
    print(f"RMS move: {rms['the model image']:.4f}° on the model image, "
          f"{rms['the star']:.4f}° on the star")


if __name__ == "__main__":
    sys.exit(main())
