"""Code outside ``src/`` and ``tests/`` uses difstar only through its public names.

The public API is the top-level package ``difstar``, ``difstar.io`` and the public
modules beside them (``difstar.fitting``, ``difstar.raw_fit``, ``difstar.batch``,
``difstar.design_study``, ``difstar.pupils``, ``difstar.stages``): names without a
leading underscore. Campaign scripts (fit/), benchmarks, notebooks and the code in the
documentation must not import an underscored module or name (``difstar._fit``,
``from difstar.fitting import _x``), nor reach one through an attribute
(``difstar._batch.shard``): those may change at any time.

Checked: every ``.py`` file (parsed with ``ast``, including Python code held in string
constants, such as the child scripts benchmarks start), every code cell of every
``.ipynb`` and every fenced code block of every ``.md`` file, all outside src/ and tests/.
"""

from __future__ import annotations

import ast
import json
import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PUBLIC_MODULES = ("difstar", "difstar.io", "difstar.fitting", "difstar.raw_fit",
                  "difstar.batch", "difstar.design_study", "difstar.pupils", "difstar.stages")
FENCE = re.compile(r"^[ \t]*```[^\n]*\n(.*?)^[ \t]*```", re.S | re.M)
IMPORT_LINE = re.compile(r"^\s*(?:>>>\s*)?((?:from|import)\s+difstar\b.*)$", re.M)


def _private(dotted: str) -> bool:
    """True for a difstar name with an underscored part (dunders such as __version__ are
    public)."""
    parts = dotted.split(".")
    return parts[0] == "difstar" and any(
        p.startswith("_") and not (p.startswith("__") and p.endswith("__")) for p in parts[1:])


def _attribute_chain(node: ast.Attribute) -> str | None:
    parts = []
    while isinstance(node, ast.Attribute):
        parts.append(node.attr)
        node = node.value
    if isinstance(node, ast.Name):
        return ".".join([node.id, *reversed(parts)])
    return None


def violations_in_code(code: str) -> list[tuple[int, str]]:
    """(line, what) for every use of an underscored difstar module or name in ``code``
    (Python source). Raises SyntaxError when ``code`` is not Python."""
    tree = ast.parse(code)
    for node in ast.walk(tree):  # mark parents so that a.b.c counts once, as a whole
        for child in ast.iter_child_nodes(node):
            child.parent = node
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, f"import {a.name}") for a in node.names if _private(a.name)]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            if _private(node.module):
                found.append((node.lineno, f"from {node.module} import ..."))
            elif node.module.split(".")[0] == "difstar":
                found += [(node.lineno, f"from {node.module} import {a.name}")
                          for a in node.names if _private(f"{node.module}.{a.name}")]
        elif isinstance(node, ast.Attribute) and not isinstance(
                getattr(node, "parent", None), ast.Attribute):
            chain = _attribute_chain(node)
            if chain and _private(chain):
                found.append((node.lineno, chain))
        elif (isinstance(node, ast.Constant) and isinstance(node.value, str)
              and "difstar" in node.value and "import" in node.value):
            try:  # a script in a string (a child process's code)
                inner = violations_in_code(node.value)
            except SyntaxError:
                continue
            found += [(node.lineno + n - 1, what) for n, what in inner]
    return sorted(set(found))


def violations_in_text(code: str) -> list[tuple[int, str]]:
    """As :func:`violations_in_code`; for a block that is not whole Python (a shell
    session, a fragment), its ``import difstar``/``from difstar`` lines one by one."""
    try:
        return violations_in_code(code)
    except SyntaxError:
        found = []
        for m in IMPORT_LINE.finditer(code):
            line = code.count("\n", 0, m.start()) + 1
            try:
                found += [(line, what) for _, what in violations_in_code(m.group(1).strip())]
            except SyntaxError:
                continue
        return found


def code_blocks(path: Path) -> list[tuple[int, str]]:
    """(first line, code) of each piece of code in ``path``: the whole of a .py file,
    each code cell of a notebook (line = cell number), each fenced block of a .md file."""
    text = path.read_text(encoding="utf-8")
    if path.suffix == ".py":
        return [(1, text)]
    if path.suffix == ".ipynb":
        cells = json.loads(text)["cells"]
        return [(i, "".join(c["source"]).replace("\n%", "\n#%").replace("\n!", "\n#!"))
                for i, c in enumerate(cells) if c["cell_type"] == "code"]
    return [(text.count("\n", 0, m.start(1)) + 1, m.group(1)) for m in FENCE.finditer(text)]


def outside_files() -> list[Path]:
    """The repository's .py, .ipynb and .md files (tracked, or new and not ignored) outside
    src/ and tests/."""
    try:
        out = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard"],
                             cwd=ROOT, capture_output=True, text=True, check=True).stdout
        names = out.split()
    except (OSError, subprocess.CalledProcessError):  # not a git checkout (an sdist, a copy)
        names = [str(p.relative_to(ROOT)) for p in ROOT.rglob("*")
                 if not any(part.startswith(".") for part in p.relative_to(ROOT).parts)]
    files = []
    for rel in sorted(set(names)):
        p = ROOT / rel
        if (p.suffix in (".py", ".ipynb", ".md") and p.is_file()
                and p.relative_to(ROOT).parts[0] not in ("src", "tests")):
            files.append(p)
    return files


def test_no_underscored_difstar_names_outside_src_and_tests():
    files = outside_files()
    kinds = {p.suffix for p in files}
    assert {".py", ".ipynb", ".md"} <= kinds, f"found only {kinds}: the scan lost its files"
    bad = []
    for path in files:
        for first, code in code_blocks(path):
            where = (f"cell {first}" if path.suffix == ".ipynb" else "line {}")
            for line, what in violations_in_text(code):
                at = where if path.suffix == ".ipynb" else where.format(first + line - 1)
                bad.append(f"{path.relative_to(ROOT)} {at}: {what}")
    assert not bad, ("private difstar names used outside src/ and tests/; use a public "
                     "name (" + ", ".join(PUBLIC_MODULES) + "):\n" + "\n".join(bad))


@pytest.mark.parametrize("code, n", [
    ("from difstar._fit import Fitter", 1),
    ("from difstar import _bench as B", 1),
    ("import difstar._pupil", 1),
    ("import difstar\nx = difstar._batch.shard", 1),
    ("from difstar.fitting import _resolve", 1),
    ("from difstar.io._output import output_dir", 1),
    ("CHILD = '''\nimport json\nfrom difstar import _batch as B\n'''", 1),
    ("import difstar\nprint(difstar.__version__)", 0),
    ("from difstar import choose_grid\nfrom difstar.fitting import fit", 0),
    ("from difstar.raw_fit import Fitter\nimport numpy._core", 0),
    ("import difstar\ncam = difstar.paper_camera('focused')\ncam._private_field", 0),
])
def test_the_check_finds_private_uses(code, n):
    """The check itself: each private use above is found once, public ones not at all."""
    assert len(violations_in_code(code)) == n


def test_the_check_reads_notebooks_and_markdown(tmp_path):
    nb = {"cells": [{"cell_type": "markdown", "source": ["`difstar._fit` in prose\n"]},
                    {"cell_type": "code", "source": ["%matplotlib inline\n",
                                                     "from difstar._fit import weights\n"]}]}
    (tmp_path / "a.ipynb").write_text(json.dumps(nb))
    md = ("Prose naming `difstar._batch`.\n\n```python\nfrom difstar import _fit\n```\n\n"
          "```\n$ python -c 'x'\n>>> from difstar._pupil import Circle\n```\n")
    (tmp_path / "b.md").write_text(md)
    found = {p.suffix: [v for _, c in code_blocks(p) for v in violations_in_text(c)]
             for p in (tmp_path / "a.ipynb", tmp_path / "b.md")}
    assert len(found[".ipynb"]) == 1
    assert [w for _, w in found[".md"]] == ["from difstar import _fit",
                                            "from difstar._pupil import ..."]
