"""Several processes for real (issue 35): two difstar processes on this machine joined by
``jax.distributed`` — a coordinator on 127.0.0.1 (a free port), ``JAX_NUM_PROCESSES=2``,
``JAX_PROCESS_ID=0/1``, one host CPU device each, JAX's Gloo CPU collectives — run sharded
work across both and give the one-process results; when one is killed the other ends
within seconds with one line; the environment of ``srun``/``mpirun`` maps to the same job;
a dry run prints the plan and computes nothing.

Each pair is started exactly as docs/sharding.md shows (*Several processes on one host*).
The children write their output to files (no pipes to fill) and every wait is bounded; a
child that cannot join or collect fails the test with its stderr (nothing is skipped: a
JAX without CPU collectives across processes fails here).
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import jax
import numpy as np
import pytest

from difstar import _batch as B

from difstar import _batch_fits as BF

from difstar import _distributed as DI
from difstar._validate import InputError

ROOT = Path(__file__).resolve().parents[1]

#: the design sweep's measures cut to the iris's geometry (area, convexity margin,
#: circumradius; the PSF measures 0): the command's own path — parsing, joining, devices,
#: chunks, progress, output folder, errors — at a compile of a second instead of 12 s
#: (the full measures are sharded and checked against one device in test_design_cli.py)
GEOMETRIC = textwrap.dedent('''
    import jax.numpy as jnp
    import difstar._design_study as D

    def geometric(family, setup, opts):
        def values(p):
            pu = family.pupil(p)
            z = 0.0 * p.curvature
            return {"curvature": p.curvature, "max_abs_radial": jnp.max(jnp.abs(p.radial)),
                    "max_abs_angular_rad": jnp.max(jnp.abs(p.angular)),
                    **{k: z for k in ("halo_anisotropy", "spike_wedge_energy",
                                      "spike_wedge_excess", "spike_length_px", "core_energy",
                                      "bokeh_cv", "bokeh_peak")},
                    "area_rel_error": pu.area() / family.area - 1,
                    "convexity_margin_rad": pu.convexity_margin(),
                    "circumradius_m": pu.circumradius}, None, None, None
        return values
''')

SWEEP = ["--x64", "design", "--sweep-curvature", "0", "0.9", "6", "--chunk", "4"]

#: process 0 and 1's work: difstar.map_batch of 8 PSFs, then the command line's design
#: sweep (`difstar design --sweep-curvature 0 0.9 6 --chunk 4 --devices 2`), one job
WORKER = GEOMETRIC + "D.measures_fn = geometric\n" + textwrap.dedent(f'''
    import json, os, sys
    import jax
    jax.config.update("jax_enable_x64", True)
    import numpy as np
    import difstar
    from difstar import _batch as B
    from difstar import _batch_fits as BF
    from difstar import _distributed as DI
    from difstar.cli import main

    out = sys.argv[1]
    joined = DI.init_distributed()
    me = jax.process_index()
    r = {{"process": me, "processes": jax.process_count(), "devices": jax.device_count(),
         "local_devices": jax.local_device_count(), "joined": joined}}
    pupil = difstar.RegularPolygon(7, 1.0e-3, 0.1)
    lams = np.linspace(450e-9, 650e-9, 8)
    kw = dict(z_image=0.05, defocus=2e-4, pixel_pitch=4e-6, shape=(24, 24))
    plan = difstar.plan_psf(pupil, wavelength=lams, **kw)
    psfs = B.map_batch(lambda lam: difstar.psf(pupil, wavelength=lam, plan=plan, **kw), lams)
    if DI.writes_output():  # every process holds every PSF; one writes them
        np.save(os.path.join(out, f"psfs-written-by-{{me}}.npy"), psfs)
    # one --out for both processes: process 0 alone checks and commits it
    r["sweep_rc"] = main({SWEEP!r} + ["--devices", "2", "--out",
                                      os.path.join(out, "sweep")])
    print("RESULT " + json.dumps(r), flush=True)
''')

#: the same sweep, 12 designs in chunks of 2: the victim stops in its third chunk and
#: waits to be killed; the survivor must end by itself
KILL_WORKER = GEOMETRIC + "D.measures_fn = geometric\n" + textwrap.dedent('''
    import os, sys, time
    import jax
    from difstar import _batch as B
    from difstar import _batch_fits as BF
    from difstar import _distributed as DI
    from difstar.cli import main

    out, victim = sys.argv[1], int(sys.argv[2])
    real_gather, calls = B.gather, [0]

    def gather(tree):
        calls[0] += 1
        if calls[0] == 3 and jax.process_index() == victim:
            with open(os.path.join(out, "victim-waits.tmp"), "w") as f:
                f.write(str(os.getpid()))
            os.replace(os.path.join(out, "victim-waits.tmp"), os.path.join(out, "victim-waits"))
            if os.environ.get("VICTIM_FAILS"):
                raise ValueError("a failure of its own")
            time.sleep(120)  # killed here by the test
        return real_gather(tree)

    B.gather = gather
    DI.init_distributed()
    if jax.process_index() == 0:
        with open(os.path.join(out, "coordinator.pid"), "w") as f:
            f.write(str(DI._JOB["helper"].pid))
    me = jax.process_index()
    sys.exit(main(["--x64", "design", "--sweep-curvature", "0", "0.9", "12", "--chunk", "2",
                   "--devices", "2", "--out", os.path.join(out, f"sweep{me}")]))
''')


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_pair(code: str | None, args: list[str], logs: Path, **extra) -> list[subprocess.Popen]:
    """The two processes of docs/sharding.md's one-host example, each with one CPU
    device, running ``python -c code args`` (``python -m difstar.cli args`` when ``code``
    is None); stdout/stderr go to ``logs/{out,err}{i}.txt``. Their system temporary folder
    (TMPDIR) is ``logs/systmp``, so that what a process leaves there can be seen."""
    port = free_port()
    (logs / "systmp").mkdir(exist_ok=True)
    procs = []
    for i in (0, 1):
        env = dict(os.environ, JAX_PLATFORMS="cpu", JAX_COORDINATOR_ADDRESS=f"127.0.0.1:{port}",
                   JAX_NUM_PROCESSES="2", JAX_PROCESS_ID=str(i), TMPDIR=str(logs / "systmp"),
                   **extra)
        for k in ("XLA_FLAGS", B.ENV_DEVICES, DI.ENV_DRY_RUN):
            env.pop(k, None)
        cmd = ["-m", "difstar.cli"] if code is None else ["-c", code]
        with open(logs / f"out{i}.txt", "w") as o, open(logs / f"err{i}.txt", "w") as e:
            procs.append(subprocess.Popen([sys.executable, *cmd, *args], cwd=ROOT,
                                          env=env, stdout=o, stderr=e, text=True))
    return procs


def stop(procs) -> None:
    for p in procs:
        if p.poll() is None:
            p.kill()
            p.wait()


def tails(logs: Path) -> str:
    return "\n".join(f"--- process {i} (exit {'?'}):\n"
                     + (logs / f"err{i}.txt").read_text()[-2500:] for i in (0, 1))


def wait_all(procs, logs: Path, limit: float) -> None:
    t_end = time.monotonic() + limit
    try:
        for p in procs:
            p.wait(timeout=max(0.1, t_end - time.monotonic()))
    except subprocess.TimeoutExpired:
        stop(procs)
        pytest.fail(f"the 2-process job did not end within {limit} s:\n{tails(logs)}")


def result(logs: Path, i: int) -> dict:
    lines = [x for x in (logs / f"out{i}.txt").read_text().splitlines()
             if x.startswith("RESULT ")]
    assert lines, f"process {i} gave no result:\n{tails(logs)}"
    return json.loads(lines[-1][7:])


def test_two_processes_give_the_one_process_results(tmp_path, monkeypatch):
    """map_batch of 8 PSFs and `difstar design --sweep-curvature ... --devices 2` across
    two processes equal one process on one device to rounding; the PSFs are written once,
    by process 0."""
    import difstar._design_study as D
    from difstar.cli import main

    space: dict = {}
    exec(GEOMETRIC, space)  # the children's measure (defined only), for the reference
    monkeypatch.setattr(D, "measures_fn", space["geometric"])

    out = tmp_path / "out"
    out.mkdir()
    procs = start_pair(WORKER, [str(out)], tmp_path)
    try:
        # the one-process run, here, while the pair works
        import difstar

        pupil = difstar.RegularPolygon(7, 1.0e-3, 0.1)
        lams = np.linspace(450e-9, 650e-9, 8)
        kw = dict(z_image=0.05, defocus=2e-4, pixel_pitch=4e-6, shape=(24, 24))
        plan = difstar.plan_psf(pupil, wavelength=lams, **kw)
        ref_psfs = np.asarray(jax.jit(jax.vmap(
            lambda lam: difstar.psf(pupil, wavelength=lam, plan=plan, **kw)))(lams))
        ref_dir = tmp_path / "ref"
        assert main(SWEEP + ["--devices", "1", "--out", str(ref_dir)]) == 0
    finally:
        wait_all(procs, tmp_path, 150)
    assert [p.returncode for p in procs] == [0, 0], tails(tmp_path)
    for i in (0, 1):
        r = result(tmp_path, i)
        assert r == {"process": i, "processes": 2, "devices": 2, "local_devices": 1,
                     "joined": True, "sweep_rc": 0}, r
    written = sorted(x.name for x in out.glob("psfs-*"))
    assert written == ["psfs-written-by-0.npy"]  # once, by process 0
    psfs = np.load(out / written[0])
    assert psfs.shape == ref_psfs.shape == (8, 24, 24)
    assert np.abs(psfs - ref_psfs).max() <= 1e-12 * ref_psfs.max()
    ref_rows = json.loads((ref_dir / "sweep.json").read_text())["rows"]
    # both processes were given the same --out: one result, written by process 0 (its
    # marker names it), and no temporary folder anywhere, the other's included
    assert sorted(x.name for x in out.iterdir()) == ["psfs-written-by-0.npy", "sweep"]
    marker = json.loads((out / "sweep" / ".difstar-output").read_text())
    assert marker["pid"] == procs[0].pid
    doc = json.loads((out / "sweep" / "sweep.json").read_text())
    assert doc["devices"] == 2 and len(doc["rows"]) == len(ref_rows) == 6
    assert doc["plan"]["per_device"] == 2 and doc["plan"]["chunks"] == 2
    for row, ref in zip(doc["rows"], ref_rows):
        assert row.keys() == ref.keys()
        for k, v in ref.items():
            if isinstance(v, float):
                assert row[k] == pytest.approx(v, rel=1e-9, abs=1e-14), (k, row[k], v)
    assert not [x for x in tmp_path.rglob("*") if "difstar-tmp" in x.name]
    assert not [x for x in (tmp_path / "systmp").iterdir() if "difstar" in x.name]


def test_two_processes_of_predict_example_write_one_result(tmp_path):
    """`difstar predict --example paper-focused --devices 2` started as both processes of
    a job (docs/sharding.md): each joins the job before the example builds any array
    (jax.distributed refuses a join after), each predicts (a trichromatic scene has
    nothing to shard), and the one --out they share is written once, by process 0,
    whole; no temporary folder is left beside it or in the system's temporary folder."""
    out = tmp_path / "pred"
    procs = start_pair(None, ["predict", "--example", "paper-focused", "--crop", "32", "32",
                              "--devices", "2", "--out", str(out)], tmp_path)
    wait_all(procs, tmp_path, 150)
    assert [p.returncode for p in procs] == [0, 0], tails(tmp_path)
    marker = json.loads((out / ".difstar-output").read_text())
    assert marker["pid"] == procs[0].pid
    assert sorted(marker["files"]) == sorted(x.name for x in out.iterdir()
                                             if x.name != ".difstar-output")
    assert {"raw.dng", "srgb16.tif", "derived.json"} <= set(marker["files"])
    assert sorted(x.name for x in tmp_path.iterdir()) == [
        "err0.txt", "err1.txt", "out0.txt", "out1.txt", "pred", "systmp"]
    assert not [x for x in (tmp_path / "systmp").iterdir() if "difstar" in x.name]
    for i in (0, 1):
        err = (tmp_path / f"err{i}.txt").read_text()
        assert "error" not in err.lower() and "Traceback" not in err, err


@pytest.mark.parametrize("victim", [1, 0])
def test_a_killed_process_ends_the_other_with_one_line(tmp_path, victim):
    """SIGKILL one process of a running `difstar design --sweep ... --devices 2`: the other
    ends within seconds (at most 30 s) with one line naming the dead process, exit status
    2 — no abort (134), no C++ stack trace, no Python traceback — and leaves nothing; the
    killed one's temporary folder is abandoned (its lock died with it), and the next run
    beside it removes it. Process 0 killed: the coordinator lives on in its own process
    for the survivor (JAX's would abort it 0.2 s later)."""
    from difstar.io._output import remove_stale

    out = tmp_path / "out"
    out.mkdir()
    procs = start_pair(KILL_WORKER, [str(out), str(victim)], tmp_path)
    survivor = procs[1 - victim]
    try:
        t_end = time.monotonic() + 90
        while not (out / "victim-waits").exists():
            if any(p.poll() is not None for p in procs) or time.monotonic() > t_end:
                stop(procs)
                pytest.fail(f"the job ended or stalled before the kill:\n{tails(tmp_path)}")
            time.sleep(0.05)
        time.sleep(0.3)  # the survivor is waiting on the victim in the third chunk
        procs[victim].send_signal(signal.SIGKILL)
        t_kill = time.monotonic()
        try:
            survivor.wait(timeout=30)
        except subprocess.TimeoutExpired:
            pytest.fail(f"process {1 - victim} did not end within 30 s of the kill of "
                        f"process {victim}:\n{tails(tmp_path)}")
        took = time.monotonic() - t_kill
    finally:
        stop(procs)
        pid = out / "coordinator.pid"
        if pid.exists():  # the coordinator waits for survivors a while: not needed now
            try:
                os.kill(int(pid.read_text()), signal.SIGKILL)
            except (ProcessLookupError, ValueError):
                pass
    err = (tmp_path / f"err{1 - victim}.txt").read_text()
    lines = err.strip().splitlines()
    errors = [x for x in lines if "error" in x.lower()]
    assert survivor.returncode == DI.EXIT_LOST == 2, (survivor.returncode, err)
    assert errors == [f"difstar: error: process {victim} of 2 stopped responding; the job is "
                      "ended, nothing was written"], err
    assert lines[-1] == errors[0], err
    for bad in ("Traceback", "Check failure", "terminate called", "Aborted", "*** "):
        assert bad not in err, err
    assert not any(x[:1] in "EFW" and x[1:5].isdigit() for x in lines), err  # C++ logs
    assert took < 30
    left = sorted(x.name for x in out.iterdir())
    assert f"sweep{1 - victim}" not in left  # nothing written
    assert not [x for x in left if x.startswith(f".sweep{1 - victim}.")]  # no temporaries
    removed = remove_stale(out)  # the killed one's folder: abandoned, removed by a next run
    assert [x.name for x in removed] == [x for x in left if x.startswith(f".sweep{victim}.")]
    assert not [x for x in out.iterdir() if "difstar-tmp" in x.name]


def test_a_process_that_fails_ends_the_other_with_one_line(tmp_path):
    """Process 1 fails with an error of its own in the third chunk (its own line, exit 2);
    process 0, waiting on it in the collective, ends at once with one line saying so."""
    out = tmp_path / "out"
    out.mkdir()
    procs = start_pair(KILL_WORKER, [str(out), "1"], tmp_path, VICTIM_FAILS="1")
    try:
        wait_all(procs, tmp_path, 60)
    finally:
        pid = out / "coordinator.pid"
        if pid.exists():
            try:
                os.kill(int(pid.read_text()), signal.SIGKILL)
            except (ProcessLookupError, ValueError):
                pass
    assert [p.returncode for p in procs] == [2, 2], tails(tmp_path)
    last = [(tmp_path / f"err{i}.txt").read_text().strip().splitlines()[-1] for i in (0, 1)]
    assert last == ["difstar: error: process 1 of 2 ended before the job was done (see its "
                    "own message); the job is ended, nothing was written",
                    "difstar: error: a failure of its own"], tails(tmp_path)
    for i in (0, 1):
        err = (tmp_path / f"err{i}.txt").read_text()
        assert sum("error" in x for x in err.splitlines()) == 1, err
        assert "Traceback" not in err and "Check failure" not in err, err
    assert sorted(x.name for x in out.iterdir()) == ["coordinator.pid", "victim-waits"]


def test_a_process_alone_is_refused_in_bounded_time(tmp_path):
    """Process 1 started without process 0 (nobody serves the coordinator): after
    DIFSTAR_JOIN_TIMEOUT one line and exit status 2 (JAX alone aborts with a C++ trace)."""
    env = dict(os.environ, JAX_PLATFORMS="cpu", JAX_COORDINATOR_ADDRESS=f"127.0.0.1:"
               f"{free_port()}", JAX_NUM_PROCESSES="2", JAX_PROCESS_ID="1",
               DIFSTAR_JOIN_TIMEOUT="1")
    p = subprocess.run([sys.executable, "-m", "difstar.cli", "design", "--sweep-curvature",
                        "0", "0.9", "2", "--quick", "--devices", "2", "--out",
                        str(tmp_path / "o")], cwd=ROOT, env=env, capture_output=True,
                       text=True, timeout=60)
    assert p.returncode == 2, p.stderr
    assert p.stderr.strip().splitlines() == [
        f"difstar: error: JAX_COORDINATOR_ADDRESS {env['JAX_COORDINATOR_ADDRESS']}: process 1 "
        "of 2 could not join the job within 1 s; start every process (ids 0 … 1) with the "
        "same address and JAX_NUM_PROCESSES, process 0 on that host (DIFSTAR_JOIN_TIMEOUT "
        "sets the wait)."], p.stderr
    assert not list(tmp_path.iterdir())


def test_dry_run_prints_the_mesh_and_each_process_work(tmp_path, monkeypatch, capsys):
    """DIFSTAR_DRY_RUN=1 with a 2-process job's environment: nothing is joined, computed
    or written; the mesh and each process's items are printed, exit status 0."""
    from difstar.cli import main

    monkeypatch.setattr(DI, "_JOB", {})
    monkeypatch.delenv(B.ENV_DEVICES, raising=False)
    monkeypatch.setenv(DI.ENV_DRY_RUN, "1")
    monkeypatch.setenv("JAX_COORDINATOR_ADDRESS", "127.0.0.1:1")  # never contacted
    monkeypatch.setenv("JAX_NUM_PROCESSES", "2")
    have = jax.local_device_count()
    for me, expect in ((0, [f"process 0: devices {'0' if have == 1 else f'0–{have - 1}'}: "
                            "items 0–2", "process 1:"]),
                       (1, ["process 1:"])):
        monkeypatch.setenv("JAX_PROCESS_ID", str(me))
        monkeypatch.setattr(DI, "_JOB", {})
        with pytest.raises(SystemExit) as e:
            main(["design", "--sweep-curvature", "0", "0.9", "5", "--quick", "--chunk",
                  str(3 * 2 * have), "--devices", str(2 * have), "--out", str(tmp_path / "o")])
        assert e.value.code == 0
        got = [x.removeprefix("difstar dry run: ") for x in capsys.readouterr().out.splitlines()
               if x.startswith("difstar dry run: ")]
        assert got[0].startswith(f"mesh: {2 * have} cpu device(s) of 2 process(es), {have} "
                                 "device(s) per process (launched by JAX_* variables; "
                                 "coordinator 127.0.0.1:1)"), got
        assert got[1].startswith("work: 5 items in 1 chunk(s)"), got
        procs = [x for x in got if x.startswith("process ")]
        assert len(procs) == len(expect) and all(
            x.startswith(w) for x, w in zip(procs, expect)), got
        assert got[-1] == "nothing was computed or written."
        assert not list(tmp_path.iterdir())
    monkeypatch.setenv(DI.ENV_DRY_RUN, "maybe")
    with pytest.raises(InputError, match="DIFSTAR_DRY_RUN"):
        DI.dry_run()


def test_plan_lines_give_each_process_its_items():
    launch = DI.Launch("h:1", 2, 0, None, "SLURM (srun)")
    lines = B.plan_lines(10, 4, chunk=4, launch=launch, local_devices=2)
    assert lines[1] == "work: 10 items in 3 chunk(s) of 4 (1 per device), 2 padding item(s)"
    assert lines[2:] == ["process 0: devices 0–1: items 0–1, 4–5, 8–9",
                         "process 1: devices 2–3: items 2–3, 6–7 (+2 padding)"]
    assert B.plan_lines(None, 2, what="Jacobian columns of one fit")[1:] == [
        "work: the Jacobian columns of one fit, shared over the 2 devices",
        "process 0: devices 0–1"]


def slurm_port(job_id: int) -> int:  # JAX's choice: the job id in the top 4096 ports
    return job_id % 4096 + 61440


@pytest.mark.parametrize("env, want", [
    ({}, None),
    ({"JAX_COORDINATOR_ADDRESS": "127.0.0.1:5000", "JAX_NUM_PROCESSES": "2",
      "JAX_PROCESS_ID": "1"}, ("127.0.0.1:5000", 2, 1, None, "JAX_* variables")),
    ({"JAX_COORDINATOR_ADDRESS": "10.0.0.1:5000", "JAX_NUM_PROCESSES": "1",
      "JAX_PROCESS_ID": "0"}, ("10.0.0.1:5000", 1, 0, None, "JAX_* variables")),
    # srun, 2 nodes × 2 tasks: the step's first node; each task its local GPU
    ({"SLURM_JOB_ID": "4242", "SLURM_NTASKS": "4", "SLURM_PROCID": "3", "SLURM_LOCALID": "1",
      "SLURM_STEP_NODELIST": "node[003-004]", "SLURM_STEP_TASKS_PER_NODE": "2(x2)",
      "SLURM_NODEID": "1"}, (f"node003:{slurm_port(4242)}", 4, 3, (1,), "SLURM (srun)")),
    # srun, one task per node: all of the node's GPUs (JAX alone would give it GPU 0 only)
    ({"SLURM_JOB_ID": "77", "SLURM_NTASKS": "2", "SLURM_PROCID": "0", "SLURM_LOCALID": "0",
      "SLURM_STEP_NODELIST": "gpu7,gpu9", "SLURM_STEP_TASKS_PER_NODE": "1(x2)",
      "SLURM_NODEID": "0", "JAX_COORDINATOR_PORT": "6000"},
     ("gpu7:6000", 2, 0, None, "SLURM (srun)")),
    # an sbatch script itself (no step): alone
    ({"SLURM_JOB_ID": "77", "SLURM_NTASKS": "4", "SLURM_PROCID": "0"}, None),
    # Open MPI 4: the launcher's host
    ({"OMPI_MCA_orte_hnp_uri": "1531576320.0;tcp://10.96.0.1,10.148.0.1:34911",
      "OMPI_COMM_WORLD_SIZE": "2", "OMPI_COMM_WORLD_RANK": "1",
      "OMPI_COMM_WORLD_LOCAL_RANK": "0", "OMPI_COMM_WORLD_LOCAL_SIZE": "1"},
     (f"10.96.0.1:{(1531576320 // 4096) % 4096 + 61440}", 2, 1, None, "Open MPI (mpirun)")),
    # Open MPI 5 / MPICH with the coordinator given: the launcher's count and rank
    ({"OMPI_COMM_WORLD_SIZE": "3", "OMPI_COMM_WORLD_RANK": "2",
      "JAX_COORDINATOR_ADDRESS": "n1:7000"},
     ("n1:7000", 3, 2, None, "Open MPI with JAX_COORDINATOR_ADDRESS")),
    ({"PMI_SIZE": "2", "PMI_RANK": "0", "JAX_COORDINATOR_ADDRESS": "n1:7000",
      "JAX_LOCAL_DEVICE_IDS": "0,1"}, ("n1:7000", 2, 0, (0, 1), "MPI (PMI) with "
                                                              "JAX_COORDINATOR_ADDRESS")),
])
def test_launchers_map_to_the_job(env, want):
    got = DI.launch_from_env(env)
    if want is None:
        assert got is None
    else:
        assert got == DI.Launch(*want)


@pytest.mark.parametrize("env, words", [
    ({"JAX_COORDINATOR_ADDRESS": "127.0.0.1:5000"}, "JAX_NUM_PROCESSES and JAX_PROCESS_ID"),
    ({"JAX_COORDINATOR_ADDRESS": "127.0.0.1", "JAX_NUM_PROCESSES": "2",
      "JAX_PROCESS_ID": "0"}, "not HOST:PORT"),
    ({"JAX_COORDINATOR_ADDRESS": "h:1", "JAX_NUM_PROCESSES": "2", "JAX_PROCESS_ID": "2"},
     "JAX_PROCESS_ID: 2 is not in [0, 2)"),
    ({"JAX_COORDINATOR_ADDRESS": "h:1", "JAX_NUM_PROCESSES": "two", "JAX_PROCESS_ID": "0"},
     "JAX_NUM_PROCESSES: 'two' is not a whole number"),
    ({"OMPI_COMM_WORLD_SIZE": "2", "OMPI_COMM_WORLD_RANK": "0"},
     "OMPI_COMM_WORLD_SIZE: started by mpirun"),
    ({"PMI_SIZE": "4", "PMI_RANK": "0"}, "PMI_SIZE: started by mpirun"),
])
def test_launcher_mistakes_are_one_line(env, words):
    with pytest.raises(InputError) as e:
        DI.launch_from_env(env)
    assert words in str(e.value) and "\n" not in str(e.value)


def test_a_process_that_does_not_write_never_touches_the_destination(tmp_path, monkeypatch):
    """output_dir in process 1 of a job (as _JOB records it after the join): the block
    gets a marked folder in the system's temporary folder, removed at the end, whether
    the block ends normally or not; the destination and its folder are not looked at (an
    existing result is neither refused nor replaced) and nothing is written beside it. A
    killed non-writer's folder (its lock gone) is removed by the next non-writer."""
    from difstar.io import _output

    systmp = tmp_path / "systmp"
    systmp.mkdir()
    monkeypatch.setenv("TMPDIR", str(systmp))
    monkeypatch.setattr(_output.tempfile, "tempdir", None)  # re-read TMPDIR
    monkeypatch.setattr(DI, "_JOB", {"launch": DI.Launch("h:1", 2, 1, None, "JAX_* variables")})
    assert not DI.writes_output()
    dest = tmp_path / "out" / "result"
    dest.mkdir(parents=True)
    (dest / "keep.txt").write_text("the user's")
    stale = systmp / ".result.difstar-tmp-0a0b0c0d0e0f1a1b"  # a killed non-writer's
    stale.mkdir()
    _output._write_marker(stale, [], "predict", "0a0b0c0d0e0f1a1b")
    before = sorted(p.name for p in (tmp_path / "out").iterdir())
    _output.check_output_free(dest)  # not refused: not this process's to check
    with _output.output_dir(dest, command="predict") as tmp:
        assert tmp.parent == systmp and tmp.name.startswith(".result.difstar-tmp-")
        assert _output.read_marker(tmp)["command"] == "predict"
        (tmp / "a.json").write_text("{}")
    assert not tmp.exists() and not stale.exists()
    with pytest.raises(RuntimeError, match="boom"):
        with _output.output_dir(dest, command="predict") as tmp:
            (tmp / "a.json").write_text("{}")
            raise RuntimeError("boom")
    assert not tmp.exists()
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == before == ["result"]
    assert sorted(p.name for p in dest.iterdir()) == ["keep.txt"]
    assert list(systmp.iterdir()) == []
    monkeypatch.setattr(DI, "_JOB", {"launch": DI.Launch("h:1", 2, 0, None, "JAX_* variables")})
    with pytest.raises(_output.OutputExistsError):  # process 0: the usual checks
        _output.check_output_free(dest)
