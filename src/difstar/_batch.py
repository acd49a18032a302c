"""Many independent items at once: a batch axis placed on a device mesh.

One code path for one device, several devices of one host and several hosts: the batch's
leading axis is split over a one-axis mesh (``"batch"``) of the devices JAX sees
(``jax.devices()``: every host's, once :func:`init_distributed` has joined them), and each
device runs ``jax.vmap(fn)`` over its own slice (``jax.shard_map`` with ``P("batch")`` in
and out; the items are independent, so no device needs another's). The host side pads the batch to a multiple
of the device count, splits it into chunks that fit the devices' memory, reports progress
per chunk and strips the padding. The jitted core is ``fn`` itself and stays pure.

- :func:`device_count` — how many devices to use: an argument, else ``DIFSTAR_DEVICES``,
  else all; anything else (< 1, more than exist, not a whole number) is refused with one
  line naming the flag and the fix.
- :func:`device_mesh` — the one-axis mesh.
- :func:`map_batch` — ``fn`` over a batch pytree (arrays with a leading axis), sharded.
- :func:`solve_many` — a :class:`difstar._fit.Fitter`'s solver steps for many fits in
  lockstep (each stops on its own test, as :meth:`Fitter.solve` does; a finished fit is
  held while the others go on).
- :class:`FitBatcher` — many fits, each the ordinary code of one fit (a recovery study's
  ``fit_manifest``), their solves gathered into :func:`solve_many` batches.
- :func:`simulate_spectral` — a spectral :func:`difstar.simulate` whose wavelengths are
  the batch: the linear image is linear in the PSF, so it is the weighted sum of the
  monochromatic images, and the sensor is applied once to the sum.
- :func:`init_distributed` — ``jax.distributed.initialize()`` when the environment
  names a multi-process job (see ``docs/sharding.md`` for the commands).

Memory: the per-item bytes of the compiled chunk (``Compiled.memory_analysis()``: its
arguments, outputs and temporaries, per device, divided by the items each device holds)
against each device's free memory (``device.memory_stats()``: ``bytes_limit −
bytes_in_use``) or, where a device reports none (CPU), ``DIFSTAR_MEMORY_LIMIT`` / the
host's memory shared by its devices; a fraction :data:`FILL` of it is used.
"""

from __future__ import annotations

import dataclasses
import math
import os
import threading
import time
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from ._validate import InputError

AXIS = "batch"
ENV_DEVICES = "DIFSTAR_DEVICES"
#: fraction of a device's free memory a chunk may use (the rest: fragmentation, the
#: runtime's own buffers, and the estimate's error)
FILL = 0.6

Progress = Callable[[int, int, float], None]  # (items done, items in all, seconds so far)


# ------------------------------------------------------------------------ devices

def init_distributed() -> bool:
    """Join a multi-process JAX job when the environment describes one; returns whether
    it did. Call it before anything touches a device (the CLI does, first thing, when
    ``--devices``/``DIFSTAR_DEVICES`` is used).

    Recognised (else nothing is done and the process runs alone):

    - ``JAX_COORDINATOR_ADDRESS`` (host:port of process 0), ``JAX_NUM_PROCESSES`` and
      ``JAX_PROCESS_ID`` — any launcher; optional ``JAX_LOCAL_DEVICE_IDS``;
    - a SLURM job step with more than one task (``SLURM_NTASKS`` > 1), or an Open MPI
      launch (``OMPI_MCA_orte_hnp_uri``) — JAX finds the rest itself.
    """
    env = os.environ
    if jax.distributed.is_initialized():
        return True
    if env.get("JAX_COORDINATOR_ADDRESS") and env.get("JAX_NUM_PROCESSES"):
        try:
            n = int(env["JAX_NUM_PROCESSES"])
            pid = int(env.get("JAX_PROCESS_ID", ""))
        except ValueError:
            raise InputError(
                "JAX_NUM_PROCESSES / JAX_PROCESS_ID: not whole numbers; set both (e.g. "
                "JAX_NUM_PROCESSES=2 JAX_PROCESS_ID=0 on the first host) or unset "
                "JAX_COORDINATOR_ADDRESS to run alone.") from None
        if not (n >= 1 and 0 <= pid < n):
            raise InputError(
                f"JAX_PROCESS_ID: {pid} is not in [0, JAX_NUM_PROCESSES = {n}); give each "
                "process its own id 0 … N − 1.")
        if n == 1:
            return False
        jax.distributed.initialize(env["JAX_COORDINATOR_ADDRESS"], num_processes=n,
                                   process_id=pid)
        return True
    slurm = env.get("SLURM_NTASKS", "1")
    if (slurm.isdigit() and int(slurm) > 1) or env.get("OMPI_MCA_orte_hnp_uri"):
        jax.distributed.initialize()
        return True
    return False


def device_count(devices=None, *, flag: str = "--devices") -> int:
    """How many devices to use: ``devices`` if given, else ``DIFSTAR_DEVICES``, else all
    of them. :class:`InputError` (one line: the flag and the fix) for < 1, NaN, a
    fraction, or more than exist."""
    have = jax.device_count()
    where = flag
    if devices is None:
        text = os.environ.get(ENV_DEVICES, "").strip()
        if not text:
            return have
        where, devices = ENV_DEVICES, text
    fix = (f"give a whole number from 1 to {have} (the devices JAX sees: "
           f"{jax.default_backend()} × {have}; for more host CPU devices set "
           "XLA_FLAGS=--xla_force_host_platform_device_count=N before starting)")
    try:
        x = float(devices)
    except (TypeError, ValueError):
        raise InputError(f"{where}: {devices!r} is not a number; {fix}.") from None
    if not math.isfinite(x):
        raise InputError(f"{where}: {devices} is not a finite number; {fix}.")
    if x != int(x) or x < 1:
        raise InputError(f"{where}: {devices} is not a device count >= 1; {fix}.")
    if int(x) > have:
        raise InputError(f"{where}: {int(x)} devices asked for, {have} available; {fix}.")
    return int(x)


def device_mesh(n_devices=None) -> Mesh:
    """A one-axis mesh (``"batch"``) of the first ``n_devices`` devices (default: as
    :func:`device_count`), across every host in a multi-process job."""
    n = device_count(n_devices)
    return Mesh(np.asarray(jax.devices()[:n]), (AXIS,))


def device_memory(device=None) -> int:
    """Bytes free on ``device`` (default the first): ``memory_stats()``'s limit minus
    what is in use where the device reports it (GPUs), else ``DIFSTAR_MEMORY_LIMIT`` or
    the host's memory, shared by the host's devices (CPU devices share it)."""
    from ._validate import memory_budget, memory_limit_from_env

    env_limit = memory_limit_from_env()  # the one parser: a bad value is refused here too
    device = jax.devices()[0] if device is None else device
    try:
        stats = device.memory_stats() or {}
    except Exception:  # some backends raise instead of returning None
        stats = {}
    if stats.get("bytes_limit"):
        return int(stats["bytes_limit"]) - int(stats.get("bytes_in_use", 0))
    if env_limit is not None:
        total = env_limit
    else:
        try:
            total = int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_AVPHYS_PAGES"))
        except (ValueError, OSError, AttributeError):
            total = memory_budget()
    return total // max(1, jax.local_device_count())


# ------------------------------------------------------------------ placing arrays

def _leading(batch) -> int:
    leaves = jax.tree_util.tree_leaves(batch)
    if not leaves:
        raise ValueError("difstar map_batch: the batch holds no arrays.")
    sizes = {np.shape(x)[0] if np.ndim(x) else None for x in leaves}
    if None in sizes or len(sizes) != 1:
        raise ValueError(f"difstar map_batch: every array of the batch needs the same leading "
                         f"(batch) axis; got leading sizes {sorted(map(str, sizes))}.")
    return sizes.pop()


def _take(batch, idx):
    return jax.tree_util.tree_map(lambda x: np.asarray(x)[idx], batch)


def shard(batch, mesh: Mesh):
    """Host arrays (leading axis a multiple of the mesh's size) → global arrays split
    over the mesh's ``"batch"`` axis. Every process passes the whole batch; each places
    its own devices' slices (the same call on one host and on several)."""
    sh = NamedSharding(mesh, P(AXIS))

    def put(x):
        x = np.asarray(x)
        return jax.make_array_from_callback(x.shape, sh, lambda idx: x[idx])

    return jax.tree_util.tree_map(put, batch)


def gather(tree):
    """Global arrays → host NumPy arrays (gathered from every process when there are
    several)."""
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        return multihost_utils.process_allgather(tree, tiled=True)
    return jax.tree_util.tree_map(np.asarray, tree)


def per_item(fn, in_turn: bool = False):
    """``fn`` over a leading axis: ``jax.vmap(fn)``, or with ``in_turn`` the items one
    after another (``jax.lax.map``), each call of ``fn`` on one item as unbatched code."""
    if in_turn:
        return lambda *xs: jax.lax.map(lambda x: fn(*x), xs)
    return jax.vmap(fn)


def sharded_vmap(fn, mesh: Mesh, *, in_turn: bool = False):
    """``jit(shard_map(vmap(fn)))``: each device maps ``fn`` over its own slice of every
    argument's leading axis (array pytrees in and out), one program, no collective: a
    mesh-wide ``jit`` would leave the split to XLA's partitioner, which can gather the
    batch around loops (seen in the fit's solver step). ``in_turn``: each device takes
    its items one after another (:func:`per_item`; see :func:`lapack_in_turn`)."""
    return jax.jit(jax.shard_map(per_item(fn, in_turn), mesh=mesh, in_specs=P(AXIS),
                                 out_specs=P(AXIS), check_vma=False))


def lapack_in_turn(lowered, device) -> bool:
    """Whether a device's items must run one after another rather than as one batch:
    on CPU devices, when the program calls LAPACK (a QR, Cholesky, LU, eigen or SVD
    custom call: every least-squares solve).

    Why: jaxlib's CPU LAPACK kernels (``lapack_*_ffi``, jaxlib 0.10) split a *batch* of
    matrices over XLA's CPU intra-op thread pool and block the pool thread that runs
    them until the pieces are done (``jax::ParallelBatchMap`` → ``BlockingCounter::
    Wait``). The pool has one thread per core and is shared by every host CPU device of
    the process; when as many device programs as the pool has threads reach a batched
    LAPACK call at once, every thread waits for pieces that no thread is left to run, and
    the process stops for ever (stacks taken with gdb on the 2-core machine: both
    ``tf_XLAEigen`` threads in ``QrFactorization::Kernel`` → ``ParallelBatchMap`` →
    ``BlockingCounter::Wait``, the main thread in ``np.asarray`` of the first step). A
    batch of one matrix runs on the calling thread, so items taken in turn never wait on
    the pool. ``--xla_cpu_multi_thread_eigen=false`` does not change this pool. GPUs (and
    batches without LAPACK, such as the spectral PSFs) keep ``vmap``."""
    if getattr(device, "platform", "") != "cpu":
        return False
    try:
        text = lowered.as_text()
    except Exception:  # cannot tell: the safe choice on CPU
        return True
    return "lapack_" in text


def _per_device_bytes(compiled) -> int | None:
    try:
        m = compiled.memory_analysis()
    except Exception:  # not every backend implements it
        return None
    if m is None:
        return None
    total = sum(int(getattr(m, k, 0) or 0) for k in (
        "argument_size_in_bytes", "output_size_in_bytes", "temp_size_in_bytes",
        "generated_code_size_in_bytes")) - int(getattr(m, "alias_size_in_bytes", 0) or 0)
    return total if total > 0 else None


@dataclasses.dataclass
class Plan:
    """How a batch runs: ``devices``, items per device per chunk (``per_device``), the
    chunk (``devices × per_device`` items), the chunks, the estimated bytes per item and
    the bytes free per device (None where unknown)."""

    devices: int
    per_device: int
    chunks: int
    item_bytes: int | None
    free_bytes: int | None

    @property
    def chunk(self) -> int:
        return self.devices * self.per_device


def plan_chunks(n_items: int, n_devices: int, *, chunk=None, item_bytes=None,
                free_bytes=None) -> Plan:
    """Items per device per chunk: ``chunk`` (items per chunk, rounded up to a multiple of
    the devices) if given, else as many as fit in ``FILL × free_bytes`` at ``item_bytes``
    each (all of them when either is unknown)."""
    need = -(-n_items // n_devices)  # items per device for the whole batch
    if chunk is not None:
        c = check_chunk(chunk)
        k = min(need, -(-c // n_devices))
    elif item_bytes and free_bytes:
        k = max(1, min(need, int(FILL * free_bytes // item_bytes)))
    else:
        k = need
    return Plan(n_devices, k, -(-need // k), item_bytes, free_bytes)


def check_chunk(chunk, flag: str = "chunk") -> int:
    try:
        x = float(chunk)
    except (TypeError, ValueError):
        raise InputError(f"{flag}: {chunk!r} is not a number; give a whole number of items "
                         ">= 1 per chunk.") from None
    if not (math.isfinite(x) and x == int(x) and x >= 1):
        raise InputError(f"{flag}: {chunk} is not a whole number >= 1; give the items per "
                         "chunk (e.g. 4), or leave it out to size chunks by memory.")
    return int(x)


# ------------------------------------------------------------------------ map_batch

def map_batch(fn: Callable, batch: Any, *, devices=None, chunk=None,
              progress: Progress | None = None, plan_out: list | None = None):
    """``fn`` over every item of ``batch`` (a pytree of arrays sharing a leading axis),
    sharded over ``devices`` devices; returns the stacked outputs as host NumPy arrays
    (a pytree of arrays with the batch's leading axis).

    ``fn`` takes one item (the pytree without the leading axis) and returns a pytree of
    arrays; it is traced once per chunk shape and must be pure. The batch is padded with
    copies of its first item to a whole number of equal chunks (so one compile serves
    all), each chunk holding ``devices × per_device`` items sized to the devices' memory
    (or ``chunk`` items if given); ``progress(done, total, seconds)`` is called after
    each chunk. ``plan_out``, a list, receives the :class:`Plan`.
    """
    n_items = _leading(batch)
    mesh = device_mesh(devices)
    nd = mesh.size
    run = sharded_vmap(fn, mesh)
    t0 = time.perf_counter()

    def padded(idx, size):
        idx = np.concatenate([idx, np.zeros(size - len(idx), dtype=int)])
        return shard(_take(batch, idx), mesh)

    plan = plan_chunks(n_items, nd, chunk=chunk)
    compiled = {}
    in_turn = False
    if plan.per_device > 1:
        # one item per device: the program's bytes per item, and whether it calls LAPACK
        lowered = run.lower(padded(np.arange(min(nd, n_items)), nd))
        in_turn = lapack_in_turn(lowered, mesh.devices.flat[0])
        if chunk is None:
            compiled[nd] = lowered.compile()
            b = _per_device_bytes(compiled[nd])
            plan = plan_chunks(n_items, nd, item_bytes=b, free_bytes=device_memory())
    if in_turn and plan.per_device > 1:  # batched LAPACK on host CPU devices can hang
        run = sharded_vmap(fn, mesh, in_turn=True)
    run = compiled.get(plan.chunk, run)  # the probe serves when chunks hold one per device
    if plan_out is not None:
        plan_out.append(plan)
    size = plan.chunk
    outs = []
    for start in range(0, n_items, size):
        idx = np.arange(start, min(start + size, n_items))
        y = gather(run(padded(idx, size)))
        outs.append(jax.tree_util.tree_map(lambda a, m=len(idx): a[:m], y))
        if progress is not None:
            progress(start + len(idx), n_items, time.perf_counter() - t0)
    return jax.tree_util.tree_map(lambda *a: np.concatenate(a), *outs)


# ------------------------------------------------------------------- many fits

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
            u2, s2, done, ok, loss, size, acc = fitter._step(u, state, a)
            d2, _ = eqx.partition(s2, eqx.is_array)
            d2 = jax.tree_util.tree_map(lambda new, old: jnp.where(hold, old, new), d2, dyn)
            return jnp.where(hold, u, u2), d2, done, ok, loss, acc

        cache[in_turn] = (jax.jit(per_item(init_one, in_turn)),
                          jax.jit(per_item(step_one, in_turn)))
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
    from ._lm import StopRule

    u0 = np.asarray(u0)
    n_items = u0.shape[0]
    if _leading(args) != n_items:
        raise ValueError("difstar solve_many: u0 and args need the same number of fits.")
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
        acc = np.zeros(size, int)
        meta = np.zeros((size, 5))  # steps, accepted, loss_start, loss, result code
        t_compile = 0.0
        finished = []
        owned = np.zeros(size, bool)
        for d in mine:
            owned[sl[d]] = True
        for k in range(1, max_steps + 1):
            t1 = time.perf_counter()
            outs = {}
            for d in mine:  # dispatched to every device before any result is read
                u, dyn, a = st[d]
                outs[d] = step(u, dyn, a, put(hold[sl[d]], devs[d]))
            for d in mine:
                u, dyn, done_a, ok_a, loss_a, acc_a = outs[d]
                st[d][:2] = [u, dyn]
                done_h, ok_h, loss_h, acc_h = (np.asarray(x) for x in (done_a, ok_a, loss_a, acc_a))
                for j, i in enumerate(range(sl[d].start, sl[d].stop)):
                    if hold[i]:
                        continue
                    loss = float(loss_h[j])
                    done, ok = bool(done_h[j]), bool(ok_h[j])
                    if k == 2:
                        loss0[i] = loss
                    if rules[i].update(loss, int(acc_h[j])) and not done:
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

            u_all, meta_all, own_all = multihost_utils.process_allgather(
                (u_blk, meta, owned.astype(float)))
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
        from ._fit import SolveResult

        results: list[Any] = [None] * len(jobs)
        errors: list[BaseException | None] = [None] * len(jobs)
        batcher = self

        class Stand_in:
            def __init__(self, job):
                self._job = job

            def solve(self, u0, args, *, max_steps=100, ftol=1e-6, progress=None):
                r = batcher._solve(self._job, u0, args, max_steps, ftol)
                if progress is not None:
                    progress(r.steps, r.loss, float("nan"), True)
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


# ------------------------------------------------------------- spectral rendering

def simulate_spectral(camera, scene, grid, *, devices=None, chunk=None,
                      progress: Progress | None = None, plan_out: list | None = None):
    """:func:`difstar.simulate` of a spectral camera (``Sensor.wavelengths`` (3, K) with
    ``spectral_weights``) with its K wavelength triples sharded over ``devices``.

    Each item is the monochromatic chain (one wavelength per channel, the grid's plan,
    no background) up to the linear image; the image and the PSFs are their sums weighted
    by the channels' normalised weights (the image is linear in the PSF), and the
    background, the sensor, the mosaic and the rendering are applied once to the sum, as
    ``simulate`` does. Returns a :class:`difstar.Prediction` (host arrays)."""
    from ._chain import _finish, check_sampling, geometry_of, simulate

    sen = camera.sensor
    if sen.spectral_weights is None or np.ndim(sen.wavelengths) != 2:
        raise ValueError("difstar simulate_spectral: the camera's sensor is trichromatic "
                         "(one wavelength per channel); give Sensor(wavelengths=(3, K), "
                         "spectral_weights=(3, K)) or call difstar.simulate.")
    lams = np.asarray(sen.wavelengths).T  # (K, 3): item l is the channels' l-th wavelength
    wts = np.asarray(sen.spectral_weights)  # (3, K), normalised per channel
    dark = eqx.tree_at(lambda s: s.background, scene, jnp.zeros_like(scene.background))

    check_sampling(camera, scene, grid)  # here, on the concrete spectral camera

    def mono(lam3):
        cam = eqx.tree_at(lambda c: (c.sensor.wavelengths, c.sensor.spectral_weights),
                          camera, (lam3, None), is_leaf=lambda x: x is None)
        # simulate's own check would call np.ravel on the traced wavelengths; an object
        # distance that is traced too (+ 0·λ: the same value) makes it stand aside, as
        # it does for every traced input (the sampling was checked above)
        sc = eqx.tree_at(lambda s: s.object_distance, dark, dark.object_distance + 0.0 * lam3[0])
        pr = simulate(cam, sc, grid)
        return pr.psf, pr.image

    psfs, images = map_batch(mono, lams, devices=devices, chunk=chunk, progress=progress,
                             plan_out=plan_out)
    psf = np.einsum("cl,lchw->chw", wts, psfs)
    image = np.einsum("cl,lchw->chw", wts, images)
    finish = eqx.filter_jit(lambda c, s, p, i: _finish(c, s, grid, geometry_of(c, s), p, i))
    return jax.tree_util.tree_map(
        lambda x: np.asarray(x) if eqx.is_array(x) else x,
        finish(camera, scene, jnp.asarray(psf), jnp.asarray(image)))


__all__ = [
    "AXIS", "ENV_DEVICES", "FILL", "FitBatcher", "ItemSolve", "Plan", "device_count", "device_memory",
    "device_mesh", "gather", "init_distributed", "map_batch", "plan_chunks", "shard",
    "lapack_in_turn", "per_item", "sharded_vmap", "simulate_spectral", "solve_many",
]
