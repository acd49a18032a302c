"""Run every notebook in this folder top to bottom and store it with its outputs, in place.

    python notebooks/run_all.py            # full sizes (DIFSTAR_NOTEBOOK_SMALL=0)
    python notebooks/run_all.py --small    # the small sizes the tests use
    python notebooks/run_all.py 02_fitting.ipynb --small   # some of them

Each notebook runs in a fresh kernel (ipykernel's "python3", i.e. this interpreter) from
this folder. What would change on every run without changing the content is left out, so
that a re-run gives a small diff: the execution timings in the cells' metadata, the
kernel's language_info, and printed Python object addresses ("<... at 0x7f...>").
Figures are stored as PNG at ``DPI`` (a matplotlibrc of this run's own, so a user's
settings do not change the stored pictures). The first cell's last line says which sizes
made the stored outputs. A notebook is written whole or not at all; one that fails is
left as it was (the error is printed and the exit status is 1).
"""

from __future__ import annotations

import argparse
import os
import re
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
SIZES_NOTE = "*Stored outputs:*"  # the first cell's last line starts with this
DPI = 80  # modest pictures: the notebooks stay small in the repository
_ADDRESS = re.compile(r" at 0x[0-9a-f]+>")


def clean(nb) -> None:
    """Drop what changes on every run: cell execution metadata, language_info, and
    outputs that are only an object's repr with its memory address."""
    nb.metadata.pop("language_info", None)
    nb.metadata.pop("widgets", None)
    for cell in nb.cells:
        cell.metadata.pop("execution", None)
        if cell.cell_type != "code":
            continue
        cell.outputs = [o for o in cell.outputs
                        if not (o.output_type == "execute_result"
                                and set(o.data) == {"text/plain"}
                                and _ADDRESS.search(o.data["text/plain"]))]


def note_sizes(nb, small: bool) -> None:
    """Put (or replace) the first cell's last line naming the sizes of the stored run."""
    first = nb.cells[0]
    lines = [ln for ln in first.source.rstrip("\n").split("\n")
             if not ln.startswith(SIZES_NOTE)]
    while lines and not lines[-1].strip():
        lines.pop()
    mode = ("the small sizes (`DIFSTAR_NOTEBOOK_SMALL=1`, `python notebooks/run_all.py "
            "--small`)" if small else "the full sizes (`python notebooks/run_all.py`)")
    first.source = "\n".join([*lines, "", f"{SIZES_NOTE} {mode}."])


def run_one(path: Path, small: bool, timeout: int) -> float:
    import nbclient
    import nbformat

    from difstar.io import write_file_atomic

    nb = nbformat.read(path, as_version=4)
    note_sizes(nb, small)
    t0 = time.perf_counter()
    nbclient.NotebookClient(nb, timeout=timeout, kernel_name="python3",
                            resources={"metadata": {"path": str(path.parent)}}).execute()
    clean(nb)
    write_file_atomic(path, nbformat.writes(nb) + "\n", overwrite=True)
    return time.perf_counter() - t0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("notebooks", nargs="*", help="names in notebooks/ (default: all)")
    ap.add_argument("--small", action="store_true", help="the small sizes (as the tests)")
    ap.add_argument("--timeout", type=int, default=1800, help="seconds per cell")
    args = ap.parse_args(argv)
    paths = [HERE / n for n in args.notebooks] or sorted(HERE.glob("*.ipynb"))
    missing = [p.name for p in paths if not p.is_file()]
    if missing:
        print(f"run_all: no such notebook in {HERE}: {', '.join(missing)}", file=sys.stderr)
        return 2
    failed = 0
    with tempfile.TemporaryDirectory() as tmp:
        rc = Path(tmp) / "matplotlibrc"
        rc.write_text(f"figure.dpi: {DPI}\n")
        # the kernels inherit these
        os.environ["DIFSTAR_NOTEBOOK_SMALL"] = "1" if args.small else "0"
        os.environ["MATPLOTLIBRC"] = str(rc)
        for path in paths:
            try:
                print(f"{path.name}: {run_one(path, args.small, args.timeout):.0f} s",
                      flush=True)
            except Exception as e:  # noqa: BLE001 - report it, leave the notebook as it was
                failed += 1
                print(f"{path.name}: FAILED, left unchanged: {e}", file=sys.stderr, flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
