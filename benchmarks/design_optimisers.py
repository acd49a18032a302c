"""Design optimisers side by side: today's Adam (``optax.adam(0.1)`` on the
sigmoid-unconstrained values of the bounds) against bound-constrained L-BFGS-B
(``jaxopt.LBFGSB`` in the bounded parameters themselves), on three design problems of
the worked study (9 blades, f/8, 550 nm, the ``--quick`` grids: 64² focused PSF):

1. spikes, curvature only: halo anisotropy over curvature in [0, 0.6], from 0.3 (the
   anisotropy falls all the way to the disc, so the optimum is the bound 0.6);
2. spikes, curvature and vertices: the study's second design, curvature in [0, 0.6] and
   each vertex's relative radial and angular deviation within ±0.015, from curvature 0.3
   with the vertices a tenth of the bound off the symmetric point;
3. match a target starburst: the log-image mismatch (``image_mismatch(log=True)``) to the
   PSF of a known iris inside the box (curvature 0.35, vertices at up to ±0.01), from the
   straight-bladed iris; the answer is known: that outline, objective 0.

For each: the best objective reached, the objective-and-gradient evaluations (Adam: one
per step, the last value-only; L-BFGS-B: one for the objective's scale, then jaxopt's
count, which includes one value-only evaluation at the start of each line search), the
evaluations needed to come within 0.1 % of the best value either reached, the
iterations, the wall time of the whole ``design`` call (compilation included: every call
compiles its step once) and per iteration once compiled, whether every iterate kept
within the bounds (exact comparisons, no tolerance) and how many parameters end exactly
on a bound.

    python benchmarks/design_optimisers.py [--steps N]     (default 60: the study's)

float32 (what ``difstar design`` runs in). About 2 minutes on 2 busy CPU cores.
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

from difstar import design, image_mismatch
from difstar.design_study import study_objective, study_setup, study_start


def problems(family, setup, opts):
    """(name, objective, start, bounds (lower, upper), known answer or None) of the
    three problems."""
    spikes = study_objective(family, setup, opts)
    box_c = family.bounds(curvature=(0.0, 0.6))
    box_v = family.bounds(curvature=(0.0, 0.6), radial=0.015, angular=0.015)
    k = np.arange(family.n)
    truth = family.params(0.35, radial=0.01 * np.sin(1.3 * k + 0.4),
                          angular=0.01 * np.cos(2.1 * k))
    target = setup.focused(family.pupil(truth))

    def match(p):
        return image_mismatch(setup.focused(family.pupil(p)), target, log=True)

    return [
        ("spikes, curvature only (optimum on the bound 0.6)", spikes,
         family.params(0.3), box_c, None),
        ("spikes, curvature + 18 vertex parameters", spikes,
         study_start(family, 0.3, 0.015), box_v, None),
        ("match a target starburst (known iris, 19 parameters)", match,
         family.params(0.0), box_v, truth),
    ]


def within_bounds(box, params) -> bool:
    return all(bool(jnp.all((lo <= p) & (p <= hi)))
               for lo, hi, p in zip(jax.tree.leaves(box[0]), jax.tree.leaves(box[1]),
                                    jax.tree.leaves(params)))


def on_bound(box, params) -> int:
    """Free parameters (a range of non-zero width) exactly on a bound."""
    n = 0
    for lo, hi, p in zip(jax.tree.leaves(box[0]), jax.tree.leaves(box[1]),
                         jax.tree.leaves(params)):
        free = lo < hi
        n += int(jnp.sum(free & ((p == lo) | (p == hi))))
    return n


def outline_error(family, params, truth) -> float:
    """Largest distance between the two irises' outlines, relative to the circumradius
    (the parameters themselves are not unique: moving every vertex out alike with a
    matching curvature gives the same outline at a fixed area)."""
    a, b = family.pupil(params), family.pupil(truth)
    return float(jnp.max(jnp.abs(a.outline() - b.outline())) / b.circumradius)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--steps", type=int, default=60, help="iterations per design (60)")
    steps = ap.parse_args().steps
    family, setup, opts = study_setup(blades=9, f_number=8.0, quick=True)
    print(f"{jax.devices()[0].platform}, float32, {steps} iterations at most, "
          f"{setup.shape[0]}² focused PSF")
    print()
    print("| problem | optimiser | best objective | evaluations | evaluations to 0.1 % "
          "of best | iterations | wall s | s per iteration | in bounds | on a bound | result |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---|---:|---|")
    for name, objective, start, box, truth in problems(family, setup, opts):
        runs = {}
        for opt in ("adam", "lbfgsb"):
            stamps = []
            t0 = time.perf_counter()
            res = design(objective, start, constraints=box, optimiser=opt, steps=steps,
                         callback=lambda *_: stamps.append(time.perf_counter()) and False)
            wall = time.perf_counter() - t0
            # per iteration once compiled: between the first and the last callback
            per_it = (stamps[-1] - stamps[0]) / (len(stamps) - 1) if len(stamps) > 1 else 0
            runs[opt] = (res, wall, per_it)
        best = min(float(r[0].best_value) for r in runs.values())
        for opt, (res, wall, per_it) in runs.items():
            h = res.history
            v = h["value"]
            # "within 0.1 %": of the best value, or 1e-3 of the start's value where the
            # best is 0 (the target match)
            tol = max(1e-3 * abs(best), 1e-6 * abs(v[0]))
            hit = np.nonzero(v <= best + tol)[0]
            to_best = str(int(h["evaluations"][hit[0]])) if hit.size else "not reached"
            ok = all(within_bounds(box, p) for p in h["params"])
            p = res.best_params
            result = f"curvature {float(p.curvature):.6f}"
            if truth is not None:
                result += f", outline error {outline_error(family, p, truth):.1e} R"
            print(f"| {name} | {opt} | {float(res.best_value):.6e} | "
                  f"{int(h['evaluations'][-1])} | {to_best} | {len(v) - 1} | {wall:.1f} | "
                  f"{per_it:.3f} | "
                  f"{'yes' if ok else 'NO'} | {on_bound(box, p)} | {result} |", flush=True)


if __name__ == "__main__":
    main()
