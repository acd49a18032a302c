"""A fit of an image-fit manifest, its studies and its result folder (what
``difstar fit-image`` runs; :func:`difstar.fitting.run_fit_image`): the fit by the
manifest's stages, then optionally fits from rough starts (``robustness``) and the
studies of ``_studies`` (copies of the star made fainter, moved, contaminated; the
noise limit).

    difstar fit-image fit/jwst-nircam/manifest.json --out fit/jwst-nircam/result

Writes ``result.json`` (values, standard errors, status, χ²/dof, residual RMS / peak,
spike angles measured from the data and from the fitted model, wall time),
``fit.png`` (data / model / residual on a log scale), ``model.npy`` (rows down, the
fitted window) and ``model.fits`` / ``residual.fits`` in the input file's own layout
(header, WCS, row order, full frame): the input minus model.fits is residual.fits.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np

from ..io import read_image
from ..io._images import write_fits_like
from ..io._output import output_dir
from . import _studies
from ._analysis import model_spike_angles, perturbed_starts, spike_angles
from ._auto import stages_text
from ._manifest import load_manifest
from ._model import parameter_unit
from ._params import PERTURB
from ._procedure import fit
from ._solve import _rms_peak, values_of_capture

_MODEL_SPIKE_WINDOW = 8.0  # degrees: the model's spikes are measured this near the data's


def _figure(res, path, title):
    """Data, model and residual on a log scale: one row per capture."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm, SymLogNorm

    def rows(x):
        return x if isinstance(x, list) else [x]

    datas, models, resids, masks = (rows(res.data), rows(res.model_image),
                                    rows(res.residual), rows(res.mask))
    n = len(datas)
    fig, axes = plt.subplots(n, 3, figsize=(13, 4.4 * n), constrained_layout=True,
                             squeeze=False)
    for i, (ax, data, model, resid, mask) in enumerate(zip(axes, datas, models, resids,
                                                           masks)):
        bg = values_of_capture(res.values, i).get("background", 0.0)
        top = float(np.max(data[mask]))
        peak = top - bg if top > bg else max(abs(top), 1.0)  # the star above its background
        lo = peak * 1e-4
        norm = LogNorm(vmin=lo, vmax=peak)
        cap = f" (capture {i})" if n > 1 else ""
        for a, img, name in ((ax[0], data - bg, "data − background"),
                             (ax[1], model - bg, "model − background")):
            im = a.imshow(np.clip(img, lo, None), norm=norm, cmap="magma", origin="upper")
            a.set_title(name + cap)
        fig.colorbar(im, ax=ax[:2], shrink=0.85, label="counts (log)")
        lin = peak * 1e-3
        grey = plt.get_cmap("RdBu_r").with_extremes(bad="0.6")  # pixels not fitted
        im2 = ax[2].imshow(np.where(mask, resid, np.nan) / peak, cmap=grey,
                           norm=SymLogNorm(linthresh=lin / peak, vmin=-0.1, vmax=0.1, base=10),
                           origin="upper")
        rms = _rms_peak(resid, data, mask)  # as result.json reports it
        ax[2].set_title(f"residual / peak (RMS {100 * rms:.2f} %)"
                        + ("; grey: not fitted" if not mask.all() else ""))
        fig.colorbar(im2, ax=ax[2], shrink=0.85, label="(data − model) / peak, symlog")
        for a in ax:
            a.set_xticks([])
            a.set_yticks([])
    fig.suptitle(title)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run(manifest: str | Path, out: str | Path, *, verbose: bool = True,
        max_steps: int | None = None, overwrite: bool = False, robustness: int = 0,
        seed: int = 0, fainter: tuple[float, ...] = (), rough_about: str = "start",
        shifted: tuple[tuple[float, float], ...] = (),
        contaminated: tuple[tuple[int, int, float], ...] = (), hits: int = 6,
        noise_limit: tuple[float, ...] = (), joint: bool = False) -> dict:
    """Fit the manifest's model to its data; write result.json, fit.png, model.npy into
    ``out``, a folder difstar creates (whole or not at all; see ``io._output``). Then,
    each into the same folder (:mod:`difstar.fitting._studies`):

    - ``robustness`` = N: refit from N rough starts (every free parameter ± 20 %,
      :func:`difstar.fitting._analysis.perturbed_starts`; about the manifest's starts,
      or with ``rough_about="result"`` about the main fit's values):
      robustness.json / .md;
    - ``fainter`` = (f1, …): fit copies of the star f times fainter
      (:func:`difstar.fitting.fit_fainter_copy`, stand-ins for other stars; noise draw
      ``seed`` + i): fainter.json / .md;
    - ``shifted`` = ((dx, dy), …): fit the star moved by dx columns and dy rows
      (:func:`difstar.fitting.fit_shifted_copy`, Lanczos3): shifted.json / .md;
    - ``contaminated`` = ((dx, dy, factor), …): fit the star with a neighbour ``factor``
      times fainter at (dx, dy) whole px and ``hits`` hot pixels (seed ``seed`` + i)
      added (:func:`difstar.fitting.fit_contaminated_copy`): contaminated.json / .md;
    - ``noise_limit`` = (f1, …): the rotation's Cramér–Rao bound for the star and for
      stars f times fainter (:func:`difstar.fitting.noise_limit`): noise_limit.json / .md;
    - ``joint``: fit the star and its moved and contaminated copies together, one
      rotation for all (:func:`difstar.fitting.fit_joint`): joint.json / .md.

    A study the manifest cannot run is refused before the main fit."""
    import jax

    jax.config.update("jax_enable_x64", True)
    t0 = time.perf_counter()
    loaded = load_manifest(manifest)  # read once here, for the checks and the main fit
    _studies._check_studies(manifest, loaded, fainter=fainter, shifted=shifted,
                            contaminated=contaminated, hits=hits, seed=seed,
                            noise_limit=noise_limit, joint=joint)
    # every file the manifest made difstar read is an input: never replaced, never held
    inputs = [manifest, *loaded[2].get("inputs", ())]
    with output_dir(out, overwrite=overwrite, inputs=inputs, command="fit-image") as tmp:
        summary = _run(manifest, loaded, t0, tmp, verbose=verbose, max_steps=max_steps,
                       final=out)
        if robustness:
            _robustness(manifest, tmp, summary, robustness, seed, max_steps=max_steps,
                        verbose=verbose, about=rough_about)
        kw = dict(max_steps=max_steps, verbose=verbose)
        if fainter:
            _studies._fainter(manifest, tmp, summary, fainter, seed, **kw)
        alone = []  # the copies' own fits, for the joint fit's comparison
        if shifted:
            alone += _studies._shifted(manifest, tmp, summary, shifted, **kw)["copies"]
        if contaminated:
            alone += _studies._contaminated(manifest, tmp, summary, contaminated, hits, seed,
                                            **kw)["copies"]
        if joint:
            _studies._joint(manifest, tmp, summary, shifted, contaminated, hits, seed, alone,
                            **kw)
        if noise_limit:
            _studies._noise_limit(manifest, tmp, summary, noise_limit, verbose=verbose)
        return summary


def _robustness(manifest, out, summary, n, seed, *, max_steps, verbose,
                about="start") -> dict:
    """Refit from ``n`` perturbed starts (about the manifest's starts or the main fit's
    ``about="result"``); compare each result with the main fit."""
    model, data, opts = load_manifest(manifest)
    ref, err = summary["values"], summary["errors"]
    # about the result: a per-capture parameter starts from its first capture's value
    centre = model if about == "start" else model.with_values(values_of_capture(ref, 0))
    rows = []
    for i, start in enumerate(perturbed_starts(centre, n, rel=PERTURB, seed=seed)):
        t = time.perf_counter()
        res = fit(model.with_values(start), data, stages=opts["stages"],
                  max_steps=max_steps or opts["max_steps"], verbose=False,
                  per_capture=opts["per_capture"])
        dev = {k: (res.values[k] - ref[k]) / err[k] for k in res.free
               if err.get(k, 0) > 0 and np.isfinite(err[k])}
        rows.append({"start": start, "values": res.values, "status": res.status,
                     "residual_rms_over_peak": res.residual_rms_peak,
                     "deviation_in_standard_errors": dev,
                     "max_deviation": max(abs(v) for v in dev.values()),
                     "seconds": time.perf_counter() - t})
        if verbose:
            print(f"robustness start {i}: rotation {res.values['rotation']:.4f}°, residual "
                  f"{100 * res.residual_rms_peak:.3f} %, max |Δ|/σ "
                  f"{rows[-1]['max_deviation']:.2f} ({rows[-1]['seconds']:.0f} s)", flush=True)
    rot = np.array([r["values"]["rotation"] for r in rows])
    study = {"n": n, "seed": seed, "perturb": PERTURB, "about": about, "starts": rows,
             "rotation_spread_deg": float(rot.max() - rot.min()),
             "max_deviation_in_standard_errors": max(r["max_deviation"] for r in rows)}
    (Path(out) / "robustness.json").write_text(json.dumps(study, indent=2, default=float) + "\n")
    what = "manifest start" if about == "start" else "value in the main fit"
    lines = [f"Refits from {n} starts, each free parameter within ± {100 * PERTURB:g} % of its "
             f"{what} (seed {seed}); deviations from the main fit in its standard "
             "errors.", "",
             "| start | rotation (°) | residual RMS / peak | max \\|Δ\\|/σ (parameter) | status "
             "| s |", "|---|---|---|---|---|---|"]
    for i, r in enumerate(rows):
        worst = max(r["deviation_in_standard_errors"].items(), key=lambda kv: abs(kv[1]))
        lines.append(f"| {i} | {r['values']['rotation']:.4f} | "
                     f"{100 * r['residual_rms_over_peak']:.3f} % | {abs(worst[1]):.2f} "
                     f"({worst[0]}) | {r['status']} | {r['seconds']:.0f} |")
    lines.append("")
    lines.append(f"Main fit: rotation {ref['rotation']:.4f}° ± {err.get('rotation', 0):.4f}°; "
                 f"spread of the refits' rotations {study['rotation_spread_deg']:.4f}°.")
    (Path(out) / "robustness.md").write_text("\n".join(lines) + "\n")
    return study


def _run(manifest, loaded, t0, out, *, verbose, max_steps, final) -> dict:
    """The main fit of ``loaded`` = :func:`load_manifest`'s (model, data, options),
    loaded at ``t0`` (the wall time counts from there)."""
    model, data, opts = loaded
    if verbose and opts["manifest"].get("stages", "auto") == "auto":
        print("stages chosen from the model and the data (the manifest gives none):\n"
              + stages_text(opts["stages"]), flush=True)
    res = fit(model, data, stages=opts["stages"], starts=opts["starts"],
              max_steps=max_steps or opts["max_steps"], verbose=verbose,
              per_capture=opts["per_capture"])
    wall = time.perf_counter() - t0
    out = Path(out)
    man = opts["manifest"]
    sp = man.get("spikes", {})
    # spike angles of the first capture (the others share the pupil)
    first = data[0] if isinstance(data, list) else data
    mimg = res.model_image[0] if isinstance(data, list) else res.model_image
    v0 = values_of_capture(res.values, 0)
    h, w = first.image.shape
    centre = (w // 2 + v0["x0"], h // 2 + v0["y0"])
    bgsub = np.where(first.mask, first.image - v0["background"], 0.0)
    measured = spike_angles(bgsub, centre, r_min=sp.get("r_min", 15), r_max=sp.get("r_max", 40),
                            n_spikes=sp.get("n_spikes", 8))
    modelled = spike_angles(mimg - v0["background"], centre,
                            r_min=sp.get("r_min", 15), r_max=sp.get("r_max", 40), near=measured,
                            window=_MODEL_SPIKE_WINDOW)
    modelled = [a if math.isfinite(a) else None for a in modelled]  # None: no peak there
    summary = {
        "manifest": str(manifest),
        "status": res.status,
        "converged": res.converged,
        "chi2_dof": res.chi2_dof,
        "dof": res.dof,
        "residual_rms_over_peak": res.residual_rms_peak,
        "wall_time_s": wall,
        "values": res.values,
        "units": {k: parameter_unit(k, model) for k in res.values},
        "errors": res.errors,
        "free": res.free,
        "warnings": res.warnings,
        "spike_angles_deg": {
            "note": "counter-clockwise from +x (image right), y up, folded into [0, 180); "
                    "azimuthal peaks of r^2 (I - background) between r_min and r_max px; "
                    f"in the model, the peak within {_MODEL_SPIKE_WINDOW:g} degrees of each "
                    "one in the data (null: no peak there)",
            "measured_in_data": measured,
            "measured_in_model": modelled,
            "implied_by_fit": model_spike_angles(res.values, opts["builder"]),
        },
        "stages": res.stages,
        "noise": next((st["noise"] for st in reversed(res.stages) if "noise" in st), None),
    }
    (out / "result.json").write_text(json.dumps(summary, indent=2, default=float) + "\n")
    np.save(out / "model.npy", np.asarray(res.model_image))  # (N, H, W) for N captures
    _write_fits(out, res, data, opts, model)
    _figure(res, out / "fit.png", man.get("name", Path(manifest).parent.name))
    if verbose:
        print(res.summary())
        print(f"spikes measured in the data: {_degrees(measured)}")
        print(f"spikes measured in the model (near the data's): {_degrees(modelled)}")
        print(f"wall time {wall:.1f} s; written to {final}")
    return summary


def _write_fits(out: Path, res, data, opts, model) -> None:
    """model.fits and residual.fits (model_I / residual_I.fits for capture I of several):
    in the input file's layout (a FITS input's header and WCS, its row order, its full
    frame with NaN outside the fitted window), so that the input minus model.fits is
    residual.fits; the fitted values as keywords with their units."""
    datas = data if isinstance(data, list) else [data]
    models = res.model_image if isinstance(data, list) else [res.model_image]
    caps = opts["manifest"]["data"]
    caps = caps if isinstance(caps, list) else [caps]
    for i, (d, m, cap) in enumerate(zip(datas, models, caps)):
        v = values_of_capture(res.values, i)
        kw = [("DIFSTAR", "fit-image", "written by difstar fit-image")]
        kw += [(f"DIFSTAR {k.upper()}", float(x), parameter_unit(k, model))
               for k, x in v.items()]
        src = d.path
        im = read_image(src) if src is not None else None
        like = dict(source=src, roi=cap.get("roi"), flipped=bool(im and im.flipped),
                    hdu=None if im is None else im.hdu)
        tag = "" if len(datas) == 1 else f"_{i}"
        write_fits_like(out / f"model{tag}.fits", np.asarray(m), keywords=kw, **like)
        resid = np.where(d.mask, d.image - np.asarray(m), np.nan)
        write_fits_like(out / f"residual{tag}.fits", resid, keywords=kw, **like)


def _degrees(angles) -> str:
    """Spike angles for the console: "1.68°, 30.32°, no peak" (None: no peak there)."""
    return ", ".join("no peak" if a is None else f"{a:.2f}°" for a in angles)
