"""The recovery study of a RAW fit (``difstar fit --recovery-study N``): the fit of
:func:`difstar._fit_run.fit_manifest` from N rough starts about the truth (in series,
or together over devices), each compared with the truth by the pass criteria of
:mod:`difstar._fit_truth`; :func:`study_table` prints the result as Markdown."""

from __future__ import annotations

import time

import numpy as np

from difstar._batch import ENV_DEVICES, device_count
from difstar._batch_fits import FitBatcher
from difstar._distributed import init_distributed
from difstar._fit import Fitter, to_unconstrained
from difstar._fit_run import _log, fit_manifest, prepare
from difstar._fit_truth import perturbed_starts
from difstar.fitting._params import PERTURB  # starts within ± 20 %: one figure for both fitters


def recovery_study(man, n_starts: int, seed: int, *, devices=None, chunk=None,
                   verbose: bool = True) -> dict:
    """Fit from ``n_starts`` perturbed starts. With ``devices`` (or ``DIFSTAR_DEVICES``)
    the fits run together, each the code of one fit (``fit_manifest``) with every
    stage's solves of all fits batched and sharded over that many devices
    (:class:`difstar._batch_fits.FitBatcher`), ``chunk`` fits at a time at most (default:
    as many as fit in memory); without, one after another. ``verbose``: a line on stderr
    per finished fit."""
    import os

    log = _log if verbose else (lambda msg: None)

    rng = np.random.default_rng(seed)
    t_study = time.perf_counter()

    def row_of(i, res, t0):
        return {"start": i, "seconds": time.perf_counter() - t0,
                "steps": sum(s.get("steps", 0) for s in res["convergence"]["stages"]),
                "compile_seconds": res["timing_s"]["compile"],
                "comparison": res["truth_comparison"],
                "values": {k: v["value"] for k, v in res["parameters"].items()}}

    batched = devices is not None or bool(os.environ.get(ENV_DEVICES, "").strip())
    extra = {}
    if not batched:
        rows = []
        model = caps = fitter = None
        for i in range(n_starts):
            if model is None:
                model, caps = prepare(man)
            starts = perturbed_starts(man, model, rng)
            u0 = to_unconstrained(model, starts)
            t0 = time.perf_counter()
            res, model, caps, fitter, u = fit_manifest(man, u0=u0, verbose=False, model=model,
                                                       caps=caps, fitter=fitter)
            rows.append(row_of(i, res, t0))
            log(_row_text(i, rows[-1]) + fits_left(rows, n_starts))
    else:
        init_distributed()
        n_dev = device_count(devices)
        model, caps = prepare(man)
        fitter = Fitter(model, method=man.solver["method"], rtol=man.solver["rtol"],
                        atol=man.solver["atol"])
        u0s = [to_unconstrained(model, perturbed_starts(man, model, rng))
               for _ in range(n_starts)]
        log(f"difstar fit: {n_starts} fits together on {n_dev} device(s); their solves "
             "run as one batch per stage")

        def job(i):
            def run(stand_in):
                t0 = time.perf_counter()
                res, *_ = fit_manifest(man, u0=u0s[i], verbose=False, model=model, caps=caps,
                                       fitter=stand_in)
                row = row_of(i, res, t0)
                log(_row_text(i, row))
                return row
            return run

        batcher = FitBatcher(fitter, devices=n_dev, chunk=chunk,
                             progress=lambda m: log(f"difstar fit: {m}"))
        rows = batcher.run([job(i) for i in range(n_starts)])
        extra = {"devices": n_dev, "chunks": [
            {"fits": p.chunk, "per_device": p.per_device, "item_bytes": p.item_bytes,
             "free_bytes": p.free_bytes} for p in batcher.plans]}
    n_pass = sum(r["comparison"]["all_pass"] for r in rows)
    return {"n_starts": n_starts, "seed": seed, "perturbation": PERTURB, "n_pass": n_pass,
            "seconds": time.perf_counter() - t_study, "rows": rows, **extra}


def fits_left(rows: list[dict], n_starts: int) -> str:
    """", about 40 s left": the fits still to run times the mean time of those done after
    the first (which compiles; the first's own time while it is the only one); "" after
    the last."""
    left = n_starts - len(rows)
    if left <= 0:
        return ""
    done = [r["seconds"] for r in rows[1:]] or [rows[0]["seconds"]]
    return f", about {left * sum(done) / len(done):.0f} s left"


def _row_text(i, row) -> str:
    tc = row["comparison"]
    parts = [f"start {i:2d}"]
    for k, v in tc.items():
        if k == "all_pass":
            continue
        if "error_deg" in v:
            parts.append(f"{k} {v['error_deg']:+.4f}°")
        elif "abs_error_m" in v:
            parts.append(f"{k} {v['abs_error_m'] * 1e6:+.2f} µm")
        elif k == "response_curves":
            parts.append("Z " + "/".join(f"{e * 100:.3f}%" for e in
                                         v["max_error_fraction_of_range"]))
        elif "pass" in v:
            rel = np.atleast_1d(v["rel_error"])
            parts.append(f"{k} " + "/".join(f"{e * 100:+.3f}%" for e in rel))
    parts.append("PASS" if tc["all_pass"] else "FAIL")
    parts.append(f"{row['steps']} steps {row['seconds']:.0f} s")
    return "  ".join(parts)


def study_table(study: dict) -> str:
    """The study of :func:`recovery_study` as a Markdown table, a row per start."""
    lines = ["| start | Δz (defocused) | Δz (focused) | rotation | circumradius | φ0 R/G/B | "
             "response R/G/B (of range) | steps | s | pass |", "|" + "---|" * 10]
    for r in study["rows"]:
        tc = r["comparison"]
        dz_def = next((f"{v['rel_error'] * 100:+.3f} %" for k, v in tc.items()
                       if k.startswith("defocus/") and "rel_error" in v), "–")
        dz_foc = next((f"{v['abs_error_m'] * 1e6:+.2f} µm" for k, v in tc.items()
                       if k.startswith("defocus/") and "abs_error_m" in v), "–")
        rot = f"{tc['rotation']['error_deg']:+.4f}°" if "rotation" in tc else "–"
        cr = f"{tc['circumradius']['rel_error'] * 100:+.4f} %" if "circumradius" in tc else "–"
        ph = "/".join(f"{e * 100:+.3f}" for e in tc["phi0"]["rel_error"]) + " %" \
            if "phi0" in tc else "–"
        zr = "/".join(f"{e * 100:.3f}" for e in
                      tc["response_curves"]["max_error_fraction_of_range"]) + " %" \
            if "response_curves" in tc else "–"
        lines.append(f"| {r['start']} | {dz_def} | {dz_foc} | {rot} | {cr} | {ph} | {zr} | "
                     f"{r['steps']} | {r['seconds']:.0f} | {'yes' if tc['all_pass'] else 'NO'} |")
    lines.append("")
    lines.append(f"{study['n_pass']} of {study['n_starts']} starts pass every criterion "
                 f"(seed {study['seed']}, starts within ±{study['perturbation'] * 100:.0f} %; "
                 f"{study['seconds']:.0f} s in all).")
    return "\n".join(lines)
