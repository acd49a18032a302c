"""Every notebook in notebooks/ is stored executed (its pictures there, no error, no
per-run noise) and runs top to bottom (small sizes) without an error."""

from __future__ import annotations

import copy
import importlib.util
import re
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent.parent / "notebooks"
NOTEBOOKS = sorted(HERE.glob("*.ipynb"))


def _run_all():
    """notebooks/run_all.py, the one command that regenerates the stored outputs."""
    spec = importlib.util.spec_from_file_location("run_all", HERE / "run_all.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _draws(nb) -> bool:
    """The notebook's code makes a matplotlib figure (read from its source, not its
    outputs)."""
    return any(re.search(r"plt\.(subplots|figure)\(", c.source)
               for c in nb.cells if c.cell_type == "code")


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_is_stored_executed(path):
    nbformat = pytest.importorskip("nbformat")
    nb = nbformat.read(path, as_version=4)
    code = [c for c in nb.cells if c.cell_type == "code"]
    assert all(c.execution_count is not None for c in code), (
        f"{path.name} has cells that were not run; run python notebooks/run_all.py")
    outputs = [o for c in code for o in c.outputs]
    assert not [o for o in outputs if o.output_type == "error"], f"{path.name}: an error"
    assert not [o for o in outputs if o.output_type == "stream" and o.name == "stderr"
                and "Traceback" in o.text], f"{path.name}: a traceback on stderr"
    images = [o for o in outputs if "image/png" in o.get("data", {})]
    if _draws(nb):
        assert images, f"{path.name} draws figures but stores none"
    # the stored run names its sizes; nothing that changes on every run is kept
    assert nb.cells[0].source.rstrip().split("\n")[-1].startswith(_run_all().SIZES_NOTE)
    assert "language_info" not in nb.metadata
    assert not [c for c in nb.cells if "execution" in c.metadata]
    assert not [o for o in outputs if o.output_type == "execute_result"
                and re.search(r" at 0x[0-9a-f]+>", o.data.get("text/plain", ""))]
    # modest pictures: the whole notebook stays small in the repository
    assert path.stat().st_size < 3_000_000, f"{path.name}: {path.stat().st_size} bytes"


def test_clean_drops_per_run_noise_and_keeps_the_rest():
    """run_all's clean() on a hand-made notebook: the execution timings, language_info
    and an address repr go; a figure, printed text and a plain result stay."""
    nbformat = pytest.importorskip("nbformat")
    v4 = nbformat.v4
    spec = {"name": "python3", "display_name": "Python 3", "language": "python"}
    nb = v4.new_notebook(metadata={"kernelspec": spec,
                                   "language_info": {"name": "python", "version": "3.12.1"}})
    cell = v4.new_code_cell("x", execution_count=1)
    cell.metadata["execution"] = {"iopub.status.busy": "2026-11-27T04:00:00Z"}
    cell.outputs = [
        v4.new_output("execute_result", {"text/plain": "<matplotlib.legend.Legend at 0x7f3a>"},
                      execution_count=1),
        v4.new_output("display_data", {"image/png": "iVBOR", "text/plain": "<Figure>"}),
        v4.new_output("stream", name="stdout", text="crop 864\n"),
        v4.new_output("execute_result", {"text/plain": "Text(0, 0.5, 'step')"},
                      execution_count=1),
    ]
    nb.cells = [v4.new_markdown_cell("# title"), cell]
    before = copy.deepcopy(nb)
    run_all = _run_all()
    run_all.clean(nb)
    assert "language_info" not in nb.metadata and nb.metadata.kernelspec == spec
    assert "execution" not in nb.cells[1].metadata
    assert nb.cells[1].outputs == before.cells[1].outputs[1:]
    run_all.note_sizes(nb, small=True)
    run_all.note_sizes(nb, small=False)  # replaces the line, does not add a second
    src = nb.cells[0].source
    assert src.startswith("# title\n\n") and src.count(run_all.SIZES_NOTE) == 1
    assert "full sizes" in src


@pytest.mark.slow
@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs(path, monkeypatch):
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    nb = nbformat.read(path, as_version=4)  # a copy in memory: the stored file is untouched
    for c in nb.cells:
        if c.cell_type == "code":
            c.outputs, c.execution_count = [], None
    monkeypatch.setenv("DIFSTAR_NOTEBOOK_SMALL", "1")
    # the kernel is this interpreter's (ipykernel's native "python3" spec)
    client = nbclient.NotebookClient(
        nb, timeout=300, kernel_name="python3",
        resources={"metadata": {"path": str(path.parent)}},
    )
    client.execute()  # raises CellExecutionError on any error
    errors = [o for c in nb.cells for o in c.get("outputs", []) if o.get("output_type") == "error"]
    assert not errors
    if _draws(nb):
        assert [o for c in nb.cells if c.cell_type == "code" for o in c.outputs
                if "image/png" in o.get("data", {})], f"{path.name} drew no figure"
