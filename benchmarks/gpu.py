"""difstar on a GPU (issue 35): compile time, run time and peak device memory of the work
users run, with the same on CPU beside it, and the cost per item of a sharded batch
against batch size and device count.

    python benchmarks/gpu.py                 # on the GPU machine: fills BENCHMARKS.md's table
    python benchmarks/gpu.py --cpu-too       # ... with each case also on its CPU
    python benchmarks/gpu.py --quick         # small sizes: a check that it runs (any machine)
    python benchmarks/gpu.py --json out.json # also the raw figures

Cases (each in a fresh child Python, so that its peak memory is its own; the platform is
JAX's default — the GPU where there is one — and ``cpu`` for the ``--cpu-too`` column):

- ``psf``: ``difstar.psf`` of the paper's iris (7 blades, f/22, 530 nm, float32,
  ``sampling="point"``) on the paper's 1250² window, in focus and defocused (as
  ``benchmarks/psf_plain_call.py``), jitted with its plan made once;
- ``simulate``: ``difstar.simulate`` of both paper scenes (``difstar.paper_camera``,
  ``difstar.choose_grid`` at a 1250² crop), jitted as ``difstar predict`` does;
- ``jwst``: ``difstar fit-image fit/jwst-nircam/manifest.json`` (the JWST star; its data
  from ``../shared/data/measured_psf``), a whole fit, compiling included;
- ``rawfit``: ``difstar fit fit/synthetic-paper-camera/manifest.json`` (the RAW campaign),
  a whole fit, compiling included;
- ``sweep``: ``difstar design``'s sweep of 64 designs (9 blades, f/8, curvature 0 … 0.9,
  the study's 96² / 128² PSFs) as one ``map_batch`` program over every device;
- ``scale``: ``map_batch`` of defocused PSFs (256², one wavelength per item) for batch
  sizes 1 … 64 on 1 … N devices (the GPUs JAX sees; on CPU, N host devices with
  ``XLA_FLAGS=--xla_force_host_platform_device_count=N``): seconds per item.

Compile = ``jit(...).lower(...).compile()``; run = best of ``--repeats`` calls of the
compiled program after one warm-up call (``block_until_ready``). Peak memory: the
device's ``memory_stats()["peak_bytes_in_use"]`` where it reports one (GPUs), else the
process's peak resident memory (``ru_maxrss``, marked "host"). ``--quick``: the fits 1
step per stage, 128² PSFs, 64² scenes, 4 designs of the quick setup, batches 1–4 on 1–2
devices, one repeat.
Prints Markdown tables (progress on stderr).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
CASES = ("psf", "simulate", "jwst", "rawfit", "sweep", "scale")

CHILD = r'''
import json, math, resource, sys, time
spec = json.loads(sys.argv[1])
import jax
if spec.get("x64"):
    jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
import numpy as np
import equinox as eqx
import difstar
from difstar import batch as B

dev = jax.devices()[0]

def peak():
    try:
        st = dev.memory_stats() or {}
    except Exception:
        st = {}
    if st.get("peak_bytes_in_use"):
        return int(st["peak_bytes_in_use"]), "device"
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024, "host"

def timed(compiled, args, repeats):
    jax.block_until_ready(compiled(*args))  # warm-up
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        best = min(best, time.perf_counter() - t0)
    return best

def compile_(f, *args):
    t0 = time.perf_counter()
    c = f.lower(*args).compile()
    return c, time.perf_counter() - t0

task, reps = spec["task"], spec["repeats"]
out = {"platform": jax.default_backend(), "device": dev.device_kind,
       "devices": jax.device_count()}
if task == "psf":
    cam, scene = difstar.paper_camera(spec["config"])
    g = difstar.geometry_of(cam, scene)
    n = spec["crop"]
    kw = dict(wavelength=530e-9, z_image=float(g.z_exit_pupil),
              defocus=float(g.defocus) if spec["config"] == "defocused" else 0.0,
              pixel_pitch=float(cam.sensor.pixel_pitch), shape=(n, n), sampling="point")
    pup = cam.lens.pupil
    plan = difstar.plan_psf(pup, **kw)
    f = jax.jit(lambda p: difstar.psf(p, plan=plan, **kw))
    c, out["compile_s"] = compile_(f, pup)
    out["run_s"] = timed(c, (pup,), reps)
elif task == "simulate":
    cam, scene = difstar.paper_camera(spec["config"])
    n = spec["crop"]
    grid = difstar.choose_grid(cam, scene, crop=(n, n))
    out["grid_n"] = int(grid.n)
    f = eqx.filter_jit(difstar.simulate)
    c, out["compile_s"] = compile_(f, cam, scene, grid)
    out["run_s"] = timed(c, (cam, scene, grid), reps)
elif task == "sweep":
    from difstar.design_study import curvature_grid, measures_fn, study_setup
    family, setup, opts = study_setup(blades=9, f_number=8.0, quick=spec["quick"])
    values = measures_fn(family, setup, opts)
    designs = curvature_grid(0.0, 0.9, spec["items"], blades=9)
    nd = jax.device_count()
    mesh = B.device_mesh(nd)
    padded = designs + designs[:(-len(designs)) % nd]  # a whole number per device
    batch = {k: jnp.asarray(np.stack([d[k] for d in padded]), jnp.result_type(float))
             for k in ("curvature", "radial", "angular")}
    run = B.sharded_vmap(lambda b: values(difstar.IrisParams(b["curvature"], b["radial"],
                                                             b["angular"]))[0], mesh)
    x = B.shard(batch, mesh)
    c, out["compile_s"] = compile_(run, x)
    out["run_s"] = timed(c, (x,), reps)
    out["items"] = spec["items"]
elif task == "scale":
    nd, items = spec["use_devices"], spec["items"]
    cam, scene = difstar.paper_camera("defocused")
    g = difstar.geometry_of(cam, scene)
    n = spec["crop"]
    kw = dict(z_image=float(g.z_exit_pupil), defocus=float(g.defocus),
              pixel_pitch=float(cam.sensor.pixel_pitch), shape=(n, n), sampling="point")
    pup = cam.lens.pupil
    lams = np.linspace(450e-9, 650e-9, items + (-items) % nd)
    plan = difstar.plan_psf(pup, wavelength=lams, **kw)
    mesh = B.device_mesh(nd)
    run = B.sharded_vmap(lambda lam: difstar.psf(pup, wavelength=lam, plan=plan, **kw), mesh)
    x = B.shard(lams, mesh)
    c, out["compile_s"] = compile_(run, x)
    out["run_s"] = timed(c, (x,), reps)
    out["items"], out["use_devices"] = items, nd
elif task == "fit":
    # a whole fit as a user runs it (compiling included: its stages compile as they go)
    import tempfile
    from difstar.cli import main
    with tempfile.TemporaryDirectory() as tmp:
        argv = [a.replace("{tmp}", tmp) for a in spec["argv"]]
        t0 = time.perf_counter()
        rc = main(argv)
        out["run_s"] = time.perf_counter() - t0
    if rc != 0:
        raise SystemExit(f"difstar {' '.join(argv)} ended with status {rc}")
out["peak_bytes"], out["peak_of"] = peak()
print("RESULT " + json.dumps(out), flush=True)
'''


def _log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def run_case(spec: dict, *, cpu: bool, host_devices: int | None = None,
             timeout: float = 900) -> dict:
    """One case in a fresh child Python; returns its figures or {"error": ...}."""
    env = dict(os.environ)
    env.pop("DIFSTAR_DEVICES", None)
    if cpu:
        env["JAX_PLATFORMS"] = "cpu"
    if host_devices:
        flags = env.get("XLA_FLAGS", "")
        env["XLA_FLAGS"] = (f"{flags} --xla_force_host_platform_device_count={host_devices}"
                            " --xla_cpu_multi_thread_eigen=false").strip()
    t0 = time.perf_counter()
    try:
        p = subprocess.run([sys.executable, "-c", CHILD, json.dumps(spec)], cwd=ROOT, env=env,
                           capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"error": f"no result in {timeout:.0f} s"}
    lines = [x for x in p.stdout.splitlines() if x.startswith("RESULT ")]
    if p.returncode != 0 or not lines:
        tail = (p.stderr.strip().splitlines() or ["(no output)"])[-1]
        return {"error": f"exit {p.returncode}: {tail[:200]}"}
    r = json.loads(lines[-1][7:])
    r["wall_s"] = time.perf_counter() - t0
    return r


def _mem(r: dict) -> str:
    if "peak_bytes" not in r:
        return "–"
    b = r["peak_bytes"] / 2**30
    return f"{b:.2f} GiB" + (" (host)" if r.get("peak_of") == "host" else "")


def _cell(r: dict | None) -> tuple[str, str, str]:
    if r is None:
        return ("", "", "")
    if "error" in r:
        return (f"failed: {r['error']}", "", "")
    if "compile_s" not in r:  # a whole fit: its compiling is part of its run
        return ("in the run", f"{r['run_s']:.1f} s", _mem(r))
    return (f"{r['compile_s']:.2f} s", f"{1e3 * r['run_s']:.1f} ms", _mem(r))


def _gpu_count() -> tuple[str, int, str]:
    """The default platform, its device count and kind (asked of a child: this process
    keeps JAX unstarted, so that every case starts fresh)."""
    code = ("import jax, json; d = jax.devices(); print(json.dumps([jax.default_backend(), "
            "len(d), d[0].device_kind]))")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=300)
    try:
        plat, n, kind = json.loads(p.stdout.strip().splitlines()[-1])
    except (ValueError, IndexError):
        return "cpu", 1, "unknown"
    return plat, n, kind


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="small sizes: a check that it runs")
    ap.add_argument("--cpu-too", action="store_true",
                    help="also run every case on the CPU (JAX_PLATFORMS=cpu)")
    ap.add_argument("--repeats", type=int, default=None, help="timed runs (default 3; 1 quick)")
    ap.add_argument("--only", nargs="+", choices=list(CASES), default=list(CASES))
    ap.add_argument("--json", help="also write every figure to this JSON file")
    a = ap.parse_args(argv)
    reps = a.repeats or (1 if a.quick else 3)
    q = a.quick
    plat, n_dev, kind = _gpu_count()
    on_gpu = plat != "cpu"
    _log(f"default platform: {plat} × {n_dev} ({kind})")
    sizes = dict(psf=128 if q else 1250, scene=64 if q else 1250, designs=4 if q else 64,
                 scale_crop=64 if q else 256, batches=[1, 2, 4] if q else [1, 4, 16, 64])
    cases = []
    if "psf" in a.only:
        cases += [("psf", f"difstar.psf, {c}, {sizes['psf']}² float32",
                   {"task": "psf", "config": c, "crop": sizes["psf"]})
                  for c in ("focused", "defocused")]
    if "simulate" in a.only:
        cases += [("simulate", f"simulate, paper {c} scene, {sizes['scene']}² crop",
                   {"task": "simulate", "config": c, "crop": sizes["scene"]})
                  for c in ("focused", "defocused")]
    if "jwst" in a.only:  # the star's data: ../shared/data/measured_psf beside the checkout
        steps = ["--max-steps", "1"] if q else []
        cases.append(("jwst", f"JWST star fit (fit-image){', 1 step per stage' if q else ''}",
                      {"task": "fit", "argv": ["fit-image", "fit/jwst-nircam/manifest.json",
                                               "--out", "{tmp}/jwst", "--quiet", *steps]}))
    if "rawfit" in a.only:
        steps = ["--max-steps", "1"] if q else []
        cases.append(("rawfit", f"RAW campaign fit (synthetic paper camera)"
                      f"{', 1 step per stage' if q else ''}",
                      {"task": "fit", "argv": ["--x64", "fit",
                                               "fit/synthetic-paper-camera/manifest.json",
                                               "--out", "{tmp}/raw", *steps]}))
    if "sweep" in a.only:
        cases.append(("sweep", f"design sweep, {sizes['designs']} designs"
                      f"{' (quick setup)' if q else ''}, all devices",
                      {"task": "sweep", "items": sizes["designs"], "quick": q}))
    results = []
    for name, label, spec in cases:
        spec = dict(spec, repeats=reps)
        _log(f"{label} ...")
        limit = 3600 if spec["task"] == "fit" else 900  # a whole fit: minutes on a CPU
        main_r = run_case(spec, cpu=False, timeout=limit)
        _log(f"  -> {json.dumps(main_r)}")  # each figure as it comes (a cut-off run keeps them)
        cpu_r = run_case(spec, cpu=True, timeout=limit) if (a.cpu_too and on_gpu) else None
        results.append({"case": label, "default": main_r, "cpu": cpu_r})
    scale = []
    if "scale" in a.only:
        # devices: the GPUs seen; on CPU (and for --cpu-too) 1 and 2 host devices
        runs = []
        if on_gpu:
            runs += [(False, d, None) for d in sorted({1, n_dev})]
        if not on_gpu or a.cpu_too:
            runs += [(True, d, d) for d in ([1, 2] if q else [1, 2, 4])]
        for cpu, d, host in runs:
            for b in sizes["batches"]:
                _log(f"scale: {'cpu' if cpu else plat} × {d}, batch {b} ...")
                spec = {"task": "scale", "items": b, "use_devices": d,
                        "crop": sizes["scale_crop"], "repeats": reps}
                scale.append(run_case(spec, cpu=cpu, host_devices=host) | {
                    "batch": b, "ndev": d, "on": "cpu" if cpu or not on_gpu else plat})
                _log(f"  -> {json.dumps(scale[-1])}")

    print(f"### {kind if on_gpu else 'CPU only'}: {'quick check' if q else 'full sizes'}\n")
    two = a.cpu_too and on_gpu
    head = "| case | compile | run | peak memory |" + (
        " CPU compile | CPU run | CPU peak |" if two else "")
    print(head)
    print("|---|---:|---:|---:|" + ("---:|---:|---:|" if two else ""))
    for r in results:
        row = f"| {r['case']} | " + " | ".join(_cell(r["default"]))
        if two:
            row += " | " + " | ".join(_cell(r["cpu"]))
        print(row + " |")
    if scale:
        print(f"\nCost per item of `map_batch` ({sizes['scale_crop']}² defocused PSFs, one "
              "wavelength each); efficiency = (s per item on 1 device) / (N × s per item on "
              "N devices) at the same batch:\n")
        print("| platform | devices | batch | compile | run | s per item | efficiency |")
        print("|---|---:|---:|---:|---:|---:|---:|")
        base = {(r["on"], r["batch"]): r["run_s"] / r["batch"]
                for r in scale if "run_s" in r and r["ndev"] == 1}
        for r in scale:
            if "error" in r:
                print(f"| {r['on']} | {r['ndev']} | {r['batch']} | failed: {r['error']} |"
                      " | | |")
                continue
            per = r["run_s"] / r["batch"]
            b1 = base.get((r["on"], r["batch"]))
            eff = f"{b1 / (r['ndev'] * per):.2f}" if b1 else "–"
            print(f"| {r['on']} | {r['ndev']} | {r['batch']} | {r['compile_s']:.2f} s | "
                  f"{1e3 * r['run_s']:.1f} ms | {1e3 * per:.2f} ms | {eff} |")
    import jax  # only for the version, after every child ran

    print(f"\njax {jax.__version__}; {platform.node()}, {os.cpu_count()} CPUs, load average "
          f"{' '.join(f'{x:.1f}' for x in os.getloadavg())}; best of {reps}; command: "
          f"python benchmarks/gpu.py {' '.join(argv if argv is not None else sys.argv[1:])}")
    if a.json:
        Path(a.json).write_text(json.dumps({"platform": plat, "devices": n_dev, "kind": kind,
                                            "cases": results, "scale": scale}, indent=1))
    failed = [r for r in results for k in ("default", "cpu") if r[k] and "error" in r[k]]
    failed += [r for r in scale if "error" in r]
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
