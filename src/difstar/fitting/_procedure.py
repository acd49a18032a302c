""":func:`fit`: an image fit's stages run in turn (windows, free parameters, scans, hops,
repeats, reweighting), every stage checked before any solves; its solving stage is
:class:`_ImageRunner`'s, the loop (hops, repeats) :func:`._loop.run_procedure`, which
the RAW fit runs too."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping, Sequence

import numpy as np

from ._analysis import chi2_at, scan_grid, scan_rivals, spike_target
from ._auto import auto_stages, stages_text
from ._data import noise_from_residuals, reject_outliers
from ._loop import StageRunner, run_procedure
from ._model import ImageModel
from ._params import FitInputError
from ._residuals import _as_list, _PixelTarget
from ._solve import FitResult, _errors, _one_fit, compile_errors_ahead, model_images
from ._stage_types import Hop, Repeat, Solve, parse_stage, stage_dicts
from ._stages import _check_fit_inputs, _put


def fit(model: ImageModel, data, *, stages: Sequence[Solve | Hop | Repeat | Mapping] | str
        | None = None,
        starts: Mapping[str, Sequence[float]] | None = None, max_steps: int = 100,
        rtol: float = 1e-6, atol: float = 1e-8, verbose: bool = False,
        per_capture: Sequence[str] | None = None) -> FitResult:
    """Fit ``model`` to ``data`` by Levenberg–Marquardt.

    ``data``: a :class:`FitData`, or a list of them (captures of the same star:
    exposures, dithers, frames) fitted together; then each name in ``per_capture``
    (default ``x0``, ``y0``, ``flux``, ``background``) has one value per capture,
    ``name@i`` in the result, and every other parameter is shared.

    ``stages``: coarse to fine, each a :class:`Solve`, :class:`Hop` or :class:`Repeat`, or
    the same as a dict (as a manifest writes it), with

    - ``free`` (names, or "all": the model's free parameters), ``fix`` (names held);
    - ``set`` (name → value): before the stage, put those parameters at those values
      (kept inside their bounds), whatever the start or the earlier stages gave them:
      coarse to fine, e.g. the wavefront at zero until the geometry is found, so that
      a rough start's wavefront cannot steer the coarse stages into another basin;
    - ``half`` (fit the central (2 half + 1)² pixels; None: the whole image) and
      ``annulus`` ([r_min, r_max] pixels: only those radii);
    - ``spikes``: fit the spikes instead of all pixels, around the directions
      :func:`spike_angles` measures in the data, about the star's centre and background
      reached so far (options of :func:`spike_target`: ``r_min``, ``r_max``,
      ``half_width``, ``n_spikes``, ``directions`` "data" or "model"; ``profiles``
      true: their angular profiles, :class:`SpikeProfiles`; false: the pixels within
      ± ``half_width`` degrees): the stage for the rotation;
    - ``noise_from_residuals`` (options of :func:`noise_from_residuals`, e.g.
      ``{"floor": 0.03}``): before the stage, σ from read noise and gain estimated from
      the residual at the values reached, for this and later stages and the errors;
    - ``reject`` (options of :func:`reject_outliers`, e.g. ``{"above": 20, "r_min": 12,
      "grow": 2, "relative": 3e-4}``): before the stage (after ``noise_from_residuals``),
      mask the pixels more than ``above`` σ from the model at the values reached, away
      from the core (a neighbouring star, a cosmic ray, a hot pixel), for this and later
      stages; the number masked and the largest |residual| / σ kept are logged;
    - ``scan`` (``{"name": "rotation", "half_range": 5, "step": 0.2}``): first move that
      parameter to the lowest χ² on a grid, then solve;
    - ``max_steps``, ``rtol``: the solver's limits (default: the arguments);
    - a stage that is only ``hop`` (``{"name": "rotation", "offsets": [-0.5, 0.5],
      "stages": 2}``): re-run the ``stages`` solving stages before it with that
      parameter moved by each offset and keep the lowest χ² on all pixels: a way out of
      a neighbouring basin that the other parameters' adaptation makes self-consistent;
      ``{"flip": ["z6"], "stages": 2}`` negates each named parameter in turn instead
      (an entry that is a list of names negates those together: ``{"flip": [["z4",
      "z5", "z6", "z11"]]}`` is the whole twin of the even terms) —
      for the sign ambiguities of even wavefront terms in an in-focus image (the
      "twin" of phase retrieval: W(x, y) and −W(−x, −y) give the same image for a
      centrally symmetric pupil, so an almost symmetric one has a near-twin minimum);
      ``{"set": {"z4": 0, "z5": 0}, "stages": 3}`` puts the named parameters at those
      values, all at once (a second start for the wavefront from zero: a rough start's
      wavefront can settle in a neighbouring minimum);
    - a stage that is only ``repeat`` (``{"until": {"rotation": 0.002}, "stages": 2,
      "max_rounds": 6}``): re-run the ``stages`` solving stages before it, round after
      round (σ as it is), until each parameter named in ``until`` moves by less than its
      tolerance over a round: the fixed point of stages that fit different parameters
      in turn (the rotation on the spikes, then the rest on all pixels), which a single
      pass leaves wherever its start put it along a long, flat valley. Not settled after
      ``max_rounds``: a warning in the result.

    A stage with a key or an option not listed here is refused before any fitting.
    Each stage starts from the last one's values. Standard errors are computed at the
    end for every free parameter on the pixels; those of parameters last fitted in a
    spikes stage come from that stage. Default: one stage, all free, whole image;
    ``"auto"``: the stages :func:`auto_stages` chooses from the model and the data.
    ``starts``: name → start values tried in the first stage (multi-start; the lowest χ²
    goes on). Raises :class:`FitInputError` for inputs that cannot be right. For several
    captures the result's images (``model_image``, ``residual``, ``data``, ``mask``)
    are lists, one per capture.
    """
    t0 = time.perf_counter()
    datas = _as_list(data)
    n_cap = len(datas)
    if n_cap == 0:
        raise FitInputError("fit: no data (an empty list of captures).")
    for i, d in enumerate(datas):
        if d.image.shape[0] < 4 or d.image.shape[1] < 4:
            raise FitInputError(f"fit: capture {i}'s window is smaller than 4 × 4 pixels.")
    if isinstance(stages, str):
        if stages != "auto":
            raise FitInputError(f"fit: stages must be a list of stages or 'auto'; got "
                                f"{stages!r}.")
        stages = auto_stages(model, datas)
        if verbose:
            print("stages chosen from the model and the data (stages='auto'):\n"
                  + stages_text(stages), flush=True)
    if n_cap > 1 or per_capture:
        per = ("x0", "y0", "flux", "background") if per_capture is None else tuple(per_capture)
        model = model.for_captures(per, n_cap)
    if not model.free:
        raise FitInputError("fit: no free parameter (set free=true on at least one).")
    stages = stage_dicts(stages or [Solve()])  # checked in this form, then parsed
    # every stage's mistakes (keys, names, windows, limits, scans, hops, repeats) and the
    # starts' are found before any fitting; a repeat's (stages, until, max_rounds) kept
    _check_fit_inputs(model, datas, stages, starts=starts, max_steps=max_steps, rtol=rtol)
    stages = [parse_stage(st) for st in stages]
    runner = _ImageRunner(model, n_cap, starts=starts, max_steps=max_steps, rtol=rtol,
                          atol=atol, verbose=verbose)
    state = run_procedure(runner, stages, _State(model.values(), tuple(datas)))
    values, datas = state.values, list(state.datas)
    status, ok, steps = state.status, state.ok, state.steps
    log, notes = runner.log, runner.notes
    spike_errors, last_stage = state.spike_errors, runner.last_stage

    final = model.with_values(values)
    errors, cov, chi2, dof, mimgs, msgs = _errors(final, datas, values)
    for k in errors:
        if last_stage.get(k) in spike_errors:
            errors[k] = spike_errors[last_stage[k]][k]
    resids = [np.where(d.mask, d.image - mi, 0.0) for d, mi in zip(datas, mimgs)]

    def one(xs):
        return xs[0] if n_cap == 1 else xs

    return FitResult(values=values, errors=errors, free=final.free, covariance=cov, chi2=chi2,
                     dof=dof, status=status, converged=ok, steps=steps,
                     model_image=one(mimgs), residual=one(resids),
                     data=one([d.image for d in datas]), mask=one([d.mask for d in datas]),
                     warnings=notes + msgs, wall_time=time.perf_counter() - t0, stages=log)


@dataclasses.dataclass(frozen=True)
class _State:
    """Where an image fit stands between stages: the values reached, the captures (σ
    and masks as the stages before left them), the last solve's outcome, and the
    standard errors of the spike stages so far (by stage)."""

    values: dict
    datas: tuple
    status: str = "converged"
    ok: bool = True
    steps: int = 0
    spike_errors: dict = dataclasses.field(default_factory=dict)


class _ImageRunner(StageRunner):
    """An image fit's solving stage (:class:`Solve`: window, spikes, noise estimate,
    rejection, scan, multi-start) for :func:`run_procedure`."""

    loss_name = "chi2"

    def __init__(self, model: ImageModel, n_cap: int, *, starts, max_steps, rtol, atol,
                 verbose):
        super().__init__(verbose=verbose)
        self.model, self.n_cap = model, n_cap
        self.starts, self.max_steps, self.rtol, self.atol = starts, max_steps, rtol, atol
        #: the stage each parameter was last fitted in
        self.last_stage: dict[str, int] = {}

    def loss(self, state: _State, ref: _State) -> float:
        return chi2_at(self.model, list(ref.datas), state.values)

    def reruns_begin(self, state: _State) -> None:
        # the standard errors' Jacobian at the end is of these shapes: compiled now, on
        # the background thread, while the hops and repeats run programs already made
        compile_errors_ahead(self.model.with_values(state.values), list(state.datas),
                             state.values)

    def value(self, state: _State, name: str) -> float:
        return state.values[name]

    def moved(self, state: _State, change) -> _State:
        v = dict(state.values)
        for q, x in change.items():
            p = self.model.params[q]
            x = float(x)
            v[q] = x if p.bounds is None else min(max(x, p.bounds[0]), p.bounds[1])
        return dataclasses.replace(state, values=v)

    def put(self, state: _State, values, where: str) -> dict:
        return _put(self.model, values, where)

    def expand(self, names) -> list[str]:
        return self.model.expand(names, self.n_cap)

    def solve(self, si: int, st: Solve, state: _State, *, again: bool = False) -> _State:
        model, n_cap, log, verbose = self.model, self.n_cap, self.log, self.verbose
        if again:
            st = st.without_estimates()
        values, datas = state.values, list(state.datas)
        names = (model.free if st.free == "all" else model.expand(st.free, n_cap))
        fix = set(model.expand(st.fix, n_cap))
        names = [k for k in names if k not in fix]
        bad = set(names) - set(model.free)
        if bad:
            raise FitInputError(f"fit: stage {si} frees {sorted(bad)}, which are not free "
                                "parameters of the model.")
        if st.set is not None:
            put = st.set
            if isinstance(put, Mapping):  # a per-capture name: every capture's own
                put = {q2: x for q, x in put.items() for q2 in model.expand([q], n_cap)}
            values = {**values, **_put(model, put, f"fit: stage {si}: set")}
            log.append({"stage": si, "set": dict(st.set)})
        if st.noise_from_residuals is not None:
            mimgs = model_images(model, values, datas)
            noises = []
            for i, mi in enumerate(mimgs):
                bg = model.capture_values(values, i)["background"]
                nz, datas[i] = noise_from_residuals(datas[i], np.asarray(mi), bg,
                                                    **dict(st.noise_from_residuals))
                noises.append({"read": nz.read, "gain": nz.gain, "floor": nz.floor})
            log.append({"stage": si, "noise": noises[0] if n_cap == 1 else noises})
            if verbose:
                for nz in noises:
                    print(f"stage {si}: noise from the residuals: read {nz['read']:.4g}, "
                          f"gain {nz['gain']:.4g}, floor {nz['floor']:g}", flush=True)
        if st.reject is not None:
            mimgs = model_images(model, values, datas)
            counts, largest = [], []
            for i, mi in enumerate(mimgs):
                h, w = datas[i].image.shape
                cv = model.capture_values(values, i)
                datas[i], n, z = reject_outliers(datas[i], np.asarray(mi), cv["background"],
                                                 (w // 2 + cv["x0"], h // 2 + cv["y0"]),
                                                 **dict(st.reject))
                counts.append(n)
                largest.append(z)
            log.append({"stage": si, "rejected": counts[0] if n_cap == 1 else counts,
                        "largest_kept": largest[0] if n_cap == 1 else largest})
            if verbose:
                print(f"stage {si}: rejected {counts[0] if n_cap == 1 else counts} pixels "
                      f"more than {st.reject.get('above', 20.0):g} σ from the model; "
                      f"the largest kept: {max(largest):.3g} σ", flush=True)
        half = st.half
        ds = [d if half is None else d.cropped(int(half)) for d in datas]
        if st.annulus is not None:
            ds = [d.annulus(*(float(r) for r in st.annulus)) for d in ds]
        if st.spikes is not None:
            mimgs = [None] * len(ds)
            if st.spikes.get("directions") == "model":
                mimgs = model_images(model, values, ds)
            targets = [spike_target(d, model.capture_values(values, i), model_image=mi,
                                    **dict(st.spikes))
                       for i, (d, mi) in enumerate(zip(ds, mimgs))]
        else:
            targets = [_PixelTarget(d) for d in ds]
        kind = targets[0].kind
        if st.scan is not None:
            values = self._scan(si, st.scan, ds, targets, values)
        tries = [{}]
        if si == 0 and self.starts:
            for k, vs in self.starts.items():
                tries = [dict(t, **{k: float(x)}) for t in tries for x in vs]
        best = None
        for tr in tries:
            m = model.with_values({**values, **tr}, free=names)
            ts = time.perf_counter()
            vals, status, ok, n, m, chi2, lin = _one_fit(
                m, ds, targets,
                max_steps=int(self.max_steps if st.max_steps is None else st.max_steps),
                rtol=float(self.rtol if st.rtol is None else st.rtol), atol=self.atol,
                label=f"stage {si}" if verbose else None)
            entry = {"stage": si, "start": tr, "free": names, "half": half, "chi2": chi2,
                     "kind": kind, "status": status, "steps": n,
                     "seconds": time.perf_counter() - ts}
            log.append(entry)
            if verbose:
                print(f"stage {si} ({kind}) start {tr}: chi2 {chi2:.6g} {status} "
                      f"{n} steps {time.perf_counter() - ts:.1f} s", flush=True)
            if best is None or chi2 < best[0]:
                best = (chi2, vals, status, ok, n, m, entry, lin)
        _, values, status, ok, steps, m, entry, lin = best
        for k in names:
            self.last_stage[k] = si
        spike_errors = state.spike_errors
        if kind != "pixels":  # from the solver's last linearisation where it serves
            errs = _errors(m, ds, values, targets, linearised=lin)[0]
            entry["errors"] = errs
            entry["directions"] = [t.directions for t in targets] if n_cap > 1 \
                else targets[0].directions
            spike_errors = {**spike_errors, si: errs}
        return _State(values, tuple(datas), status, ok, steps, spike_errors)

    def _scan(self, si: int, scan, ds, targets, values) -> dict:
        """Move ``scan["name"]`` to the lowest χ² on its grid (noting rivals the data
        hardly tell from it)."""
        model = self.model
        name = scan["name"]
        grid, cost = scan_grid(model, ds, targets, values, **dict(scan),
                               progress=f"stage {si} scan" if self.verbose else None)
        entry = {"stage": si, "scan": dict(scan), "best": values[name]}
        if grid.size:
            values = {**values, name: float(grid[int(np.argmin(cost))])}
            # Δχ² of one standard error, scaled by χ²/dof where the model's
            # mismatch makes that exceed 1
            n_used = sum(t.n for t in targets if hasattr(t, "n"))
            within = max(1.0, float(np.min(cost)) / max(n_used - len(model.free), 1))
            rivals = scan_rivals(grid, cost, within=within)
            entry |= {"best": values[name], "rivals": rivals}
            if rivals:
                self.notes.append(
                    f"stage {si}: the scan of {name} found other minima that the data "
                    f"hardly tell from the lowest ({values[name]:g}): " + ", ".join(
                        f"{x:g} (Δχ² {d:.3g})" for x, d in rivals[:4])
                    + f", each within Δχ² {within:.3g} (one standard error, scaled by "
                    "χ²/dof). The answer may belong to another of them: bound "
                    f"{name} nearer the value you expect, or compare the fits from "
                    "each (chi2_slice shows the curve).")
        self.log.append(entry)
        if self.verbose:
            print(f"stage {si}: scan of {name}: best {values[name]:.4g}", flush=True)
        return values
