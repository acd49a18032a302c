"""Cost of the pupil raster and of its derivative: autodiff of the edge-by-edge
Green's-theorem terms (``_pupil.outline_coverage``) against the shape derivative on the
outline's cell pieces (``_pupil.tiled_outline_coverage``, what the ATF uses on square
grids). Prints a table: forward, reverse mode (gradient of a weighted sum), forward mode
(3 Jacobian columns), and the two gradients' relative difference.

    python benchmarks/coverage_gradient.py            # windows 1380 and 2234 (n = 4000, 6480)
    python benchmarks/coverage_gradient.py 512 1024   # other window sizes
"""

from __future__ import annotations

import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from difstar.pupils import outline_coverage, regular_polygon_vertices, tiled_outline_coverage


def _best(fn, repeats=3):
    jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - t0)
    return min(times)


def row(m: int, fn):
    r = 1.17e-3  # the paper lens's exit-pupil circumradius at f/22 (metres)
    cell = 2.2 * r / m
    x = ((jnp.arange(m) - m // 2) * cell)[None, :].astype(jnp.float32)
    y = -x.T  # rows run along −y, as on the frequency grid
    w = jax.random.normal(jax.random.PRNGKey(0), (m, m), jnp.float32)

    def cov(p):  # circumradius, rotation, and a scale of the whole grid (as λ or Δz move it)
        v = regular_polygon_vertices(7, p[0], p[1])
        return fn(v, jnp.roll(v, -1, axis=0), x * p[2], y * p[2], cell * p[2])

    p = jnp.asarray([r, 0.1, 1.0], jnp.float32)
    f = jax.jit(cov)
    g = jax.jit(jax.grad(lambda p: jnp.sum(cov(p) * w)))
    jf = jax.jit(jax.jacfwd(cov))
    return (_best(lambda: f(p)), _best(lambda: g(p)), _best(lambda: jf(p)),
            np.asarray(g(p), np.float64))


def main(argv) -> int:
    sizes = [int(a) for a in argv] or [1380, 2234]
    print(f"7-blade pupil raster, float32, {jax.devices()[0].platform} backend\n")
    print("| window | method | forward s | gradient s | jacfwd (3 columns) s | grad rel. diff |")
    print("|---|---|---|---|---|---|")
    for m in sizes:
        rows = {name: row(m, fn) for name, fn in (("autodiff of Green terms", outline_coverage),
                                                  ("shape derivative (tiled)", tiled_outline_coverage))}
        ga = rows["autodiff of Green terms"][3]
        for name, (tf, tg, tj, gr) in rows.items():
            diff = float(np.max(np.abs(gr - ga) / np.abs(ga)))
            print(f"| {m}² | {name} | {tf:.4f} | {tg:.4f} | {tj:.4f} | {diff:.1e} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
