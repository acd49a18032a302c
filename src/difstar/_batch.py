"""Many independent items at once: a batch axis placed on a device mesh.

One code path for one device, several devices of one host and several hosts: the batch's
leading axis is split over a one-axis mesh (``"batch"``) of the devices JAX sees
(``jax.devices()``: every host's, once :func:`init_distributed` has joined them), and each
device runs ``jax.vmap(fn)`` over its own slice (``jax.shard_map`` with ``P("batch")`` in
and out; the items are independent, so no device needs another's). The host side pads
the batch to a multiple of the device count, splits it into chunks that fit the devices'
memory, reports progress per chunk and strips the padding. The jitted core is ``fn``
itself and stays pure.

- :func:`device_count` — how many devices to use: an argument, else ``DIFSTAR_DEVICES``,
  else all; anything else (< 1, more than exist, not a whole number) is refused with one
  line naming the flag and the fix.
- :func:`device_mesh` — the one-axis mesh.
- :func:`map_batch` — ``fn`` over a batch pytree (arrays with a leading axis), sharded.
- many fits in lockstep (:func:`difstar._batch_fits.solve_many`, ``FitBatcher``) are in
  :mod:`difstar._batch_fits`.
- :func:`simulate_spectral` — a spectral :func:`difstar.simulate` whose wavelengths are
  the batch: the linear image is linear in the PSF, so it is the weighted sum of the
  monochromatic images, and the sensor is applied once to the sum.
- the multi-process job (``init_distributed``, ``writes_output``, ``dry_run``: the
  launch, the watchdog, who writes) is in :mod:`difstar._distributed` (see
  ``docs/sharding.md`` for the commands).

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
import time
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from . import _distributed
from ._chain import _finish, check_sampling, geometry_of, simulate
from ._distributed import DryRun, Launch, _collective, check_lost, dry_run
from ._validate import InputError, memory_budget, memory_limit_from_env

AXIS = "batch"
ENV_DEVICES = "DIFSTAR_DEVICES"
#: fraction of a device's free memory a chunk may use (the rest: fragmentation, the
#: runtime's own buffers, and the estimate's error)
FILL = 0.6

Progress = Callable[[int, int, float], None]  # (items done, items in all, seconds so far)


def device_count(devices=None, *, flag: str = "--devices") -> int:
    """How many devices to use: ``devices`` if given, else ``DIFSTAR_DEVICES``, else all
    of them. :class:`InputError` (one line: the flag and the fix) for < 1, NaN, a
    fraction, or more than exist. In a dry run of a multi-process job, the devices of
    every process (each assumed to have as many as this one)."""
    planned = _distributed._JOB.get("planned")
    have = (planned.num_processes * jax.local_device_count() if planned is not None
            else jax.device_count())
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
    :func:`device_count`), across every host in a multi-process job. In a dry run: the
    mesh is printed (one fit's Jacobian columns are its work) and :class:`DryRun` raised."""
    n = device_count(n_devices)
    if dry_run():
        _print_plan(None, n, what="Jacobian columns of one fit")
    return Mesh(np.asarray(jax.devices()[:n]), (AXIS,))


def _ranges(idx) -> str:
    """0 1 2 5 6 → '0–2, 5–6'."""
    idx = list(idx)
    if not idx:
        return "none"
    out, start = [], idx[0]
    for a, b in zip(idx, idx[1:] + [None]):
        if b != a + 1:
            out.append(f"{start}" if start == a else f"{start}–{a}")
            start = b
    return ", ".join(out)


def plan_lines(n_items: int | None, n_devices: int, *, chunk=None, what: str = "items",
               launch: Launch | None = None, local_devices: int | None = None,
               platform: str = "cpu") -> list[str]:
    """The dry run's text: the mesh (processes × devices each) and, per process, its
    devices and the items each chunk gives it (``n_items`` None: the mesh only)."""
    n_proc = 1 if launch is None else launch.num_processes
    local = local_devices or max(1, -(-n_devices // n_proc))
    who = "" if launch is None else (f" (launched by {launch.launcher}; coordinator "
                                     f"{launch.coordinator})")
    lines = [f"mesh: {n_devices} {platform} device(s) of {n_proc} process(es), {local} "
             f"device(s) per process{who}"]
    if n_items is None:
        lines.append(f"work: the {what}, shared over the {n_devices} devices")
        procs = range(n_proc)
        for p in procs:
            devs = [d for d in range(n_devices) if d // local == p]
            lines.append(f"process {p}: devices {_ranges(devs)}")
        return lines
    plan = plan_chunks(n_items, n_devices, chunk=chunk)
    size, k = plan.chunk, plan.per_device
    pad = plan.chunks * size - n_items
    sizing = ("" if chunk is not None else
              " (the run may split it further to fit the devices' memory)")
    lines.append(f"work: {n_items} {what} in {plan.chunks} chunk(s) of {size} ({k} per "
                 f"device), {pad} padding item(s){sizing}")
    for p in range(n_proc):
        devs = [d for d in range(n_devices) if d // local == p]
        items = [c * size + d * k + j for c in range(plan.chunks) for d in devs
                 for j in range(k)]
        real = [i for i in items if i < n_items]
        extra = len(items) - len(real)
        lines.append(f"process {p}: devices {_ranges(devs)}: {what} {_ranges(real)}"
                     + (f" (+{extra} padding)" if extra else ""))
    return lines


def _print_plan(n_items, n_devices, *, chunk=None, what="items"):
    """Print the dry run's plan to stdout and raise :class:`DryRun`."""
    import sys

    launch = _distributed._JOB.get("planned") or _distributed._JOB.get("launch")
    lines = plan_lines(n_items, n_devices, chunk=chunk, what=what, launch=launch,
                       local_devices=jax.local_device_count(), platform=jax.default_backend())
    me = 0 if launch is None else launch.process_id
    if me != 0:  # every process prints its own line; process 0 the whole plan
        lines = lines[:2] + [x for x in lines[2:] if x.startswith(f"process {me}:")]
    sys.stdout.write("".join(f"difstar dry run: {x}\n" for x in lines)
                     + "difstar dry run: nothing was computed or written.\n")
    sys.stdout.flush()
    raise DryRun()


def device_memory(device=None) -> int:
    """Bytes free on ``device`` (default the first): ``memory_stats()``'s limit minus
    what is in use where the device reports it (GPUs), else ``DIFSTAR_MEMORY_LIMIT`` or
    the host's memory, shared by the host's devices (CPU devices share it)."""
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

        return _collective(lambda: multihost_utils.process_allgather(tree, tiled=True))
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
    if dry_run():
        _print_plan(n_items, device_count(devices), chunk=chunk)
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
        check_lost()
        idx = np.arange(start, min(start + size, n_items))
        y = gather(run(padded(idx, size)))
        outs.append(jax.tree_util.tree_map(lambda a, m=len(idx): a[:m], y))
        if progress is not None:
            progress(start + len(idx), n_items, time.perf_counter() - t0)
    return jax.tree_util.tree_map(lambda *a: np.concatenate(a), *outs)


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
    "AXIS", "ENV_DEVICES", "FILL", "Plan", "device_count", "device_memory", "device_mesh",
    "gather", "lapack_in_turn", "map_batch", "per_item", "plan_chunks", "plan_lines",
    "shard", "sharded_vmap", "simulate_spectral",
]
