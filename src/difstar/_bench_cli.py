"""``difstar bench``: speed against error (BENCHMARKS.md). Outer layer only."""

from __future__ import annotations

import json
import sys
from pathlib import Path


def register(subparsers, name: str) -> None:
    from ._validate import _arg_type, nonnegative_float, positive_float, positive_int

    p = subparsers.add_parser(
        name, help="speed against error: NumPy paper baseline vs difstar settings",
        description="Time and measure the error of the paper's method (NumPy, 3750² grid) "
        "and difstar at several accuracy settings, on the paper's focused and defocused "
        "scenes; prints a Markdown table (progress on stderr).")
    p.add_argument("--quick", action="store_true",
                   help="128 px crop, small source, few settings (about a minute)")
    p.add_argument("--config", choices=("focused", "defocused"), action="append",
                   help="scene(s) to run (default both)")
    p.add_argument("--accuracy", type=positive_float, action="append",
                   help="difstar accuracy target(s) to time (default: the default and one tighter)")
    p.add_argument("--padding", type=nonnegative_float, action="append",
                   help="extra difstar padding settings for the speed-against-error curve "
                   "(default: none)")
    p.add_argument("--baseline-n", type=_arg_type("n", integer=True, ge=8, le=65536),
                   help="grid of the NumPy baseline, 8 to 65536 (default 3750)")
    p.add_argument("--repeats", type=positive_int, default=3,
                   help="timed runs per setting (best kept)")
    p.add_argument("--cache", default=".bench_cache",
                   help="directory caching the float64 references (default .bench_cache)")
    p.add_argument("--no-prysm", action="store_true", help="skip the prysm comparison")
    p.add_argument("--psf", action="store_true",
                   help="instead: the PSF engine's figures (issue 13), by "
                   "benchmarks/psf_engine.py; needs a clone of the repository")
    p.add_argument("--spectral", action="store_true",
                   help="instead: spectral mode against trichromatic (issue 14), by "
                   "benchmarks/spectral.py; needs a clone of the repository")
    p.add_argument("--json", help="also write the full result as JSON to this file (its "
                   "folder must exist; an existing file is replaced)")
    p.set_defaults(func=_cmd_bench)


def _cmd_bench(a) -> int:
    from . import _bench
    from .io._output import OutputError, write_file_atomic

    if a.psf:
        return _run_repo_benchmark("psf_engine.py", "--psf")
    if a.spectral:
        return _run_repo_benchmark("spectral.py", "--spectral")
    cache = Path(a.cache)
    if cache.exists() and not cache.is_dir():
        raise OutputError(f"--cache {cache} is a file; give a folder.")
    if a.json:
        j = Path(a.json)
        if j.is_dir() or not j.parent.is_dir():
            raise OutputError(f"--json {j}: give a file in an existing folder.")
    cache.mkdir(parents=True, exist_ok=True)
    result = _bench.run(
        quick=a.quick, configs=tuple(a.config or ("focused", "defocused")),
        accuracies=tuple(a.accuracy) if a.accuracy else None,
        paddings=tuple(a.padding) if a.padding else None, baseline_n=a.baseline_n,
        cache=cache, repeats=a.repeats, with_prysm=not a.no_prysm,
    )
    result["command"] = "difstar bench " + " ".join(sys.argv[2:] if len(sys.argv) > 2 else [])
    sys.stdout.write(_bench.table(result) + "\n")
    if a.json:
        write_file_atomic(a.json, json.dumps(result, indent=1, default=str) + "\n",
                          overwrite=True, what="--json")
    return 0


def _run_repo_benchmark(name: str, flag: str) -> int:
    """benchmarks/NAME's main, from the repository checkout this package runs from."""
    import importlib.util

    script = Path(__file__).resolve().parents[2] / "benchmarks" / name
    if not script.is_file():
        raise SystemExit(
            f"difstar bench {flag}: {script} not found. This benchmark runs from a clone of "
            "the repository (pip install -e . there), not from an installed package.")
    spec = importlib.util.spec_from_file_location("difstar_bench_" + script.stem, script)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod.main([], prog=f"difstar bench {flag}")
