"""Where a fit's first step waits: the start of ``difstar fit`` to its first solver step,
as a timeline of what the process traces and compiles.

    python benchmarks/first_step_timeline.py [fit/synthetic-paper-camera/manifest.json]
        [--cache first|again]

Runs ``difstar fit MANIFEST`` in a fresh Python process with an empty compilation cache
of its own (``--cache again``: a second run on that cache, as a later fit of the same
shapes). JAX's compile log (``jax_log_compiles``) is read with timestamps: every trace,
lowering (jaxpr to MLIR) and XLA compile that took 0.2 s or more, with the thread that
ran it (``main``, or ``difstar-compile``: the background thread that compiles the
solver's step ahead), and the first step as ``difstar fit`` reports it. Prints one
Markdown table: seconds from the process's start at which each event ended, and how long
it took.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: run in the child: the compile log, each line "EVENT t thread took what"
_CHILD = r"""
import logging, sys, threading, time
T0 = time.perf_counter()

def say(what, took=None):
    t = time.perf_counter() - T0
    name = threading.current_thread().name
    thread = "main" if name == "MainThread" else name.split("_")[0]
    print(f"EVENT\t{t:.2f}\t{thread}\t{'' if took is None else f'{took:.2f}'}\t{what}",
          flush=True)

class Log(logging.Handler):
    def emit(self, record):
        m = record.getMessage()
        if m.startswith("Finished ") and " in " in m:
            what, took = m.rsplit(" in ", 1)
            took = float(took.split()[0])
            if took >= 0.2:
                say(what[len("Finished "):], took)

import jax
jax.config.update("jax_log_compiles", True)
for name in ("jax._src.dispatch", "jax._src.interpreters.pxla", "jax._src.compiler",
             "jax._src.pjit", "jax"):
    lg = logging.getLogger(name)
    lg.addHandler(Log())
    lg.propagate = False
    lg.setLevel(logging.DEBUG)
say("jax imported")
import difstar.cli
say("difstar imported")
rc = difstar.cli.main(sys.argv[1:])
say("exit")
sys.exit(rc)
"""


def run(manifest: str, cache_runs: int) -> list[tuple[float, str, str, str]]:
    """The child's events of its last run (``cache_runs`` runs on one cache)."""
    with tempfile.TemporaryDirectory() as tmp:
        env = dict(os.environ, DIFSTAR_COMPILATION_CACHE=str(Path(tmp) / "cache"))
        for k in range(cache_runs):
            out = Path(tmp) / f"out{k}"
            proc = subprocess.run(
                [sys.executable, "-c", _CHILD, "fit", manifest, "--out", str(out)],
                cwd=ROOT, env=env, capture_output=True, text=True)
            if proc.returncode != 0:
                raise RuntimeError(f"difstar fit exited {proc.returncode}:\n"
                                   + "\n".join(proc.stderr.splitlines()[-20:]))
    events = []
    for line in (proc.stdout + proc.stderr).splitlines():
        if line.startswith("EVENT\t"):
            _, t, thread, took, what = line.split("\t", 4)
            events.append((float(t), thread, took, what))
        elif "first step done" in line:
            events.append((float(line.split(" done ")[1].split()[0]), "main", "",
                           "first solver step done (as difstar fit reports it)"))
    return sorted(events)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("manifest", nargs="?", default="fit/synthetic-paper-camera/manifest.json")
    ap.add_argument("--cache", choices=("first", "again"), default="first",
                    help="first: an empty compilation cache; again: a second run on it")
    a = ap.parse_args(argv)
    events = run(a.manifest, 1 if a.cache == "first" else 2)
    first = next((t for t, *_ in events if "first solver step" in _[-1]), None)
    print(f"`difstar fit {a.manifest}`, {'an empty' if a.cache == 'first' else 'a filled'} "
          "compilation cache; traces, lowerings and compiles of 0.2 s or more:\n")
    print("| ended at, s | took, s | thread | what |")
    print("|---:|---:|---|---|")
    for t, thread, took, what in events:
        if first is not None and t > first + 1e-9 and "first solver step" not in what:
            break  # up to the first step
        print(f"| {t:.2f} | {took} | {thread} | {what} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
