"""A RAW fit against the truth: rough starts about the true values and the pass criteria
(for captures whose truth is known: ``difstar synth``'s, or an independent generator's,
given in the manifest's ``truth`` block)."""

from __future__ import annotations

import math

import jax
import numpy as np

from ._fit import zernike_index
from ._sensor import response_curve
from .fitting._params import PERTURB


def perturbed_starts(man, model, rng) -> dict:
    """Starts within ±20 % of the truth (of the manifest's start where no truth is
    known), at least ±20 % of ``perturb_scale``, inside the bounds."""
    truth = man.truth
    out = {}
    for name in model.free:
        p = model.params[name]
        t = np.asarray(truth.get(name, p.value), float)
        scale = np.maximum(np.abs(t), man.parameters[name]["perturb_scale"])
        v = t + rng.uniform(-PERTURB, PERTURB, p.shape) * scale
        span = p.hi - p.lo
        out[name] = np.clip(v, p.lo + 1e-3 * span, p.hi - 1e-3 * span)
    return out


def compare_truth(model, x_fit: dict, truth: dict, h_range, stderr: dict | None = None
                  ) -> dict:
    """Errors against the truth (the free parameters whose truth is known) and the pass
    criteria: circumradius ≤ 0.5 %, rotation ≤ 0.2°, Δz ≤ 1 %, φ0 ≤ 1 %, response
    curves ≤ 1 % of the range; blade curvature and Zernike terms within 2 standard
    errors of the truth with a standard error under 5 % of the true value."""
    n = model.camera.n_blades
    out = {}
    free = set(model.free) & set(truth)
    dz_scale = max([abs(float(truth[k])) for k in truth if k.startswith("defocus/")] or [0.0])
    for name in free:
        t, f = np.asarray(truth[name], float), np.asarray(x_fit[name], float)
        if name == "rotation":
            err = float(np.rad2deg(wrap_rotation(f - t, n)))
            out[name] = {"error_deg": err, "pass": abs(err) <= 0.2, "criterion": "|Δ| ≤ 0.2°"}
        elif name == "circumradius":
            rel = float((f - t) / t)
            out[name] = {"rel_error": rel, "pass": abs(rel) <= 5e-3, "criterion": "≤ 0.5 %"}
        elif name.startswith("defocus/"):
            if abs(float(t)) > 0:
                rel = float((f - t) / t)
                out[name] = {"rel_error": rel, "pass": abs(rel) <= 1e-2, "criterion": "≤ 1 %"}
            else:
                err = float(f - t)
                out[name] = {"abs_error_m": err, "pass": abs(err) <= 1e-2 * dz_scale,
                             "criterion": "|Δ| ≤ 1 % of the largest true |Δz|"}
        elif (name == "curvature" or zernike_index(name) is not None) and stderr is not None:
            se = float(np.asarray(stderr[name]))
            err = float(f - t)
            ok = abs(err) <= 2 * se and se <= 0.05 * abs(float(t))
            out[name] = {"error": err, "stderr": se, "rel_error": err / abs(float(t)) if t else err,
                         "pass": bool(ok),
                         "criterion": "|Δ| ≤ 2 standard errors, standard error ≤ 5 % of the value"}
        elif name == "phi0":
            rel = ((f - t) / t).tolist()
            out[name] = {"rel_error": rel, "pass": bool(np.all(np.abs(rel) <= 1e-2)),
                         "criterion": "≤ 1 % per channel"}
        else:
            den = np.where(np.abs(t) > 0, np.abs(t), 1.0)
            out[name] = {"error": (f - t).tolist(), "rel_error": ((f - t) / den).tolist()}
    if {"phi0", "toe", "knee"} <= set(truth) and {"phi0", "toe", "knee"} & free:
        err = response_error(x_fit, truth, h_range)
        out["response_curves"] = {
            "max_error_fraction_of_range": err.tolist(), "pass": bool(np.all(err <= 1e-2)),
            "criterion": "max |ζ_fit(H) − ζ_true(H)| ≤ 1 % of the range, per channel, over "
                         f"H = C·t in [{h_range[0]:.3g}, {h_range[1]:.3g}] s",
        }
    crit = [v["pass"] for v in out.values() if "pass" in v]
    out["all_pass"] = bool(all(crit))
    return out


def wrap_rotation(delta, n_blades: int):
    """An angle difference wrapped into [−π/n, π/n): a regular n-gon rotated by 2π/n is
    the same aperture."""
    period = 2 * math.pi / n_blades
    return (np.asarray(delta) + period / 2) % period - period / 2


def response_error(x_fit: dict, x_true: dict, h_range: tuple[float, float], *, n: int = 512):
    """Max |ζ_fit(H) − ζ_true(H)| per channel over physical exposures H = C·t in
    ``h_range`` (log-spaced), as a fraction of the true curve's range there."""
    h = np.geomspace(max(h_range[0], 1e-12), h_range[1], n)
    curve = jax.jit(response_curve)  # one program, not each operation compiled eagerly
    out = []
    for c in range(3):
        zt = np.asarray(curve(h / x_true["phi0"][c], x_true["toe"][c], x_true["knee"][c]))
        zf = np.asarray(curve(h / x_fit["phi0"][c], x_fit["toe"][c], x_fit["knee"][c]))
        rng = zt.max() - zt.min()
        out.append(float(np.max(np.abs(zf - zt)) / max(rng, 1e-12)))
    return np.asarray(out)
