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
- :func:`init_distributed` — join the multi-process job the environment names
  (:func:`launch_from_env`: ``JAX_*`` variables, ``srun``, ``mpirun``), with a watchdog
  that turns a lost process into one :class:`ProcessLost` line instead of JAX's abort;
  :func:`writes_output` (process 0 writes); ``DIFSTAR_DRY_RUN=1`` (:func:`dry_run`)
  prints the mesh and each process's items and computes nothing (see
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

ENV_DRY_RUN = "DIFSTAR_DRY_RUN"
ENV_HEARTBEAT = "DIFSTAR_HEARTBEAT_TIMEOUT"
ENV_JOIN_TIMEOUT = "DIFSTAR_JOIN_TIMEOUT"
#: exit status of a process whose job lost another process (as the CLI's other
#: "machine" errors: one ``difstar: error:`` line, status 2)
EXIT_LOST = 2
#: seconds between two heartbeats of a process's watchdog (a counter in the job's
#: key-value store) and two looks at the others'
WATCH_EVERY = 0.25
#: seconds without a heartbeat after which a process counts as lost; after a collective
#: failed (a peer's sockets closed), :data:`SUSPECT_AFTER`
LOST_AFTER = 10.0
SUSPECT_AFTER = 1.0
#: seconds a process that saw another die gives its main thread to end by itself (the
#: clean way: the exception unwinds, temporaries are removed) before it ends the process
LOST_GRACE = 10.0
#: seconds the coordinator stays up after process 0 died, for the others to see it and end
COORDINATOR_LINGER = LOST_GRACE + 20.0


class ProcessLost(ConnectionError):
    """Another process of the multi-process job died (or ended before the job was done):
    the job cannot finish. One line, naming the process; the command line prints it as
    ``difstar: error: …`` and exits with status 2, leaving nothing behind."""


class DryRun(SystemExit):
    """``DIFSTAR_DRY_RUN=1``: the plan was printed and nothing is computed (exit status 0,
    no output: a command's temporary folder is removed as for any early end)."""

    def __init__(self):
        super().__init__(0)


@dataclasses.dataclass(frozen=True)
class Launch:
    """A multi-process job as the environment describes it (:func:`launch_from_env`)."""

    coordinator: str  # host:port of the coordination service (served for process 0)
    num_processes: int
    process_id: int
    local_device_ids: tuple[int, ...] | None  # this process's devices (GPUs), None: all
    launcher: str  # which variables described it


def _whole(env, name: str) -> int | None:
    text = env.get(name, "").strip()
    if not text:
        return None
    try:
        return int(text)
    except ValueError:
        raise InputError(f"{name}: {text!r} is not a whole number; it is set by the "
                         "launcher (or by you: a process count or id 0, 1, …); fix or unset "
                         "it to run alone.") from None


def _slurm_tasks_on_node(env) -> int | None:
    """Tasks of this SLURM step on this node, from ``SLURM_STEP_TASKS_PER_NODE`` (e.g.
    ``2(x3),1``: 2 on each of the first 3 nodes, 1 on the fourth) and ``SLURM_NODEID``."""
    text, node = env.get("SLURM_STEP_TASKS_PER_NODE", ""), _whole(env, "SLURM_NODEID")
    counts = []
    for part in filter(None, text.split(",")):
        n, _, rep = part.partition("(x")
        try:
            counts += [int(n)] * (int(rep.rstrip(")")) if rep else 1)
        except ValueError:
            return None
    if node is None or not 0 <= node < len(counts):
        return None
    return counts[node]


def launch_from_env(env=None) -> Launch | None:
    """The multi-process job the environment describes, or None (run alone). Reads only
    variables (no network, no JAX): what :func:`init_distributed` joins and what a dry
    run prints. One line naming the variable and the fix for a contradiction.

    - ``JAX_COORDINATOR_ADDRESS`` (host:port of process 0) with ``JAX_NUM_PROCESSES`` and
      ``JAX_PROCESS_ID`` — any launcher; without those two the count and the rank come
      from the launcher's own variables: Open MPI (``OMPI_COMM_WORLD_SIZE``/``_RANK``),
      MPICH / Intel MPI / Hydra (``PMI_SIZE``/``PMI_RANK``) or a SLURM step
      (``SLURM_NTASKS``/``SLURM_PROCID``);
    - a SLURM job step of more than one task (``srun``: ``SLURM_NTASKS`` > 1 with
      ``SLURM_STEP_NODELIST``, ``SLURM_PROCID`` and ``SLURM_JOB_ID``): the coordinator is
      the step's first node, the port ``JAX_COORDINATOR_PORT`` or derived from the job id
      (as JAX derives it). A batch script itself (``sbatch``, no step) runs alone;
    - an Open MPI 4 launch (``OMPI_MCA_orte_hnp_uri``, ``OMPI_COMM_WORLD_SIZE`` > 1): the
      coordinator is the launcher's host (as JAX derives it). Open MPI 5 and other MPIs
      name no coordinator: give ``-x JAX_COORDINATOR_ADDRESS=HOST:PORT``.

    ``JAX_LOCAL_DEVICE_IDS`` (e.g. ``0,1``) picks this process's GPUs; else, where a
    launcher starts several processes on one node, each gets the GPU of its local rank
    (``SLURM_LOCALID``, ``OMPI_COMM_WORLD_LOCAL_RANK``), and a lone process per node all
    of them."""
    env = os.environ if env is None else env
    addr = env.get("JAX_COORDINATOR_ADDRESS", "").strip()
    slurm_step = all(env.get(k) for k in ("SLURM_STEP_NODELIST", "SLURM_PROCID",
                                            "SLURM_JOB_ID"))
    n_slurm = _whole(env, "SLURM_NTASKS") if slurm_step else None
    n_ompi = _whole(env, "OMPI_COMM_WORLD_SIZE")
    n_pmi = _whole(env, "PMI_SIZE")
    local = None
    if addr:
        n, pid = _whole(env, "JAX_NUM_PROCESSES"), _whole(env, "JAX_PROCESS_ID")
        who = "JAX_* variables"
        for name, size, rank in (("Open MPI", "OMPI_COMM_WORLD_SIZE", "OMPI_COMM_WORLD_RANK"),
                                 ("MPI (PMI)", "PMI_SIZE", "PMI_RANK"),
                                 ("SLURM", "SLURM_NTASKS", "SLURM_PROCID")):
            if n is None and pid is None and _whole(env, size) and (
                    name != "SLURM" or slurm_step):
                n, pid = _whole(env, size), _whole(env, rank)
                who = f"{name} with JAX_COORDINATOR_ADDRESS"
        if n is None or pid is None:
            raise InputError(
                "JAX_COORDINATOR_ADDRESS is set but not JAX_NUM_PROCESSES and JAX_PROCESS_ID "
                "(and no srun/mpirun variables give them): set both (e.g. JAX_NUM_PROCESSES=2 "
                "JAX_PROCESS_ID=0 for the first process), or unset JAX_COORDINATOR_ADDRESS to "
                "run alone.")
        if ":" not in addr or not addr.rsplit(":", 1)[1].isdigit():
            raise InputError(f"JAX_COORDINATOR_ADDRESS: {addr!r} is not HOST:PORT; give process "
                             "0's host and a free port, e.g. 10.0.0.1:12345 (127.0.0.1:PORT on "
                             "one machine).")
    elif n_slurm is not None and n_slurm > 1:
        n, pid, who = n_slurm, _whole(env, "SLURM_PROCID"), "SLURM (srun)"
        addr = _cluster_address("SlurmCluster", env)
        if (_slurm_tasks_on_node(env) or 1) > 1:
            local = _whole(env, "SLURM_LOCALID")
    elif env.get("OMPI_MCA_orte_hnp_uri") and (n_ompi or 1) > 1:
        n, pid, who = n_ompi, _whole(env, "OMPI_COMM_WORLD_RANK"), "Open MPI (mpirun)"
        addr = _cluster_address("OmpiCluster", env)
        if (_whole(env, "OMPI_COMM_WORLD_LOCAL_SIZE") or 1) > 1:
            local = _whole(env, "OMPI_COMM_WORLD_LOCAL_RANK")
    elif (n_ompi or 1) > 1 or (n_pmi or 1) > 1:
        raise InputError(
            f"{'OMPI_COMM_WORLD_SIZE' if (n_ompi or 1) > 1 else 'PMI_SIZE'}: started by mpirun "
            "as one of several processes, but the launcher names no coordinator: pass "
            "JAX_COORDINATOR_ADDRESS=HOST:PORT (the first rank's host, a free port) to every "
            "process, e.g. mpirun -x JAX_COORDINATOR_ADDRESS=… (Open MPI) or "
            "mpiexec -genv JAX_COORDINATOR_ADDRESS … (MPICH).")
    else:
        return None
    if pid is None or not (n >= 1 and 0 <= pid < n):
        raise InputError(f"JAX_PROCESS_ID: {pid} is not in [0, {n}) (the number of processes, "
                         f"from the {who}); give each process its own id 0 … N − 1.")
    ids = env.get("JAX_LOCAL_DEVICE_IDS", "").strip()
    if ids:
        try:
            local_ids = tuple(int(x) for x in ids.split(","))
        except ValueError:
            raise InputError(f"JAX_LOCAL_DEVICE_IDS: {ids!r} is not a list of device numbers "
                             "such as 0,1; fix or unset it (all of this host's GPUs).") from None
    else:
        local_ids = None if local is None else (local,)
    return Launch(addr, n, pid, local_ids, who)


def _cluster_address(name: str, env) -> str:
    """The coordinator JAX itself would derive for a SLURM / Open MPI launch."""
    try:
        from jax._src import clusters

        cls = getattr(clusters, name)
        env, saved = dict(env), dict(os.environ)
        os.environ.clear()
        os.environ.update(env)  # JAX's classes read os.environ
        try:
            return cls.get_coordinator_address(
                timeout_secs=None, override_coordinator_port=env.get("JAX_COORDINATOR_PORT"))
        finally:
            os.environ.clear()
            os.environ.update(saved)
    except Exception as exc:  # an unusual node list or URI, or another JAX version
        var = "SLURM_STEP_NODELIST" if name == "SlurmCluster" else "OMPI_MCA_orte_hnp_uri"
        raise InputError(f"{var}: cannot derive the coordinator's address ({exc}); set "
                         "JAX_COORDINATOR_ADDRESS=HOST:PORT (the first process's host).") from None


def dry_run() -> bool:
    """``DIFSTAR_DRY_RUN``: 1/true/yes/on print the plan and compute nothing; unset, empty,
    0/false/no/off run. Anything else is refused with one line."""
    text = os.environ.get(ENV_DRY_RUN, "").strip().lower()
    if text in ("", "0", "false", "no", "off"):
        return False
    if text in ("1", "true", "yes", "on"):
        return True
    raise InputError(f"{ENV_DRY_RUN}: {text!r}; give 1 to print the mesh and each process's "
                     "work without computing, or unset it.")


#: the job this process joined (or, in a dry run, would join): its Launch, JAX client,
#: the coordinator process (process 0), and what the watchdog saw
_JOB: dict = {}


def init_distributed() -> bool:
    """Join the multi-process job the environment describes (:func:`launch_from_env`);
    returns whether it did. Call it before anything touches a device (the CLI does, first
    thing, when ``--devices``/``DIFSTAR_DEVICES`` is used). In a dry run
    (``DIFSTAR_DRY_RUN=1``) nothing is joined: the job is only noted, for the plan.

    How a lost process is handled (docs/sharding.md, *When a process dies*): process 0
    serves the coordination service from a small process of its own (so that the others
    still reach it when process 0 itself dies), and a thread of each process beats a
    counter in the job's key-value store and watches the others' (:func:`_watch`). When
    one stops without having ended, the next collective (or the next chunk, solver step
    or solve round) raises :class:`ProcessLost` naming it; a process stuck elsewhere is
    ended after :data:`LOST_GRACE` seconds with the same one line. Without this JAX's
    coordination service aborts the survivors (SIGABRT, a C++ stack trace), 0.2 s after
    process 0 dies or 100 s after another does.
    """
    if jax.distributed.is_initialized() or _JOB.get("client") is not None:
        return True
    launch = launch_from_env()
    if launch is None or launch.num_processes == 1:
        return False
    if dry_run():
        _JOB["planned"] = launch
        return False
    _join(launch)
    return True


_COORDINATOR = r"""
import sys, time
try:
    from jaxlib import _jax
except ImportError:
    from jax._src.lib import _jax
bind, n, beat, linger = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4])
kw = dict(heartbeat_timeout=beat, shutdown_timeout=60)
try:
    try:  # recoverable: a dead task is not reported to the others as a fatal error
        svc = _jax.get_distributed_runtime_service(bind, n, recoverable=True, **kw)
    except TypeError:
        svc = _jax.get_distributed_runtime_service(bind, n, **kw)
except Exception as e:
    print("error: " + " ".join(str(e).split()), flush=True)
    sys.exit(1)
print("ready", flush=True)
said = sys.stdin.readline().strip()  # "bye" when process 0 ends; "" when it died
time.sleep(0.5 if said == "bye" else linger)
svc.shutdown()
"""


def _join(launch: Launch) -> None:
    import atexit
    import subprocess
    import sys

    try:
        from jax._src import distributed as jd
        from jax._src.lib import _jax

        make_client = _jax.get_distributed_runtime_client
        state = jd.global_state
    except (ImportError, AttributeError):  # another JAX: its own join, its own failures
        jax.distributed.initialize(launch.coordinator, launch.num_processes,
                                   launch.process_id, local_device_ids=launch.local_device_ids)
        return
    try:
        from jax._src.xla_bridge import backends_are_initialized
    except ImportError:  # pragma: no cover - another JAX
        def backends_are_initialized():
            return False
    if backends_are_initialized():
        raise RuntimeError("difstar init_distributed: JAX's devices were used before the "
                           "job was joined; call it first (before jax.devices(), any array "
                           "or computation), as jax.distributed.initialize requires.")
    env = os.environ
    beat = _whole(env, ENV_HEARTBEAT) or 100
    wait = _whole(env, ENV_JOIN_TIMEOUT) or 300
    n, me = launch.num_processes, launch.process_id
    try:
        # a Python error callback, though jaxlib cannot hand it the error (the status
        # does not convert): with it a failed connect raises here, without it the
        # default callback aborts the process with a C++ stack trace
        client = make_client(launch.coordinator, me, init_timeout=wait, heartbeat_timeout=beat,
                             use_compression=True, shutdown_on_destruction=False,
                             missed_heartbeat_callback=_agent_error)
    except TypeError:  # another jaxlib: JAX's own join, its own failures
        jax.distributed.initialize(launch.coordinator, n, me,
                                   local_device_ids=launch.local_device_ids)
        return
    helper = None
    if me == 0:
        import select

        port = launch.coordinator.rsplit(":", 1)[1]
        bind = env.get("JAX_COORDINATOR_BIND_ADDRESS", f"[::]:{port}")
        helper = subprocess.Popen(
            [sys.executable, "-c", _COORDINATOR, bind, str(n), str(beat),
             str(COORDINATOR_LINGER)], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL, text=True, start_new_session=True)
        ready, _, _ = select.select([helper.stdout], [], [], 120.0)
        said = helper.stdout.readline().strip() if ready else ""
        helper.stdout.close()
        if said != "ready":
            helper.kill()
            helper.wait()
            raise InputError(f"JAX_COORDINATOR_ADDRESS {launch.coordinator}: process 0 cannot "
                             f"serve the job's coordinator on {bind} "
                             f"({said.removeprefix('error: ') or 'it ended'}); choose a free "
                             "port.")
    if launch.local_device_ids:
        visible = ",".join(map(str, launch.local_device_ids))
        for flag in ("jax_cuda_visible_devices", "jax_rocm_visible_devices"):
            try:
                jax.config.update(flag, visible)
            except (AttributeError, ValueError):
                pass
    try:
        state.coordinator_address = launch.coordinator
        state.process_id, state.num_processes = me, n
        state.client = client
        client.connect()
    except Exception:
        state.client = None
        if helper is not None:
            helper.kill()
        try:  # never destroyed: its destructor would log a page about its error state
            import ctypes

            ctypes.pythonapi.Py_IncRef(ctypes.py_object(client))
        except Exception:
            pass
        raise InputError(
            f"JAX_COORDINATOR_ADDRESS {launch.coordinator}: process {me} of {n} could not join "
            f"the job within {wait} s; start every process (ids 0 … {n - 1}) with the same "
            f"address and JAX_NUM_PROCESSES, process 0 on that host ({ENV_JOIN_TIMEOUT} "
            "sets the wait).") from None
    # JAX's preemption service is left off: it swallows SIGTERM (a scheduler's or
    # timeout's stop would be ignored) and difstar has no preemption sync points
    _JOB.update(launch=launch, client=client, helper=helper, lost=None, reported=False,
                ending=False, beating=True, lock=threading.Lock())
    _JOB["watch"] = threading.Thread(target=_watch, name="difstar-watch", daemon=True)
    _JOB["watch"].start()
    atexit.register(_at_exit)  # runs before JAX's own clean-up (registered earlier)


def _agent_error(*args) -> None:
    """The coordination client's error callback (see :func:`_join`; never reached)."""


def _beats(client) -> dict[int, str]:
    """Every process's heartbeat counter (or ``"exit"``: it ended normally)."""
    return {int(k.rsplit("/", 1)[1]): v for k, v in client.key_value_dir_get("difstar/beat/")}


def _lost_message(p: int, n: int, ended: bool) -> str:
    if ended:
        return (f"process {p} of {n} ended before the job was done (see its own message); "
                "the job is ended, nothing was written")
    return f"process {p} of {n} stopped responding; the job is ended, nothing was written"


def _lose(message: str) -> None:
    if _JOB.get("lost"):
        return
    _JOB["lost"] = message

    def end():
        time.sleep(LOST_GRACE)
        _hard_exit()

    threading.Thread(target=end, name="difstar-lost", daemon=True).start()


def _hard_exit() -> None:
    """End this process now: the main thread did not end by itself (it waits inside a
    computation or a collective that will not return)."""
    import sys

    if not _JOB.get("reported"):
        _JOB["reported"] = True
        try:
            sys.stderr.write(f"difstar: error: {_JOB['lost']}\n")
        except Exception:
            pass
    for f in (sys.stdout, sys.stderr):
        try:
            f.flush()
        except Exception:
            pass
    helper, launch = _JOB.get("helper"), _JOB.get("launch")
    if helper is not None and launch is not None and launch.num_processes == 2:
        try:  # the one other process is lost: nobody needs the coordinator any more
            helper.stdin.write("bye\n")
            helper.stdin.close()
        except Exception:
            pass
    os._exit(EXIT_LOST)


def _watch() -> None:
    """The watchdog thread: beats this process's counter in the job's key-value store and
    watches the others'. A process whose counter stops for :data:`LOST_AFTER` seconds
    (:data:`SUSPECT_AFTER` once a collective failed) without having said it ended is
    lost. (The coordination service's own liveness call, ``get_live_nodes``, waits for
    every listed process to call it as well, and a call made before a process died
    waits for its heartbeat timeout: unusable here.)"""
    job = _JOB
    client, launch = job["client"], job["launch"]
    me, n = launch.process_id, launch.num_processes
    seen = {p: (None, time.monotonic()) for p in range(n) if p != me}
    count, last = 0, time.monotonic()
    while not job["ending"] and not job["lost"]:
        time.sleep(WATCH_EVERY)
        count += 1
        try:
            with job["lock"]:  # never after this process's "exit" (see _at_exit)
                if job["beating"]:
                    client.key_value_set(f"difstar/beat/{me}", str(count),
                                         allow_overwrite=True)
            beats = _beats(client)
        except Exception:  # the coordination service is gone with process 0's host
            if not job["ending"]:
                _lose(_lost_message(0, n, False).replace(
                    "stopped responding", "(the coordinator) stopped responding"))
            return
        now = time.monotonic()
        if now - last > LOST_AFTER / 2:  # this thread itself was held up: judge nobody
            seen = {p: (v, now) for p, (v, _) in seen.items()}
        last = now
        limit = SUSPECT_AFTER if job.get("suspect") else LOST_AFTER
        for p, (v, t) in list(seen.items()):
            b = beats.get(p)
            if b == "exit":
                seen.pop(p)
                if job.get("suspect"):  # it left while this process waits on it
                    _lose(_lost_message(p, n, True))
            elif b != v:
                seen[p] = (b, now)
            elif now - t > limit and not job["ending"]:
                _lose(_lost_message(p, n, False))
        if job["lost"]:
            return


def check_lost() -> None:
    """Raise :class:`ProcessLost` if the job has lost a process (called between chunks,
    solver steps and solve rounds, so a process busy with its own work ends soon too)."""
    msg = _JOB.get("lost")
    if msg:
        _JOB["reported"] = True
        raise ProcessLost(msg)


def _collective(fn, *args):
    """A cross-process collective: a failure that comes from a lost process is raised as
    :class:`ProcessLost` naming it (a killed process's sockets close and Gloo fails at
    once; its heartbeat then stops, and the watchdog names it within
    :data:`SUSPECT_AFTER` seconds; one that ended early has said so)."""
    job = _JOB
    if job.get("client") is None:
        return fn(*args)
    check_lost()
    try:
        return fn(*args)
    except Exception:
        job["suspect"] = True
        launch = job["launch"]
        try:
            early = [p for p, v in _beats(job["client"]).items()
                     if v == "exit" and p != launch.process_id]
        except Exception:
            early = []
        if early:  # it ended (with an error of its own) while this one waited on it
            _lose(_lost_message(min(early), launch.num_processes, True))
        t_end = time.monotonic() + SUSPECT_AFTER + 3.0
        while not job.get("lost") and time.monotonic() < t_end:
            time.sleep(0.05)
        if job.get("lost"):
            job["reported"] = True
            raise ProcessLost(job["lost"]) from None
        job["suspect"] = False
        raise


def _at_exit() -> None:
    """At the end of a process of the job. After a loss: end now (JAX's own shut-down
    would wait for the lost process, then abort). Else say so in the key-value store and
    disconnect; process 0, whose helper serves the coordinator, first waits until every
    other process has said so (or is lost)."""
    import sys

    job = _JOB
    client = job.get("client")
    if client is None:
        return
    if job.get("lost"):
        _hard_exit()
    launch = job["launch"]
    me, n = launch.process_id, launch.num_processes
    if me != 0:
        job["ending"] = True
    with job["lock"]:
        job["beating"] = False
        try:
            client.key_value_set(f"difstar/beat/{me}", "exit", allow_overwrite=True)
        except Exception:
            pass
    if me == 0:
        while not job.get("lost"):
            try:
                if sum(v == "exit" for p, v in _beats(client).items() if p) == n - 1:
                    break
            except Exception:
                break
            time.sleep(0.1)
        job["ending"] = True
        if job.get("lost"):  # after every result was gathered: a warning
            sys.stderr.write(f"difstar: warning: {job['lost'].split(';')[0]} as the job "
                             "ended (after every result was gathered)\n")
            job["lost"] = None
        time.sleep(0.5)  # the others' disconnection, sent right after their word
    # the watchdog must be out of the client's calls before the interpreter ends: a daemon
    # thread inside a C++ call at finalisation is unwound by force, and the C++ runtime
    # aborts ("FATAL: exception not rethrown")
    watch = job.get("watch")
    if watch is not None and watch is not threading.current_thread():
        watch.join(timeout=5.0)
    try:
        jax.distributed.shutdown()
    except Exception:
        pass
    job["client"] = None
    helper = job.get("helper")
    if helper is not None:
        try:
            helper.stdin.write("bye\n")
            helper.stdin.close()
        except Exception:
            pass


def writes_output() -> bool:
    """Whether this process writes the job's outputs: process 0 of a multi-process job
    (every process holds every result, one writes them), the only process otherwise.
    Starts nothing (no JAX backend), so an output module may ask it at any time."""
    launch = _JOB.get("launch")
    if launch is not None:
        return launch.process_id == 0
    if jax.distributed.is_initialized():  # joined by JAX itself (another JAX version)
        return jax.process_index() == 0
    return True


def device_count(devices=None, *, flag: str = "--devices") -> int:
    """How many devices to use: ``devices`` if given, else ``DIFSTAR_DEVICES``, else all
    of them. :class:`InputError` (one line: the flag and the fix) for < 1, NaN, a
    fraction, or more than exist. In a dry run of a multi-process job, the devices of
    every process (each assumed to have as many as this one)."""
    planned = _JOB.get("planned")
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

    launch = _JOB.get("planned") or _JOB.get("launch")
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
        acc = np.zeros(size, int)
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
        from ._lm import SolveResult

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
    "AXIS", "ENV_DEVICES", "ENV_DRY_RUN", "EXIT_LOST", "FILL", "DryRun", "FitBatcher",
    "ItemSolve", "Launch", "Plan", "ProcessLost", "check_lost", "device_count",
    "device_memory", "device_mesh", "dry_run", "gather", "init_distributed",
    "launch_from_env", "map_batch", "plan_chunks", "plan_lines", "shard", "lapack_in_turn",
    "per_item", "sharded_vmap", "simulate_spectral", "solve_many", "writes_output",
]
