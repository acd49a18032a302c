"""What a user gets from a plain ``difstar.psf(...)`` call (no plan, no jit of their own),
side by side with the same PSF jitted with its plan made once and with the paper's method
in plain NumPy, on the paper's 1250² window (7-blade f/22 iris, 530 nm, float32,
``sampling="point"``), in focus and defocused.

    python benchmarks/psf_plain_call.py [--repeats 3]

Prints one Markdown table (BENCHMARKS.md, "Plain calls"). The first plain call includes
planning and compiling; later plain calls reuse both (difstar._psf keeps the plan by the
inputs' values and the compiled program by the plan and the shapes)."""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

LAM = 530e-9
CROP = (1250, 1250)


def _best(fn, repeats):
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    a = ap.parse_args(argv)
    import jax
    from psf_engine import paper_numpy_psf

    import difstar

    rows = []
    for config in ("focused", "defocused"):
        cam, scene = difstar.paper_camera(config)
        g = difstar.geometry_of(cam, scene)
        kw = dict(wavelength=LAM, z_image=float(g.z_exit_pupil),
                  defocus=float(g.defocus) if config == "defocused" else 0.0,
                  pixel_pitch=float(cam.sensor.pixel_pitch), shape=CROP, sampling="point")
        pup = cam.lens.pupil

        def plain():
            return jax.block_until_ready(difstar.psf(pup, **kw))

        t0 = time.perf_counter()
        first = plain()
        t_first = time.perf_counter() - t0
        t_plain = _best(plain, a.repeats)
        plan = difstar.plan_psf(pup, **kw)
        lam = kw.pop("wavelength")
        f = jax.jit(lambda p, lm: difstar.psf(p, wavelength=lm, plan=plan, **kw))
        jitted = f(pup, jax.numpy.asarray(lam))
        t_jit = _best(lambda: jax.block_until_ready(f(pup, jax.numpy.asarray(lam))), a.repeats)
        t_np = paper_numpy_psf(config, 2, CROP)[0]
        same = float(np.max(np.abs(np.asarray(first) - np.asarray(jitted)))
                     / np.max(np.asarray(jitted)))
        rows.append((config, t_first, t_plain, t_jit, t_np, same))
        print(f"{config}: done", file=sys.stderr, flush=True)
    print("| case | plain call, first (plan + compile) | plain call, again | jitted with "
          "its plan | NumPy paper method (3750²) | NumPy / plain again | plain again / "
          "jitted | max |plain − jitted| / peak |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for c, t1, tp, tj, tn, d in rows:
        print(f"| {c} | {t1:.3f} s | {1e3 * tp:.1f} ms | {1e3 * tj:.1f} ms | {tn:.2f} s | "
              f"{tn / tp:.0f}× | {tp / tj:.2f} | {d:.1e} |")
    print(f"\njax {jax.__version__} on {jax.default_backend()}, {os.cpu_count()} CPUs, "
          f"load average {' '.join(f'{x:.1f}' for x in os.getloadavg())}; float32; best of "
          f"{a.repeats} (NumPy: of 2).")
    return 0


if __name__ == "__main__":
    sys.exit(main())
