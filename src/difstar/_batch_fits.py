"""Many fits at once on a device mesh (a recovery study's starts, many stars):

- :func:`solve_many` — a :class:`difstar._fit.Fitter`'s solver steps for many fits in
  lockstep (each stops on its own test, as :meth:`Fitter.solve` does; a finished fit is
  held while the others go on).
- :class:`FitBatcher` — many fits, each the ordinary code of one fit (a recovery study's
  ``fit_manifest``), their solves gathered into :func:`solve_many` batches.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._batch import (
    Plan,
    _leading,
    _per_device_bytes,
    _print_plan,
    _take,
    device_count,
    device_memory,
    device_mesh,
    lapack_in_turn,
    per_item,
    plan_chunks,
)
from ._distributed import _collective, check_lost, dry_run
from ._lm import SolveResult, StopRule
from ._xla import solver_jit_options


@dataclasses.dataclass
class ItemSolve:
    """One fit's outcome in :func:`solve_many` (as :class:`difstar._fit.SolveResult`,
    with the seconds of its chunk shared among the chunk's fits)."""

    u: np.ndarray
    steps: int
    accepted: int
    loss_start: float
    loss: float
    result: str
    seconds: float
    compile_seconds: float


def _batched_steps(fitter, in_turn: bool):
    """The fitter's init and step over a leading axis of fits (:func:`per_item`), jitted
    once per fitter and kept on it, so that a recovery study's many solve rounds compile
    each shape once (new closures per call would compile every round)."""
    cache = vars(fitter).setdefault("_difstar_batched_steps", {})
    if in_turn not in cache:
        box = {}

        def init_one(u, a):
            dyn, static = eqx.partition(fitter._init(u, a), eqx.is_array)
            box["static"] = static  # the same for every item (trace-time structure)
            return dyn

        def step_one(u, dyn, a, hold):
            state = eqx.combine(dyn, box["static"])
            u2, s2, done, ok, loss, size, acc, gain = fitter._step(u, state, a)
            d2, _ = eqx.partition(s2, eqx.is_array)
            d2 = jax.tree_util.tree_map(lambda new, old: jnp.where(hold, old, new), d2, dyn)
            return jnp.where(hold, u, u2), d2, done, ok, loss, acc, gain

        options = solver_jit_options()
        cache[in_turn] = (jax.jit(per_item(init_one, in_turn), **options),
                          jax.jit(per_item(step_one, in_turn), **options))
    return cache[in_turn]


def solve_many(fitter, u0, args, *, devices=None, max_steps: int = 100, ftol: float = 1e-6,
               chunk=None, progress: Callable[[int, ItemSolve], None] | None = None,
               plan_out: list | None = None) -> list[ItemSolve]:
    """Many fits of one :class:`difstar._fit.Fitter` (same model, data of the same shapes)
    at once: ``u0`` (B, P) starts and ``args`` (:func:`difstar._fit.make_args` pytrees
    stacked on a leading B axis), split over ``devices`` devices.

    The fits step in lockstep: each step is ``jax.vmap`` of the fitter's own step
    (optimistix), and each fit stops by :meth:`Fitter.solve`'s tests (optimistix's, or a
    ``difstar._lm.StopRule``'s on the loss); a finished fit is held (its u
    and solver state no longer change) while the others go on, so it ends where
    :meth:`Fitter.solve` would. ``progress(i, result)`` is called as fit ``i`` finishes.

    Each device runs its own slice as a program of its own (one compile per device):
    under ``shard_map`` lineax compares the residuals' structure with one that carries
    the mesh and refuses the solve, and a mesh-wide ``jit`` makes XLA's partitioner
    gather the batch around the solver's loops. On CPU devices a device's fits step
    one after another inside its program (:func:`lapack_in_turn`: batched LAPACK calls
    of several host devices at once exhaust XLA's CPU thread pool and hang); elsewhere
    they are ``vmap``-ed. In a multi-process job each process steps its own devices' fits
    and the results are gathered at the end.
    """
    u0 = np.asarray(u0)
    n_items = u0.shape[0]
    if _leading(args) != n_items:
        raise ValueError("difstar solve_many: u0 and args need the same number of fits.")
    if dry_run():
        _print_plan(n_items, device_count(devices), chunk=chunk, what="fits")
    mesh = device_mesh(devices)
    devs = list(mesh.devices.flat)
    nd = len(devs)
    me = jax.process_index()
    init, step = _batched_steps(fitter, False)

    def put(tree, dev):
        return jax.tree_util.tree_map(lambda x: jax.device_put(np.asarray(x), dev), tree)

    plan = plan_chunks(n_items, nd, chunk=chunk)
    in_turn = False
    if plan.per_device > 1:
        # one item: the step's bytes per item, and whether it calls LAPACK (it does on
        # CPU: the solver's linear solve), see lapack_in_turn
        ex = put(_take({"u": u0, "a": args}, np.zeros(1, dtype=int)), devs[0])
        dyn = init(ex["u"], ex["a"])
        lowered = step.lower(ex["u"], dyn, ex["a"], put(np.zeros(1, bool), devs[0]))
        in_turn = lapack_in_turn(lowered, devs[0])
        if chunk is None:
            plan = plan_chunks(n_items, nd, item_bytes=_per_device_bytes(lowered.compile()),
                               free_bytes=device_memory(devs[0]))
    if in_turn and plan.per_device > 1:  # each device's fits one after another
        init, step = _batched_steps(fitter, True)
    if plan_out is not None:
        plan_out.append(plan)
    size, k_dev = plan.chunk, plan.per_device
    results: list[ItemSolve | None] = [None] * n_items
    for start in range(0, n_items, size):
        idx = np.arange(start, min(start + size, n_items))
        m = len(idx)
        full = np.concatenate([idx, np.zeros(size - m, dtype=int)])
        hold = np.arange(size) >= m  # the padding never moves
        mine = [d for d in range(nd) if devs[d].process_index == me]
        sl = {d: slice(d * k_dev, (d + 1) * k_dev) for d in mine}
        t_start = time.perf_counter()
        st = {}
        for d in mine:
            a = put(_take(args, full[sl[d]]), devs[d])
            u = put(u0[full[sl[d]]], devs[d])
            st[d] = [u, init(u, a), a]
        rules = [StopRule(ftol) for _ in range(size)]  # Fitter.solve's own stopping rule
        loss0 = [None] * size
        meta = np.zeros((size, 5))  # steps, accepted, loss_start, loss, result code
        t_compile = 0.0
        finished = []
        owned = np.zeros(size, bool)
        for d in mine:
            owned[sl[d]] = True
        for k in range(1, max_steps + 1):
            check_lost()
            t1 = time.perf_counter()
            outs = {}
            for d in mine:  # dispatched to every device before any result is read
                u, dyn, a = st[d]
                outs[d] = step(u, dyn, a, put(hold[sl[d]], devs[d]))
            for d in mine:
                u, dyn, done_a, ok_a, loss_a, acc_a, gain_a = outs[d]
                st[d][:2] = [u, dyn]
                done_h, ok_h, loss_h, acc_h, gain_h = (
                    np.asarray(x) for x in (done_a, ok_a, loss_a, acc_a, gain_a))
                for j, i in enumerate(range(sl[d].start, sl[d].stop)):
                    if hold[i]:
                        continue
                    loss = float(loss_h[j])
                    done, ok = bool(done_h[j]), bool(ok_h[j])
                    if k == 2:
                        loss0[i] = loss
                    if rules[i].update(loss, int(acc_h[j]), float(gain_h[j])) and not done:
                        done = ok = True
                    if done or k == max_steps:
                        hold[i] = True
                        finished.append(i)
                        code = (1 if ok else 2) if done else 3
                        meta[i] = (k, int(acc_h[j]), loss if loss0[i] is None else loss0[i],
                                   loss, code)
            if k == 1:
                t_compile = time.perf_counter() - t1
            if hold[owned].all():
                break
        u_blk = np.zeros((size,) + u0.shape[1:])
        for d in mine:
            u_blk[sl[d]] = np.asarray(st[d][0])
        if jax.process_count() > 1:  # every process's fits, to every process
            from jax.experimental import multihost_utils

            u_all, meta_all, own_all = _collective(
                multihost_utils.process_allgather, (u_blk, meta, owned.astype(float)))
            pick = np.argmax(own_all, axis=0)
            u_blk = u_all[pick, np.arange(size)]
            meta = meta_all[pick, np.arange(size)]
        secs = time.perf_counter() - t_start - t_compile
        for i in range(m):
            steps_i, acc_i, l0, l1, code = meta[i]
            results[idx[i]] = ItemSolve(
                u=u_blk[i], steps=int(steps_i), accepted=int(acc_i), loss_start=float(l0),
                loss=float(l1), result={1: "converged", 2: "failed", 3: "max_steps"}[int(code)],
                seconds=secs / m, compile_seconds=t_compile / m)
        if progress is not None:
            for i in finished:
                if i < m:
                    progress(int(idx[i]), results[idx[i]])
    return results


class FitBatcher:
    """Run many fit jobs, each ordinary sequential code given a fitter, with their solves
    gathered into :func:`solve_many` batches.

    ``run(jobs)`` calls every ``job(fitter)`` in its own thread with a stand-in for the
    :class:`difstar._fit.Fitter`: its ``solve`` waits until every job still running has
    asked for a solve (or finished), then all the waiting solves run as one sharded
    batch (grouped by ``max_steps`` and ``ftol``); everything else (``predict``,
    ``loss``, ``covariance``, …) is the real fitter's. So a recovery study runs the very
    code of one fit, stage by stage, with the stages' solves of all its fits batched.
    Returns the jobs' results in order; a job's exception is raised after all end.
    """

    def __init__(self, fitter, *, devices=None, chunk=None,
                 progress: Callable[[str], None] | None = None):
        self.fitter = fitter
        self.devices, self.chunk, self.progress = devices, chunk, progress
        self.plans: list[Plan] = []
        self._cv = threading.Condition()
        self._pending: dict[int, dict] = {}
        self._live: set[int] = set()
        self._round = 0

    def _solve(self, job: int, u0, args, max_steps: int, ftol: float):
        req = {"u": np.asarray(u0), "args": args, "key": (int(max_steps), float(ftol)),
               "out": None}
        with self._cv:
            self._pending[job] = req
            self._cv.notify_all()
            while req["out"] is None:
                self._cv.wait()
        if isinstance(req["out"], BaseException):
            raise req["out"]
        return req["out"]

    def run(self, jobs: list[Callable]):
        results: list[Any] = [None] * len(jobs)
        errors: list[BaseException | None] = [None] * len(jobs)
        batcher = self

        class Stand_in:
            def __init__(self, job):
                self._job = job

            def solve(self, u0, args, *, max_steps=100, ftol=1e-6, progress=None):
                r = batcher._solve(self._job, u0, args, max_steps, ftol)
                if progress is not None:
                    progress(r.steps, r.loss, float("nan"), True, np.asarray(r.u))
                return SolveResult(u=jnp.asarray(r.u), steps=r.steps, accepted=r.accepted,
                                   loss_start=r.loss_start, loss=r.loss, result=r.result,
                                   seconds=r.seconds, compile_seconds=r.compile_seconds)

            def __getattr__(self, name):
                return getattr(batcher.fitter, name)

        def body(i):
            try:
                results[i] = jobs[i](Stand_in(i))
            except BaseException as exc:  # handed to the caller below
                errors[i] = exc
            finally:
                with self._cv:
                    self._live.discard(i)
                    self._cv.notify_all()

        self._live = set(range(len(jobs)))
        threads = [threading.Thread(target=body, args=(i,), daemon=True)
                   for i in range(len(jobs))]
        for t in threads:
            t.start()
        while True:
            with self._cv:
                while self._live and len(self._pending) < len(self._live):
                    self._cv.wait()
                if not self._live:
                    break
                batch, self._pending = self._pending, {}
            self._round += 1
            check_lost()
            groups: dict[tuple, list[int]] = {}
            for job, req in sorted(batch.items()):
                groups.setdefault(req["key"], []).append(job)
            for (max_steps, ftol), members in groups.items():
                try:
                    out = self._solve_group([batch[j] for j in members], members,
                                            max_steps, ftol)
                except BaseException as exc:  # every waiting job raises it
                    out = [exc] * len(members)
                with self._cv:
                    for j, o in zip(members, out):
                        batch[j]["out"] = o
                    self._cv.notify_all()
        for t in threads:
            t.join()
        for e in errors:
            if e is not None:
                raise e
        return results

    def _solve_group(self, reqs, members, max_steps, ftol):
        u0 = np.stack([r["u"] for r in reqs])
        args = jax.tree_util.tree_map(lambda *x: np.stack([np.asarray(v) for v in x]),
                                      *[r["args"] for r in reqs])
        rnd = self._round
        say = self.progress

        def each(i, r):
            if say is not None:
                say(f"solve round {rnd}: fit {members[i]} {r.result} after {r.steps} steps")

        return solve_many(self.fitter, u0, args, devices=self.devices, max_steps=max_steps,
                          ftol=ftol, chunk=self.chunk, progress=each, plan_out=self.plans)
