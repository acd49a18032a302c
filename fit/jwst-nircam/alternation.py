"""Where the rotation settles when the spike stage and the whole-image stage alternate to
their fixed point, for copies of the star of several brightnesses and two weightings.

    python fit/jwst-nircam/alternation.py fit/jwst-nircam/manifest.json \
        fit/jwst-nircam/result [--factors 1 4] [--relative 3e-4] [--seed 1]

Starts every row at a `difstar fit-image` result's values (the flux divided by the
factor) and runs the manifest's spikes stage (the rotation) and the whole-image stage
after it, then a ``repeat`` of both until the rotation moves by less than 0.002°
(difstar's stage ``{"repeat": {"until": {"rotation": 0.002}}}``). The data: the star
itself (factor 1) or a copy ``factor`` times fainter with the noise such a star would
have (``difstar.fainter_copy``: the result's read noise and gain). σ: re-estimated from
the residual at the start, as the manifest's spike stage does it, with the star's own
noise ("own": read noise and gain) and, for each ``--relative`` r, with weights that
scale with the star ("relative": σ² = (r·peak)² + (floor·I)²). The manifest's own
``relative``, if any, is replaced by the row's.

Whether the rotation depends on the star's brightness with each weighting, with the
start and the rest of the procedure held: prints one row per (weights, factor) and the
rounds the repeat took. Writes nothing. About 3–5 minutes per row on 2 cores.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from _weights_args import parse


def main(argv=None) -> int:
    a = parse(__doc__, argv, factors=[1.0, 4.0], relative=[3e-4], extra=[
        (("--seed",), {"type": int, "default": 1, "help": "of the fainter copies' noise"})])

    import jax

    jax.config.update("jax_enable_x64", True)
    from difstar import (
        FitData,
        FitInputError,
        Noise,
        fainter_copy,
        fit_image,
        load_fit_manifest,
        model_images,
        noise_from_residuals,
    )

    try:
        ref = json.loads((Path(a.result) / "result.json").read_text())
        model, data, opts = load_fit_manifest(a.manifest)
        stages = opts["stages"] or ()
        si = next(i for i, st in enumerate(stages) if st.get("spikes"))
        if si + 1 >= len(stages) or stages[si + 1].get("hop") or stages[si + 1].get("repeat"):
            raise StopIteration
    except (OSError, json.JSONDecodeError, FitInputError, StopIteration) as e:
        why = e or "the manifest needs a spikes stage followed by a solving stage"
        print(f"alternation: {why}", file=sys.stderr)
        return 2
    spike = {k: x for k, x in stages[si].items() if k != "noise_from_residuals"}
    rest = dict(stages[si + 1])
    sigma_opts = {k: x for k, x in (stages[si].get("noise_from_residuals") or {}).items()
                  if k != "relative"}
    sigma_opts.setdefault("floor", 0.03)
    start = {k: x for k, x in ref["values"].items() if k in model.params}
    noise = Noise(ref["noise"]["read"], ref["noise"]["gain"], 0.0)
    original = model_images(model, start, data)[0]
    print(f"start: the result's values (rotation {start['rotation']:.4f}°); stages {si} and "
          f"{si + 1}, then repeated until the rotation moves < 0.002°")
    print("| weights | star | rotation (°) | ± | rounds |\n|---|---|---|---|---|")
    weightings = [("own", None)] + [(f"relative {r:g}", r) for r in a.relative]
    for label, r in weightings:
        for fi, f in enumerate(a.factors):
            d = data
            if f > 1:
                copy = fainter_copy(data, original, start["background"], f, noise,
                                    seed=a.seed + fi)
                d = FitData.from_array(copy.image, mask=data.mask,
                                       pixel_scale=data.pixel_scale)
            v = dict(start, flux=start["flux"] / f)
            kw = dict(sigma_opts, **({"relative": r} if r is not None else {}))
            _, d = noise_from_residuals(d, model_images(model, v, d)[0], v["background"], **kw)
            res = fit_image(model.with_values(v), d, stages=[
                spike, rest, {"repeat": {"until": {"rotation": 0.002}, "stages": 2,
                                         "max_rounds": 8}}])
            (log,) = [e for e in res.stages if "repeat" in e]
            star = "the star" if f == 1 else f"{f:g} × fainter"
            print(f"| {label} | {star} | {res.values['rotation']:.4f} | "
                  f"{res.errors.get('rotation', float('nan')):.4f} | {len(log['rounds'])}"
                  f"{'' if log['settled'] else ' (not settled)'} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
