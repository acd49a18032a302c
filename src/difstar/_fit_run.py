"""The RAW camera fit from a manifest (``difstar fit``, ``difstar synth``): captures →
:class:`difstar.raw_fit.FitModel` (:func:`prepare`), a start from the data's photometry,
the staged Levenberg–Marquardt solve with knee restarts (:func:`fit_manifest`) and the
synthetic captures a manifest's truth makes (:func:`synthesize`).

Outside jit: files are read here and progress goes to stderr; :mod:`difstar._fit` is the
pure layer. The command line (:mod:`difstar.cli._fit`) only parses, calls and writes.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import equinox as eqx
import numpy as np

from difstar import Grid
from difstar._cfa import bayer_masks_np
from difstar._fit import (
    CameraConstants,
    CaptureSpec,
    ConfigSpec,
    FitModel,
    Fitter,
    camera_scene,
    equal_brackets,
    joint_grid,
    make_args,
    merged_grid,
    to_unconstrained,
)
from difstar._fit_procedure import FIRST_STEP, _log, observed_data, procedure_of, run_stages
from difstar._fit_truth import compare_truth
from difstar._param import Param
from difstar._sampling import choose_grid
from difstar.io._dng import synthesize_capture, write_dng, written_by_difstar
from difstar.io._manifest import camera_pupil, roi_origin
from difstar.io._output import output_dir
from difstar.io._raw import read_raw
from difstar.io._scene import SceneError

# ------------------------------------------------------------------------ model setup

def _nested_tuple(v):
    """Numbers as floats, lists as tuples (3 numbers, or 3 lists of K)."""
    return tuple(_nested_tuple(x) for x in v) if isinstance(v, (list, tuple)) else float(v)


def camera_constants(man):
    c = man.camera
    return CameraConstants(
        focal_length=float(c["focal_length"]),
        principal_separation=float(c["principal_separation"]),
        pupil_magnification=float(c["pupil_magnification"]),
        pixel_pitch=float(c["pixel_pitch"]), pattern=c.get("pattern", "RGGB"),
        wavelengths=_nested_tuple(c["wavelengths"]), n_blades=int(c["blades"]),
        spectral_weights=(None if c.get("spectral_weights") is None
                          else _nested_tuple(c["spectral_weights"])),
        white_balance=tuple(float(w) for w in c["white_balance"]),
        colour_matrix=None if "colour_matrix" not in c else tuple(map(tuple, c["colour_matrix"])),
        zernike_radius=None if "zernike_radius" not in c else float(c["zernike_radius"]),
        pupil=camera_pupil(c, man.path), halos=c["halos"],
    )


def build_model(man, *, crops: dict, base_offsets: dict, exposure_times: dict,
                pattern: str, padding: float | None = None, values: dict | None = None,
                accuracy: float | None = None, joint: bool = False):
    """A FitModel for the manifest: grids from ``choose_grid`` at the parameters' most
    demanding bounds (largest |Δz| and source), ``crops`` per configuration, the
    captures' rough source offsets from their region centres (px) and exposure times.
    ``padding`` (default: the manifest's ``grid.padding``, else 1) sets the PSF engine's
    period; ``accuracy`` (default: the manifest's ``grid.accuracy``) its target, which
    alone (no ``padding`` given here) also chooses the period.

    ``joint``: configurations whose periods ``padding`` sets are planned again on the
    longest of them and given one grid holding what each needs (:func:`difstar._fit_model.
    merged_grid`), so that the fit traces and compiles the chain once for all of them
    (:func:`difstar._fit_model.jointly`); each then costs what the most demanding one costs.
    The fit asks for it; a synthesis keeps each configuration's own grid."""
    import dataclasses

    cc = dataclasses.replace(camera_constants(man), pattern=pattern)
    params = {}
    for name, p in man.parameters.items():
        start = p["start"] if values is None else values[name]
        start = np.broadcast_to(np.asarray(start, float), p["shape"])
        params[name] = Param(start, p["free"], (p["lo"], p["hi"]) if p["free"] else None)
    caps = tuple(
        CaptureSpec(c.name, c.configuration, float(exposure_times[c.name]),
                    tuple(float(v) for v in base_offsets[c.name]))
        for c in man.captures
    )
    # the engine's period: the padding given here, else the one the manifest's accuracy
    # plans, else the manifest's padding (default 1)
    acc = man.grid.get("accuracy") if accuracy is None else accuracy
    if padding is None and acc is None:
        padding = man.grid.get("padding", 1.0)

    def probe_of(name, cfg):
        # the configuration's camera and scene at the values its grid must hold
        crop = tuple(crops[name])
        dummy = ConfigSpec(name, float(cfg["focus_distance"]), float(cfg["object_distance"]),
                           Grid(n=max(crop), crop=crop, raw_only=True))
        probe = FitModel(cc, (dummy,), tuple(c for c in caps if c.config == name), params)
        # the grid must hold the values the solver will try: the starts with 30 % to spare
        # (the bounds would often double the grid, and with it time and memory)
        x = {k: np.asarray(p.value) for k, p in probe.params.items()}
        for key in (f"defocus/{name}", "source_radius", "circumradius"):
            p = probe.params.get(key)
            if p is not None and p.free:
                x[key] = 1.3 * np.abs(p.value) + 0.3 * man.parameters[key]["perturb_scale"]
        # one compiled program instead of dozens of eager operations, each compiled
        camera, scene, _, _ = eqx.filter_jit(lambda x: camera_scene(probe, x, name))(x)
        return dummy, probe, camera, scene

    def grid_of(probed, n=None, oversample=None):
        dummy, probe, camera, scene = probed
        name, crop = dummy.name, dummy.grid.crop
        g = choose_grid(camera, scene, crop=crop, raw_only=True, n=n,
                        oversample=man.grid.get("oversample") if oversample is None
                        else oversample, accuracy=acc, padding=padding)
        plan = g.psf_plan
        dz = probe.params.get(f"defocus/{name}")
        if dz is not None and dz.free and not plan.use_defocus and plan.method != "exact":
            # a free Δz moves from where the plan found its phase negligible: compute it
            plan = dataclasses.replace(plan, use_defocus=True)
        use_dz = plan.use_defocus or (dz is not None and dz.free)
        # the sources' window as the grid sized it, plus the source offsets' bounds
        off = probe.params.get(f"source_offset/{name}")
        reach = 0 if off is None or not off.free else int(np.ceil(np.max(np.abs(
            np.concatenate([off.lo, off.hi])))))
        # difstar.psf's engine on exactly the crop's offsets (padding: the grid's period)
        grid = Grid(n=g.n, oversample=g.oversample, crop=crop, use_defocus=use_dz,
                    raw_only=True, method="engine", source_window=g.source_window + 2 * reach,
                    psf_plan=plan, blur_reach=g.blur_reach)
        return dataclasses.replace(dummy, grid=grid)

    probes = [probe_of(name, cfg) for name, cfg in man.configurations.items()]
    configs = [grid_of(p) for p in probes]
    # one grid for all: only where the padding sets each period (else n is the crop's),
    # and where the configurations have as many captures each (else they are not mapped)
    if (joint and len(configs) > 1 and padding is not None
            and equal_brackets(caps, list(man.configurations))):
        common = joint_grid([c.grid for c in configs])
        if common is not None:
            n, q = common
            again = [grid_of(p, n=n, oversample=q) for p in probes]
            merged = merged_grid([c.grid for c in again])
            if merged is not None:
                configs = [dataclasses.replace(c, grid=merged) for c in again]
    return FitModel(cc, tuple(configs), caps, params)


def load_captures(man):
    """Read each capture's region of interest: ζ, the saturated mask, levels."""
    out = {}
    pattern = None
    for c in man.captures:
        if c.path.is_dir():
            raise SceneError(f"{man.path}: field captures/{c.name}/file: {c.path} is a folder, "
                             "not a RAW file.")
        if not c.path.is_file():
            raise SceneError(f"{man.path}: field captures/{c.name}/file: {c.path} does not "
                             "exist (paths are relative to the manifest's folder).")
        rc = read_raw(c.path)
        fh, fw = rc.shape
        if man.synthetic is not None and tuple(man.synthetic["frame_size"]) != (fh, fw):
            raise SceneError(
                f"{man.path}: field captures/{c.name}/file: {c.path} is {fh} × {fw} pixels, "
                f"not the synthetic.frame_size {man.synthetic['frame_size'][0]} × "
                f"{man.synthetic['frame_size'][1]}; re-run `difstar synth` or fix frame_size."
            )
        r, col = c.source_position
        if not (0 <= r < fh and 0 <= col < fw):
            raise SceneError(
                f"{man.path}: field captures/{c.name}/source_position: {[r, col]} is outside "
                f"the {fh} × {fw} frame of {c.path.name}; give the source's (row, col) in "
                "that frame."
            )
        if pattern is None:
            pattern = rc.pattern
        elif rc.pattern != pattern:
            raise SceneError(f"{c.path}: Bayer layout {rc.pattern} differs from the other "
                             f"captures' {pattern}")
        t = c.exposure_time if c.exposure_time is not None else rc.exposure_time
        if t is None:
            raise SceneError(f"{man.path}: field captures/{c.name}/exposure_time: {c.path} has "
                             "no EXIF ExposureTime; give exposure_time in the manifest")
        if not (math.isfinite(float(t)) and float(t) > 0):
            raise SceneError(f"{man.path}: field captures/{c.name}/exposure_time: {t} (from "
                             f"{c.path.name}) is not a finite time > 0; give exposure_time "
                             "in the manifest")
        try:
            r0, c0 = roi_origin(c.source_position, c.roi_size, rc.shape)
        except ValueError as exc:
            raise SceneError(f"{man.path}: field captures/{c.name}/roi_size: {exc}") from exc
        h, w = c.roi_size
        sl = (slice(r0, r0 + h), slice(c0, c0 + w))
        full = float(rc.white_level - np.mean(rc.black_level))
        out[c.name] = {
            "zeta": rc.cfa[sl], "saturated": rc.saturated[sl], "origin": (r0, c0),
            "base_offset": (c.source_position[0] - (r0 + h // 2),
                            c.source_position[1] - (c0 + w // 2)),
            "exposure_time": float(t), "full_scale_dn": full, "crop": (h, w),
        }
    return out, pattern


def prepare(man):
    """The manifest's captures read (:func:`load_captures`) and its :class:`FitModel`
    built for them (:func:`build_model`): returns (model, captures)."""
    caps, pattern = load_captures(man)
    crops = {}
    for c in man.captures:
        crops[c.configuration] = caps[c.name]["crop"]
    model = build_model(
        man, crops=crops, base_offsets={k: v["base_offset"] for k, v in caps.items()},
        exposure_times={k: v["exposure_time"] for k, v in caps.items()}, pattern=pattern,
        joint=True,
    )
    return model, caps


# ------------------------------------------------------------------------------ fit

def photometric_start(fitter, caps, u0):
    """``u0`` with a free φ0 set, per channel, so that the model's linear image at ``u0``
    carries the light of the unsaturated pixels in the linear range (ζ < 0.7) of the
    data: φ0 = Σ C·t / Σ ζ over those pixels. The exposure scale's start then no longer
    depends on the camera's units (a wrong start by orders of magnitude saturates or
    blanks the whole prediction, where the solver cannot move it); left alone when φ0
    is fixed."""
    model = fitter.model
    spec = model.params.get("phi0")
    if spec is None or not spec.free:
        return u0
    x = fitter.values(u0)
    # the Fitter's compiled prediction (the restarts and the outputs use it again)
    pred = fitter.linear_images(u0)
    num = np.zeros(3)
    den = np.zeros(3)
    for cfg in model.configs:
        caps_c = model.captures_of(cfg.name)
        img = np.asarray(pred[cfg.name])  # (K, 3, h, w)
        masks = bayer_masks_np(img.shape[-2:], model.camera.pattern).astype(bool)  # (3, h, w)
        for k, c in enumerate(caps_c):
            z = np.asarray(caps[c.name]["zeta"])
            ok = ~np.asarray(caps[c.name]["saturated"]) & (z < 0.7)
            t = c.exposure_time
            for ch in range(3):
                m = masks[ch] & ok
                num[ch] += np.sum(img[k, ch][m]) * t
                den[ch] += np.sum(z[m])
    phi0 = np.where((num > 0) & (den > 0), num / np.maximum(den, 1e-300), x["phi0"])
    phi0 = np.clip(phi0, spec.lo * (1 + 1e-6), spec.hi * (1 - 1e-6))
    values = {k: x[k] for k in model.free} | {"phi0": phi0}
    return to_unconstrained(model, values)


def exposure_range(fitter, model, u, caps) -> tuple[float, float]:
    """Physical exposures H = C·t covered by the captures' pixels (min > 0, max)."""
    pred = fitter.predict(u, full=True)
    los, his = [], []
    for cfg in model.configs:
        p = pred[cfg.name]
        img = np.asarray(p.image)  # (K, 3, h, w)
        ts = np.asarray([c.exposure_time for c in model.captures_of(cfg.name)])
        h = img * ts[:, None, None, None]
        los.append(h[h > 0].min())
        his.append(h.max())
    return float(min(los)), float(max(his))


def fit_manifest(man, *, u0=None, verbose: bool = True, model=None, caps=None, fitter=None,
                 devices=None):
    """Fit once. Returns (result document, model, caps, fitter, u). ``devices``: share
    the Jacobian's columns out over that many devices (``Fitter(devices=)``)."""
    import jax

    t_all = time.perf_counter()
    if model is None:
        model, caps = prepare(man)
    procedure = procedure_of(model, man.solver, str(man.path))  # checked before compiling
    if fitter is None:
        fitter = Fitter(model, method=man.solver["method"], rtol=man.solver["rtol"],
                        atol=man.solver["atol"], devices=devices)
    if u0 is None:
        u0 = to_unconstrained(model)
    # the solver's step compiles on a second thread while the photometric start compiles
    # and runs the forward model (the step's compile is most of the first step's wait)
    fitter.compile_ahead(u0, make_args(model, observed_data(model, caps, man.noise), u0))
    u0 = photometric_start(fitter, caps, u0)
    if verbose:
        _log(f"difstar fit: {len(model.captures)} captures, {model.n_free} free parameters, "
             "grids " + "; ".join(f"{c.name}: {c.grid.describe()}" for c in model.configs))
    solved, stages, args = run_stages(fitter, model, caps, man.noise, u0, man.solver,
                                      procedure=procedure, verbose=verbose)
    u = solved.u
    t0 = time.perf_counter()
    if not np.all(np.asarray(args["active"]) == 1):
        # a written procedure's last solve held some parameters: the standard errors are
        # every free parameter's, from a Jacobian of them all at the answer
        args, solved = make_args(model, args["data"], u), None
    cov, se, diag = fitter.covariance(u, args, solved)
    t_cov = time.perf_counter() - t0
    x = fitter.values(u)
    params = {}
    for name, p in model.params.items():
        d = {"value": x[name].tolist(), "free": p.free, "start": np.asarray(p.value).tolist()}
        if p.free:
            d["stderr"] = se[name].tolist()
            d["bounds"] = [np.asarray(p.lo).tolist(), np.asarray(p.hi).tolist()]
            at = (np.isclose(x[name], p.lo, rtol=1e-4, atol=0)
                  | np.isclose(x[name], p.hi, rtol=1e-4, atol=0))
            d["at_bound"] = bool(np.any(at))
        params[name] = d
    n = model.camera.n_blades
    period = 2 * math.pi / n
    derived = {
        "rotation_mod_symmetry_deg": float(np.rad2deg(float(x["rotation"]) % period)),
        "circumradius_mm": float(x["circumradius"]) * 1e3,
        "entrance_f_number": model.camera.focal_length * model.camera.pupil_magnification
        / (2 * float(x["circumradius"])),
    }
    result = {
        "schema": "difstar-fit-result/1", "manifest": str(man.path), "name": man.name,
        "parameters": params, "derived": derived,
        "convergence": {"solver": {"lm": "optimistix.LevenbergMarquardt",
                                   "gn": "optimistix.GaussNewton"}[fitter.method],
                        "stages": stages, **diag},
        "timing_s": {"total": time.perf_counter() - t_all, "covariance": t_cov,
                     "first_step_since_start": FIRST_STEP.get("first_step"),
                     "solve": sum(s.get("seconds", 0.0) for s in stages),
                     "compile": sum(s.get("compile_seconds", 0.0) for s in stages)},
        "jax": {"version": jax.__version__, "backend": jax.default_backend(),
                "x64": bool(jax.config.jax_enable_x64)},
    }
    if man.truth is not None:
        h_range = exposure_range(fitter, model, u, caps)
        result["truth_comparison"] = compare_truth(model, x, man.truth, h_range, se)
    return result, model, caps, fitter, u


# ------------------------------------------------------------------------ synth

#: The PSF engine's accuracy for synthetic captures (its default, tighter than a fit's
#: grid default of 1e-2): the truth a recovery study is measured against is simulated
#: with sub-cells finer than the fit's, on its own ``synthetic.padding`` period.
SYNTH_ACCURACY = 1e-3


def synthesize(man, out_dir: Path, *, overwrite: bool = False) -> list[Path]:
    """Simulate the manifest's captures from ``synthetic.truth`` on full frames and
    write them as DNGs into ``out_dir`` (whole or not at all). ``out_dir`` is checked
    before the computation (output policy of :mod:`difstar.io._output`; it may replace a
    folder holding exactly these captures), and never replaces the manifest."""
    syn = man.synthetic
    fh, fw = syn["frame_size"]
    pattern = man.camera.get("pattern", "RGGB")
    written = []
    with output_dir(out_dir, overwrite=overwrite, inputs=[man.path],
                    replaceable=synth_replaceable(man), command="synth") as tmp:
        model = build_model(
            man, crops={k: (fh, fw) for k in man.configurations},
            base_offsets={c.name: (c.source_position[0] - fh // 2,
                                   c.source_position[1] - fw // 2) for c in man.captures},
            exposure_times={c.name: c.exposure_time for c in man.captures}, pattern=pattern,
            padding=syn["padding"], values=syn["truth"], accuracy=SYNTH_ACCURACY,
        )
        model = model.fixed_at(syn["truth"])
        _log("difstar synth: grids " + "; ".join(f"{c.name}: {c.grid.describe()}"
                                                 for c in model.configs))
        pred = Fitter(model).predict(to_unconstrained(model))
        rng = np.random.default_rng(int(syn["seed"]))
        black, white = float(syn["black_level"]), int(syn["white_level"])
        r = float(syn["truth"]["circumradius"])
        f_number = man.camera["focal_length"] * man.camera["pupil_magnification"] / (2 * r)
        for cfg in model.configs:
            for i, c in enumerate(model.captures_of(cfg.name)):
                entry = next(e for e in man.captures if e.name == c.name)
                z = np.asarray(pred[cfg.name][i])
                if not np.all(np.isfinite(z)):
                    raise RuntimeError(f"synthesized capture {c.name} holds NaN or infinity")
                z = np.clip(z, 0.0, None)
                raw = synthesize_capture(
                    z, black_level=black, white_level=white,
                    gain_e_per_dn=man.noise["gain_e_per_dn"],
                    read_noise_dn=man.noise["read_noise_dn"], rng=rng)
                write_dng(tmp / entry.path.name, raw, pattern=pattern, black_level=black,
                          white_level=white, exposure_time=c.exposure_time, f_number=f_number,
                          focal_length=man.camera["focal_length"],
                          camera_white_balance=man.camera["white_balance"])
                written.append(Path(out_dir) / entry.path.name)
                _log(f"difstar synth: {entry.path.name}: t = {c.exposure_time:g} s, "
                     f"saturated {np.mean(raw >= white) * 100:.2f} %")
    return written


def synth_replaceable(man):
    """What ``synth --overwrite`` may replace in a folder without difstar's marker: a
    DNG that difstar wrote, under the name of one of the manifest's captures (never a
    camera's own RAW file, nor any other file)."""
    names = {c.path.name for c in man.captures}
    return lambda p: p.name in names and written_by_difstar(p)
