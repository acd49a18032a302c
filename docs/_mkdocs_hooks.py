"""mkdocs hook: the documentation links files outside docs/ by their path in the
repository (BENCHMARKS.md, fit/*/README.md and their figures), so that the pages read
the same in a checkout and on the built site. Here each such file is put into the site
under ``_repo/<its path>``, the links are rewritten to it, and a link to a file that does
not exist is a warning (an error under ``mkdocs build --strict``). Markdown files brought
in this way are rendered as pages and their own links follow the same rule."""

from __future__ import annotations

import logging
import posixpath
import re
from pathlib import Path

from mkdocs.structure.files import File, InclusionLevel

log = logging.getLogger("mkdocs.plugins.difstar")

LINK = re.compile(r"(\]\()([^)\s#]+)((?:#[^)\s]*)?\))")
REPO_DIR = "_repo"
_state: dict = {}


def _is_external(target: str) -> bool:
    return bool(re.match(r"^[a-z][a-z0-9+.-]*:", target)) or target.startswith("/")


def _repo_path(page_repo_path: str, target: str) -> str:
    return posixpath.normpath(posixpath.join(posixpath.dirname(page_repo_path), target))


def _links(text: str):
    # links inside code spans and fenced blocks are not links
    text = re.sub(r"```.*?```", "", text, flags=re.S)
    text = re.sub(r"`[^`\n]*`", "", text)
    for m in LINK.finditer(text):
        if not _is_external(m.group(2)):
            yield m.group(2)


def on_files(files, config):
    repo = Path(config["docs_dir"]).resolve().parent
    _state["repo"] = repo
    outside: set[str] = set()
    todo = [("docs/" + f.src_uri, (repo / "docs" / f.src_uri).read_text())
            for f in files if f.src_uri.endswith(".md")]
    while todo:
        where, text = todo.pop()
        for target in _links(text):
            path = _repo_path(where, target)
            if path.startswith("docs/") or path in outside:
                continue
            if path.startswith("..") or not (repo / path).is_file():
                log.warning(f"{where} links '{target}', which is no file of the repository")
                continue
            outside.add(path)
            if path.endswith(".md"):
                todo.append((path, (repo / path).read_text()))
    for path in sorted(outside):
        # part of the site, reached by the links to it, not by the navigation
        files.append(File.generated(config, f"{REPO_DIR}/{path}", abs_src_path=str(repo / path),
                                    inclusion=InclusionLevel.NOT_IN_NAV))
    return files


def on_page_markdown(markdown, page, config, files):
    uri = page.file.src_uri
    where = uri[len(REPO_DIR) + 1:] if uri.startswith(REPO_DIR + "/") else "docs/" + uri

    def rewrite(m):
        target = m.group(2)
        if _is_external(target):
            return m.group(0)
        path = _repo_path(where, target)
        new = path[len("docs/"):] if path.startswith("docs/") else f"{REPO_DIR}/{path}"
        rel = posixpath.relpath(new, posixpath.dirname(uri) or ".")
        return m.group(1) + rel + m.group(3)

    return LINK.sub(rewrite, markdown)


def _api_entries(api: Path) -> dict[str, set[str] | None]:
    """``::: difstar...`` entries of docs/api/*.md: identifier -> its ``members`` list
    (None: every member)."""
    entries: dict[str, set[str] | None] = {}
    for md in sorted(api.glob("*.md")):
        current = None
        in_members = False
        for line in md.read_text().splitlines():
            m = re.match(r"^::: (difstar[\w.]*)\s*$", line)
            if m:
                current, in_members = m.group(1), False
                entries[current] = None
                continue
            if current is None:
                continue
            if re.match(r"^\s+members:\s*$", line):
                in_members, entries[current] = True, set()
            elif in_members and (item := re.match(r"^\s+- (\w+)\s*$", line)):
                entries[current].add(item.group(1))
            elif not line.startswith(" "):
                current, in_members = None, False
    return entries


def on_post_build(config):
    """Every public name has an entry in the API reference (docs/api/): each name of the
    top-level ``difstar``, and each public module's names that the top level lacks."""
    import importlib
    import pkgutil

    import difstar

    entries = _api_entries(Path(config["docs_dir"]) / "api")
    public = {n for n in vars(difstar) if not n.startswith("_")
              and getattr(getattr(difstar, n), "__module__", "").startswith("difstar")}
    for name in sorted(public):
        if f"difstar.{name}" not in entries:
            log.warning(f"difstar.{name} is public but has no '::: difstar.{name}' in docs/api/")
    top = {n for n in vars(difstar) if not n.startswith("_")}
    for info in pkgutil.iter_modules(difstar.__path__):
        if info.name.startswith("_") or info.name == "cli":  # cli: docs/cli.md
            continue
        ident = f"difstar.{info.name}"
        if ident not in entries:
            log.warning(f"{ident} is a public module but has no '::: {ident}' in docs/api/")
            continue
        members = entries[ident]
        if members is None:
            continue
        mod = importlib.import_module(ident)
        names = set(getattr(mod, "__all__", [n for n in vars(mod) if not n.startswith("_")]))
        for name in sorted(names - top - members):
            log.warning(f"{ident}.{name} is public but not in the members of '::: {ident}' "
                        "in docs/api/")
