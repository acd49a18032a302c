"""The command line end to end on a small scene: outputs whole, derived values right,
clear errors for bad input, nothing overwritten."""

import json

import numpy as np
import pytest
import rawpy
import tifffile
from PIL import Image

from difstar.cli import main
from difstar.cli._main import example_document
from difstar.io._dng import written_by_difstar


def _srgb16(path):
    """srgb16.tif read back: (h, w, 3) uint16 values, after checking that it is an RGB
    TIFF tagged sRGB by its ICC profile (read by LittleCMS through Pillow)."""
    import io

    from PIL import ImageCms

    with tifffile.TiffFile(path) as tif:
        page = tif.pages[0]
        assert page.photometric == tifffile.PHOTOMETRIC.RGB and page.dtype == np.uint16
        icc = page.tags["InterColorProfile"].value
        a = page.asarray()
    profile = ImageCms.ImageCmsProfile(io.BytesIO(bytes(icc)))
    assert "sRGB" in ImageCms.getProfileDescription(profile)
    assert profile.profile.xcolor_space.strip() == "RGB"
    return a.astype(float)


def _small_doc():
    doc = example_document("paper-defocused", crop=(64, 64))
    doc["scene"]["sources"][0]["radius"] = 0.3e-3
    doc["grid"]["padding"] = 0.5
    return doc


def test_predict_writes_everything(tmp_path, monkeypatch):
    from difstar.io import _image_files

    got = {}  # the float sRGB image predict renders, as handed to its writers
    keep = _image_files.write_tiff_srgb16

    def srgb16(path, srgb):
        got["srgb"] = np.array(srgb, dtype=float)
        return keep(path, srgb)

    monkeypatch.setattr(_image_files, "write_tiff_srgb16", srgb16)
    scene = tmp_path / "scene.json"
    scene.write_text(json.dumps(_small_doc()))
    out = tmp_path / "out"
    assert main(["predict", str(scene), "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == [
        ".difstar-output", "derived.json", "psf_log.png", "raw.dng", "scene.json", "srgb.png",
        "srgb16.tif"]
    marker = json.loads((out / ".difstar-output").read_text())
    assert marker["difstar"] == "output" and marker["files"] == [
        "derived.json", "psf_log.png", "raw.dng", "scene.json", "srgb.png", "srgb16.tif"]
    assert not [p for p in tmp_path.iterdir() if "difstar-" in p.name]  # no temporaries
    d = json.loads((out / "derived.json").read_text())
    assert d["geometry"]["defocus_m"] == pytest.approx(4.78e-3, abs=2e-5)  # paper: 4.78 mm
    assert d["grid"]["crop"] == [64, 64]
    assert d["grid"]["defocus_phase"] is True
    with rawpy.imread(str(out / "raw.dng")) as r:  # the layout and levels difstar wrote
        raw = r.raw_image_visible.copy()
        desc = r.color_desc.decode()
        assert "".join(desc[i] for i in r.raw_pattern.ravel()) == "RGGB"
        assert list(r.black_level_per_channel) == [0, 0, 0, 0] and r.white_level == 65535
        wb = np.asarray(r.camera_whitebalance[:3])
        np.testing.assert_allclose(wb / wb[1], [2.0, 1.0, 2.0], rtol=1e-6)  # the scene's
    assert raw.dtype == np.uint16 and raw.shape == (64, 64)
    assert written_by_difstar(out / "raw.dng")
    srgb16 = _srgb16(out / "srgb16.tif")
    assert srgb16.shape == (64, 64, 3)
    # the rendering quantised to 16 bits, exactly
    want = np.round(np.clip(np.moveaxis(got["srgb"], 0, -1), 0, 1) * 65535)
    assert np.array_equal(srgb16, want) and 0 < want.max() <= 65535
    assert not written_by_difstar(out / "srgb16.tif")  # only the DNG is marked difstar's
    with Image.open(out / "srgb.png") as im:  # 8 bits, tagged sRGB, the same picture
        assert im.size == (64, 64) and im.mode == "RGB" and im.info.get("srgb") == 0
        srgb8 = np.asarray(im).astype(float)
    assert np.abs(srgb8 - srgb16 / 257.0).max() <= 0.5 + 1e-9
    with Image.open(out / "psf_log.png") as im:  # a figure: three panels and a colour bar
        assert im.size == (1300, 440)
    # refuses to overwrite, and leaves the earlier result intact
    before = (out / "derived.json").read_bytes()
    assert main(["predict", str(scene), "--out", str(out)]) == 2
    assert (out / "derived.json").read_bytes() == before


def test_raw_dng_develops_in_libraw_like_srgb16(tmp_path):
    """LibRaw's development of `predict`'s raw.dng (camera white balance, the embedded
    colour matrix, AHD, sRGB curve, no auto-brightening, 16 bits) against difstar's own
    rendering of the same mosaic, srgb16.tif (Malvar 2004), on a scene below saturation
    (the paper's defocused disc at 1/100 of its exposure, peak 22 % of the sRGB range).

    The two demosaic a starburst's sharp edges differently, so pixels differ where the
    image changes fast: measured at most 0.0067 of the sRGB range per pixel (tolerance
    0.02). Averaged, they agree: the linear-light means per channel within 0.2 % (tolerance
    1 %), and after a Gaussian blur of σ = 2 pixels in linear light within 4e-4 (tolerance
    2e-3), away from a 4-pixel border that LibRaw fills its own way. (At clipped
    highlights they differ more, by design of each: LibRaw clips before demosaicing,
    difstar after.)"""
    from scipy.ndimage import gaussian_filter

    doc = _small_doc()
    doc["scene"]["exposure_time"] = 0.01
    scene = tmp_path / "scene.json"
    scene.write_text(json.dumps(doc))
    out = tmp_path / "out"
    assert main(["predict", str(scene), "--out", str(out)]) == 0
    ours = _srgb16(out / "srgb16.tif") / 65535
    assert 0.1 < ours.max() < 0.99  # nothing clipped
    with rawpy.imread(str(out / "raw.dng")) as r:
        theirs = r.postprocess(use_camera_wb=True, no_auto_bright=True, gamma=(2.4, 12.92),
                               output_bps=16, user_flip=0,
                               demosaic_algorithm=rawpy.DemosaicAlgorithm.AHD) / 65535

    def linear(v):  # IEC 61966-2-1 decoding
        return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)

    inner = (slice(4, -4), slice(4, -4))
    assert np.abs(theirs - ours)[inner].max() < 0.02
    lin_ours, lin_theirs = linear(ours)[inner], linear(theirs)[inner]
    np.testing.assert_allclose(lin_theirs.mean((0, 1)), lin_ours.mean((0, 1)), rtol=0.01)
    blur = [gaussian_filter(x, (2, 2, 0)) for x in (lin_ours, lin_theirs)]
    assert np.abs(blur[0] - blur[1]).max() < 2e-3


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
    doc["grid"]["method"] = "fft"  # the paper's grid: its pupil must fit (the engine folds)
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


def test_fit_takes_either_kind_of_manifest(tmp_path, monkeypatch, capsys):
    """``difstar fit`` runs the image fitter on an image-fit manifest (extends merged
    first), with --out defaulting to the manifest's folder/result, and refuses a
    manifest that says neither or both kinds by naming the fields."""
    from pathlib import Path

    import difstar.fitting._run as image_run
    from difstar.io import manifest_kind

    root = Path(__file__).resolve().parents[1]
    assert manifest_kind(root / "fit" / "spitzer-irac" / "manifest.json") == "image"
    assert manifest_kind(root / "fit" / "synthetic-paper-camera" / "manifest.json") == "raw"
    variant = tmp_path / "variant.json"  # a variant that only overlays a field
    variant.write_text(json.dumps({"extends": str(root / "fit" / "spitzer-irac" /
                                                  "manifest.json"), "max_steps": 3}))
    assert manifest_kind(variant) == "image"
    calls = []
    monkeypatch.setattr(image_run, "run", lambda *a, **k: calls.append((a, k)))
    assert main(["fit", str(variant), "--max-steps", "2"]) == 0
    (path, out), kw = calls[0]
    assert Path(path) == variant and Path(out) == tmp_path / "result"
    assert kw["max_steps"] == 2 and kw["overwrite"] is False
    assert main(["fit", str(variant), "--recovery-study", "3"]) == 2
    assert "--robustness" in capsys.readouterr().err
    for doc, word in (({"name": "x"}, "neither"), ({"data": "a.npy", "captures": []}, "both")):
        bad = tmp_path / f"{word}.json"
        bad.write_text(json.dumps(doc))
        assert main(["fit", str(bad)]) == 2
        err = capsys.readouterr().err
        assert word in err and "captures" in err and "pupil" in err


def test_fit_quiet_says_nothing_and_writes_the_same(tmp_path, monkeypatch, capsys):
    """``difstar fit --quiet`` runs the fit without progress (stderr) or summary (stdout)
    and writes its folder as without it; without the flag both are shown. The image
    fitter is handed ``verbose=False`` the same way."""
    from pathlib import Path

    import difstar.cli._fit as cli_fit
    import difstar.fitting._run as image_run

    root = Path(__file__).resolve().parents[1]
    manifest = root / "fit" / "synthetic-paper-camera" / "manifest.json"
    seen = []
    result = {"parameters": {"phi0": {"free": True, "value": [1.0], "stderr": [0.1],
                                      "at_bound": False}},
              "convergence": {"reduced_chi2": 1.0, "n_residuals": 10, "n_free": 1},
              "timing_s": {"total": 1.0, "compile": 0.5}}

    def fake_fit(man, **kw):
        seen.append(kw["verbose"])
        if kw["verbose"]:
            cli_fit._log("difstar fit: progress")
        return result, None, None, None, None

    def fake_outputs(tmp, *a):
        (tmp / "fit_result.json").write_text("{}")
        return ["fit_result.json"]

    monkeypatch.setattr(cli_fit, "fit_manifest", fake_fit)
    monkeypatch.setattr(cli_fit, "write_outputs", fake_outputs)
    for quiet, out in ((True, tmp_path / "quiet"), (False, tmp_path / "loud")):
        assert main(["fit", str(manifest), "--out", str(out)] + ["--quiet"] * quiet) == 0
        said = capsys.readouterr()
        assert (out / "fit_result.json").exists()
        assert (said.out == "" and said.err == "") if quiet else ("χ²" in said.out
                                                                 and "wrote" in said.err)
    assert seen == [False, True]
    calls = []
    monkeypatch.setattr(image_run, "run", lambda *a, **k: calls.append(k))
    assert main(["fit", str(root / "fit" / "spitzer-irac" / "manifest.json"), "--quiet",
                 "--out", str(tmp_path / "image")]) == 0
    assert calls[0]["verbose"] is False


def test_warnings_are_one_line(monkeypatch):
    """The command line shows a library warning as its other messages: one line,
    ``difstar: warning:``, with no source line of the library's code (Python's own
    format names the file and line and prints the line of code that warned)."""
    import warnings

    from difstar.cli._main import _one_line_warnings

    monkeypatch.setattr(warnings, "formatwarning", warnings.formatwarning)
    _one_line_warnings()
    text = warnings.formatwarning("field data/path: 3 pixels\n  are NaN", UserWarning,
                                  "/x/_manifest.py", 447, "fds = [_load_capture(d)]")
    assert text == "difstar: warning: field data/path: 3 pixels are NaN\n"
