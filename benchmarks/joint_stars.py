"""What a joint fit of several stars of one field costs as the stars grow in number:
the Spitzer star (``fit/spitzer-irac/variants/auto.json``, the automatic stages) and
copies of it moved by fractions of a pixel (Lanczos3, ``difstar.fitting.shifted_image``),
fitted together (one pupil, rotation, wavefront and detector; each star its own centre,
flux and background: ``difstar.fitting.fit_joint``), each count in a fresh process with
JAX's compilation cache off (every program traced and compiled, as on a first run).

    python benchmarks/joint_stars.py [--stars 1,2,4,8] [--manifest MANIFEST]

Prints one Markdown table (BENCHMARKS.md, "Several stars: cost against their number"):
wall time of the fit (imports excluded), peak memory of the process, the rotation and
its standard error, χ²/dof. The copies share the star's noise, so the standard errors
count that noise once per copy: they show the fit's arithmetic, not a field's gain."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MANIFEST = ROOT / "fit/spitzer-irac/variants/auto.json"
#: the moves of the copies (columns right, rows down, pixels), in order
MOVES = [(0.5, 0.0), (0.0, -0.5), (0.3, 0.3), (-0.4, 0.2), (0.25, -0.35), (-0.3, -0.3),
         (0.45, 0.1), (-0.15, 0.45), (0.35, -0.2), (-0.45, -0.1), (0.1, 0.4), (-0.2, -0.45),
         (0.4, 0.35), (-0.35, 0.3), (0.2, -0.1)]

_CHILD = """
import json, resource, sys, time
from difstar.fitting import fit_joint, shifted_image
moves = json.loads(sys.argv[2])
changes = [lambda im, d=d: shifted_image(im, *d) for d in moves]
t0 = time.perf_counter()
res = fit_joint(sys.argv[1], changes)
t = time.perf_counter() - t0
print(json.dumps({"seconds": t, "rotation": res.values["rotation"],
                  "error": res.errors.get("rotation"), "chi2_dof": res.chi2_dof,
                  "rss_kb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss}))
"""


#: the most stars a run takes
MOST = 200


def moves(n: int) -> list[tuple[float, float]]:
    """The moves of ``n`` copies: :data:`MOVES`, then a grid of tenths of a pixel."""
    extra = [(round(0.1 * (k % 9) - 0.4, 2), round(0.1 * (k // 9 % 9) - 0.4, 2))
             for k in range(max(0, n - len(MOVES)))]
    return (list(MOVES) + extra)[:n]


def run(n: int, manifest: Path) -> dict:
    env = dict(os.environ, DIFSTAR_COMPILATION_CACHE="off")
    moves_json = json.dumps(moves(n - 1))
    t0 = time.perf_counter()
    out = subprocess.run([sys.executable, "-c", _CHILD, str(manifest), moves_json], env=env,
                         capture_output=True, text=True, check=True)
    row = json.loads(out.stdout.strip().splitlines()[-1])
    row["process"] = time.perf_counter() - t0
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--manifest", default=str(MANIFEST.relative_to(ROOT)),
                    help="the star's manifest (default: the Spitzer star's automatic stages)")
    ap.add_argument("--stars", default="1,2,4,8",
                    help=f"comma-separated counts, each 1 to {MOST}")
    a = ap.parse_args(argv)
    counts = [int(c) for c in a.stars.split(",") if c.strip()]
    if any(not 1 <= c <= MOST for c in counts):
        ap.error(f"--stars: each count from 1 to {MOST}")
    rows = []
    for n in counts:
        rows.append((n, run(n, ROOT / a.manifest)))
        print(f"{n} stars: {rows[-1][1]['seconds']:.1f} s", file=sys.stderr, flush=True)
    one = rows[0][1]["seconds"] / rows[0][0] if rows else 1.0
    print("| stars | fit (s) | per star (s) | process (s) | peak RSS (GB) | rotation (°) "
          "| χ²/dof |")
    print("|---:|---:|---:|---:|---:|---|---:|")
    for n, r in rows:
        err = "–" if r["error"] is None else f"{r['error']:.4f}"
        print(f"| {n} | {r['seconds']:.1f} | {r['seconds'] / n:.1f} | {r['process']:.1f} | "
              f"{r['rss_kb'] / 2**20:.2f} | {r['rotation']:.4f} ± {err} | "
              f"{r['chi2_dof']:.3f} |")
    load = os.getloadavg()
    print(f"\n{a.manifest}; {os.cpu_count()} CPUs, load average {load[0]:.1f} "
          f"{load[1]:.1f} {load[2]:.1f} after the runs; first count's fit per star "
          f"{one:.1f} s.")
    return 0


if __name__ == "__main__":
    sys.exit(main())
