"""The package's layout: modules import one another in one direction, only the command
line parses arguments, and modules stay small enough to read.

- **No import cycles.** The graph of difstar's modules, built from every ``import``
  statement with ``ast`` (function-local imports included: a cycle broken only by
  importing late is still two modules that need each other), has no cycle. A package's
  ``__init__`` is a node of its own (``import difstar`` inside a module is an edge to the
  facade, which imports nearly everything).
- **argparse only in the command line**, the package :data:`CLI_PACKAGE`, and the
  library never imports that package (it imports the library, not the other way round).
- **Module size.** A module has at most :data:`MAX_LINES` lines; the modules still over it
  are listed in :data:`OVER_LIMIT` with their line count when the list was made, as a
  ceiling: they may shrink (then lower the number, or drop the entry once under the
  limit), never grow.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parent.parent / "src" / "difstar"

#: the package that makes the command line (its modules alone may import argparse)
CLI_PACKAGE = "difstar.cli"


def is_cli(module: str) -> bool:
    """Whether ``module`` is the command-line package or one of its modules."""
    return module == CLI_PACKAGE or module.startswith(CLI_PACKAGE + ".")

MAX_LINES = 600

#: modules over MAX_LINES, each with a ceiling: its line count when it was listed
OVER_LIMIT = {
}


def module_files(package: Path = PACKAGE) -> dict[str, Path]:
    """{dotted module name: file} for every module of the package."""
    out = {}
    for p in sorted(package.rglob("*.py")):
        parts = list(p.relative_to(package.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        out[".".join(parts)] = p
    return out


def import_graph(files: dict[str, Path]) -> dict[str, set[str]]:
    """{module: the package's modules it imports}, from every import statement anywhere
    in its source (top level, inside functions, under ``if``)."""
    root = next(iter(files)).split(".")[0]
    graph: dict[str, set[str]] = {}
    for name, path in files.items():
        is_package = path.name == "__init__.py"
        here = name.split(".") if is_package else name.split(".")[:-1]
        deps: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                deps.update(a.name for a in node.names)
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base_parts = here[: len(here) - (node.level - 1)]
                    base = ".".join(base_parts + ([node.module] if node.module else []))
                else:
                    base = node.module or ""
                for a in node.names:  # `from pkg import module` names a module
                    full = f"{base}.{a.name}"
                    deps.add(full if full in files else base)
        graph[name] = {d for d in deps if d in files and d != name
                       and d.split(".")[0] == root}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(found)


def test_no_import_cycles():
    graph = import_graph(module_files())
    assert len(graph) > 30 and graph["difstar"], "the graph lost its modules"
    found = cycles(graph)
    msg = "\n".join(" <-> ".join(c) + ": " + "; ".join(
        f"{a} imports {', '.join(sorted(graph[a] & set(c)))}" for a in c) for c in found)
    assert not found, ("import cycles (move the shared piece to the module below, so "
                       "that one module decides it):\n" + msg)


def test_argparse_only_in_the_command_line():
    files = module_files()
    graph_like = {}
    for name, path in files.items():
        tree = ast.parse(path.read_text(encoding="utf-8"))
        graph_like[name] = any(
            (isinstance(n, ast.Import) and any(a.name == "argparse" for a in n.names))
            or (isinstance(n, ast.ImportFrom) and n.module == "argparse")
            for n in ast.walk(tree))
    assert CLI_PACKAGE in files, f"the command-line package {CLI_PACKAGE} is gone"
    assert any(graph_like[n] for n in files if is_cli(n)), "the command line lost argparse"
    bad = sorted(n for n, uses in graph_like.items() if uses and not is_cli(n))
    assert not bad, (f"argparse imported outside the command-line package {CLI_PACKAGE}: "
                     f"{bad}; parse arguments in a module of {CLI_PACKAGE} and pass values "
                     "to the library")


def test_the_library_does_not_import_the_command_line():
    graph = import_graph(module_files())
    bad = sorted(f"{n} imports {', '.join(sorted(d for d in deps if is_cli(d)))}"
                 for n, deps in graph.items() if not is_cli(n) and any(map(is_cli, deps)))
    assert not bad, (f"library modules import the command line ({CLI_PACKAGE}): {bad}; "
                     "move what they need into the library and let the command line "
                     "import it from there")


def test_module_size():
    files = module_files()
    sizes = {n: len(p.read_text(encoding="utf-8").splitlines()) for n, p in files.items()}
    gone = sorted(set(OVER_LIMIT) - set(sizes))
    assert not gone, f"OVER_LIMIT names modules that no longer exist: {gone}; drop them"
    problems = []
    for n, lines in sorted(sizes.items()):
        ceiling = OVER_LIMIT.get(n, MAX_LINES)
        if lines > ceiling:
            problems.append(f"{n}: {lines} lines > {ceiling}" + (
                " (its ceiling in OVER_LIMIT: split it, don't grow it)" if n in OVER_LIMIT
                else f" (split it into modules of at most {MAX_LINES} lines)"))
        elif n in OVER_LIMIT and lines <= MAX_LINES:
            problems.append(f"{n}: {lines} lines, now within {MAX_LINES}: drop it from "
                            "OVER_LIMIT")
    assert not problems, "\n".join(problems)


# ----------------------------------------------------------------- the checks themselves


def _package(tmp_path: Path, sources: dict[str, str]) -> dict[str, Path]:
    for rel, text in sources.items():
        p = tmp_path / "pkg" / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
    return module_files(tmp_path / "pkg")


@pytest.mark.parametrize("sources, expected", [
    # a function-local import closing a cycle counts
    ({"__init__.py": "", "a.py": "from . import b\n",
      "b.py": "def f():\n    from .a import x\n"}, [["pkg.a", "pkg.b"]]),
    # through the facade: a module that imports the package it is imported by
    ({"__init__.py": "from ._m import f\n", "_m.py": "def f():\n    import pkg\n"},
     [["pkg", "pkg._m"]]),
    # relative imports two levels up, from a subpackage
    ({"__init__.py": "", "x.py": "from .sub import y\n", "sub/__init__.py": "",
      "sub/y.py": "from ..x import z\n"}, [["pkg.sub.y", "pkg.x"]]),
    # one direction only: no cycle
    ({"__init__.py": "from .a import f\n", "a.py": "from .b import g\n", "b.py": ""}, []),
])
def test_the_cycle_check_finds_cycles(tmp_path, sources, expected):
    assert cycles(import_graph(_package(tmp_path, sources))) == expected
