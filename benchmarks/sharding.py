"""Sharding over devices (issue 17): scaling from 1 to 2 host CPU devices.

Each measurement runs in a fresh child Python with ``XLA_FLAGS`` giving it N host CPU
devices (their Eigen operations single-threaded: ``--xla_cpu_multi_thread_eigen=false``,
so that N devices use about N cores), and
times, after a first run that compiles:

- spectral render: ``difstar.batch.simulate_spectral`` of the paper's focused scene in
  the spectral model (``--wavelengths`` per channel, evenly over ±40 nm about the
  paper's 600/530/450 nm, equal weights), ``--crop`` pixels;
- fits: ``difstar.batch.solve_many`` of ``--fits`` small fits (the tiny synthetic model
  of ``tests/test_fit.py``: 64² crop, 2 captures, 7 free values) for ``--steps`` solver
  steps each (on CPU a device's fits step one after another, see
  ``difstar.batch.lapack_in_turn``);
- design sweep: ``difstar.design_study.sweep_designs`` of ``--designs`` 9-blade irises at
  f/8 (``difstar design --quick``'s setup: 64² focused and 64² defocused PSFs per design),
  curvature evenly over [0, 0.9];
- one fit's Jacobian: a solver step of the synthetic campaign's fit (10 captures, 21
  free values; ``difstar fit --devices N``), its Jacobian's columns shared out over the
  devices (``Fitter(devices=N)``), mean over ``--steps`` steps.

Efficiency = t1 / (N · tN); cost per item = tN / items. Prints a Markdown table.

    python benchmarks/sharding.py [--devices 1 2] [--crop 64] [--wavelengths 8] [--fits 4]
        [--designs 16] [--only spectral fit design jacobian]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

CHILD = r'''
import json, sys, time
import jax, numpy as np
jax.config.update("jax_enable_x64", True)
import difstar
from difstar import batch as B
cfg = json.loads(sys.argv[1])
n = jax.device_count()
out = {"devices": n, "cpus": len(__import__("os").sched_getaffinity(0))}

camera, scene = difstar.paper_camera("focused")
k = cfg["wavelengths"]
wl = np.stack([np.linspace(c - 40e-9, c + 40e-9, k) for c in (600e-9, 530e-9, 450e-9)])
s = camera.sensor
cam = difstar.Camera(camera.lens, difstar.Sensor(
    pixel_pitch=s.pixel_pitch, pattern=s.pattern, wavelengths=wl,
    spectral_weights=np.ones_like(wl), phi0=s.phi0, response=s.response,
    white_balance=s.white_balance))
grid = difstar.choose_grid(cam, scene, crop=(cfg["crop"], cfg["crop"]), raw_only=True)
if "design" in cfg["only"]:
  from difstar.design_study import curvature_grid, sweep_designs
  designs = curvature_grid(0.0, 0.9, cfg["designs"], blades=9)
  sweep_designs(designs, quick=True, devices=n)  # compile
  best = float("inf")
  for _ in range(cfg["repeats"]):
    t0 = time.perf_counter()
    sweep_designs(designs, quick=True, devices=n)
    best = min(best, time.perf_counter() - t0)
  out["design_s"] = best
  out["design_items"] = len(designs)
  print("RESULT " + json.dumps(out))
  sys.exit(0)
if "jacobian" in cfg["only"]:
  # one fit: the synthetic campaign's 10 captures, its Jacobian's columns shared out
  from difstar.raw_fit import (Fitter, load_manifest, make_args, observed_data, prepare,
                               to_unconstrained)
  man = load_manifest("fit/synthetic-paper-camera/manifest.json")
  model, caps = prepare(man)
  fitter = Fitter(model, method=man.solver["method"], devices=n)
  u = to_unconstrained(model)
  a = make_args(model, observed_data(model, caps, man.noise), u)
  state = fitter._init(u, a)
  jax.block_until_ready(fitter._step(u, state, a))  # compile
  best = float("inf")
  for _ in range(cfg["repeats"]):
    v, st = u, state
    t0 = time.perf_counter()
    for _ in range(cfg["steps"]):
      v, st, *_ = fitter._step(v, st, a)
    jax.block_until_ready(v)
    best = min(best, (time.perf_counter() - t0) / cfg["steps"])
  out["jacobian_s"] = best
  out["jacobian_items"] = model.n_free
  print("RESULT " + json.dumps(out))
  sys.exit(0)
if "spectral" in cfg["only"]:
  B.simulate_spectral(cam, scene, grid, devices=n)  # compile
  best = float("inf")
  for _ in range(cfg["repeats"]):
    t0 = time.perf_counter()
    B.simulate_spectral(cam, scene, grid, devices=n)
    best = min(best, time.perf_counter() - t0)
  out["spectral_s"] = best
  out["spectral_items"] = k
  out["method"] = grid.method
  print("RESULT " + json.dumps(out))
  sys.exit(0)

sys.path.insert(0, "tests")
from test_fit import F, _data, _model, _start
model = _model()
fitter, data = _data(model, noise_sigma=1e-3)
m = cfg["fits"]
u0 = np.stack([np.asarray(_start(model, 0.1, seed=i)) for i in range(m)])
args = jax.tree_util.tree_map(lambda *x: np.stack([np.asarray(v) for v in x]),
                              *[F.make_args(model, data, u) for u in u0])
B.solve_many(fitter, u0, args, devices=n, max_steps=2)  # compile
best = float("inf")
for _ in range(cfg["repeats"]):
    t0 = time.perf_counter()
    # ftol < 0: no early stop, every fit takes exactly --steps steps (a fixed workload)
    B.solve_many(fitter, u0, args, devices=n, max_steps=cfg["steps"], ftol=-1.0)
    best = min(best, time.perf_counter() - t0)
out["fit_s"] = best
out["fit_items"] = m
print("RESULT " + json.dumps(out))
'''

FLAGS = "--xla_force_host_platform_device_count={n} --xla_cpu_multi_thread_eigen=false"


def measure(n: int, cfg: dict, only: str, timeout: float) -> dict | None:
    cfg = dict(cfg, only=only)
    env = dict(os.environ, XLA_FLAGS=FLAGS.format(n=n))
    env.pop("DIFSTAR_DEVICES", None)
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    try:
        p = subprocess.run([sys.executable, "-c", CHILD, json.dumps(cfg)], cwd=root, env=env,
                           capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return None  # reported as such in the table
    line = [x for x in p.stdout.splitlines() if x.startswith("RESULT ")]
    if p.returncode or not line:
        raise SystemExit(f"child with {n} devices failed:\n{p.stderr[-3000:]}")
    return json.loads(line[-1][7:])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--devices", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--crop", type=int, default=64)
    ap.add_argument("--wavelengths", type=int, default=8, help="per channel")
    ap.add_argument("--fits", type=int, default=4)
    ap.add_argument("--steps", type=int, default=6)
    ap.add_argument("--designs", type=int, default=16)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--timeout", type=float, default=300, help="seconds per measurement")
    ap.add_argument("--only", nargs="+", choices=["spectral", "fit", "design", "jacobian"],
                    help="measure only these workloads (default: all)")
    a = ap.parse_args(argv)
    cfg = {"crop": a.crop, "wavelengths": a.wavelengths, "fits": a.fits, "steps": a.steps,
           "repeats": a.repeats, "designs": a.designs}
    keys = a.only or ["spectral", "fit", "design", "jacobian"]
    rows = {key: {n: measure(n, cfg, key, a.timeout) for n in a.devices} for key in keys}
    n0 = a.devices[0]
    print(f"# Sharding (issue 17): {os.cpu_count()} CPUs, host CPU devices, single-threaded Eigen; "
          f"float64; best of {a.repeats} after compiling")
    print("| workload | devices | items | wall (s) | per item (s) | efficiency t1/(N·tN) |")
    print("|---|---|---|---|---|---|")
    for key, label in (("spectral", f"spectral render ({a.crop}² crop, "
                        f"{a.wavelengths} wavelengths per channel; item = one per channel)"),
                       ("fit", f"small fits ({a.steps} LM steps each)"),
                       ("design", "design sweep (9-blade irises, 64² focused + 64² "
                        "defocused PSF each)"),
                       ("jacobian", f"one fit's solver step, Jacobian columns shared out "
                        f"(synthetic campaign: 10 captures; item = one column; wall = one "
                        f"step, mean of {a.steps})")):
        if key not in rows:
            continue
        r0 = rows[key][n0]
        for n, r in rows[key].items():
            if r is None or r0 is None:
                print(f"| {label} | {n} | – | no result within {a.timeout:.0f} s (hung or "
                      "too slow) | – | – |")
                continue
            t1 = r0[f"{key}_s"] * n0
            t = r[f"{key}_s"]
            items = r[f"{key}_items"]
            print(f"| {label} | {n} | {items} | {t:.2f} | {t / items:.3f} | "
                  f"{t1 / (n * t):.2f} |")
    print("\ncommand: python benchmarks/sharding.py " + " ".join(argv or sys.argv[1:]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
