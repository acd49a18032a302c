"""The ``difstar`` command line (outer layer: files, progress, exit codes).

    difstar predict SCENE.json --out DIR      predict RAW + sRGB for a scene file
    difstar predict --example paper-focused --out DIR
    difstar example NAME [--crop H W]         print a built-in scene as JSON
    difstar synth ... / difstar fit ...       synthetic captures and fitting
    difstar fit-image MANIFEST --out DIR      fit a PSF model to a star image
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

EXAMPLES = ("paper-focused", "paper-defocused")


def _log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def example_document(name: str, *, crop=None) -> dict:
    import difstar
    from difstar._examples import PAPER
    from difstar._validate import InputError, check_crop
    from difstar.io._scene import scene_to_dict

    if name not in EXAMPLES:
        raise InputError(f"unknown example {name!r}; choose one of {', '.join(EXAMPLES)}.")
    if crop is not None:
        crop = check_crop(crop, "--crop")
    config = name.split("-", 1)[1]
    camera, scene = difstar.paper_camera(config)
    crop = list(PAPER["crop"]) if crop is None else list(crop)
    return scene_to_dict(camera, scene, {"crop": crop}, name=name)


def run_predict(doc: dict, *, source: str, out: Path, overwrite: bool, crop=None,
                inputs=(), devices=None) -> dict:
    """Predict one scene document and write the outputs to ``out`` (whole or not at all).

    Everything the user gave is checked before anything is computed: the scene (finite,
    in range, physically consistent), the grid (it must fit in memory) and the output
    folder (difstar's own or new, never an input); the computation runs inside the
    output's temporary folder, which any failure removes."""
    import equinox as eqx
    import jax
    import numpy as np

    import difstar
    from difstar._sampling import choose_grid
    from difstar._validate import check_crop
    from difstar.io._image_files import write_png_srgb, write_raw_dng, write_tiff_srgb16
    from difstar.io._output import check_output_free, output_dir, write_json
    from difstar.io._scene import scene_from_dict

    check_output_free(out, overwrite=overwrite, inputs=inputs)
    camera, scene, gopt = scene_from_dict(doc, source=source)
    if crop is not None:
        gopt["crop"] = list(check_crop(crop, "--crop"))
    crop_t = tuple(gopt.get("crop", (512, 512)))
    grid = choose_grid(
        camera, scene, crop=crop_t, padding=gopt.get("padding"), n=gopt.get("n"),
        oversample=gopt.get("oversample"), raw_only=gopt.get("raw_only", False),
        scaling=gopt.get("scaling", "fresnel"), accuracy=gopt.get("accuracy"),
        method=gopt.get("method"),
    )
    difstar.check_sampling(camera, scene, grid)
    _log(f"difstar: {grid.describe()}")
    with output_dir(out, overwrite=overwrite, inputs=inputs, command="predict") as tmp:
        spectral = camera.sensor.spectral_weights is not None
        if spectral and (devices is not None or os.environ.get("DIFSTAR_DEVICES", "").strip()):
            # the wavelengths sharded over devices (docs/sharding.md)
            from difstar._batch import simulate_spectral

            k = camera.sensor.wavelengths.shape[1]
            _log(f"difstar: {k} wavelengths per channel, sharded over the devices ...")
            t0 = time.perf_counter()
            pred = simulate_spectral(camera, scene, grid, devices=devices, progress=lambda d, n, s:
                                     _log(f"difstar: wavelengths {d}/{n} done ({s:.1f} s)"))
            t_compile, t_run = 0.0, time.perf_counter() - t0
            _log(f"difstar: compiled and ran in {t_run:.2f} s")
        else:
            if devices is not None:
                _log("difstar: --devices: one wavelength per channel (not spectral); "
                     "nothing to shard, running on one device (a spectral scene gives "
                     "camera/sensor/wavelengths as 3 lists of K)")
            run = eqx.filter_jit(difstar.simulate)
            t0 = time.perf_counter()
            _log("difstar: compiling the chain ...")
            compiled = run.lower(camera, scene, grid).compile()
            t_compile = time.perf_counter() - t0
            _log(f"difstar: compiled in {t_compile:.1f} s; running ...")
            t0 = time.perf_counter()
            pred = jax.block_until_ready(compiled(camera, scene, grid))
            t_run = time.perf_counter() - t0
            _log(f"difstar: ran in {t_run:.2f} s")
        for name in ("psf", "cfa", "srgb"):
            a = getattr(pred, name)
            if a is not None and not np.all(np.isfinite(np.asarray(a))):
                raise InternalError(
                    f"the predicted {name} contains NaN or infinity although the scene "
                    "passed validation; nothing was written (please report this scene)."
                )
        g = pred.geometry
        derived = {
            "source": source,
            "geometry": {
                "lens_extension_m": float(g.extension),
                "s_prime_m": float(g.s_prime),
                "object_to_front_principal_plane_m": float(g.s_object),
                "image_distance_from_rear_principal_plane_m": float(g.s_image),
                "exit_pupil_to_sensor_m": float(g.z_exit_pupil),
                "exit_pupil_to_in_focus_image_m": float(g.z_in_focus),
                "defocus_m": float(g.defocus),
                "magnification": float(g.magnification),
                "working_f_number": float(g.working_f_number),
            },
            "grid": {
                "method": grid.method, "source_window": grid.source_window,
                "n": grid.n, "oversample": grid.oversample, "crop": list(grid.crop),
                "pixel_pitch_m": camera.sensor.pixel_pitch,
                "grid_pitch_m": camera.sensor.pixel_pitch / grid.oversample,
                "field_m": grid.n * camera.sensor.pixel_pitch,
                "defocus_phase": grid.use_defocus, "scaling": grid.scaling,
            },
            "timing_s": {"compile": t_compile, "run": t_run},
            "summary": {
                "saturated_fraction": float(np.mean(np.asarray(pred.cfa) > 0.999)),
                "psf_peak": [float(x) for x in np.asarray(pred.psf).max(axis=(1, 2))],
            },
            "jax": {"version": jax.__version__, "backend": jax.default_backend(),
                    "x64": bool(jax.config.jax_enable_x64)},
        }
        sen = camera.sensor
        if pred.srgb is not None:
            write_png_srgb(tmp / "srgb.png", pred.srgb)
            write_tiff_srgb16(tmp / "srgb16.tif", pred.srgb)
        write_raw_dng(tmp / "raw.dng", pred.cfa, pattern=sen.pattern,
                      white_balance=np.asarray(sen.white_balance),
                      colour_matrix=np.asarray(sen.colour_matrix),
                      exposure_time=float(scene.exposure_time),
                      focal_length=float(camera.lens.focal_length))
        write_psf_png(tmp / "psf_log.png", np.asarray(pred.psf))
        write_json(tmp / "scene.json", doc)
        write_json(tmp / "derived.json", derived)
        written = sorted(p.name for p in tmp.iterdir() if not p.name.startswith("."))
    if min(grid.crop) < 22:
        _log(f"difstar: note: raw.dng is {grid.crop[0]} × {grid.crop[1]} pixels; LibRaw "
             "(rawpy, darktable, RawTherapee) opens only 22 × 22 and larger")
    _log(f"difstar: wrote {out}/ ({', '.join(written)})")
    return derived


class InternalError(RuntimeError):
    """A failure that is difstar's, not the user's (exit status 1)."""


def write_psf_png(path, psf) -> None:
    """The three channels' PSFs as a figure: log10 of the fraction of the channel's power
    per pixel (the PSF sums to 1 over the plane), one panel per channel on one colour
    scale from 10⁻⁷ × the highest peak to that peak, with a colour bar; axes in pixels
    from the crop's centre (the optical axis)."""
    import numpy as np
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    psf = np.asarray(psf, float)
    hi = float(np.log10(psf.max())) if psf.max() > 0 else 0.0
    lo = hi - 7.0
    logp = np.log10(np.clip(psf, 10.0**lo, None))
    h, w = psf.shape[-2:]
    # pixel i of the crop sits i − size//2 pixels from the axis (the crop is centred)
    extent = (-(w // 2) - 0.5, w - w // 2 - 0.5, h - h // 2 - 0.5, -(h // 2) - 0.5)
    fig = Figure(figsize=(13.0, 4.4), dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, 3, sharey=True)
    for ax, c, name in zip(axes, logp, ("R", "G", "B")):
        im = ax.imshow(c, cmap="magma", vmin=lo, vmax=hi, extent=extent,
                       interpolation="antialiased")
        ax.set_title(f"{name} channel PSF")
        ax.set_xlabel("x (pixels from the axis)")
    axes[0].set_ylabel("y (pixels from the axis, downwards)")
    bar = fig.colorbar(im, ax=list(axes), shrink=0.9)
    bar.set_label("log10(fraction of the channel's power per pixel)")
    fig.savefig(path, format="png")


def _cmd_predict(a) -> int:
    from difstar._validate import InputError, check_crop
    from difstar.io._output import check_output_free
    from difstar.io._scene import read_json

    if (a.scene is None) == (a.example is None):
        raise InputError("difstar predict: give a scene file or --example NAME (one of them).")
    crop = None if a.crop is None else check_crop(a.crop, "--crop")
    inputs = [a.scene] if a.scene else []
    out = Path(a.out)
    devices = None
    if a.devices is not None or os.environ.get("DIFSTAR_DEVICES", "").strip():
        # first of all: the job is joined before anything touches a device (the example
        # and the scene below build JAX arrays), as jax.distributed requires
        from difstar._distributed import init_distributed

        init_distributed()
    if a.example:
        doc = example_document(a.example)
        source = f"example:{a.example}"
    else:
        doc = read_json(a.scene, what="scene file")
        source = str(a.scene)
    check_output_free(out, overwrite=a.overwrite, inputs=inputs)
    if a.devices is not None:
        from difstar._batch import device_count

        devices = device_count(a.devices)
    run_predict(doc, source=source, out=out, overwrite=a.overwrite, crop=crop, inputs=inputs,
                devices=devices)
    return 0


def _cmd_example(a) -> int:
    from difstar.io._output import write_file_atomic

    doc = example_document(a.name, crop=a.crop)
    text = json.dumps(doc, indent=2) + "\n"
    if a.out:
        write_file_atomic(a.out, text, overwrite=a.overwrite)
    else:
        sys.stdout.write(text)
    return 0


class _Formatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Help that gives every default (unless the text already says it, or the option is
    a switch or has none), descriptions as written."""

    def _get_help_string(self, action):
        h = action.help or ""
        if "default" in h or action.default is None or isinstance(action.default, bool):
            return h
        return super()._get_help_string(action)


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("difstar")
    except PackageNotFoundError:  # run from a source tree that was never installed
        return "(not installed)"


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="difstar", description=__doc__.split("\n\n")[0], formatter_class=_Formatter,
        epilog="Exit status: 0 success; 2 a user error (one line naming the field and the "
        "fix); 1 an internal failure; 130/143 interrupted (nothing is left behind).")
    ap.add_argument("--x64", action="store_true", help="compute in float64 (else float32)")
    ap.add_argument("--version", action="version", version=f"difstar {_version()}")
    sub = ap.add_subparsers(dest="command", required=True)

    p = sub.add_parser("predict", help="predict RAW mosaic (DNG) + sRGB image for a scene",
                       formatter_class=_Formatter)
    p.add_argument("scene", nargs="?", help="scene JSON (data_schemas/scene.schema.json)")
    p.add_argument("--example", choices=EXAMPLES, help="use a built-in scene instead of a file")
    p.add_argument("--out", required=True,
                   help="output folder, created by difstar (written whole or not at all)")
    p.add_argument("--crop", nargs=2, type=int, metavar=("H", "W"),
                   help="output size in pixels, even, at least 8 (default: the scene's "
                   "grid.crop, else 512 512)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace --out if it is a folder difstar made (its .difstar-output "
                   "marker lists every file in it); never a folder with other files, never "
                   "an input")
    p.add_argument("--devices", metavar="N",
                   help="spectral scenes (camera/sensor/wavelengths as 3 lists of K, "
                   "with spectral_weights): shard the wavelengths over N devices (default: "
                   "$DIFSTAR_DEVICES, else one device); see docs/sharding.md")
    p.set_defaults(func=_cmd_predict)

    p = sub.add_parser("example", help="print a built-in scene as JSON", formatter_class=_Formatter)
    p.add_argument("name", choices=EXAMPLES)
    p.add_argument("--crop", nargs=2, type=int, metavar=("H", "W"),
                   help="grid.crop of the scene, even, at least 8 (default: 1250 1250)")
    p.add_argument("--out", help="write to this file (its folder must exist) instead of stdout")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    p.set_defaults(func=_cmd_example)

    for name, module in (("synth", "difstar.cli._fit"), ("fit", "difstar.cli._fit"),
                         ("design", "difstar.cli._design"),
                         ("fit-image", "difstar.cli._fit_image")):
        try:
            mod = __import__(module, fromlist=["register"])
        except ImportError:
            continue
        mod.register(sub, name)
    for p in sub.choices.values():
        p.formatter_class = _Formatter
    return ap


def _one_line_warnings() -> None:
    """Warnings as the command line's other messages: one line, ``difstar: warning:``,
    without the library's source line (which says nothing to a user of the command)."""
    import warnings

    def one_line(message, category, *_args, **_kwargs):
        return f"difstar: warning: {' '.join(str(message).split())}\n"

    warnings.formatwarning = one_line


def main(argv=None) -> int:
    """Run the command line; returns the exit status (argparse's own errors exit 2)."""
    ap = build_parser()
    a = ap.parse_args(argv)
    _one_line_warnings()
    from difstar._compilation_cache import enable_compilation_cache

    enable_compilation_cache()  # compiled programs kept on disk for the next run
    if a.x64:
        import jax

        jax.config.update("jax_enable_x64", True)
    from difstar.io._output import Terminated

    try:
        return int(a.func(a) or 0)
    except (ValueError, OSError) as exc:  # the user's input, files or machine
        _log(f"difstar: error: {' '.join(str(exc).split())}")
        return 2
    except (KeyboardInterrupt, Terminated) as exc:
        _log("difstar: interrupted; nothing was written.")
        return exc.code if isinstance(exc, Terminated) else 130
    except RecursionError:
        _log("difstar: error: the input is nested too deeply.")
        return 2
    except MemoryError:
        _log("difstar: error: out of memory; use a smaller --crop or grid.")
        return 2
    except Exception as exc:  # noqa: BLE001 - everything else is ours
        if "RESOURCE_EXHAUSTED" in str(exc):
            _log("difstar: error: out of memory on the device; use a smaller --crop or grid.")
            return 2
        return _internal(exc)


def _internal(exc: BaseException) -> int:
    import traceback

    traceback.print_exception(exc, file=sys.stderr)
    _log(f"difstar: internal error ({type(exc).__name__}): {exc}. This is a difstar bug: "
         "please report it with the command and its input.")
    return 1


if __name__ == "__main__":
    sys.exit(main())
