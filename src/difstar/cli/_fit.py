"""``difstar synth`` and ``difstar fit``: synthetic DNG captures and inverse characterization.

    difstar synth fit/CAMPAIGN/manifest.json [--overwrite]
        simulate the manifest's captures from its ``synthetic.truth`` and write them as
        DNG files (Poisson–Gaussian noise, clipped at the white level) that rawpy reads.
    difstar fit fit/CAMPAIGN/manifest.json [--out DIR] [--overwrite]
        fit the free parameters to the RAW captures; writes fit_result.json, predicted /
        observed / residual maps, Fig. 5-style profiles and a Table 1-style MSE/SSIM table.
    difstar fit fit/CAMPAIGN/manifest.json --recovery-study 10 [--seed S]
        (manifests with a ``synthetic`` block) fit from 10 starts perturbed by up to 20 %
        on every free parameter and tabulate the errors against the truth.
    difstar fit fit/STAR/manifest.json [--out DIR] [--overwrite] [--max-steps N]
        an image-fit manifest (a star's intensity image: FITS, TIFF, PNG, NumPy) is fitted
        by the same command, through :func:`difstar.fitting.run_fit_image` (what
        ``difstar fit-image`` runs, which adds its studies: rough starts, fainter copies).

The command line only: it parses, calls :mod:`difstar._fit_run` (the fit) or
:mod:`difstar._fit_recovery` (the recovery study) and writes the results and figures.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from difstar._fit_recovery import recovery_study, study_table
from difstar._fit_run import _log, fit_manifest, synth_replaceable, synthesize

# ------------------------------------------------------------------------- outputs

def _capture_figure(plt, shown):
    """A capture's figure: observed and predicted ζ (log10) and the residual in σ,
    saturated pixels blank; (figure, its three images) for ``set_data``."""
    fig, ax = plt.subplots(1, 3, figsize=(12, 4))
    titles = ("observed ζ (log10)", "predicted ζ (log10)",
              "residual (pred − obs)/σ, saturated blank")
    limits = ((-4, 0, "magma"), (-4, 0, "magma"), (-5, 5, "RdBu_r"))
    images = []
    for a, im, title, (lo, hi, cmap) in zip(ax, shown, titles, limits):
        images.append(a.imshow(im, vmin=lo, vmax=hi, cmap=cmap))
        a.set_title(title)
        fig.colorbar(images[-1], ax=a, fraction=0.046)
        a.set_xticks([])
        a.set_yticks([])
    # fixed margins (no ticks to make room for): tight_layout measured every colorbar's
    # labels, a second per fit
    fig.subplots_adjust(left=0.01, right=0.96, bottom=0.03, top=0.86, wspace=0.25)
    return fig, images


def write_outputs(tmp: Path, result: dict, model, caps, fitter, u, noise) -> list[str]:
    import jax
    import jax.numpy as jnp
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from difstar._demosaic import demosaic
    from difstar._fit import noise_sigma
    from difstar._metrics import compare_raw, profile_circle, profile_line
    from difstar.io._image_files import write_png_srgb
    from difstar.io._output import write_json

    written = ["fit_result.json"]
    panels = None
    # one program for every configuration's capture, not its operations one by one
    demosaic_once = jax.jit(demosaic, static_argnames=("pattern", "method"))
    pred = fitter.predict(u, full=True)
    cc = model.camera
    rows = []
    for cfg in model.configs:
        p = pred[cfg.name]
        cfa = np.asarray(p.cfa)  # NumPy: eager slices of it would each compile
        for i, c in enumerate(model.captures_of(cfg.name)):
            obs = caps[c.name]["zeta"]
            sat = caps[c.name]["saturated"]
            pc = cfa[i]
            sig = noise_sigma(pc, gain_e_per_dn=noise["gain_e_per_dn"],
                              read_noise_dn=noise["read_noise_dn"],
                              full_scale_dn=caps[c.name]["full_scale_dn"], xp=np)
            shown = (np.log10(np.clip(obs, 1e-4, 1)), np.log10(np.clip(pc, 1e-4, 1)),
                     np.where(sat, np.nan, (pc - obs) / sig))
            if panels is None:  # one figure for every capture: only its pixels change
                panels = _capture_figure(plt, shown)
            fig, images = panels
            for im, a in zip(images, shown):
                im.set_data(a)
            fig.suptitle(f"{c.name}: t = {c.exposure_time:g} s")
            fig.savefig(tmp / f"capture_{c.name}.png", dpi=80)
            written.append(f"capture_{c.name}.png")
            s_pred, s_obs, t1 = compare_raw(
                pc, obs, pattern=cc.pattern, white_balance=tuple(cc.white_balance),
                matrix=tuple(map(tuple, np.eye(3) if cc.colour_matrix is None
                                 else np.asarray(cc.colour_matrix, float))))
            row = {"capture": c.name, "configuration": cfg.name,
                   "exposure_time_s": c.exposure_time}
            for ch, d in t1.items():
                row[ch] = {"MSE": float(d["MSE"]), "SSIM": float(d["SSIM"])}
            rows.append(row)
            if i == len(model.captures_of(cfg.name)) - 1:
                write_png_srgb(tmp / f"srgb_pred_{c.name}.png", s_pred)
                write_png_srgb(tmp / f"srgb_obs_{c.name}.png", s_obs)
                written += [f"srgb_pred_{c.name}.png", f"srgb_obs_{c.name}.png"]
        # Fig. 5-style profiles on the brightest capture that is not saturated at the
        # profile radius: per channel, model lines, observation dots
        capl = model.captures_of(cfg.name)
        pz_all = np.asarray(p.zeta)
        h, w = pz_all.shape[-2:]
        i = 0
        for j, cj in enumerate(capl):  # the longest exposure unsaturated on the circle
            ring = np.asarray(profile_circle(jnp.asarray(pz_all[j]),
                                             (h // 2 + cj.base_offset[0],
                                              w // 2 + cj.base_offset[1]), 0.335 * w / 2, 90))
            if ring.max() < 0.95 and cj.exposure_time >= capl[i].exposure_time:
                i = j
        c = capl[i]
        obs_rgb = np.asarray(demosaic_once(jnp.asarray(caps[c.name]["zeta"]), cc.pattern,
                                           method="bilinear"))
        pz = pz_all[i]
        h, w = pz.shape[-2:]
        r0 = h // 2 + c.base_offset[0]
        c0 = w // 2 + c.base_offset[1]
        rad = 0.335 * (w / 2)
        fig, ax = plt.subplots(1, 3, figsize=(14, 3.8))
        specs = [
            ("circle r = 0.335 u_max", lambda im: profile_circle(im, (r0, c0), rad, 720),
             np.arange(720) / 2.0, "angle (deg)"),
            ("row 0.35 v_max from top", lambda im: profile_line(im, 0.35 * h / 2, 0, w - 1, w),
             np.arange(w), "column (px)"),
            ("row v_max from top (centre)", lambda im: profile_line(im, h / 2, 0, w - 1, w),
             np.arange(w), "column (px)"),
        ]
        for a, (title, f, xs, xl) in zip(ax, specs):
            po = np.asarray(f(jnp.asarray(obs_rgb)))
            pp = np.asarray(f(jnp.asarray(pz)))
            for ch, col in enumerate(("tab:red", "tab:green", "tab:blue")):
                a.plot(xs, pp[ch], color=col, lw=1)
                a.plot(xs, po[ch], ".", color=col, ms=2)
            a.set_title(title)
            a.set_xlabel(xl)
            a.set_ylabel("ζ")
        fig.suptitle(f"{cfg.name}: {c.name} (lines: model, dots: capture)")
        fig.tight_layout()
        fig.savefig(tmp / f"profiles_{cfg.name}.png", dpi=80)
        plt.close(fig)
        written.append(f"profiles_{cfg.name}.png")
    if panels is not None:
        plt.close(panels[0])
    result["table1"] = rows
    lines = ["| capture | t (s) | " + " | ".join(f"{ch} MSE | {ch} SSIM" for ch in
                                                 ("R", "G", "B", "B/W")) + " |",
             "|---|---|" + "---|" * 8]
    for r in rows:
        lines.append(f"| {r['capture']} | {r['exposure_time_s']:g} | " + " | ".join(
            f"{r[ch]['MSE']:.2e} | {r[ch]['SSIM']:.4f}" for ch in ("R", "G", "B", "B/W")) + " |")
    (tmp / "table1.md").write_text(
        "MSE and SSIM of the rendered sRGB images, prediction against capture (style of "
        "the paper's Table 1)\n\n" + "\n".join(lines) + "\n")
    written.append("table1.md")
    write_json(tmp / "fit_result.json", result)
    return written


# --------------------------------------------------------------------------- commands

def _enable_x64():
    import jax

    jax.config.update("jax_enable_x64", True)


def _cmd_synth(a) -> int:
    from difstar.io._manifest import load_manifest
    from difstar.io._output import check_output_free
    from difstar.io._scene import SceneError

    _enable_x64()
    man = load_manifest(a.manifest)
    if man.synthetic is None:
        raise SceneError(f"{man.path}: field synthetic: missing; `difstar synth` needs the "
                         "true parameters (synthetic.truth) and the frame size")
    folders = {c.path.parent.resolve() for c in man.captures}
    if len(folders) != 1:
        raise SceneError(f"{man.path}: field captures: `difstar synth` writes all captures "
                         f"into one folder; these name {len(folders)}")
    missing_t = [c.name for c in man.captures if c.exposure_time is None]
    if missing_t:
        raise SceneError(f"{man.path}: field captures: synthetic captures need exposure_time "
                         f"(missing for {missing_t})")
    out = Path(a.out) if a.out else folders.pop()
    check_output_free(out, overwrite=a.overwrite, inputs=[man.path, *man.bases],
                      replaceable=synth_replaceable(man))
    synthesize(man, out, overwrite=a.overwrite)
    _log(f"difstar synth: wrote {len(man.captures)} DNG files to {out}/")
    return 0


def _cmd_fit_image_manifest(a) -> int:
    """``difstar fit`` given an image-fit manifest: the image fitter, its result in
    ``--out`` (default ``<manifest folder>/result``)."""
    from difstar.fitting._params import FitInputError
    from difstar.fitting._run import run as run_fit_image
    from difstar.io._scene import SceneError

    if a.recovery_study or getattr(a, "devices", None) is not None:
        raise SceneError(f"{a.manifest}: --recovery-study and --devices are for RAW "
                         "manifests; for an image fit's rough starts use difstar fit-image "
                         "--robustness N.")
    out = Path(a.out) if a.out else Path(a.manifest).parent / "result"
    try:
        run_fit_image(a.manifest, out, verbose=not a.quiet, max_steps=a.max_steps,
                      overwrite=a.overwrite)
    except FitInputError as e:
        raise ValueError(f"difstar fit: {e}") from None
    return 0


def _cmd_fit(a) -> int:
    from difstar._batch import ENV_DEVICES
    from difstar.io._manifest import load_manifest, manifest_kind

    if manifest_kind(a.manifest) == "image":
        return _cmd_fit_image_manifest(a)
    from difstar.io._output import check_output_free, output_dir, write_json
    from difstar.io._scene import SceneError

    _enable_x64()
    devices = None
    if not a.recovery_study and (getattr(a, "devices", None) is not None
                                 or os.environ.get(ENV_DEVICES, "").strip()):
        from difstar._batch import device_count
        from difstar._distributed import init_distributed

        init_distributed()
        devices = device_count(a.devices)  # a single fit: its Jacobian's columns shared out
    man = load_manifest(a.manifest)
    if a.max_steps is not None:
        man.solver["max_steps"] = a.max_steps
    inputs = [man.path, *man.bases] + [c.path for c in man.captures]
    if a.recovery_study:
        if man.truth is None:
            raise SceneError(f"{man.path}: field truth: --recovery-study needs the true values "
                             "(a `synthetic` block, or `truth` for captures made elsewhere)")
        out = Path(a.out) if a.out else man.folder / "recovery"
        check_output_free(out, overwrite=a.overwrite, inputs=inputs)
        with output_dir(out, overwrite=a.overwrite, inputs=inputs, command="fit") as tmp:
            study = recovery_study(man, a.recovery_study, a.seed, devices=a.devices,
                                   verbose=not a.quiet)
            table = study_table(study)
            write_json(tmp / "recovery.json", study)
            (tmp / "recovery.md").write_text(table + "\n")
        if not a.quiet:
            print(table)
        return 0 if study["n_pass"] >= math.ceil(0.9 * a.recovery_study) else 1
    out = Path(a.out) if a.out else man.folder / "result"
    check_output_free(out, overwrite=a.overwrite, inputs=inputs)
    with output_dir(out, overwrite=a.overwrite, inputs=inputs, command="fit") as tmp:
        result, model, caps, fitter, u = fit_manifest(man, devices=devices,
                                                      verbose=not a.quiet)
        if not math.isfinite(result["convergence"].get("reduced_chi2", 0.0)):
            raise RuntimeError("the fit's χ² is NaN or infinite; nothing was written")
        files = write_outputs(tmp, result, model, caps, fitter, u, man.noise)
    if not a.quiet:
        _print_summary(result)
        _log(f"difstar fit: wrote {out}/ ({', '.join(files[:4])}, ...)")
    return 0


def _print_summary(result: dict) -> None:
    print(f"{'parameter':<26} {'value':>40} {'std. error':>34}")
    for k, v in result["parameters"].items():
        if not v["free"]:
            continue
        val = np.atleast_1d(v["value"])
        se = np.atleast_1d(v["stderr"])
        print(f"{k:<26} {' '.join(f'{x:.6g}' for x in val):>40} "
              f"{' '.join(f'{x:.2g}' for x in se):>34}" + ("  AT BOUND" if v["at_bound"] else ""))
    c = result["convergence"]
    print(f"χ² / dof = {c['reduced_chi2']:.4f} ({c['n_residuals']} pixels, {c['n_free']} free); "
          f"total {result['timing_s']['total']:.1f} s "
          f"(compile {result['timing_s']['compile']:.1f} s)")
    if "truth_comparison" in result:
        print("against the truth: " + ("all criteria pass" if
                                       result["truth_comparison"]["all_pass"] else "FAIL"))


def register(subparsers, name: str) -> None:
    from ._args import nonnegative_int, positive_int

    if name == "synth":
        p = subparsers.add_parser("synth", help="write synthetic DNG captures for a fit manifest")
        p.add_argument("manifest", help="fit manifest JSON with a `synthetic` block")
        p.add_argument("--out", help="folder for the DNGs (default: the captures' folder)")
        p.add_argument("--overwrite", action="store_true",
                       help="replace the folder if difstar made it or it holds only the "
                       "manifest's captures (never the manifest itself)")
        p.set_defaults(func=_cmd_synth)
    elif name == "fit":
        p = subparsers.add_parser("fit", help="fit a camera to RAW captures, or a PSF model to "
                                  "a star image (by the manifest's kind)")
        p.add_argument("manifest", help="fit manifest JSON: RAW captures (data_schemas/"
                       "fit_manifest.schema.json) or a star image (image_fit_manifest"
                       ".schema.json)")
        p.add_argument("--out", help="output folder (default: <manifest folder>/result, or "
                                     "/recovery with --recovery-study)")
        p.add_argument("--overwrite", action="store_true",
                       help="replace --out if it is a folder difstar made (never one holding "
                       "other files or an input)")
        p.add_argument("--max-steps", type=positive_int,
                       help="solver steps per stage, >= 1 (default: the manifest's "
                       "solver.max_steps, else 100)")
        p.add_argument("--recovery-study", type=nonnegative_int, metavar="N", default=0,
                       help="fit from N starts perturbed by up to 20 %% (needs `synthetic`; "
                       "0: a single fit)")
        p.add_argument("--seed", type=nonnegative_int, default=0,
                       help="seed of the recovery study")
        p.add_argument("--devices", metavar="N",
                       help="with --recovery-study: run the fits together, sharded over N "
                       "devices; for a single fit: share its Jacobian's columns out over N "
                       "devices (default: $DIFSTAR_DEVICES; unset: one device); see "
                       "docs/sharding.md")
        p.add_argument("--quiet", action="store_true",
                       help="no progress (stderr) or summary (stdout): only errors; the "
                       "results are written as without it")
        p.set_defaults(func=_cmd_fit)
    else:
        raise ValueError(f"difstar.cli._fit.register: unknown command {name!r}")
