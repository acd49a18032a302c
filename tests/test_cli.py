"""The command line end to end on a small scene: outputs whole, derived values right,
clear errors for bad input, nothing overwritten."""

import json

import numpy as np
import pytest
import tifffile
from PIL import Image

from difstar.cli import example_document, main


def _small_doc():
    doc = example_document("paper-defocused", crop=(64, 64))
    doc["scene"]["sources"][0]["radius"] = 0.3e-3
    doc["grid"]["padding"] = 0.5
    return doc


def test_predict_writes_everything(tmp_path):
    scene = tmp_path / "scene.json"
    scene.write_text(json.dumps(_small_doc()))
    out = tmp_path / "out"
    assert main(["predict", str(scene), "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == [
        ".difstar-output", "derived.json", "psf_log.png", "raw.tiff", "scene.json", "srgb.png"]
    marker = json.loads((out / ".difstar-output").read_text())
    assert marker["difstar"] == "output" and marker["files"] == [
        "derived.json", "psf_log.png", "raw.tiff", "scene.json", "srgb.png"]
    assert not [p for p in tmp_path.iterdir() if "difstar-" in p.name]  # no temporaries
    d = json.loads((out / "derived.json").read_text())
    assert d["geometry"]["defocus_m"] == pytest.approx(4.78e-3, abs=2e-5)  # paper: 4.78 mm
    assert d["grid"]["crop"] == [64, 64]
    assert d["grid"]["defocus_phase"] is True
    raw = tifffile.imread(out / "raw.tiff")
    assert raw.dtype == np.uint16 and raw.shape == (64, 64)
    with tifffile.TiffFile(out / "raw.tiff") as tf:
        assert json.loads(tf.pages[0].description)["cfa_pattern"] == "RGGB"
    with Image.open(out / "srgb.png") as im:
        assert im.size == (64, 64)
    # refuses to overwrite, and leaves the earlier result intact
    before = (out / "derived.json").read_bytes()
    assert main(["predict", str(scene), "--out", str(out)]) == 2
    assert (out / "derived.json").read_bytes() == before


def test_bad_scene_field_is_named(tmp_path, capsys):
    doc = _small_doc()
    doc["camera"]["sensor"]["pattern"] = "RGBG"
    scene = tmp_path / "bad.json"
    scene.write_text(json.dumps(doc))
    assert main(["predict", str(scene), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "camera/sensor/pattern" in err and "RGBG" in err
    assert not (tmp_path / "o").exists()  # nothing written


def test_undersampled_override_names_rule(tmp_path, capsys):
    doc = _small_doc()
    doc["camera"]["lens"]["pupil"]["circumradius"] = 51.5e-3 / (2 * 2.0)  # f/2
    doc["grid"]["oversample"] = 1
    scene = tmp_path / "s.json"
    scene.write_text(json.dumps(doc))
    assert main(["predict", str(scene), "--out", str(tmp_path / "o")]) == 2
    assert "rule 1" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_missing_and_malformed_files(tmp_path, capsys):
    assert main(["predict", str(tmp_path / "nope.json"), "--out", str(tmp_path / "o")]) == 2
    assert "does not exist" in capsys.readouterr().err
    bad = tmp_path / "b.json"
    bad.write_text("{not json")
    assert main(["predict", str(bad), "--out", str(tmp_path / "o")]) == 2
    assert "not valid JSON" in capsys.readouterr().err


def test_example_roundtrips_through_schema(tmp_path):
    from difstar.io import load_scene

    p = tmp_path / "ex.json"
    assert main(["example", "paper-focused", "--out", str(p)]) == 0
    camera, scene, grid = load_scene(p)
    assert grid["crop"] == [1250, 1250]
    assert camera.lens.pupil.n == 7
    assert float(scene.exposure_time) == 2.5


def test_version(capsys):
    from importlib.metadata import version

    from difstar.cli import main

    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    assert capsys.readouterr().out.strip() == f"difstar {version('difstar')}"
