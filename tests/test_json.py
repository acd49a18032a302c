"""io/_json.py: strict JSON and manifests that extend another (``"extends"``): the overlay
rule, the base's files named from its own folder, and the refusals (a missing base, a
cycle, too long a chain, not a file name), each naming the manifest and the field."""

from __future__ import annotations

import json

import pytest

from difstar.fitting import load_manifest
from difstar.fitting._manifest import PATH_KEYS
from difstar.fitting._params import FitInputError
from difstar.io._json import MAX_EXTENDS, SceneError, overlay, read_json_extends


def test_overlay_merges_objects_and_replaces_the_rest():
    base = {"a": 1, "b": {"c": 2, "d": [1, 2]}, "e": [3]}
    over = {"b": {"d": [9], "x": None}, "e": [], "f": "new"}
    assert overlay(base, over) == {"a": 1, "b": {"c": 2, "d": [9], "x": None}, "e": [],
                                   "f": "new"}
    assert base == {"a": 1, "b": {"c": 2, "d": [1, 2]}, "e": [3]}  # inputs untouched


def _write(p, doc):
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(doc))
    return p


def test_a_chain_merges_in_order_and_keeps_each_base_files(tmp_path):
    (tmp_path / "base").mkdir()
    (tmp_path / "base" / "star.npy").write_bytes(b"x")
    _write(tmp_path / "base" / "m.json", {"name": "base", "data": {"path": "star.npy"},
                                           "params": {"flux": 1, "x0": 0}})
    _write(tmp_path / "v" / "mid.json", {"extends": "../base/m.json", "name": "mid",
                                         "params": {"x0": 2}})
    top = _write(tmp_path / "v" / "sub" / "top.json", {"extends": "../mid.json",
                                                        "params": {"flux": 5}})
    doc, chain = read_json_extends(top, path_keys=PATH_KEYS)
    assert doc == {"name": "mid", "data": {"path": str((tmp_path / "base" / "star.npy")
                                                       .resolve())},
                   "params": {"flux": 5, "x0": 2}}
    assert [c.name for c in chain] == ["top.json", "mid.json", "m.json"]


@pytest.mark.parametrize("case,words", [
    ("missing", ["field extends", "does not exist"]),
    ("cycle", ["field extends", "cycle"]),
    ("self", ["field extends", "cycle"]),
    ("number", ["field extends", "not a file name"]),
    ("long", ["field extends", f"more than {MAX_EXTENDS}"]),
    ("array", ["holds a JSON object"]),
])
def test_bad_extends_are_refused_naming_the_field(tmp_path, case, words):
    a = tmp_path / "a.json"
    if case == "missing":
        _write(a, {"extends": "nowhere.json"})
    elif case == "cycle":
        _write(a, {"extends": "b.json"})
        _write(tmp_path / "b.json", {"extends": "a.json"})
    elif case == "self":
        _write(a, {"extends": "a.json"})
    elif case == "number":
        _write(a, {"extends": 3})
    elif case == "long":
        for i in range(MAX_EXTENDS + 1):
            _write(tmp_path / f"m{i}.json", {"extends": f"m{i + 1}.json"})
        _write(tmp_path / f"m{MAX_EXTENDS + 1}.json", {"name": "end"})
        a = tmp_path / "m0.json"
    elif case == "array":
        _write(a, {"extends": "b.json"})
        _write(tmp_path / "b.json", [1, 2])
    before = {p: p.read_bytes() for p in tmp_path.iterdir()}
    with pytest.raises(SceneError) as e:
        read_json_extends(a, path_keys=PATH_KEYS)
    assert all(w in str(e.value) for w in words), str(e.value)
    assert str(a) in str(e.value) or case == "long"
    assert {p: p.read_bytes() for p in tmp_path.iterdir()} == before  # nothing modified


def test_every_variant_of_the_jwst_campaign_loads_as_its_base_plus_its_changes():
    """fit/jwst-nircam/variants/*.json extend the campaign's manifest (or
    segment-wavefront.json): each loads, its stages are its own and its data is the
    base's star; a broken variant would be refused by load_manifest as any manifest."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[1] / "fit" / "jwst-nircam"
    base_model, base_data, _ = load_manifest(root / "manifest.json")
    variants = sorted((root / "variants").glob("*.json"))
    extending = [p for p in variants if "extends" in json.loads(p.read_text())]
    assert len(extending) >= 10
    for p in extending:
        model, data, opts = load_manifest(p)
        assert (data.image == base_data.image).all()
        stages = json.loads(p.read_text()).get("stages", opts["stages"])
        if stages == "auto":  # the stages chosen from the model and the data
            from difstar.fitting import auto_stages

            stages = auto_stages(model, data)
        assert opts["stages"] == stages
        assert any(str(root) in s for s in opts["inputs"])  # its bases are inputs


def test_a_variant_that_breaks_the_schema_is_refused_like_any_manifest(tmp_path):
    from pathlib import Path

    root = Path(__file__).resolve().parents[1] / "fit" / "jwst-nircam"
    bad = _write(tmp_path / "v.json", {"extends": str(root / "manifest.json"),
                                       "light": {"n": 0}})
    with pytest.raises(FitInputError, match=r"light"):
        load_manifest(bad)
