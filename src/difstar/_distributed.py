"""The multi-process job: several processes (hosts, or GPUs of one host) joined by
``jax.distributed`` so that the device meshes of :mod:`difstar._batch` span them all.

- :func:`init_distributed` — join the job the environment names (:func:`launch_from_env`:
  ``JAX_*`` variables, ``srun``, ``mpirun``), with a watchdog that turns a lost process
  into one :class:`ProcessLost` line (exit status :data:`EXIT_LOST`) instead of JAX's
  abort.
- :func:`writes_output` — process 0 writes the job's outputs (every process holds every
  result).
- ``DIFSTAR_DRY_RUN=1`` (:func:`dry_run`) — print the mesh and each process's items and
  compute nothing (:class:`DryRun`).

See ``docs/sharding.md`` for the commands.
"""

from __future__ import annotations

import dataclasses
import os
import threading
import time

import jax

from ._validate import InputError

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
