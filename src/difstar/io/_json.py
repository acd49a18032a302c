"""JSON documents: read strictly (no NaN/Infinity, bounded nesting) and validated against
difstar's schemas (``data_schemas/``), with errors that name the file and the field.

Every JSON file difstar reads (scene files, manifests, design sweeps) passes here; the
scene-file reader (:mod:`._scene`) builds difstar objects from what this returns.

:func:`loads_strict` refuses ``NaN``/``Infinity`` (Python's ``json`` reads them), numbers
that overflow to infinity, duplicated keys and documents nested too deeply, naming the
field; :func:`check_finite_doc` does the same for a document built in Python.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from .._limits import MAX_JSON_DEPTH, InputError


class _NonFinite:
    """What ``json`` hands ``parse_constant`` for NaN / Infinity / -Infinity."""

    __slots__ = ("text",)

    def __init__(self, text: str):
        self.text = text

    def __repr__(self) -> str:
        return self.text


class _Duplicated(dict):
    """A JSON object in which a key was given twice (``duplicate``: the first such)."""

    duplicate: Any = None


def _path_str(path: Iterable) -> str:
    return "/".join(str(p) for p in path) or "(top level)"


def _walk(doc: Any):
    """Yield (path tuple, leaf value) for every leaf, depth first, without recursion."""
    stack = [((), doc)]
    while stack:
        path, v = stack.pop()
        if isinstance(v, dict):
            for k in reversed(list(v)):
                stack.append(((*path, k), v[k]))
        elif isinstance(v, (list, tuple)):
            for i in range(len(v) - 1, -1, -1):
                stack.append(((*path, i), v[i]))
        else:
            yield path, v


def json_depth(doc: Any) -> int:
    """Nesting depth of a parsed JSON document (a scalar is 0), without recursion."""
    deepest = 0
    stack = [(doc, 0)]
    while stack:
        v, d = stack.pop()
        if isinstance(v, dict):
            stack.extend((x, d + 1) for x in v.values())
            deepest = max(deepest, d + 1)
        elif isinstance(v, (list, tuple)):
            stack.extend((x, d + 1) for x in v)
            deepest = max(deepest, d + 1)
    return deepest


def _bad_number(v) -> str | None:
    """Why ``v`` is not a usable number, or None (non-numbers are the schema's job)."""
    if isinstance(v, _NonFinite):
        return f"{v.text} is not a finite number (JSON has no NaN or Infinity)"
    if isinstance(v, bool):
        return None
    if isinstance(v, (float, np.floating)):
        if not math.isfinite(float(v)):
            return f"{float(v)!r} is not a finite number"
    elif isinstance(v, (int, np.integer)):
        if abs(int(v)) > 2**53:
            return f"{v} is too large to be a number difstar can use"
    elif isinstance(v, np.ndarray) and v.dtype.kind in "fc":
        if not np.all(np.isfinite(v)):
            return "contains NaN or infinity"
    return None


def check_finite_doc(doc: Any, *, source: str = "<document>") -> None:
    """Refuse a document (parsed JSON or built in Python) holding a non-finite or
    overflowing number, or nested deeper than :data:`MAX_JSON_DEPTH`."""
    depth = json_depth(doc)
    if depth > MAX_JSON_DEPTH:
        raise InputError(
            f"{source}: the document is nested {depth} levels deep; a difstar document "
            f"needs at most {MAX_JSON_DEPTH} (check the brackets)."
        )
    for path, v in _walk(doc):
        why = _bad_number(v)
        if why:
            raise InputError(f"{source}: field {_path_str(path)}: {why}; give a finite number.")


#: float32's largest finite value and its smallest normal one
_F32_MAX, _F32_TINY = float(np.finfo(np.float32).max), float(np.finfo(np.float32).tiny)


def check_float32_doc(doc: Any, *, source: str = "<document>") -> None:
    """Where difstar computes in float32 (JAX without x64, the command without
    ``--x64``), refuse a number float32 cannot hold (beyond ±3.4e38, or nonzero below
    1.2e-38 in size), naming its field: it would become infinity or zero, and a later
    error would name a value the user never gave. Raises :class:`SceneError`."""
    import jax

    if jax.config.jax_enable_x64:
        return
    for path, v in _walk(doc):
        if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
            continue
        x = abs(float(v)) if abs(v) < 2**1023 else math.inf
        if x > _F32_MAX or 0 < x < _F32_TINY:
            raise SceneError(f"{source}: field {_path_str(path)}: {v!r} is beyond what "
                             "float32 holds (1.2e-38 … 3.4e38 in size); give the value in "
                             "its documented units, or compute in float64 (difstar --x64).")


def loads_strict(text: str, *, source: str = "<document>") -> Any:
    """``json.loads`` that refuses NaN, Infinity, numbers that overflow and deep nesting,
    with the field's path in the message (:class:`InputError`); also a key given twice
    in one object (the field's path named)."""
    duplicated = []

    def pairs(kv):  # a key given twice: JSON readers silently keep the last one
        d = dict(kv)
        if len(d) != len(kv):
            duplicated.append(True)
            seen: set = set()
            dup = next(k for k, _ in kv if k in seen or seen.add(k))
            d = _Duplicated(d)
            d.duplicate = dup
        return d

    try:
        doc = json.loads(text, parse_constant=_NonFinite, object_pairs_hook=pairs)
    except RecursionError:
        raise InputError(
            f"{source}: the JSON is nested too deeply to read; a difstar document needs "
            f"at most {MAX_JSON_DEPTH} levels (check the brackets)."
        ) from None
    except json.JSONDecodeError as exc:
        raise InputError(
            f"{source}: not valid JSON at line {exc.lineno}, column {exc.colno}: {exc.msg}"
        ) from None
    except ValueError as exc:  # e.g. an integer with more digits than Python converts
        raise InputError(f"{source}: not valid JSON: {exc}") from None
    stack = [((), doc)] if duplicated else []  # the first key given twice, its path
    while stack:
        path, v = stack.pop()
        if isinstance(v, _Duplicated):
            raise InputError(
                f"{source}: field {_path_str((*path, v.duplicate))}: the key "
                f"{v.duplicate!r} is given more than once in one object; keep one (a JSON "
                "reader would silently use only the last)."
            )
        if isinstance(v, dict):
            stack.extend(((*path, k), x) for k, x in reversed(list(v.items())))
        elif isinstance(v, list):
            stack.extend(((*path, i), x) for i, x in reversed(list(enumerate(v))))
    check_finite_doc(doc, source=source)
    return doc


class SceneError(InputError):
    """A scene file is missing, unreadable or invalid; the message names the field."""


def schema_path(name: str) -> Path:
    """Path of a JSON Schema shipped in the repository's ``data_schemas/`` (or packaged
    beside the module when installed as a wheel)."""
    here = Path(__file__).resolve()
    for base in (here.parent / "schemas", here.parents[3] / "data_schemas"):
        p = base / f"{name}.schema.json"
        if p.is_file():
            return p
    raise FileNotFoundError(f"schema {name!r} not found beside difstar or in data_schemas/")


def load_schema(name: str) -> dict:
    return json.loads(schema_path(name).read_text())


def _short(x, limit: int = 60) -> str:
    r = repr(x)
    return r if len(r) <= limit else r[: limit - 5] + " ...)"


def _pick(e):
    """For oneOf/anyOf errors, the error of the branch the document meant (the one not
    failing on its discriminating ``type``/``const``), so that the message names the
    innermost field instead of dumping the whole object."""
    import jsonschema

    while e.context:
        branches: dict = {}
        for c in e.context:
            branches.setdefault(c.relative_schema_path[0], []).append(c)

        def off(errs):
            return any(c.validator == "const" or (c.validator == "type"
                                                  and not list(c.relative_path))
                       for c in errs)

        cand = [errs for errs in branches.values() if not off(errs)]
        if not cand:
            return e
        errs = min(cand, key=len)
        e = jsonschema.exceptions.best_match(errs)
    return e


def _message(e) -> str:
    v, inst = e.validator, e.instance
    if v == "exclusiveMinimum":
        return f"{_short(inst)} must be > {e.validator_value}"
    if v == "minimum":
        return f"{_short(inst)} must be >= {e.validator_value}"
    if v == "exclusiveMaximum":
        return f"{_short(inst)} must be < {e.validator_value}"
    if v == "maximum":
        return f"{_short(inst)} must be <= {e.validator_value}"
    if v == "multipleOf":
        return f"{_short(inst)} must be a multiple of {e.validator_value}"
    if v == "type":
        return f"{_short(inst)} is not of type {e.validator_value!r}"
    if v in ("minItems", "maxItems"):
        n = len(inst) if isinstance(inst, (list, dict)) else "?"
        return (f"has {n} items; needs at {'least' if v == 'minItems' else 'most'} "
                f"{e.validator_value}")
    if v in ("oneOf", "anyOf"):
        return f"{_short(inst)} is not one of the allowed forms (see the schema)"
    msg = e.message
    return msg if len(msg) <= 300 else msg[:295] + " ..."


def validate(doc: Any, schema_name: str, *, source: str = "<document>") -> None:
    """Validate ``doc`` against a schema; raise SceneError naming the field on failure.
    NaN, Infinity and overflowing numbers (which JSON Schema lets through) are refused
    first, naming their field."""
    import jsonschema

    try:
        check_finite_doc(doc, source=source)
    except InputError as exc:
        raise SceneError(str(exc)) from None
    schema = load_schema(schema_name)
    validator = jsonschema.Draft202012Validator(schema)
    try:
        errors = sorted(validator.iter_errors(doc), key=lambda e: list(e.absolute_path))
    except RecursionError:
        raise SceneError(f"{source}: the document is nested too deeply.") from None
    if errors:
        e = _pick(jsonschema.exceptions.best_match(errors))
        where = "/".join(str(p) for p in e.absolute_path) or "(top level)"
        raise SceneError(f"{source}: field {where}: {_message(e)}")


def read_json(path: str | Path, *, what: str = "file") -> Any:
    """Read a JSON file strictly (no NaN/Infinity, bounded nesting), with errors naming
    the file."""
    p = Path(path)
    if p.is_dir():
        raise SceneError(f"{what} {p} is a folder, not a file; give the JSON file itself.")
    if not p.is_file():
        if p.exists():
            raise SceneError(f"{what} {p} is not a regular file; give a JSON file.")
        raise SceneError(f"{what} {p} does not exist (check the path).")
    try:
        text = p.read_text()
    except UnicodeDecodeError:
        raise SceneError(f"{what} {p} is not a text (UTF-8 JSON) file.") from None
    except OSError as exc:
        raise SceneError(f"{what} {p} cannot be read ({exc.strerror}).") from None
    try:
        return loads_strict(text, source=str(p))
    except InputError as exc:
        raise SceneError(str(exc)) from None


#: how many manifests a chain of ``extends`` may hold (a variant of a variant of ...)
MAX_EXTENDS = 8


def overlay(base: Any, over: Any) -> Any:
    """``over`` laid on ``base``: objects merge key by key (recursively); anything else in
    ``over`` (a number, a string, a list, null) replaces what ``base`` has there."""
    if isinstance(base, dict) and isinstance(over, dict):
        out = dict(base)
        for k, v in over.items():
            out[k] = overlay(base[k], v) if k in base else v
        return out
    return over


def _rebase(doc: Any, folder: Path, path_keys: frozenset, anchored: bool) -> Any:
    """``doc`` with each relative file name under a key of ``path_keys`` made absolute
    from ``folder`` (``anchored``: always; else where that file exists, the reader
    looking elsewhere too): a base manifest's files keep their meaning in the manifest
    that extends it, wherever that one lies."""
    if isinstance(doc, dict):
        out = {}
        for k, v in doc.items():
            if k in path_keys and isinstance(v, str) and not Path(v).is_absolute() \
                    and (anchored or (folder / v).exists()):
                out[k] = str((folder / v).resolve())
            else:
                out[k] = _rebase(v, folder, path_keys, anchored)
        return out
    if isinstance(doc, list):
        return [_rebase(v, folder, path_keys, anchored) for v in doc]
    return doc


def read_json_extends(path: str | Path, *, what: str = "manifest",
                      path_keys: frozenset = frozenset(),
                      anchored: bool = False) -> tuple[Any, list[Path]]:
    """A JSON object read strictly, with its ``"extends": "BASE.json"`` resolved: the
    base (relative to this file's folder; itself possibly extending another, up to
    :data:`MAX_EXTENDS` files, no cycle) is read, its relative file names under
    ``path_keys`` made absolute from its own folder (``anchored``: whether or not the
    file exists yet, for files named only from the manifest's folder), and this file's
    keys laid over it (:func:`overlay`). Returns (the merged document without ``extends``, every file read:
    this one first). Errors name the file and the field ``extends``."""
    p = Path(path)
    chain = [p]
    doc = read_json(p, what=what)
    layers = [doc]
    while isinstance(doc, dict) and "extends" in doc:
        ref = doc["extends"]
        here = chain[-1]
        if not isinstance(ref, str) or not ref.strip():
            raise SceneError(f"{here}: field extends: {ref!r} is not a file name; give the "
                             "path of the manifest this one varies (relative to its folder).")
        base = Path(ref) if Path(ref).is_absolute() else here.parent / ref
        if any(base.resolve() == c.resolve() for c in chain if c.exists()):
            names = " → ".join(str(c) for c in [*chain, base])
            raise SceneError(f"{here}: field extends: a cycle ({names}); a manifest cannot "
                             "extend itself.")
        if len(chain) >= MAX_EXTENDS:
            raise SceneError(f"{here}: field extends: more than {MAX_EXTENDS} manifests in "
                             "one chain; extend the base directly.")
        if not base.is_file():
            raise SceneError(f"{here}: field extends: {base} does not exist or is not a file "
                             "(a path relative to this manifest's folder, or absolute).")
        doc = read_json(base, what=what)
        if not isinstance(doc, dict):
            raise SceneError(f"{base}: a manifest holds a JSON object; this one, which "
                             f"{here} extends, does not.")
        chain.append(base)
        layers.append(_rebase(doc, base.parent, path_keys, anchored))
    merged = layers[-1]
    for layer in reversed(layers[:-1]):
        merged = overlay(merged, layer)
    if isinstance(merged, dict):
        merged = {k: v for k, v in merged.items() if k != "extends"}
    return merged, chain
