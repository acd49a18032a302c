"""The one stage loop of every difstar fit (:func:`run_procedure`): a procedure's stages in
turn, its hops and repeats run the same way for an image fit and a RAW fit.

What a kind of fit does in a solving stage, how it measures its loss on one yardstick and
how it moves its parameters is its :class:`StageRunner`: the image fit's is in
:mod:`difstar.fitting._procedure`, the RAW camera fit's in :mod:`difstar._fit_procedure`.
The loop holds no state of its own: a runner's state (values reached, σ, pixels kept,
the last solve) goes in and comes out of each stage, so that a hop can keep whichever of
its tries ended lowest, whole."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from ._stage_types import Hop, Repeat, Solve


class StageRunner(ABC):
    """What :func:`run_procedure` needs from a kind of fit.

    ``log`` collects one record per event (a solve, a hop, a repeat) in the order they
    happen; ``notes`` the procedure's warnings (e.g. a repeat that did not settle);
    ``loss_name`` is what the loss is called in the log (``"chi2"``, ``"loss"``)."""

    loss_name: str = "chi2"

    def __init__(self, *, verbose: bool = False):
        self.verbose = verbose
        self.log: list[dict] = []
        self.notes: list[str] = []

    def reruns_begin(self, state: Any) -> None:
        """Called once, as the procedure's first hop or repeat begins from ``state``: the
        programs of the stages it re-runs are compiled by then, and running them leaves
        a core idle at times. A runner may start here what the end of the fit needs (the
        image fit compiles its standard errors' Jacobian on the background thread)."""

    @abstractmethod
    def solve(self, si: int, st: Any, state: Any, *, again: bool = False) -> Any:
        """Run stage ``si`` (a :class:`Solve`, or a stage of this kind's own) from
        ``state``; returns the new state. ``again``: a hop's or a repeat's re-run of a
        solve before it, which compares on one yardstick: σ and the pixels kept as they
        are (no noise estimate, no rejection, no reweighting)."""

    @abstractmethod
    def loss(self, state: Any, ref: Any) -> float:
        """The loss at ``state``'s values with ``ref``'s σ and pixels, on all of them."""

    @abstractmethod
    def value(self, state: Any, name: str) -> Any:
        """Parameter ``name``'s value in ``state`` (a float, or an array for a parameter
        with several values)."""

    @abstractmethod
    def moved(self, state: Any, change: Mapping[str, Any]) -> Any:
        """``state`` with the parameters of ``change`` put at those values, each kept
        inside its bounds."""

    def put(self, state: Any, values: Mapping[str, Any], where: str) -> dict:
        """The values a hop's ``set`` puts (checked; default: as given)."""
        return dict(values)

    def expand(self, names: Sequence[str]) -> list[str]:
        """The parameters ``names`` stand for (a family's name stands for its members)."""
        return list(names)


def _plain(x):
    """A value as the log writes it: a float, or a list for several."""
    a = np.asarray(x, dtype=float)
    return float(a) if a.ndim == 0 else a.tolist()


def _fmt(x, spec: str) -> str:
    a = np.asarray(x, dtype=float)
    if a.ndim == 0:
        return format(float(a), spec)
    return "[" + ", ".join(format(float(v), spec) for v in a.ravel()) + "]"


def run_procedure(runner: StageRunner, stages: Sequence, state: Any) -> Any:
    """Run ``stages`` (parsed and checked: :class:`Solve`, :class:`Hop`,
    :class:`Repeat`, or the runner's own kinds) in turn from ``state``; returns the
    final state. Each stage starts where the last ended."""
    stages = list(stages)
    reruns = False
    for si, st in enumerate(stages):
        if isinstance(st, (Hop, Repeat)) and not reruns:
            runner.reruns_begin(state)
            reruns = True
        if isinstance(st, Hop):
            state = _hop(runner, stages, si, st, state)
        elif isinstance(st, Repeat):
            state = _repeat(runner, stages, si, st, state)
        else:
            state = runner.solve(si, st, state)
    return state


def _solving_before(stages: Sequence, si: int) -> list[int]:
    """The solving stages before stage ``si`` (hops, repeats and restarts passed over)."""
    return [sj for sj in range(si) if isinstance(stages[sj], Solve)]


def _rerun(runner: StageRunner, stages: Sequence, which: Sequence[int], state: Any) -> Any:
    for sj in which:
        state = runner.solve(sj, stages[sj], state, again=True)
    return state


def _repeat(runner: StageRunner, stages: Sequence, si: int, st: Repeat, state: Any) -> Any:
    """Re-run the ``stages`` solving stages before this one, round after round, until
    every parameter named in ``until`` moves by less than its tolerance over a round
    (or ``max_rounds``): the fixed point of stages that fit different parameters in
    turn (e.g. the rotation on the spikes, then the rest on all pixels), which one pass
    leaves wherever its start put it in a long, flat valley."""
    solving = _solving_before(stages, si)
    names = {q2: tol for q, tol in st.until.items() for q2 in runner.expand([q])}
    rounds, settled = [], False
    for _ in range(st.max_rounds):
        before = {q: runner.value(state, q) for q in names}
        state = _rerun(runner, stages, solving[-st.stages:], state)
        now = {q: runner.value(state, q) for q in names}
        moved = {q: np.asarray(now[q]) - np.asarray(before[q]) for q in names}
        loss = runner.loss(state, state)
        rounds.append({"values": {q: _plain(now[q]) for q in names},
                       "moved": {q: _plain(moved[q]) for q in names},
                       runner.loss_name: loss})
        if runner.verbose:
            print(f"stage {si}: repeat round {len(rounds)}: " + ", ".join(
                f"{q} {_fmt(now[q], '.6g')} (moved {_fmt(moved[q], '+.3g')})" for q in names)
                + f", {runner.loss_name} {loss:.6g}", flush=True)
        if all(np.all(np.abs(moved[q]) < names[q]) for q in names):
            settled = True
            break
    runner.log.append({"stage": si, "repeat": st.as_dict()["repeat"], "rounds": rounds,
                       "settled": settled})
    if not settled:
        runner.notes.append(f"repeat (stage {si}): {', '.join(names)} still moved by more "
                            f"than the tolerance after {st.max_rounds} rounds: raise "
                            "max_rounds or the tolerance.")
    return state


def _hop(runner: StageRunner, stages: Sequence, si: int, st: Hop, state: Any) -> Any:
    """Re-run the ``stages`` solving stages before this one from the values changed in
    each way the hop names: ``name`` moved by each of ``offsets``, each entry of
    ``flip`` negated, or the parameters of ``set`` put at its values, all at once (σ and
    pixels as before the hop); keep whichever ends at the lowest loss on all pixels, the
    unchanged state included."""
    solving = _solving_before(stages, si)
    # each entry of flip: one name, or a tuple of names negated together (the twin)
    flips = [(q,) if isinstance(q, str) else tuple(q) for q in st.flip]
    put = dict(st.set or {})
    put_at = runner.put(state, put, f"fit: stage {si}: hop set") if put else {}
    ref = state
    best_loss, best = runner.loss(state, ref), state
    tried = [{"change": "none", runner.loss_name: best_loss}]
    moves = ([(f"{st.name} {off:+g}",
               {st.name: np.asarray(runner.value(state, st.name)) + off})
              for off in st.offsets if st.name is not None]
             + [(", ".join(g) + " negated", {q: -np.asarray(runner.value(state, q))
                                             for q in g}) for g in flips]
             + ([("set " + ", ".join(f"{q}={x:g}" for q, x in put.items()), put_at)]
                if put else []))
    for label, change in moves:
        tried_state = _rerun(runner, stages, solving[-st.stages:], runner.moved(ref, change))
        loss = runner.loss(tried_state, ref)
        ends = {q: runner.value(tried_state, q) for q in change}
        tried.append({"change": label, runner.loss_name: loss,
                      "ends_at": {q: _plain(x) for q, x in ends.items()}})
        if runner.verbose:
            print(f"stage {si}: hop {label}: ends at "
                  f"{ {q: _fmt(x, '.4g') for q, x in ends.items()} }, {runner.loss_name} "
                  f"{loss:.6g} (best so far {best_loss:.6g})", flush=True)
        if loss < best_loss:
            best_loss, best = loss, tried_state
    runner.log.append({"stage": si, "hop": st.as_dict()["hop"], "tried": tried})
    return best
