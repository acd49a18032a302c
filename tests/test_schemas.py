"""Every document difstar reads is checked against its schema in data_schemas/ (issue 31).

The schemas are valid Draft 2020-12 schemas whose own examples validate; each schema of a
file difstar reads is enforced by the code that reads it; every JSON document in the
repository of a known kind (scene, RAW-fit manifest, image-fit manifest, design sweep,
fit result) validates against its schema, and then passes the reader's own checks where
they read no other file. Documents are found by their content, not from a list, so a new
campaign or variant is covered; a JSON file under fit/ that matches no kind fails.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

from difstar.io._scene import load_schema, validate

REPO = Path(__file__).resolve().parents[1]
SCHEMAS = sorted(p.name.removesuffix(".schema.json")
                 for p in (REPO / "data_schemas").glob("*.schema.json"))
#: schemas of files difstar reads (each must be enforced by a ``validate`` call in src/)
INPUT_SCHEMAS = ("scene", "fit_manifest", "image_fit_manifest", "design_sweep")
#: schemas of files difstar writes (checked here against what difstar writes)
OUTPUT_SCHEMAS = ("fit_result",)
#: where JSON documents are looked for (besides the built-in examples)
SEARCHED = ("fit", "docs", "notebooks", "benchmarks")


# ------------------------------------------------------------------- the schemas


def test_every_schema_is_listed():
    assert sorted(INPUT_SCHEMAS + OUTPUT_SCHEMAS) == SCHEMAS


@pytest.mark.parametrize("name", SCHEMAS)
def test_schema_is_a_valid_draft_2020_12_schema(name):
    import jsonschema

    schema = load_schema(name)
    assert schema["$schema"] == "https://json-schema.org/draft/2020-12/schema"
    jsonschema.Draft202012Validator.check_schema(schema)
    for i, example in enumerate(schema.get("examples", [])):
        validate(example, name, source=f"{name} examples/{i}")


@pytest.mark.parametrize("name", INPUT_SCHEMAS)
def test_input_schema_is_enforced_by_its_reader(name):
    """A ``validate(doc, "<name>", ...)`` call in src/difstar: the schema is the one the
    code enforces, not documentation only."""
    call = re.compile(r"validate\(\s*\w+\s*,\s*[\"']" + re.escape(name) + r"[\"']")
    readers = [p for p in (REPO / "src" / "difstar").rglob("*.py") if call.search(p.read_text())]
    assert readers, f"no reader validates against data_schemas/{name}.schema.json"


# ------------------------------------------------------------ finding documents


def _kind(doc) -> str | None:
    """The kind of a JSON document, from its content."""
    if not isinstance(doc, dict):
        return None
    if doc.get("schema") == "difstar-fit-result/1":
        return "fit_result"
    if "camera" in doc and "scene" in doc:
        return "scene"
    if "configurations" in doc and "captures" in doc:
        return "fit_manifest"
    if isinstance(doc.get("pupil"), dict) and "builder" in doc["pupil"]:
        return "image_fit_manifest"
    keys = {k for k in doc if not k.startswith("$")}
    if keys and keys <= {"designs", "grid"}:
        return "design_sweep"
    # outputs of `difstar fit-image` (its result and its studies) and of the campaigns'
    # former scripts: no schema (yet)
    if {"manifest", "status", "converged", "values", "errors"} <= set(doc):
        return "image_fit_result (no schema)"
    if {"starts", "rotation_spread_deg", "perturb"} <= set(doc):
        return "fit-image robustness study (no schema)"
    if {"copies", "rotation_original", "noise"} <= set(doc):
        return "fit-image fainter-copies study (no schema)"
    if {"kernel", "copies"} <= set(doc):
        return "fit-image shifted-copies study (no schema)"
    if set(doc) == {"copies"}:
        return "fit-image contaminated-copies study (no schema)"
    if {"param", "within", "noise", "rows"} <= set(doc):
        return "fit-image noise-limit study (no schema)"
    if {"slices", "grid_deg", "result"} <= set(doc):  # a script of the campaign's, removed
        return "fit/jwst-nircam rotation slices (no schema)"
    return None


def _json_files():
    for top in SEARCHED:
        for p in sorted((REPO / top).rglob("*.json")):
            yield p
    for p in sorted(REPO.glob("*.json")):
        yield p


def _markdown_blocks():
    """(where, document) of every ```json block of the documentation that is a whole JSON
    document (fragments, such as a few fields of a scene, are not)."""
    mds = [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md")),
           *sorted((REPO / "fit").rglob("*.md"))]
    for md in mds:
        text = md.read_text()
        for m in re.finditer(r"```json\n(.*?)```", text, re.S):
            try:
                doc = json.loads(m.group(1))
            except json.JSONDecodeError:
                continue
            line = text[: m.start()].count("\n") + 1
            yield f"{md.relative_to(REPO)}:{line}", doc


def _examples():
    from difstar.cli._main import EXAMPLES, example_document

    for name in EXAMPLES:
        yield f"difstar example {name}", example_document(name)


def _read(p: Path):
    """A JSON file as difstar reads it: a manifest that ``extends`` another, merged by
    its own kind's reader (the kind known once merged)."""
    doc = json.loads(p.read_text())
    if isinstance(doc, dict) and "extends" in doc:
        from difstar.fitting._manifest import manifest_document as image_document
        from difstar.io._manifest import manifest_document as raw_document

        doc, _ = image_document(p)
        if _kind(doc) == "fit_manifest":
            doc, _ = raw_document(p)
    return doc


def _documents():
    out = [(str(p.relative_to(REPO)), _read(p)) for p in _json_files()]
    return out + list(_markdown_blocks()) + list(_examples())


DOCUMENTS = _documents()


def test_documents_are_found():
    """The search finds what the repository holds (so that the tests below are not
    vacuous): both examples, the campaigns' manifests, the variants, a sweep."""
    kinds = [_kind(d) for _, d in DOCUMENTS]
    assert kinds.count("scene") >= 2
    assert kinds.count("fit_manifest") >= 1
    assert kinds.count("image_fit_manifest") >= 3
    assert kinds.count("design_sweep") >= 1


def test_every_json_file_under_fit_is_of_a_known_kind():
    unknown = [where for where, doc in DOCUMENTS
               if where.startswith("fit/") and _kind(doc) is None]
    assert not unknown, (
        f"JSON files under fit/ of no known kind: {unknown}; give them a schema in "
        "data_schemas/ and a kind in tests/test_schemas.py::_kind")


def _reader_checks(kind: str, doc, where: str) -> None:
    """The reader's own checks after the schema (those that open no other file)."""
    if kind == "scene":
        from difstar.io._scene import scene_from_dict

        scene_from_dict(doc, source=where)
    elif kind == "fit_manifest":
        from difstar.io._manifest import manifest_from_dict

        manifest_from_dict(doc, path=REPO / where if (REPO / where).is_file() else where)
    elif kind == "design_sweep":
        from difstar._design_study import parse_sweep

        lists = [v for d in doc.get("designs", []) for k, v in d.items()
                 if k in ("radial", "angular") and isinstance(v, list)]
        parse_sweep(doc, blades=len(lists[0]) if lists else 9, source=where)


SCHEMA_DOCUMENTS = [(where, doc) for where, doc in DOCUMENTS if _kind(doc) in SCHEMAS]


@pytest.mark.parametrize("where,doc", SCHEMA_DOCUMENTS, ids=[w for w, _ in SCHEMA_DOCUMENTS])
def test_document_validates_against_its_schema(where, doc):
    kind = _kind(doc)
    validate(doc, kind, source=where)
    _reader_checks(kind, doc, where)


def test_outputs_without_a_schema_are_strict_json():
    """What `difstar fit-image` and its studies write (no schema yet) is at least JSON
    that difstar's strict reader takes (no NaN or Infinity): the studies read
    result.json back (fit_fainter_copy, noise_limit)."""
    from difstar.io._json import loads_strict

    for p in _json_files():
        rel = str(p.relative_to(REPO))
        if "(no schema)" in (_kind(json.loads(p.read_text())) or ""):
            loads_strict(p.read_text(), source=rel)


# ------------------------------------------------------------------ fit results


def test_fit_result_schema_refuses_what_difstar_never_writes():
    """The schema is not vacuous: a stage without its losses, an unknown solver result,
    a restart record without its tries are refused, naming the field."""
    from difstar.io._scene import SceneError

    stage = {"label": "all free", "held": [], "steps": 3, "accepted": 3, "loss_start": 2.0,
             "loss_end": 1.0, "result": "converged", "seconds": 0.1, "compile_seconds": 1.0}
    restarts = {"label": "response-curve restarts", "steps": 2, "result": "1 of 2 kept",
                "seconds": 0.2, "compile_seconds": 0.0,
                "tries": [{"parameter": "knee[0]", "factor": 0.5, "loss": 1.0, "kept": True,
                           "steps": 1},
                          {"parameter": "knee[0]", "factor": 2.0, "loss": 3.0, "kept": False,
                           "steps": 1}]}
    good = {"schema": "difstar-fit-result/1", "manifest": "m.json",
            "parameters": {"circumradius": {"value": 1e-3, "free": True, "start": 1e-3,
                                            "stderr": 1e-6, "bounds": [8e-4, 2e-3],
                                            "at_bound": False}},
            "derived": {"circumradius_mm": 1.0},
            "convergence": {"solver": "optimistix.LevenbergMarquardt",
                            "stages": [stage, restarts], "chi2": 1.0, "dof": 10,
                            "reduced_chi2": 0.1},
            "timing_s": {"total": 1.0, "first_step_since_start": None},
            "table1": [{"capture": "a", "configuration": "c", "exposure_time_s": 0.1,
                        **{ch: {"MSE": 1e-4, "SSIM": 0.99} for ch in ("R", "G", "B", "B/W")}}],
            "truth_comparison": {"all_pass": True}}
    validate(good, "fit_result")
    for change, field in (
        (lambda d: d["convergence"]["stages"][0].pop("loss_end"), "convergence/stages/0"),
        (lambda d: d["convergence"]["stages"][0].update(result="done"),
         "convergence/stages/0/result"),
        (lambda d: d["convergence"]["stages"][1].pop("tries"), "convergence/stages/1"),
        (lambda d: d["convergence"]["stages"][1].update(result="kept"),
         "convergence/stages/1/result"),
        (lambda d: d["timing_s"].update(total="1 s"), "timing_s/total"),
        (lambda d: d.update(schema="difstar-fit-result/2"), "schema"),
        (lambda d: d["table1"][0].pop("B/W"), "table1/0"),
    ):
        bad = json.loads(json.dumps(good))
        change(bad)
        with pytest.raises(SceneError, match=f"field {field}:"):
            validate(bad, "fit_result")
