"""χ² against the pupil's rotation at each minimum an image fit found.

    python fit/jwst-nircam/rotation_slices.py fit/jwst-nircam/manifest.json \
        fit/jwst-nircam/result --out fit/jwst-nircam/result/rotation_slices

Reads a `difstar fit-image` result folder (result.json and, when there,
robustness.json: the main fit and its rough-start refits) and writes into a new folder
``--out`` (whole or not at all; refused if it exists, unless ``--overwrite``):

- ``rotation_slices.json``: for each minimum (the main fit, each rough start, and a fit
  of the same model with the wavefront held at zero), its rotation, Z4/Z11 and the χ² of
  all pixels along a grid of rotations with every other parameter held
  (:func:`difstar.chi2_slice`);
- ``rotation_slices.png``: those curves, each minus the lowest χ² of all;
- in the JSON too: σ re-estimated at each minimum, and on it the χ² of every minimum
  and that minimum's own −2 ln L (whether the minima's order depends on the σ), with
  the intensity in σ that the manifest's ``noise_from_residuals`` names (the model's
  or the data's) and again with the other one.

All χ² share one σ: estimated from the main fit's residual with the options (floor,
intensity, relative weights) of the manifest's last ``noise_from_residuals`` stage, the σ
the campaign's final stages are fitted on, so the minima's depths compare.
The point: to see whether the rotation has one minimum, and how far apart and how deep
the ones the fits end in are. About 2 minutes on 2 cores for this star.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("manifest")
    ap.add_argument("result", help="a difstar fit-image --out folder")
    ap.add_argument("--out", required=True, help="new folder for the slices")
    ap.add_argument("--grid", nargs=3, type=float, default=(-0.6, 1.6, 0.05),
                    metavar=("LO", "HI", "STEP"), help="rotations in degrees (default "
                    "-0.6 1.6 0.05)")
    ap.add_argument("--overwrite", action="store_true")
    a = ap.parse_args(argv)

    import jax

    jax.config.update("jax_enable_x64", True)
    from difstar import FitInputError, chi2_slice, fit_image, load_fit_manifest
    from difstar.io import OutputError, output_dir

    lo, hi, step = a.grid
    if not (np.isfinite([lo, hi, step]).all() and step > 0 and hi > lo):
        print(f"--grid: need LO < HI and STEP > 0, all finite; got {a.grid}.", file=sys.stderr)
        return 2
    grid = np.arange(lo, hi + step / 2, step)
    res_dir = Path(a.result)
    try:
        ref = json.loads((res_dir / "result.json").read_text())
    except (OSError, json.JSONDecodeError) as e:
        print(f"{res_dir}: no readable result.json ({e}).", file=sys.stderr)
        return 2
    model, data, opts = load_fit_manifest(a.manifest)
    if isinstance(data, list):
        print("rotation_slices: the manifest has several captures; give one.", file=sys.stderr)
        return 2
    minima = [("main fit", ref["values"])]
    rob = res_dir / "robustness.json"
    if rob.exists():
        for i, s in enumerate(json.loads(rob.read_text())["starts"]):
            minima.append((f"rough start {i}", s["values"]))
    # σ as the manifest's last noise_from_residuals stage makes it: the σ its end is fitted on
    sigma_opts = next((dict(st["noise_from_residuals"])
                       for st in reversed(opts["stages"] or ())
                       if st.get("noise_from_residuals") is not None), {"floor": 0.0})
    try:
        with output_dir(a.out, overwrite=a.overwrite,
                        inputs=[a.manifest, *opts.get("inputs", ())],
                        command="rotation_slices") as tmp:
            t0 = time.perf_counter()
            main_v = ref["values"]
            main_img = _image_at(model, data, main_v)
            noise, main_d = _sigma_at(data, main_img, main_v, sigma_opts)
            # the same model with the wavefront held at zero, fitted from the main values
            zs = {k: 0.0 for k in model.params if k[0] == "z" and k[1:].isdigit()}
            free = [k for k in model.free if k not in zs]
            flat = fit_image(model.with_values({**main_v, **zs}, free=free), main_d,
                             stages=[{"free": "all", "max_steps": 40, "rtol": 1e-6}])
            minima.append(("zero wavefront", flat.values))
            images = [main_img] + [_image_at(model, data, v) for _, v in minima[1:]]
            sigmas = [(noise, main_d)] + [_sigma_at(data, im, v, sigma_opts)
                                          for im, (_, v) in zip(images[1:], minima[1:])]
            cross = _cross_chi2(model, minima, sigmas)
            # the same comparison with the other choice of the intensity in σ
            other = "model" if sigma_opts.get("intensity", "model") == "data" else "data"
            print(f"with the {other}'s intensity in σ:", flush=True)
            cross_other = _cross_chi2(model, minima, [
                _sigma_at(data, im, v, {**sigma_opts, "intensity": other})
                for im, (_, v) in zip(images, minima)])
            rows = []
            for label, v in minima:
                c = chi2_slice(model, main_d, v, "rotation", grid)
                rows.append({"label": label, "rotation": v["rotation"],
                             "z4": v.get("z4"), "z11": v.get("z11"),
                             "chi2_at_own_rotation": cross[0]["chi2"][label],
                             "slice_minimum_at": float(grid[int(np.argmin(c))]),
                             "chi2": c.tolist()})
                print(f"{label}: rotation {v['rotation']:.4f}°, χ² there "
                      f"{rows[-1]['chi2_at_own_rotation']:.1f}, slice lowest at "
                      f"{rows[-1]['slice_minimum_at']:.2f}°", flush=True)
            out = {"manifest": str(a.manifest), "result": str(res_dir),
                   "noise": {"read": noise.read, "gain": float(noise.gain),
                             "floor": noise.floor},
                   "dof_pixels": int(main_d.mask.sum()), "grid_deg": grid.tolist(),
                   "slices": rows, "sigma_intensity": sigma_opts.get("intensity", "model"),
                   "sigma_relative": sigma_opts.get("relative"),
                   "chi2_on_each_minimums_own_sigma": cross,
                   f"chi2_on_each_minimums_own_sigma_{other}_intensity": cross_other,
                   "seconds": time.perf_counter() - t0}
            (tmp / "rotation_slices.json").write_text(json.dumps(out, indent=2) + "\n")
            _plot(rows, grid, tmp / "rotation_slices.png")
    except (FitInputError, OutputError) as e:
        print(str(e), file=sys.stderr)
        return 2
    print(f"written to {a.out}")
    return 0


def _image_at(model, data, values):
    """The model image at ``values`` (one per minimum, shared by both σ estimates)."""
    from difstar import model_images

    return model_images(model, values, data)[0]


def _sigma_at(data, model_image, values, sigma_opts):
    """(noise, data with σ) re-estimated from the residual of ``model_image`` (the model
    at ``values``), as a fit's ``noise_from_residuals`` stage would."""
    from difstar import noise_from_residuals

    return noise_from_residuals(data, model_image, values["background"], **sigma_opts)


def _cross_chi2(model, minima, sigmas) -> list[dict]:
    """For each minimum's σ (``sigmas``, one (noise, data) per minimum, from
    :func:`_sigma_at`): the χ² of every minimum on it, and that minimum's own −2 ln L
    (χ² + Σ ln σ²: the σ's own term, which a comparison across different σ needs).
    Whether the minima's order holds whichever σ is used tells whether the data can
    tell them apart under this model."""
    from difstar import chi2_at

    out = []
    for (label, _), (noise, d) in zip(minima, sigmas):
        chi2 = {lab: chi2_at(model, d, w) for lab, w in minima}
        logdet = float(np.sum(np.log(d.sigma[d.mask] ** 2)))
        out.append({"sigma_at": label, "gain": float(noise.gain), "read": noise.read,
                    "chi2": chi2, "minus_2_log_likelihood": chi2[label] + logdet})
        print(f"σ at {label} (gain {noise.gain:.0f}): χ² " + ", ".join(
            f"{lab} {c:.0f}" for lab, c in chi2.items())
            + f"; its own −2 ln L {out[-1]['minus_2_log_likelihood']:.0f}", flush=True)
    return out


def _plot(rows, grid, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    best = min(min(r["chi2"]) for r in rows)
    fig, ax = plt.subplots(figsize=(7, 4.2))
    for r in rows:
        line, = ax.plot(grid, np.asarray(r["chi2"]) - best,
                        label=f"{r['label']} (at {r['rotation']:.2f}°)")
        ax.axvline(r["rotation"], color=line.get_color(), lw=0.8, ls=":")
    ax.set_xlabel("rotation of the pupil (°), every other parameter held")
    ax.set_ylabel("χ² − lowest χ² (all pixels, one σ)")
    ax.set_yscale("symlog", linthresh=100)
    ax.set_ylim(bottom=0)
    ax.legend(fontsize=8)
    ax.set_title("χ² along the rotation at each minimum found")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
