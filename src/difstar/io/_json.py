"""JSON documents: read strictly (no NaN/Infinity, bounded nesting) and validated against
difstar's schemas (``data_schemas/``), with errors that name the file and the field.

Every JSON file difstar reads (scene files, manifests, design sweeps) passes here; the
scene-file reader (:mod:`._scene`) builds difstar objects from what this returns.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from .._validate import InputError, check_finite_doc, loads_strict


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
