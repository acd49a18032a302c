"""What one model image of a star campaign costs: the forward model an image fit
evaluates at every step and at every point of its rotation scan, jitted, at the
manifest's start values, in float64 as ``difstar fit`` runs it.

    python benchmarks/model_image.py [--cases jwst,spitzer] [--repeats 7] [--profile]

Prints one Markdown table: the PSF plan, the window, the first call (trace and compile)
and the best of ``--repeats`` calls after it. ``--profile`` adds the XLA operations that
take the most time in one image (``jax.profiler``; per call, from five calls;
the loops themselves left out, their operations listed). To compare
two versions of difstar, run the script with ``PYTHONPATH`` at each one's ``src``.
"""

from __future__ import annotations

import argparse
import collections
import gzip
import json
import sys
import tempfile
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CASES = {"jwst": "fit/jwst-nircam/manifest.json", "spitzer": "fit/spitzer-irac/manifest.json"}


def _image_program(manifest: str):
    from difstar.fitting import load_manifest

    model, data, _ = load_manifest(ROOT / manifest)
    data = data[0] if isinstance(data, list) else data
    plan = model.plan(model.padded_shape(data.image.shape), data.light)
    values = {k: jnp.asarray(float(p.value)) for k, p in model.params.items()
              if jnp.ndim(p.value) == 0}
    fn = jax.jit(lambda v: model.image(v, data.image.shape, plan, light=data.light))
    return fn, values, plan, data, model


def _profile(fn, values, calls: int = 5) -> list[tuple[str, float]]:
    with tempfile.TemporaryDirectory() as folder:
        jax.profiler.start_trace(folder)
        for _ in range(calls):
            jax.block_until_ready(fn(values))
        jax.profiler.stop_trace()
        trace = sorted(Path(folder).rglob("*.trace.json.gz"))[-1]
        events = json.load(gzip.open(trace))["traceEvents"]
    total: collections.Counter = collections.Counter()
    for e in events:
        name = e.get("name", "")
        skip = name.startswith(("$", "Thunk", "Pjit", "while"))
        if e.get("ph") == "X" and "dur" in e and not skip:
            total[name] += e["dur"]
    return [(k, v / calls / 1e3) for k, v in total.most_common(8)]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", default="jwst,spitzer")
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--profile", action="store_true")
    a = ap.parse_args(argv)
    rows, profiles = [], {}
    for name in a.cases.split(","):
        fn, values, plan, data, model = _image_program(CASES[name])
        t0 = time.perf_counter()
        jax.block_until_ready(fn(values))
        first = time.perf_counter() - t0
        best = float("inf")
        for _ in range(a.repeats):
            t0 = time.perf_counter()
            jax.block_until_ready(fn(values))
            best = min(best, time.perf_counter() - t0)
        light = data.light if data.light is not None else model.light
        rows.append((name, plan, data.image.shape, len(light.wavelengths), first, best))
        if a.profile:
            profiles[name] = _profile(fn, values)
        print(f"{name}: done", file=sys.stderr, flush=True)
    print("| case | plan | window | wavelengths | first call s | image ms |")
    print("|---|---|---|---|---:|---:|")
    for name, plan, shape, nl, first, best in rows:
        print(f"| {name} | {plan.method}, pupil window {plan.pupil_window}, "
              f"{plan.subcells}² sub-cells | {shape[0]} × {shape[1]} | {nl} | {first:.2f} | "
              f"{1e3 * best:.1f} |")
    for name, ops in profiles.items():
        print(f"\n{name}: the XLA operations that take longest, ms per image")
        for op, ms in ops:
            print(f"- {op}: {ms:.2f}")
    print(f"\njax {jax.__version__} on {jax.default_backend()}; float64; best of {a.repeats}.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
