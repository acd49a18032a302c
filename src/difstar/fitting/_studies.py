"""Studies of a fitted star (what ``difstar fit-image --fainter / --shifted /
--contaminated / --noise-limit`` run after the main fit): copies of the star changed as
another star of its kind would differ from it, each fitted by the same manifest, and the
noise limit of the fit's parameters.

- fainter copies (:func:`fit_fainter_copy`): the star ``f`` times fainter, with the noise
  such a star would have;
- moved copies (:func:`shifted_image`, :func:`fit_shifted_copy`): the star moved by a
  fraction of a pixel with Lanczos3 resampling (the kernel SWarp resamples co-adds with),
  as a star elsewhere on the pixel grid;
- contaminated copies (:func:`contaminated_image`, :func:`fit_contaminated_copy`): a
  fainter neighbour and hot pixels added, which the model does not describe;
- any other change of the image (:func:`fit_changed_copy`, e.g. its mirror image);
- the star and its moved and contaminated copies fitted together (:func:`fit_joint`):
  one pupil, rotation and wavefront for all, each its own centre, flux and background,
  as the stars of one field are;
- the noise limit (:func:`noise_limit`): the Cramér–Rao standard errors for the star and
  for stars of its kind ``f`` times fainter, and how likely two such stars agree.

Each ``_NAME`` writer below puts a study's ``NAME.json`` / ``NAME.md`` into the result
folder that :func:`difstar.fitting.run_fit_image` is writing.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np

from ._data import FitData, Noise, data_intensity, fainter_copy
from ._manifest import load_manifest
from ._params import FitInputError
from ._procedure import fit
from ._solve import noise_limited_errors

_PAD = 4  # Lanczos3 reaches 3 px; edge pixels are repeated beyond the border
_NEEDS_NOISE = ("needs a stage with noise_from_residuals in the manifest (the study needs "
                "a noise model in the data's units); add one or leave the option out.")


def shifted_image(img: np.ndarray, dx: float | int, dy: float | int) -> np.ndarray:
    """``img`` moved by ``dx`` columns (right) and ``dy`` rows (down): out[r, c] =
    img[r − dy, c − dx], by Pillow's Lanczos3 resampling, in float32 (Pillow's float
    mode). Integer shifts are exact moves; beyond the border the edge pixels repeat. For
    an image read by the fitter (rows down) the star's ``x0`` and ``y0`` move by about
    ``dx`` and ``dy`` (exactly for whole pixels; for a fraction, by the Lanczos3 taps'
    first moment, e.g. 0.2302 px for 0.25)."""
    from PIL import Image

    if not (math.isfinite(dx) and math.isfinite(dy)):
        raise FitInputError(f"shifted_image: the shift must be finite; got ({dx}, {dy}).")
    h, w = np.shape(img)
    pad = _PAD + math.ceil(max(abs(dx), abs(dy)))
    a = np.pad(np.asarray(img, np.float32), pad, mode="edge")
    box = (pad - dx, pad - dy, pad - dx + w, pad - dy + h)
    return np.asarray(Image.fromarray(a).resize((w, h), Image.LANCZOS, box=box))


def _moved_whole(img: np.ndarray, dx: int, dy: int) -> np.ndarray:
    """``img`` moved by ``dx`` columns and ``dy`` rows, whole pixels: out[r, c] =
    img[r − dy, c − dx], 0 where that falls outside."""
    h, w = img.shape
    out = np.zeros_like(img)
    rs, cs = slice(max(dy, 0), h + min(dy, 0)), slice(max(dx, 0), w + min(dx, 0))
    out[rs, cs] = img[max(-dy, 0):h - max(dy, 0), max(-dx, 0):w - max(dx, 0)]
    return out


def contaminated_image(img: np.ndarray, *, neighbour=(26, 15, 30.0), hits=6, seed=0,
                       clear=15.0) -> np.ndarray:
    """``img`` (the star, its brightest pixel its centre) plus a neighbour and hot pixels.

    The neighbour (``neighbour`` = (dx, dy, factor)) is the star itself less the median of
    the image's 4-pixel border, ``factor`` times fainter, moved by whole pixels (``dx``
    columns right, ``dy`` rows down; 0 beyond the border), so it has real spikes and real
    noise; the default puts it on the JWST star's spike at 150° (−30°), 30 px out, in an
    image read by the fitter (rows down). ``hits`` hot pixels, half of them two-pixel
    cosmic-ray tracks (the next pixel along a random axis, 30–100 % as bright), land at
    random (``seed``) at least ``clear`` px from the brightest pixel, each 0.3–10 % of its
    height above the border. NaN pixels stay NaN; the input is not changed."""
    a = np.asarray(img, float)
    h, w = a.shape
    dx, dy, factor = neighbour
    if not (float(dx).is_integer() and float(dy).is_integer() and math.isfinite(factor)
            and factor >= 1 and int(hits) >= 0):
        raise FitInputError(f"contaminated_image: the neighbour's dx, dy must be whole pixels "
                            f"and its factor >= 1, hits >= 0; got {tuple(neighbour)}, {hits}.")
    finite = np.where(np.isfinite(a), a, np.nan)
    border = np.concatenate([finite[:4].ravel(), finite[-4:].ravel(),
                             finite[:, :4].ravel(), finite[:, -4:].ravel()])
    star = np.nan_to_num(finite - float(np.nanmedian(border)))
    out = a + _moved_whole(star, int(dx), int(dy)) / float(factor)
    peak = float(star.max())
    r0, c0 = np.unravel_index(np.argmax(star), star.shape)
    rr, cc = np.mgrid[1:h - 1, 1:w - 1]
    if hits and not (np.hypot(rr - r0, cc - c0) >= clear).any():
        raise FitInputError(f"contaminated_image: no pixel of this {h} × {w} image lies {clear:g} "
                            "px or more from the star for the hot pixels; ask for none.")
    rng = np.random.default_rng(seed)
    placed = 0
    while placed < hits:
        r, c = int(rng.integers(1, h - 1)), int(rng.integers(1, w - 1))
        if math.hypot(r - r0, c - c0) < clear:
            continue
        level = peak * 10 ** rng.uniform(math.log10(3e-3), -1)
        out[r, c] += level
        if rng.random() < 0.5:  # a two-pixel track: the next pixel along a random axis
            dr, dc = ((0, 1), (1, 0), (1, 1))[int(rng.integers(3))]
            out[r + dr, c + dc] += level * rng.uniform(0.3, 1.0)
        placed += 1
    return out


def fit_changed_copy(manifest, transform, *, max_steps=None, verbose=False):
    """Fit, by ``manifest``'s stages and starts, a changed copy of its star: each capture's
    image as ``transform(image)`` returns it (:func:`difstar.fitting.load_manifest`'s
    ``transform``: the file's frame, rows down; e.g. ``lambda im: im[:, ::-1]``, the
    mirror image). Returns the copy's FitResult."""
    model, data, opts = load_manifest(manifest, transform=transform)
    return fit(model, data, stages=opts["stages"], starts=opts["starts"],
               max_steps=max_steps or opts["max_steps"], verbose=verbose,
               per_capture=opts["per_capture"])


def fit_shifted_copy(manifest, dx, dy, *, max_steps=None, verbose=False):
    """Fit, by ``manifest``'s stages, its star moved by ``dx`` columns and ``dy`` rows
    (:func:`shifted_image`: Lanczos3): a star elsewhere on the pixel grid. The fit's
    ``x0``, ``y0`` should move by about (``dx``, ``dy``), its geometry not at all."""
    return fit_changed_copy(manifest, lambda im: shifted_image(im, dx, dy),
                            max_steps=max_steps, verbose=verbose)


def fit_contaminated_copy(manifest, *, neighbour=(26, 15, 30.0), hits=6, seed=0,
                          max_steps=None, verbose=False):
    """Fit, by ``manifest``'s stages, its star with a neighbour and hot pixels added
    (:func:`contaminated_image`): what the manifest's ``reject`` stages are for."""
    return fit_changed_copy(
        manifest, lambda im: contaminated_image(im, neighbour=neighbour, hits=hits, seed=seed),
        max_steps=max_steps, verbose=verbose)


def _moved_label(dx, dy) -> str:
    return f"moved by ({dx:g}, {dy:g}) px"


def _contaminated_label(dx, dy, f) -> str:
    return f"contaminated ({dx:g}, {dy:g}) × 1/{f:g}"


def _copy_changes(shifted=(), contaminated=(), hits=6, seed=0) -> list:
    """The image changes that make the moved copies, then the contaminated ones (the
    i-th with hot-pixel seed ``seed`` + i), as :func:`fit_changed_copy` takes them."""
    changes = [lambda im, d=d: shifted_image(im, *d) for d in shifted]
    changes += [lambda im, n=n, i=i: contaminated_image(im, neighbour=n, hits=hits,
                                                        seed=seed + i)
                for i, n in enumerate(contaminated)]
    return changes


def fit_joint(manifest, changes, *, max_steps=None, verbose=False):
    """Fit, by ``manifest``'s stages and starts, its star and a copy of it changed by each
    of ``changes`` together (as :func:`fit_changed_copy` changes it): the stars of one
    field, each with its own ``x0``, ``y0``, ``flux``, ``background`` (``name@i``: the
    star is capture 0) and everything else (the pupil, its rotation, the wavefront, the
    detector) shared. Returns the joint FitResult."""
    model, data, opts = load_manifest(manifest)
    datas = [data] + [load_manifest(manifest, transform=c)[1] for c in changes]
    return fit(model, datas, stages=opts["stages"], starts=opts["starts"],
               max_steps=max_steps or opts["max_steps"], verbose=verbose,
               per_capture=opts["per_capture"])


def _copy_noise(summary, option="--fainter"):
    """The read noise and gain that the manifest's noise_from_residuals estimated
    (result.json's ``noise``): the noise of the fainter copies and of the noise limit."""
    n = summary.get("noise")
    if n is None:
        raise FitInputError(f"{option} {_NEEDS_NOISE}")
    return Noise(n["read"], n["gain"], 0.0)


def fit_fainter_copy(manifest, summary, model_image, factor, seed, *, max_steps=None,
                     verbose=False):
    """Fit, by ``manifest``'s stages, a copy of its star ``factor`` times fainter with the
    noise of draw ``seed`` (:func:`difstar.fitting.fainter_copy`), made from a fit of
    the star: ``summary`` (result.json's content: the background and the noise estimated
    from the residuals) and its ``model_image``. Returns the copy's FitResult."""
    model, data, opts = load_manifest(manifest)
    noise = _copy_noise(summary)
    d = fainter_copy(data, model_image, summary["values"]["background"], factor, noise,
                     seed=seed)
    nz = opts["manifest"]["data"].get("noise", {})  # σ as the manifest makes them
    d = FitData.from_array(d.image, mask=data.mask, pixel_scale=data.pixel_scale,
                           noise=Noise(nz.get("read"), float(nz.get("gain", 1.0)),
                                       float(nz.get("floor", 0.0))))
    m = model.with_values({"flux": model.params["flux"].value / factor})
    return fit(m, d, stages=opts["stages"], max_steps=max_steps or opts["max_steps"],
               verbose=verbose)


def noise_limit(manifest, summary, factors=(1.0, 2.0, 4.0, 8.0, 16.0, 32.0), *,
                param="rotation", within=0.05) -> dict:
    """The noise limit of a fit: how precisely the pixels of its star, and of stars of
    its kind ``factors`` times fainter, can tell ``param``.

    At ``summary``'s values (result.json's content; its ``noise``, the read noise and
    gain the manifest's noise_from_residuals estimated), with every parameter the
    manifest frees still free, the Cramér–Rao standard errors
    (:func:`difstar.fitting.noise_limited_errors`) for σ² = (f·read)² + f·I/gain (a star
    f times fainter, in this star's units; I the data's intensity,
    :func:`difstar.fitting.data_intensity`) and, a lower limit, for σ = f·read alone (the
    gain so estimated takes in some of the model's mismatch). No unbiased fit, however
    good its model, can be more precise on average; a model's mismatch only adds to it.
    ``p_agree``: the chance that ``param`` of this star and of the row's, fitted
    independently, each at its bound and unbiased, agree within ``within``:
    erf(within / (√2 σ_pair)), σ_pair² = σ_star² + σ_row².

    Returns {"param", "within", "noise": {"read", "gain"}, "peak", "rows"}, a row per
    factor: "factor", "peak_snr" (the fainter star's peak over its σ there), "errors" and
    "errors_read_only" (every free parameter), "error", "error_read_only",
    "error_others_held" (``param`` with every other parameter held) and "p_agree"."""
    fs = [float(f) for f in factors]
    if not fs or not all(math.isfinite(f) and f >= 1 for f in fs):
        raise FitInputError(f"noise_limit: factors must be finite and >= 1; got {factors}.")
    if not (math.isfinite(within) and within > 0):
        raise FitInputError(f"noise_limit: within must be > 0; got {within}.")
    model, data, _ = load_manifest(manifest)
    if isinstance(data, list):
        raise FitInputError("noise_limit takes a manifest with one capture.")
    if param not in model.free:
        raise FitInputError(f"noise_limit: the manifest holds {param} fixed; free it or "
                            "name a free parameter.")
    noise = _copy_noise(summary, "noise_limit")
    v = summary["values"]
    inten = data_intensity(data, v["background"])
    every = [1.0] + fs  # this star first: the pair's other member
    sigmas = [np.sqrt((f * noise.read) ** 2 + f * inten / noise.gain) for f in every]
    reads = [np.full(data.image.shape, f * noise.read) for f in every]
    start = model.with_values(v)
    full = {k: p.value for k, p in start.params.items()}  # the manifest's where v has none
    both = noise_limited_errors(start, data, full, sigmas + reads)
    held = noise_limited_errors(model.with_values(v, free=[param]), data, full, sigmas)
    errs, errs_read = both[:len(every)], both[len(every):]
    peak_at = np.argmax(inten[data.mask])
    peak = float(inten[data.mask][peak_at])
    s1 = errs[0][param]
    rows = []
    for f, e, er, eh, sig in zip(every[1:], errs[1:], errs_read[1:], held[1:], sigmas[1:]):
        pair = math.sqrt(s1**2 + e[param] ** 2)
        rows.append({"factor": f, "peak_snr": peak / float(sig[data.mask][peak_at]),
                     "errors": e, "errors_read_only": er, "error": e[param],
                     "error_read_only": er[param], "error_others_held": eh[param],
                     "p_agree": math.erf(within / (math.sqrt(2) * pair))})
    return {"param": param, "within": within,
            "noise": {"read": noise.read, "gain": noise.gain}, "peak": peak, "rows": rows}


# the writers of run_fit_image's studies ------------------------------------------------

def _dump(path: Path, doc) -> None:
    path.write_text(json.dumps(doc, indent=2, default=float) + "\n")


def _pm(err):  # no standard error where the manifest holds the parameter
    return "(fixed)" if err is None else f"± {err:.4f}"


def _fainter(manifest, out, summary, factors, seed, *, max_steps, verbose) -> dict:
    """Fit copies of the star made ``factors`` times fainter; compare the geometry."""
    noise = _copy_noise(summary)
    ref = summary["values"]
    mimg = np.load(Path(out) / "model.npy")
    rows = []
    for i, f in enumerate(factors):
        t = time.perf_counter()
        res = fit_fainter_copy(manifest, summary, mimg, f, seed + i, max_steps=max_steps)
        rows.append({"factor": f, "rotation": res.values["rotation"],
                     "rotation_error": res.errors.get("rotation"),
                     "residual_rms_over_peak": res.residual_rms_peak, "status": res.status,
                     "values": res.values, "seconds": time.perf_counter() - t})
        if verbose:
            print(f"fainter × {f:g}: rotation {res.values['rotation']:.4f}° "
                  f"({rows[-1]['seconds']:.0f} s)", flush=True)
    rot = np.array([ref["rotation"]] + [r["rotation"] for r in rows])
    study = {"seed": seed, "noise": {"read": noise.read, "gain": noise.gain},
             "rotation_original": ref["rotation"], "copies": rows,
             "rotation_spread_deg": float(rot.max() - rot.min())}
    _dump(Path(out) / "fainter.json", study)
    lines = ["Copies of the star made f times fainter, with the noise a fainter star would "
             f"have (read {noise.read:.3g}, gain {noise.gain:.4g} in the data's units, "
             "estimated from the residuals), fitted by the same manifest.", "",
             "| star | rotation (°) | residual RMS / peak | status | s |", "|---|---|---|---|---|",
             f"| original | {ref['rotation']:.4f} {_pm(summary['errors'].get('rotation'))} "
             f"| {100 * summary['residual_rms_over_peak']:.3f} % | {summary['status']} | "
             f"{summary['wall_time_s']:.0f} |"]
    for r in rows:
        lines.append(f"| × 1/{r['factor']:g} | {r['rotation']:.4f} {_pm(r['rotation_error'])} "
                     f"| {100 * r['residual_rms_over_peak']:.3f} % | {r['status']} | "
                     f"{r['seconds']:.0f} |")
    lines += ["", f"Spread of the rotations: {study['rotation_spread_deg']:.4f}°."]
    (Path(out) / "fainter.md").write_text("\n".join(lines) + "\n")
    return study


def _copy_row(res, summary, seconds, expected=None) -> dict:
    """A changed copy's fit against the star's: each free parameter's difference from
    the star's value (or from ``expected(name, star_value)``) in the star's standard
    errors."""
    ref, err = summary["values"], summary["errors"]
    dev = {}
    for k in res.free:
        e = err.get(k)
        if k in ref and e is not None and math.isfinite(e) and e > 0:
            want = expected(k, ref[k]) if expected else ref[k]
            dev[k] = (res.values[k] - want) / e
    worst = max(dev.items(), key=lambda kv: abs(kv[1]), default=None)
    return {"values": res.values, "errors": res.errors, "status": res.status,
            "rotation": res.values.get("rotation"), "rotation_error": res.errors.get("rotation"),
            "residual_rms_over_peak": res.residual_rms_peak, "chi2_dof": res.chi2_dof,
            "deviation_in_standard_errors": dev,
            "max_deviation": None if worst is None else abs(worst[1]),
            "max_deviation_parameter": None if worst is None else worst[0],
            "seconds": seconds}


def _copy_cells(r, ref_rotation) -> list[str]:
    worst = ("—" if r["max_deviation"] is None
             else f"{r['max_deviation']:.2f} ({r['max_deviation_parameter']})")
    return [f"{r['rotation']:.4f} {_pm(r['rotation_error'])}",
            f"{r['rotation'] - ref_rotation:+.4f}", worst,
            f"{100 * r['residual_rms_over_peak']:.3f} %", f"{r['chi2_dof']:.4g}", r["status"],
            f"{r['seconds']:.0f}"]


def _copies_md(path, intro, what_col, rows, labels, summary) -> None:
    ref = summary["values"]["rotation"]
    cols = [what_col, "rotation (°)", "from the star's", "largest \\|Δ\\|/σ (parameter)",
            "residual RMS / peak", "χ²/dof", "status", "s"]
    lines = [intro, "", "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols),
             f"| the star | {ref:.4f} {_pm(summary['errors'].get('rotation'))} | — | — | "
             f"{100 * summary['residual_rms_over_peak']:.3f} % | {summary['chi2_dof']:.4g} | "
             f"{summary['status']} | {summary['wall_time_s']:.0f} |"]
    lines += ["| " + " | ".join([lab] + _copy_cells(r, ref)) + " |"
              for lab, r in zip(labels, rows)]
    rot = [ref] + [r["rotation"] for r in rows]
    lines += ["", f"Spread of the rotations, the star's included: {max(rot) - min(rot):.4f}°."]
    Path(path).write_text("\n".join(lines) + "\n")


def _copy_study(out, name, copies, summary, *, intro, column, verbose, extra=None) -> dict:
    """Fit each copy of ``copies`` — (table label, progress label, the row's own fields,
    a function fitting it, the expected change of each value or None) — compare it with
    the star's fit, and write NAME.json and NAME.md into ``out``."""
    rows = []
    for _, said, fields, fit_copy, expected in copies:
        t = time.perf_counter()
        res = fit_copy()
        rows.append({**fields, **_copy_row(res, summary, time.perf_counter() - t, expected)})
        if verbose:
            print(f"{said}: rotation {res.values['rotation']:.4f}° "
                  f"({rows[-1]['seconds']:.0f} s)", flush=True)
    study = {**(extra or {}), "copies": rows}
    _dump(Path(out) / f"{name}.json", study)
    _copies_md(Path(out) / f"{name}.md", intro, column, rows, [c[0] for c in copies],
               summary)
    return study


def _shifted(manifest, out, summary, moves, *, max_steps, verbose) -> dict:
    """Fit the star moved by each (dx, dy) of ``moves``; compare with the star's fit."""

    def expected(dx, dy):  # the centre moves with the star
        return lambda k, v: v + {"x0": dx, "y0": dy}.get(k.split("@")[0], 0.0)

    copies = [(f"({dx:g}, {dy:g})", _moved_label(dx, dy), {"shift": [dx, dy]},
               lambda dx=dx, dy=dy: fit_shifted_copy(manifest, dx, dy, max_steps=max_steps),
               expected(dx, dy)) for dx, dy in moves]
    return _copy_study(
        out, "shifted", copies, summary, verbose=verbose, extra={"kernel": "lanczos3"},
        column="move (DX, DY) px",
        intro="The star moved by (DX, DY) px (DX columns right, DY rows down) with Lanczos3 "
              "resampling (the kernel SWarp resamples co-adds with), as another star of "
              "its kind elsewhere on the pixel grid, fitted by the same manifest. Δ: each "
              "free parameter less the star's (x0, y0: less the star's plus the move), in "
              "the star's standard errors.")


def _contaminated(manifest, out, summary, neighbours, hits, seed, *, max_steps,
                  verbose) -> dict:
    """Fit the star with each neighbour of ``neighbours`` and ``hits`` hot pixels (seed
    ``seed`` + i for the i-th copy) added; compare with the star's fit."""
    copies = [(f"({dx:g}, {dy:g}), × 1/{f:g}; {hits} ({seed + i})",
               _contaminated_label(dx, dy, f),
               {"neighbour": [dx, dy, f], "hits": hits, "seed": seed + i},
               lambda n=(dx, dy, f), s=seed + i: fit_contaminated_copy(
                   manifest, neighbour=n, hits=hits, seed=s, max_steps=max_steps),
               None) for i, (dx, dy, f) in enumerate(neighbours)]
    return _copy_study(
        out, "contaminated", copies, summary, verbose=verbose,
        column="neighbour (DX, DY) px, × 1/F; hits (seed)",
        intro="The star with a neighbour (the star itself less its border's median, F times "
              "fainter, moved by (DX, DY) whole px: columns right, rows down) and hot "
              "pixels and two-pixel tracks (0.3–10 % of the peak, at least 15 px from the "
              "star), fitted by the same manifest; what its reject stages are for. Δ: each "
              "free parameter less the star's, in the star's standard errors.")


def _noise_limit(manifest, out, summary, factors, *, verbose) -> dict:
    """The noise limit of the rotation for the star and stars ``factors`` times fainter."""
    study = noise_limit(manifest, summary, factors)
    _dump(Path(out) / "noise_limit.json", study)
    w = study["within"]
    lines = ["The noise limit of the rotation: Cramér–Rao standard errors at the fit's values, "
             "every free parameter free, for σ² = (f·read)² + f·I/gain (read "
             f"{study['noise']['read']:.3g}, gain {study['noise']['gain']:.4g} in the data's "
             "units, estimated from the residuals; a star f times fainter) and for the read "
             "noise alone (a lower limit). No unbiased fit can scatter less from the noise. "
             f"P: the chance that two such stars, each fitted at its bound, agree within {w:g}°.",
             "", "| star | peak S/N | σ(rotation), noise alone (°) | read noise alone (°) | "
             f"every other parameter held (°) | P(agree with this star within {w:g}°) |",
             "|---|---|---|---|---|---|"]
    for r in study["rows"]:
        name = "another as bright" if r["factor"] == 1 else f"{r['factor']:g} × fainter"
        lines.append(f"| {name} | {r['peak_snr']:.0f} | {r['error']:.4f} | "
                     f"{r['error_read_only']:.4f} | {r['error_others_held']:.4f} | "
                     f"{r['p_agree']:.2f} |")
    (Path(out) / "noise_limit.md").write_text("\n".join(lines) + "\n")
    if verbose:
        print("\n".join(lines[2:]), flush=True)
    return study


def _check_studies(manifest, loaded, *, fainter=(), shifted=(), contaminated=(), hits=6,
                   seed=0, noise_limit=(), joint=False) -> None:
    """Refuses, before the main fit, studies the manifest cannot run: copies made fainter
    or a noise limit without a noise_from_residuals stage or of several captures, a noise
    limit of a rotation held fixed, a change of the image the manifest's checks refuse."""
    model, data, opts = loaded
    for option, asked in (("--fainter", fainter), ("--noise-limit", noise_limit)):
        if not asked:
            continue
        if isinstance(data, list):
            raise FitInputError(f"{option} takes a manifest with one capture (its data is a "
                                f"list of captures); leave {option} out.")
        if not any(isinstance(st, dict) and st.get("noise_from_residuals") is not None
                   for st in opts["stages"] or ()):
            raise FitInputError(f"{option} {_NEEDS_NOISE}")
    if noise_limit and "rotation" not in model.free:
        raise FitInputError("--noise-limit: the manifest holds the rotation fixed; free it or "
                            "leave --noise-limit out.")
    if joint:
        if not (shifted or contaminated):
            raise FitInputError("--joint fits the star together with its --shifted and "
                                "--contaminated copies; add at least one, or leave --joint "
                                "out.")
        if "rotation" not in model.free:
            raise FitInputError("--joint: the manifest holds the rotation fixed; free it or "
                                "leave --joint out.")
        if isinstance(data, list):
            raise FitInputError("--joint takes a manifest with one capture (its data is a "
                                "list of captures, which it fits together already); leave "
                                "--joint out.")
    for change in _copy_changes(shifted, contaminated, hits, seed):  # read as the fit will
        load_manifest(manifest, transform=change)


def _joint(manifest, out, summary, shifted, contaminated, hits, seed, alone, *, max_steps,
           verbose) -> dict:
    """Fit the star and its moved and contaminated copies together (:func:`fit_joint`);
    compare the joint rotation and its standard error with each star's alone (the star's
    fit, and ``alone``: the copies' rows of the shifted and contaminated studies, in
    order). Writes joint.json and joint.md into ``out``."""
    labels = ([_moved_label(*d) for d in shifted]
              + [_contaminated_label(*n) for n in contaminated])
    t = time.perf_counter()
    res = fit_joint(manifest, _copy_changes(shifted, contaminated, hits, seed),
                    max_steps=max_steps)
    seconds = time.perf_counter() - t
    rot, err = res.values.get("rotation"), res.errors.get("rotation")
    singles = [("the star", summary["values"].get("rotation"),
                summary["errors"].get("rotation"))]
    singles += [(lab, r["rotation"], r["rotation_error"]) for lab, r in zip(labels, alone)]
    best_alone = min((e for _, _, e in singles if e is not None), default=None)
    study = {"captures": ["the star", *labels], "rotation": rot, "rotation_error": err,
             "alone": [{"capture": lab, "rotation": r, "rotation_error": e}
                       for lab, r, e in singles],
             "smaller_error_than_any_alone": (None if err is None or best_alone is None
                                              else bool(err < best_alone)),
             "values": res.values, "errors": res.errors, "status": res.status,
             "chi2_dof": res.chi2_dof, "seconds": seconds}
    if verbose:
        print(f"joint fit of {len(singles)} stars: rotation {rot:.4f}° {_pm(err)} "
              f"({seconds:.0f} s)", flush=True)
    _dump(Path(out) / "joint.json", study)
    lines = ["The star and its copies fitted together, as the stars of one field: one pupil, "
             "rotation and wavefront for all, each its own centre, flux and background. "
             "The copies are made from the star's own pixels, so their noise is the star's: "
             "the joint standard error is smaller than any one star's partly because the "
             "same noise is counted more than once.", "",
             "| fit | rotation (°) |", "|---|---|"]
    lines += [f"| {lab} alone | {r:.4f} {_pm(e)} |" for lab, r, e in singles if r is not None]
    lines += [f"| the {len(singles)} stars together | {rot:.4f} {_pm(err)} |", "",
              f"χ²/dof {res.chi2_dof:.4g}, {res.status}, {seconds:.0f} s."]
    Path(out, "joint.md").write_text("\n".join(lines) + "\n")
    return study
