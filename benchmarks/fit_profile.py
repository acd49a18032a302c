"""Where the time of a fit goes: one Levenberg–Marquardt step split into its parts.

    python benchmarks/fit_profile.py [fit/synthetic-paper-camera/manifest.json] [--repeats 3]

Loads the campaign's captures, builds the fit model and its compiled machinery exactly
as ``difstar fit`` does, and times (best of ``--repeats``, after compiling):

- the residuals (the forward model for every capture, one PSF per configuration);
- the Jacobian (forward-mode, ``jac_batch`` parameter directions at a time);
- the dense linear algebra of one damped step (QR of the Jacobian, numpy);
- one whole solver step (``Fitter._step``: what ``difstar fit`` runs per iteration);

and prints a Markdown table with each part's share of the step. Then the size of what a
first run compiles and how long it takes (no compilation cache): the chain's equations
(``jax.make_jaxpr``, counted through every nested jaxpr) for the residuals and for
their linearisation, the solver step's trace and lowering, its XLA compile in
wall-clock and CPU seconds (a compile uses more than one core), and the compiled
step's run time (what ``difstar fit`` runs per iteration).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402


def _best(fn, repeats: int) -> tuple[float, float]:
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    first = time.perf_counter() - t0
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - t0)
    return first, best


def _equations(jaxpr) -> int:
    """Equations of ``jaxpr`` and of every jaxpr nested in its equations' parameters."""
    jaxpr = getattr(jaxpr, "jaxpr", jaxpr)
    n = 0
    for eqn in jaxpr.eqns:
        n += 1
        for v in eqn.params.values():
            for sub in v if isinstance(v, (tuple, list)) else (v,):
                if hasattr(sub, "eqns") or hasattr(getattr(sub, "jaxpr", None), "eqns"):
                    n += _equations(sub)
    return n


def _program_sizes(fitter, u, args) -> list[str]:
    """The first run's compile, on a Fitter that has compiled nothing yet: the solver's
    first state (its trace is the chain's linearisation's), the step's trace and
    lowering, its XLA compile; then the chain's equations."""
    lm = fitter._lm
    sol = lm.solver()
    t0 = time.perf_counter()
    state = lm._init_with(sol, u, args)
    t_init = time.perf_counter() - t0
    t0 = time.perf_counter()
    lowered = lm._step_with.jitted.lower(sol, u, state, args)
    t_lower = time.perf_counter() - t0
    t0, c0 = time.perf_counter(), time.process_time()
    step = lowered.compile()
    t_xla, c_xla = time.perf_counter() - t0, time.process_time() - c0
    _, t_step = _best(lambda: step(sol, u, state, args)[0], 5)
    fn = fitter._fn
    primal = _equations(jax.make_jaxpr(lambda v: fn(v, args))(u))
    lin = _equations(jax.make_jaxpr(lambda v: jax.linearize(lambda w: fn(w, args), v)[0])(u))
    return [f"- the chain's equations: {primal} (residuals), {lin} (their linearisation)",
            f"- the solver's first state (the chain's linearisation traced): {t_init:.2f} s; "
            f"the step traced and lowered: {t_lower:.2f} s; XLA compiled it in "
            f"{t_xla:.2f} s wall, {c_xla:.2f} s CPU; it runs in {1e3 * t_step:.0f} ms "
            "(best of 5)"]


def main(argv=None) -> int:
    from difstar.raw_fit import (
        Fitter,
        load_manifest,
        make_args,
        observed_data,
        prepare,
        to_unconstrained,
    )

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("manifest", nargs="?",
                    default=str(Path(__file__).resolve().parents[1] / "fit"
                                / "synthetic-paper-camera" / "manifest.json"))
    ap.add_argument("--repeats", type=int, default=3)
    a = ap.parse_args(argv)

    man = load_manifest(a.manifest)
    model, caps = prepare(man)
    fitter = Fitter(model, method=man.solver["method"], rtol=man.solver["rtol"],
                    atol=man.solver["atol"])
    u = to_unconstrained(model)
    args = make_args(model, observed_data(model, caps, man.noise), u)
    n_res = sum(int(np.prod(caps[c.name]["crop"])) for c in model.captures)

    sizes = _program_sizes(Fitter(model, method=man.solver["method"]), u, args)
    rows = []
    c_res, t_res = _best(lambda: fitter._flat(u, args), a.repeats)
    rows.append(("residuals (forward model, all captures)", c_res, t_res))
    c_jac, t_jac = _best(lambda: fitter._jac(u, args), a.repeats)
    rows.append((f"Jacobian ({model.n_free} columns, forward mode)", c_jac, t_jac))
    j = np.asarray(fitter._jac(u, args))
    c_qr, t_qr = _best(lambda: np.linalg.qr(j), a.repeats)
    rows.append((f"QR of the {j.shape[0]} × {j.shape[1]} Jacobian (numpy)", 0.0, t_qr))
    state = fitter._init(u, args)
    c_step, t_step = _best(lambda: fitter._step(u, state, args)[4], a.repeats)
    rows.append(("one solver step (optimistix LM, all of the above)", c_step, t_step))

    print(f"Fit profile: {man.path}")
    print(f"{len(model.captures)} captures, {n_res} residuals, {model.n_free} free parameters; "
          "grids " + ", ".join(f"{c.name} n = {c.grid.n}" for c in model.configs))
    print(f"jax {jax.__version__}, backend {jax.default_backend()}, "
          f"{jax.device_count()} device(s)\n")
    print("| part | first call s (compile + run) | run s | share of one step |")
    print("|---|---|---|---|")
    for name, first, best in rows:
        share = best / t_step
        print(f"| {name} | {first:.2f} | {best:.3f} | {share * 100:.0f} % |")
    print("\nWhat a first run compiles (no compilation cache):")
    print("\n".join(sizes))
    return 0


if __name__ == "__main__":
    sys.exit(main())
