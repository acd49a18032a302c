"""``difstar design``: the command line of the aperture-design study (it parses, calls
:mod:`difstar._design_study` and writes the results, tables and figures)."""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path

from difstar._design_study import (
    MAX_BOKEH_WEIGHT,
    MAX_F_NUMBER,
    MAX_STEPS,
    MAX_SWEEP_BYTES,
    MAX_SWEEP_DESIGNS,
    MIN_F_NUMBER,
    STUDY_FLAGS,
    _log,
    check_convex,
    check_f_number,
    check_study_args,
    curvature_grid,
    iris_study,
    parse_sweep,
    sweep_designs,
    table_markdown,
)


def plot_study(result: dict, path_prefix: Path) -> list[str]:
    """psfs.png (focused, log scale), bokeh.png (defocused, linear), pupils.png,
    history.png. Returns the file names."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    names = list(result["psfs"])
    files = []
    panels = (("psfs.png", "focused PSF, log scale", "log10(PSF / its peak)", "magma", -7),
              ("bokeh.png", "defocused highlight (bokeh), linear", "intensity / its peak",
               "gray", 0))
    for k, (file, title, unit, cmap, vmin) in enumerate(panels):  # one shared scale each
        fig, axes = plt.subplots(1, len(names), figsize=(3.4 * len(names), 3.4),
                                 layout="constrained")
        for ax, name in zip(axes, names):
            p = result["psfs"][name][k] / result["psfs"][name][k].max()
            shown = ax.imshow(np.log10(np.maximum(p, 1e-8)) if k == 0 else p, vmin=vmin,
                              vmax=0 if k == 0 else 1, cmap=cmap)
            row = result["rows"][name]
            ax.set_title(f"{name}\n" + (f"aniso {row['halo_anisotropy']:.2e}" if k == 0
                                        else f"CV {row['bokeh_cv']:.4f}"), fontsize=9)
            ax.axis("off")
        fig.colorbar(shown, ax=axes, label=unit, shrink=0.85)
        fig.suptitle(title)
        fig.savefig(path_prefix / file, dpi=110)
        plt.close(fig)
        files.append(file)
    fig, ax = plt.subplots(figsize=(4.5, 4.5))
    for name in names:
        o = result["outlines"][name] * 1e3
        o = np.vstack([o, o[:1]])
        ax.plot(o[:, 0], o[:, 1], lw=1, label=name)
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.legend(fontsize=8)
    ax.set_title("exit-pupil outlines (same open area)")
    fig.tight_layout()
    fig.savefig(path_prefix / "pupils.png", dpi=110)
    plt.close(fig)
    files.append("pupils.png")
    fig, ax = plt.subplots(figsize=(5, 3.5))
    for name, h in result["histories"].items():
        ax.plot(h, label=name)
    ax.set_xlabel("step")
    ax.set_ylabel("objective")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path_prefix / "history.png", dpi=110)
    plt.close(fig)
    files.append("history.png")
    return files


#: the study's defaults for the flags a sweep does not take (None on the command line:
#: given or not can then be told apart)
STUDY_DEFAULT_ARGS = {"max_curvature": 0.6, "vertex_bound": 0.015, "bokeh_weight": 0.0,
                      "optimiser": "adam"}


def _read_sweep_file(path: Path, *, blades: int) -> list[dict]:
    """The designs of the ``--sweep`` file: strict JSON, then the schema and
    :func:`parse_sweep`'s checks (no computation)."""
    from difstar._validate import InputError
    from difstar.io._json import loads_strict

    # as difstar.io._scene.read_json, which is typed to return an object: a sweep file
    # holding an array is refused by parse_sweep, naming what a sweep is
    fix = "give a sweep file (JSON, data_schemas/design_sweep.schema.json)"
    if path.is_dir():
        raise InputError(f"--sweep {path}: cannot read it: it is a folder; {fix}.")
    if not path.exists():
        raise InputError(f"--sweep {path}: cannot read it: it does not exist (check the "
                         f"path); {fix}.")
    if not path.is_file():
        raise InputError(f"--sweep {path}: cannot read it: not a regular file; {fix}.")
    size = path.stat().st_size
    if size > MAX_SWEEP_BYTES:
        raise InputError(f"--sweep {path}: {size / 2**20:.0f} MiB; a sweep of at most "
                         f"{MAX_SWEEP_DESIGNS} designs takes far less than "
                         f"{MAX_SWEEP_BYTES // 2**20} MiB: split it into several sweeps.")
    try:
        text = path.read_text()
    except UnicodeDecodeError:
        raise InputError(f"--sweep {path}: cannot read it: not a text (UTF-8 JSON) file; "
                         f"{fix}.") from None
    except OSError as exc:
        raise InputError(f"--sweep {path}: cannot read it ({exc.strerror or exc}); "
                         f"{fix}.") from None
    return parse_sweep(loads_strict(text, source=str(path)), blades=blades,
                       source=str(path))


def _cmd_sweep(a) -> int:
    """``difstar design --sweep FILE`` / ``--sweep-curvature LO HI N``: many designs'
    measures at once, sharded over ``--devices``; writes sweep.json and sweep.md.
    Everything is checked before anything is computed: the flags, the file (strict JSON,
    the schema, the blade counts and names), the devices, then every iris's convexity
    (its outline only)."""
    import os

    from difstar._batch import ENV_DEVICES, check_chunk, device_count
    from difstar._distributed import init_distributed
    from difstar._validate import MAX_BLADES, InputError, check_number
    from difstar.io._output import check_output_free, output_dir, write_json

    blades = check_number(a.blades, "--blades", integer=True, ge=3, le=MAX_BLADES)
    f_number = check_f_number(a.f_number, "--f-number")
    for key in ("steps", *STUDY_DEFAULT_ARGS):
        if getattr(a, key, None) is not None:
            flag = STUDY_FLAGS[key]
            raise InputError(f"{flag}: a sweep measures its designs as given (nothing is "
                             f"optimised); drop {flag}, or drop --sweep and "
                             "--sweep-curvature to run the optimisation study.")
    designs = []
    inputs = []
    if a.sweep:
        path = Path(a.sweep)
        designs += _read_sweep_file(path, blades=blades)
        inputs.append(path)
    if a.sweep_curvature:
        designs += curvature_grid(*a.sweep_curvature, blades=blades)
    if len(designs) > MAX_SWEEP_DESIGNS:
        raise InputError(f"--sweep and --sweep-curvature: {len(designs)} designs in all; a "
                         f"sweep holds at most {MAX_SWEEP_DESIGNS}: split it into several.")
    seen = set()
    for d in designs:
        if d["name"] in seen:
            raise InputError(f"--sweep and --sweep-curvature: two designs are named "
                             f"{d['name']!r}; give every design in the sweep file its own "
                             "name.")
        seen.add(d["name"])
    chunk = None if a.chunk is None else check_chunk(a.chunk, "--chunk")
    if a.devices is not None or os.environ.get(ENV_DEVICES, "").strip():
        init_distributed()
    n_dev = device_count(a.devices)
    source = str(a.sweep or "--sweep-curvature")
    check_convex(designs, blades=blades, f_number=f_number, source=source)
    check_output_free(Path(a.out), overwrite=a.overwrite, inputs=inputs)
    t0 = time.perf_counter()
    plans = []
    log = _logger(a.quiet)
    log(f"difstar design: {len(designs)} designs on {n_dev} device(s) ...")
    with output_dir(Path(a.out), overwrite=a.overwrite, inputs=inputs,
                    command="design") as tmp:
        result = sweep_designs(
            designs, blades=blades, f_number=f_number, quick=a.quick, devices=n_dev,
            chunk=chunk, plan_out=plans, source=source, convexity_checked=True,
            progress=lambda d, n, sec: log(f"difstar design: {d}/{n} designs ({sec:.1f} s)"))
        wall = time.perf_counter() - t0
        bad = [r["name"] for r in result["rows"]
               if not all(math.isfinite(v) for k, v in r.items()
                          if isinstance(v, float))]
        if bad:
            raise RuntimeError(f"sweep designs {bad} hold NaN or infinity; nothing was "
                               "written")
        md = table_markdown({r["name"]: r for r in result["rows"]})
        (tmp / "sweep.md").write_text(md)
        p = plans[0]
        doc = dict(result, devices=n_dev, timing_s={"total": wall},
                   plan={"designs_per_chunk": p.chunk, "per_device": p.per_device,
                         "chunks": p.chunks, "item_bytes": p.item_bytes,
                         "free_bytes": p.free_bytes})
        write_json(tmp / "sweep.json", doc)
    sys.stdout.write(md)
    log(f"difstar design: {len(designs)} designs in {wall:.1f} s on {n_dev} device(s); "
         f"wrote {a.out}/ (sweep.json, sweep.md)")
    return 0


def _logger(quiet: bool):
    """The command's progress lines on stderr, or nothing with --quiet."""
    return (lambda msg: None) if quiet else _log


def _cmd_design(a) -> int:
    from difstar._validate import InputError
    from difstar.io._output import check_output_free, output_dir, write_json

    if a.sweep or a.sweep_curvature:
        return _cmd_sweep(a)
    for flag, v in (("--devices", a.devices), ("--chunk", a.chunk)):
        if v is not None:
            raise InputError(f"{flag}: only a sweep (--sweep FILE or --sweep-curvature LO "
                             f"HI N) evaluates several designs to share out; add one, or "
                             f"drop {flag} for the study.")
    given = {k: getattr(a, k, None) for k in STUDY_DEFAULT_ARGS}
    args = check_study_args(
        blades=a.blades, f_number=a.f_number, steps=a.steps,
        **{k: STUDY_DEFAULT_ARGS[k] if v is None else v for k, v in given.items()},
        names=STUDY_FLAGS)
    args.pop("learning_rate")
    check_output_free(Path(a.out), overwrite=a.overwrite)
    t0 = time.perf_counter()
    log = _logger(a.quiet)
    with output_dir(Path(a.out), overwrite=a.overwrite, command="design") as tmp:
        result = iris_study(quick=a.quick, log=log, progress=not a.quiet, **args)
        wall = time.perf_counter() - t0
        bad = [k for k, r in result["rows"].items()
               if not all(math.isfinite(v) for v in r.values())]
        if bad:
            raise RuntimeError(f"design rows {bad} hold NaN or infinity; nothing was written")
        md = table_markdown(result["rows"])
        (tmp / "table.md").write_text(md)
        doc = {k: result[k] for k in ("config", "rows", "params", "histories",
                                      "evaluations")}
        doc["timing_s"] = {"optimise": result["optimise_s"], "total": wall}
        write_json(tmp / "study.json", doc)
        plot_study(result, tmp)
    sys.stdout.write(md)
    log(f"difstar design: {wall:.1f} s; wrote {a.out}/ (table.md, study.json, psfs.png, "
         "bokeh.png, pupils.png, history.png)")
    return 0


def register(subparsers, name: str) -> None:
    from difstar._validate import MAX_BLADES

    from ._args import arg_type as _arg_type

    p = subparsers.add_parser(
        name, help="aperture design study: spikes vs bokeh for curved iris blades",
        description="For an n-blade iris at f/8 and a fixed open area (an f/8 disc's), how "
        "far can blade curvature and vertex placement cut the spikes, and what does that cost "
        "in the smoothness of a defocused highlight (bokeh)?",
    )
    p.add_argument("--out", required=True,
                   help="output folder, created by difstar (written whole or not at all)")
    p.add_argument("--blades", type=_arg_type("blades", integer=True, ge=3, le=MAX_BLADES),
                   default=9, help=f"blade count, 3 to {MAX_BLADES}")
    p.add_argument("--f-number", type=_arg_type("f_number", ge=MIN_F_NUMBER,
                                                le=MAX_F_NUMBER),
                   default=8.0, help=f"f-number of the open area, {MIN_F_NUMBER:g} to "
                   f"{MAX_F_NUMBER:g}")
    p.add_argument("--quick", action="store_true", help="small grids and 12 steps (CI)")
    p.add_argument("--steps", type=_arg_type("steps", integer=True, ge=1, le=MAX_STEPS),
                   help="optimiser steps per design (default: 60, or 12 with --quick), "
                   f"1 to {MAX_STEPS}")
    p.add_argument("--max-curvature", type=_arg_type("curvature", gt=0, le=1),
                   help="blade curvature bound, relative to the circumradius, in (0, 1] "
                   f"(1 = circle) (default: {STUDY_DEFAULT_ARGS['max_curvature']:g})")
    p.add_argument("--vertex-bound", type=_arg_type("bound", ge=0, lt=0.5),
                   help="bound on each vertex's relative radial and angular (rad) deviation, "
                   "in [0, 0.5); with --max-curvature and --blades it must keep every iris "
                   f"convex (default: {STUDY_DEFAULT_ARGS['vertex_bound']:g})")
    p.add_argument("--bokeh-weight", type=_arg_type("weight", ge=0, le=MAX_BOKEH_WEIGHT),
                   help=f"weight of the bokeh CV in the objective, 0 to {MAX_BOKEH_WEIGHT:g} "
                   f"(0: spikes only) (default: {STUDY_DEFAULT_ARGS['bokeh_weight']:g})")
    p.add_argument("--optimiser", metavar="NAME",
                   help="adam: Adam on sigmoid-unconstrained values (the default); "
                   "lbfgsb: L-BFGS-B (jaxopt) in the bounded parameters themselves, "
                   "which can stop early and puts parameters exactly on their bounds")
    p.add_argument("--overwrite", action="store_true",
                   help="replace --out if it is a folder difstar made (never one holding "
                   "other files)")
    p.add_argument("--sweep", metavar="FILE",
                   help="instead of the study, measure every design of FILE (JSON, "
                   "data_schemas/design_sweep.schema.json) at once; writes sweep.json and "
                   "sweep.md (--blades, --f-number and --quick apply; nothing is optimised, "
                   "so --steps, --max-curvature, --vertex-bound, --bokeh-weight and "
                   "--optimiser are refused)")
    p.add_argument("--sweep-curvature", nargs=3, metavar=("LO", "HI", "N"),
                   help="a sweep of N designs, curvature evenly from LO to HI (in [0, 1]), "
                   f"straight-cut vertices, N at most {MAX_SWEEP_DESIGNS}; with --sweep, "
                   "added after its designs")
    p.add_argument("--devices", metavar="N",
                   help="with a sweep: shard the designs over N devices (default: "
                   "$DIFSTAR_DEVICES, else every device); see docs/sharding.md")
    p.add_argument("--chunk", metavar="N",
                   help="with a sweep: at most N designs at a time (default: as many as "
                   "fit in the devices' memory)")
    p.add_argument("--quiet", action="store_true",
                   help="no progress on stderr (the study's bar per optimisation: step, "
                   "objective, the parameter that moved most, time left; a sweep's "
                   "designs done)")
    p.set_defaults(func=_cmd_design)
