"""The RAW fit's procedure: its stages as the types the image fit uses
(:class:`difstar.fitting.Solve`, and :class:`difstar.fitting.Restart` for the response
curves), the default one, the checks of a manifest's ``solver.stages`` and the loop that
runs them. Pure layer under ``difstar fit``: no files; progress on stderr.

The default procedure (:func:`default_procedure`), as a manifest would write it::

    "stages": [{"fix": ["toe", "knee"]},                       # σ from the data
               {"sigma": "prediction"},                         # × solver.reweight
               {"restart": {"parameter": "knee", "factors": [0.5, 2]}}]

A solve frees ``free`` ("all", or names: a parameter's name, or the base name of a
per-configuration or per-capture family such as ``defocus``) less ``fix``, every other
free parameter held where the stages before left it; ``sigma`` "prediction" takes σ
from the model's prediction at the values reached (the Poisson–Gaussian noise of the
predicted mosaic), otherwise from the observed values; ``max_steps`` (default: the
solver's). A restart moves each channel's ``parameter`` (a response-curve parameter:
``phi0``, ``toe`` or ``knee``) by each factor and keeps what ends lower
(:func:`restart_response_curves`). A hop or a repeat (as in an image fit:
:func:`difstar.fitting.fit`) re-runs the solves before it with σ as it was; one loop runs
every fit's stages (:func:`difstar.fitting._loop.run_procedure`; this module's
:class:`RawRunner` is the RAW fit's part of it)."""

from __future__ import annotations

import dataclasses
import math
import sys
import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from difstar._fit import (
    base_name,
    free_parts,
    make_args,
    noise_sigma,
    to_unconstrained,
    weights,
)
from difstar._progress import moved_most
from difstar.fitting._loop import StageRunner, run_procedure
from difstar.fitting._params import FitInputError
from difstar.fitting._stage_types import Hop, Repeat, Restart, Solve, parse_stage
from difstar.fitting._stages import _check_hop, _check_repeat, _InputAt
from difstar.io._scene import SceneError

#: Restarts of each channel's response-curve parameters, as factors of the value reached:
#: the knee and toe of a channel whose captures barely reach its shoulder are weakly
#: constrained, and Levenberg–Marquardt can stop in a shallow basin (a knee half or
#: twice its true value) that the other channels' data do not pull it out of.
RESTART_FACTORS = (0.5, 2.0)

#: The sensor's parameters a restart may move (one value per channel).
RESTARTABLE = ("phi0", "toe", "knee")

#: Seconds from the command's start to the end of its first solver step (once per process).
FIRST_STEP: dict = {}


def _log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def seconds_since_process_start() -> float | None:
    """Seconds since this process started (Linux /proc; None elsewhere)."""
    import os

    try:
        with open("/proc/self/stat") as f:
            start = float(f.read().rsplit(")", 1)[1].split()[19])  # field 22, in ticks
        with open("/proc/uptime") as f:
            up = float(f.read().split()[0])
        return up - start / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None


#: Also mask pixels expected within this many σ of the white level (see observed_data).
SATURATION_GUARD = 4.0


def observed_data(model, caps: dict, noise: dict, sigma_from: dict | None = None):
    """{config: (ζ_obs, weight)} with σ from ``sigma_from`` ({config: ζ (K, h, w)}, e.g.
    a prediction) or from the observed ζ."""
    import jax.numpy as jnp

    data = {}
    for cfg in model.configs:
        names = [c.name for c in model.captures_of(cfg.name)]
        z = np.stack([caps[n]["zeta"] for n in names])
        sat = np.stack([caps[n]["saturated"] for n in names])
        fs = np.asarray([caps[n]["full_scale_dn"] for n in names])[:, None, None]
        ref = z if sigma_from is None else np.asarray(sigma_from[cfg.name])
        kw = dict(gain_e_per_dn=noise["gain_e_per_dn"], read_noise_dn=noise["read_noise_dn"],
                  full_scale_dn=fs.astype(float), xp=np)
        sig = noise_sigma(ref.astype(float), **kw)
        # Censoring: a pixel whose expected value lies within a few σ of the white level
        # is clipped by its noise more often one way than the other, so its unclipped
        # values are biased low (a 1 % bias in φ0 here). Mask them as well as the clipped.
        near = ref >= 1.0 - SATURATION_GUARD * noise_sigma(1.0, **kw)
        data[cfg.name] = (jnp.asarray(z), jnp.asarray(weights(sig, sat | near, xp=np)))
    return data


def default_procedure(model, solver: dict) -> tuple:
    """The response curves held and σ from the data; then everything free with σ from
    the prediction (``solver.reweight`` times, at least once); then, where the knee is
    free, its restarts."""
    stages = [Solve(fix=("toe", "knee"))]
    stages += [Solve(sigma="prediction")] * max(1, int(solver.get("reweight", 1)))
    knee = model.params.get("knee")
    if knee is not None and knee.free:
        stages.append(Restart("knee", RESTART_FACTORS))
    return tuple(stages)


def _members(model, q: str) -> list[str]:
    """The parameters ``q`` names: itself, or a family's members (``defocus`` →
    ``defocus/<config>`` …)."""
    return [k for k in model.params if k == q or base_name(k) == q]


def _inside_bounds(p, x):
    """``x`` kept 1e-3 of the range inside ``p``'s bounds (where the bound map's
    unconstrained value stays finite and its slope usable)."""
    margin = 1e-3 * (np.asarray(p.hi) - np.asarray(p.lo))
    return np.clip(x, p.lo + margin, p.hi - margin)


def _names(model, given, where: str) -> set[str]:
    """The model's free parameters that ``given`` names (a full name, or a family's base
    name); a name that is no parameter of the model is refused."""
    out = set()
    for q in given:
        named = set(_members(model, q))
        if not named:
            raise ValueError(f"{where}: {q!r} is not a parameter of the fit; known: "
                             f"{sorted(model.params)}.")
        out |= named & set(model.free)
    return out


def freed(model, st: Solve, where: str = "stage") -> set[str]:
    """The free parameters a solve moves."""
    free = set(model.free) if st.free == "all" else _names(model, st.free, where + "/free")
    return free - _names(model, st.fix, where + "/fix")


def procedure_of(model, solver: dict, src: str = "<manifest>") -> tuple:
    """The procedure ``solver.stages`` gives (dicts, as a manifest writes them, or typed
    stages), checked against ``model``; the default one where it gives none. Raises
    ``SceneError`` naming the stage and field."""
    given = solver.get("stages")
    if given is None:
        return default_procedure(model, solver)
    if not isinstance(given, (list, tuple)) or not given:
        raise SceneError(f"{src}: field solver/stages: a non-empty list of stages; got "
                         f"{given!r}.")
    out = []
    solve_fields = ("free", "fix", "max_steps", "sigma")
    for i, st in enumerate(given):
        where = f"{src}: field solver/stages/{i}"
        try:
            if isinstance(st, dict):
                st = parse_stage(st)
        except TypeError as e:
            raise SceneError(f"{where}: {e}") from None
        if isinstance(st, Restart):
            if not out:
                raise SceneError(f"{where}: a restart needs a solve before it.")
            p = model.params.get(st.parameter)
            if st.parameter not in RESTARTABLE or p is None or not p.free:
                raise SceneError(f"{where}/restart/parameter: restarts move a free response-"
                                 f"curve parameter (one of {list(RESTARTABLE)}); got "
                                 f"{st.parameter!r}.")
            if not st.factors or not all(isinstance(f, (int, float)) and math.isfinite(f)
                                         and f > 0 for f in st.factors):
                raise SceneError(f"{where}/restart/factors: finite numbers > 0; got "
                                 f"{list(st.factors)}.")
            last = next(s for s in reversed(out) if isinstance(s, Solve))
            if st.parameter not in freed(model, last):
                # its re-solves run on that solve's terms, where a held value cannot move
                raise SceneError(f"{where}/restart/parameter: {st.parameter} is held by the "
                                 "solve before it; restart a parameter that solve frees.")
            out.append(st)
            continue
        if isinstance(st, (Hop, Repeat)):
            _check_hop_or_repeat(model, i, st, sum(isinstance(s, Solve) for s in out), where)
            out.append(st)
            continue
        if not isinstance(st, Solve):
            raise SceneError(f"{where}: a RAW fit's stage is a solve ({list(solve_fields)}), "
                             f"a restart, a hop or a repeat; got {type(st).__name__}.")
        extra = sorted(k for k in st.as_dict() if k not in solve_fields)
        if extra:
            raise SceneError(f"{where}: {extra} apply to image fits; a RAW fit's solve takes "
                             f"{list(solve_fields)}.")
        if st.sigma not in (None, "data", "prediction"):
            raise SceneError(f"{where}/sigma: 'data' or 'prediction'; got {st.sigma!r}.")
        if st.max_steps is not None and not (float(st.max_steps).is_integer()
                                             and st.max_steps >= 1):
            raise SceneError(f"{where}/max_steps: a whole number >= 1; got {st.max_steps!r}.")
        try:
            moved = freed(model, st, where)
        except ValueError as e:
            raise SceneError(str(e)) from None
        if not moved:
            raise SceneError(f"{where}: frees no free parameter; free one (\"free\": \"all\").")
        out.append(st)
    return tuple(out)


def _check_hop_or_repeat(model, si: int, st, n_solving: int, where: str) -> None:
    """The image fit's checks of a hop or a repeat (names, offsets, tolerances, how
    many solves it re-runs), as a RAW manifest's field: a family's base name (e.g.
    ``defocus``) stands for its members in ``until``."""
    try:
        if isinstance(st, Hop):
            _check_hop(model, si, st.as_dict()["hop"], n_solving)
        else:
            families = sorted({base_name(k) for k in model.params if "/" in k})
            _check_repeat(model, si, st.as_dict()["repeat"], n_solving, families)
    except _InputAt as e:  # its place in the stage: hop, hop/set
        raise SceneError(f"{where}/{'/'.join(map(str, e.path[2:]))}: {e.detail}") from None
    except FitInputError as e:
        kind = "hop" if isinstance(st, Hop) else "repeat"
        raise SceneError(f"{where}/{kind}: {str(e).removeprefix(f'fit: stage {si}: ')}"
                         ) from None


def stage_label(st: Solve) -> str:
    what = "all free parameters" if st.free == "all" else ", ".join(st.free)
    if st.fix:
        what += " except " + ", ".join(st.fix)
    return f"{what}, σ from the {'prediction' if st.sigma == 'prediction' else 'data'}"


def run_stages(fitter, model, caps, noise, u0, solver: dict, *,
               procedure: Sequence | None = None, verbose: bool = True):
    """The stages of ``procedure`` (default: ``solver["stages"]``, else
    :func:`default_procedure`; checked by :func:`procedure_of`) in turn, each from where
    the last ended, by the one stage loop of every fit
    (:func:`difstar.fitting._loop.run_procedure`: hops and repeats as in an image fit).
    Returns the final solve (:class:`difstar._lm.SolveResult`: its ``u``, and its
    linearisation for the covariance), the per-stage records and the last solve's
    ``args``."""
    procedure = procedure_of(model, solver if procedure is None
                             else {**solver, "stages": list(procedure)}, "run_stages")
    runner = RawRunner(fitter, model, caps, noise, solver, verbose=verbose)
    state = run_procedure(runner, procedure, RawState(u0))
    return state.solved, runner.log, state.args


@dataclasses.dataclass(frozen=True)
class RawState:
    """Where a RAW fit stands between stages: the solver's vector ``u``, the last solve
    (None before the first), the data with the σ that solve used ({config: (ζ,
    weight)}) and its ``args``."""

    u: Any
    solved: Any = None
    data: dict | None = None
    args: dict | None = None


class RawRunner(StageRunner):
    """The RAW camera fit's stages for the one stage loop: a :class:`Solve` (``free``,
    ``fix``, ``sigma``, ``max_steps``) and a :class:`Restart` of the response curves;
    its loss is the solver's, ½ Σ ((ζ_pred − ζ_obs)/σ)²."""

    loss_name = "loss"

    def __init__(self, fitter, model, caps, noise, solver: dict, *, verbose: bool = True):
        super().__init__(verbose=verbose)
        self.fitter, self.model, self.caps, self.noise = fitter, model, caps, noise
        self.solver = solver

    def value(self, state: RawState, name: str):
        x = self.fitter.values(state.u)[name]
        return float(x) if x.ndim == 0 else x

    def moved(self, state: RawState, change) -> RawState:
        vals = self.fitter.values(state.u)
        for q, x in change.items():
            p = self.model.params[q]
            vals[q] = _inside_bounds(p, np.broadcast_to(np.asarray(x, float), p.shape))
        return dataclasses.replace(state, u=to_unconstrained(self.model, vals))

    def expand(self, names) -> list[str]:
        return [k for q in names for k in _members(self.model, q)]

    def loss(self, state: RawState, ref: RawState) -> float:
        if state.data is ref.data and state.solved is not None \
                and np.array_equal(np.asarray(state.solved.u), np.asarray(state.u)):
            return float(state.solved.loss)  # the solve's own, on the same σ
        return self.fitter.loss(state.u, make_args(self.model, ref.data, state.u))

    def solve(self, si: int, st, state: RawState, *, again: bool = False) -> RawState:
        model, fitter, solver, verbose = self.model, self.fitter, self.solver, self.verbose
        records = self.log
        if isinstance(st, Restart):
            t0 = time.perf_counter()
            solved, tries = restart_response_curves(
                fitter, model, state.solved, state.args, solver, parameter=st.parameter,
                factors=st.factors, verbose=verbose)
            if tries:
                kept = [t for t in tries if t["kept"]]
                records.append({"label": "response-curve restarts", "tries": tries,
                                "steps": sum(t["steps"] for t in tries),
                                "result": f"{len(kept)} of {len(tries)} kept",
                                "seconds": time.perf_counter() - t0, "compile_seconds": 0.0})
            return dataclasses.replace(state, u=solved.u, solved=solved)
        u = state.u
        label = stage_label(st) + (" (again, σ as it was)" if again else "")
        moving = freed(model, st)
        hold = tuple(k for k in model.free if k not in moving)
        if again and state.data is not None:
            data = state.data
        else:
            sigma_from = fitter.predict(u) if st.sigma == "prediction" else None
            data = observed_data(model, self.caps, self.noise, sigma_from)
        args = make_args(model, data, u, hold=hold)
        # the process's first solve: its first step (tracing, compiling) is said before
        # it starts and timed when it ends
        first = not any("loss_end" in r for r in records) and "first_step" not in FIRST_STEP
        max_steps = int(solver.get("max_steps", 100) if st.max_steps is None else st.max_steps)
        if verbose:
            _log(f"difstar fit: stage {si + 1}: {label}")
            _log(f"{'iter':>6} {'loss':>14} {'step size':>11} {'time left':>10}  moved most")
            if first:
                _log("  (the first step traces and compiles the solver's programs: tens of "
                     "seconds the first time these shapes are fitted on this machine, a "
                     "few from the compilation cache after)")
        last = [free_parts(model, u)]
        after_first = [0.0]

        def progress(k, loss, size, done, u_k):
            if k == 1 and first:
                FIRST_STEP["first_step"] = seconds_since_process_start()
                if verbose and FIRST_STEP["first_step"] is not None:
                    _log(f"difstar fit: first step done {FIRST_STEP['first_step']:.1f} s "
                         "after the command started")
            if verbose:
                parts = free_parts(model, u_k)
                name, _ = moved_most(last[0], parts)
                last[0] = parts
                _log(f"{k:>6d} {loss:>14.6g} {size:>11.3g} "
                     f"{time_left(k, max_steps, done, after_first):>10}  {name or '-'}"
                     + ("  (done)" if done else ""))

        res = fitter.solve(u, args, max_steps=max_steps, ftol=float(solver.get("ftol", 1e-6)),
                           progress=progress)
        records.append({
            "label": label, "held": list(hold), "steps": res.steps, "accepted": res.accepted,
            "loss_start": res.loss_start, "loss_end": res.loss, "result": res.result,
            "seconds": res.seconds, "compile_seconds": res.compile_seconds,
        })
        if verbose:
            _log(f"difstar fit: stage {si + 1} {res.result} after {res.steps} steps, "
                 f"{res.seconds:.1f} s (+ {res.compile_seconds:.1f} s compile)")
        return RawState(res.u, res, data, args)


def time_left(k: int, max_steps: int, done: bool, after_first: list) -> str:
    """The most time a solve may still take after step ``k`` of ``max_steps``, from the
    mean time of its steps after the first (which compiles): "≤12s" ("-" after the
    first step, "0s" when done), one word. It stops earlier where its rule is met.
    ``after_first``: [the clock when step 1 ended], kept by the caller."""
    now = time.perf_counter()
    if k == 1:
        after_first[0] = now
        return "0s" if done else "-"
    if done:
        return "0s"
    return f"≤{(now - after_first[0]) / (k - 1) * (max_steps - k):.0f}s"


def restart_response_curves(fitter, model, solved, args, solver: dict, *,
                            parameter: str = "knee", factors=RESTART_FACTORS,
                            verbose: bool = True):
    """From the converged solve ``solved`` (a :class:`difstar._lm.SolveResult` on
    ``args``), try each channel's ``parameter`` moved by each of ``factors`` (inside its
    bounds), everything else as reached; keep any start that ends at a lower loss.
    Returns (the best solve, tries). (The toe, pinned by the unsaturated dark pixels of
    every capture, has not needed it.)

    A restart first re-solves that channel's sensor parameters alone (φ0, toe, knee),
    the optics held where ``solved`` put them (:meth:`difstar._fit.Fitter.solve_sensor`:
    a step costs the sensor's arithmetic on the linear images predicted once, not the
    PSF). The basin a restart looks for is the response curve's; only a restart that
    ends lower there is then solved with everything free, from where it ended, and kept
    if that ends lower than ``solved``."""
    tries = []
    spec = model.params.get(parameter)
    if spec is None or not spec.free:
        return solved, tries
    max_steps = int(solver.get("max_steps", 100))
    ftol = float(solver.get("ftol", 1e-6))
    images = fitter.linear_images(solved.u)  # the optics' work, once
    for ch in range(spec.size):
        sensor_args = fitter.sensor_args(solved.u, args["data"], ch, images)
        floor = fitter.sensor_loss(solved.u, sensor_args)  # = the loss at solved.u
        for f in factors:
            vals = fitter.values(solved.u)
            x = vals[parameter].copy()
            x[ch] = _inside_bounds(spec, x * f)[ch]
            vals[parameter] = x
            res = fitter.solve_sensor(to_unconstrained(model, vals), sensor_args,
                                      max_steps=max_steps, ftol=ftol)
            steps = res.steps
            # a lower basin (by more than χ² 1, a 1-σ change of one parameter, and than
            # rounding): solve it whole
            lower = floor - res.loss > max(0.5, 1e-6 * floor)
            if lower:
                res = fitter.solve(res.u, args, max_steps=max_steps, ftol=ftol)
                steps += res.steps
            # solved.loss: the loss at solved.u (no model evaluation to compile)
            better = lower and res.loss < solved.loss * (1 - 1e-9)
            tries.append({"parameter": f"{parameter}[{ch}]", "factor": f, "loss": res.loss,
                          "kept": bool(better), "steps": steps})
            if verbose:
                _log(f"difstar fit: restart {parameter}[{'RGB'[ch] if spec.size == 3 else ch}]"
                     f" × {f:g}: loss {res.loss:.7g} ({'lower: kept' if better else 'not lower'})")
            if better:
                solved = res
                images = fitter.linear_images(solved.u)
                sensor_args = fitter.sensor_args(solved.u, args["data"], ch, images)
                floor = fitter.sensor_loss(solved.u, sensor_args)
    return solved, tries
