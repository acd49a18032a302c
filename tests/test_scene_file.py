"""Spectral scene files (issue 17): a sensor's ``wavelengths`` as 3 lists of K numbers
with ``spectral_weights``; ``difstar predict`` of such a file against ``difstar.simulate``
of the same camera built in Python, with and without ``--devices 2`` (two host CPU
devices, in a child Python), and bad spectral inputs refused with one line. Point
sources (issue 34): read, written back, refused when bad, naming the field."""

from __future__ import annotations

import copy
import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

import difstar
from difstar.cli import _main as cli
from difstar.io import _image_files
from difstar.io._scene import SceneError, scene_from_dict, scene_to_dict

#: K = 3 wavelengths per channel, each channel its own; the blue channel's last weight 0
WAVELENGTHS = [[580e-9, 610e-9, 640e-9], [500e-9, 530e-9, 560e-9], [430e-9, 450e-9, 470e-9]]
WEIGHTS = [[1.0, 2.0, 1.0], [1.0, 3.0, 1.0], [0.5, 1.0, 0.0]]


def spectral_doc(crop=(32, 32)) -> dict:
    """The paper's defocused scene, cut small, with a spectral sensor."""
    doc = cli.example_document("paper-defocused", crop=crop)
    doc["scene"]["sources"][0]["radius"] = 0.3e-3
    doc["grid"]["padding"] = 0.5
    doc["camera"]["sensor"]["wavelengths"] = copy.deepcopy(WAVELENGTHS)
    doc["camera"]["sensor"]["spectral_weights"] = copy.deepcopy(WEIGHTS)
    return doc


def python_camera():
    """The same camera and scene as :func:`spectral_doc`, built in Python."""
    camera, scene = difstar.paper_camera("defocused")
    s = camera.sensor
    cam = difstar.Camera(camera.lens, difstar.Sensor(
        pixel_pitch=s.pixel_pitch, pattern=s.pattern, wavelengths=np.array(WAVELENGTHS),
        spectral_weights=np.array(WEIGHTS), phi0=s.phi0, response=s.response,
        white_balance=s.white_balance, colour_matrix=s.colour_matrix))
    src = scene.sources[0]
    scene = difstar.Scene(
        object_distance=scene.object_distance, exposure_time=scene.exposure_time,
        background=scene.background,
        sources=[difstar.DiscSource(0.3e-3, src.position, src.radiance)])
    return cam, scene


def test_spectral_sensor_loads_and_roundtrips():
    camera, _, _ = scene_from_dict(spectral_doc())
    sen = camera.sensor
    assert sen.wavelengths.shape == (3, 3) and sen.spectral_weights.shape == (3, 3)
    np.testing.assert_allclose(sen.wavelengths, WAVELENGTHS, rtol=0)
    w = np.array(WEIGHTS)
    np.testing.assert_allclose(sen.spectral_weights, w / w.sum(1, keepdims=True), rtol=1e-15)
    # written back (normalised weights) and read again: the same sensor
    doc = scene_to_dict(*scene_from_dict(spectral_doc())[:2])
    assert np.shape(doc["camera"]["sensor"]["spectral_weights"]) == (3, 3)
    again = scene_from_dict(doc)[0].sensor
    np.testing.assert_allclose(again.spectral_weights, sen.spectral_weights, rtol=1e-15)
    # equal weights when spectral_weights is left out; trichromatic files unchanged
    doc = spectral_doc()
    del doc["camera"]["sensor"]["spectral_weights"]
    np.testing.assert_allclose(scene_from_dict(doc)[0].sensor.spectral_weights, 1 / 3)
    tri = cli.example_document("paper-focused", crop=(16, 16))
    assert scene_from_dict(tri)[0].sensor.spectral_weights is None


def _capture(monkeypatch) -> dict:
    """The predicted float arrays that ``predict`` writes to raw.dng, srgb.png and
    psf_log.png (the files themselves are quantised)."""
    got = {}
    raw, png, psf_log = _image_files.write_raw_dng, _image_files.write_png_srgb, cli.write_psf_png

    def tiff(path, cfa, **kw):
        got["cfa"] = np.array(cfa, dtype=float)
        return raw(path, cfa, **kw)

    def srgb(path, img):
        if str(path).endswith("srgb.png"):
            got["srgb"] = np.array(img, dtype=float)
        return png(path, img)

    def psf_png(path, psf):
        got["psf"] = np.array(psf, dtype=float)
        return psf_log(path, psf)

    monkeypatch.setattr(_image_files, "write_raw_dng", tiff)
    monkeypatch.setattr(_image_files, "write_png_srgb", srgb)
    monkeypatch.setattr(cli, "write_psf_png", psf_png)
    return got


@pytest.mark.slow
def test_spectral_predict_equals_simulate(tmp_path, monkeypatch):
    import equinox as eqx

    monkeypatch.delenv("DIFSTAR_DEVICES", raising=False)
    scene_file = tmp_path / "spectral.json"
    scene_file.write_text(json.dumps(spectral_doc()))
    got = _capture(monkeypatch)
    assert cli.main(["predict", str(scene_file), "--out", str(tmp_path / "out")]) == 0
    cam, scene = python_camera()
    grid = difstar.choose_grid(cam, scene, crop=(32, 32), padding=0.5)
    ref = eqx.filter_jit(difstar.simulate)(cam, scene, grid)
    assert ref.psf.shape[0] == 3 and got["cfa"].shape == (32, 32)
    for name in ("cfa", "srgb", "psf"):
        want = np.asarray(getattr(ref, name))
        assert np.abs(got[name] - want).max() <= 1e-12 * np.abs(want).max(), name
    # not a trichromatic render: the blue channel differs from 450 nm alone
    tri = eqx.tree_at(lambda c: (c.sensor.wavelengths, c.sensor.spectral_weights), cam,
                      (cam.sensor.wavelengths[:, 1], None), is_leaf=lambda x: x is None)
    # under jit, as ``ref`` above: run eagerly, op by op, it takes four times as long
    mono = eqx.filter_jit(difstar.simulate)(tri, scene, grid)
    assert np.abs(np.asarray(mono.psf) - got["psf"]).max() > 1e-3 * got["psf"].max()
    written = json.loads((tmp_path / "out" / "scene.json").read_text())
    assert written["camera"]["sensor"]["spectral_weights"] == WEIGHTS


CHILD = textwrap.dedent('''
    import json, sys
    import numpy as np
    sys.path.insert(0, "tests")
    import jax
    from test_scene_file import spectral_doc
    from difstar.cli import _main as cli
    from difstar.io import _image_files

    got = {}
    raw = _image_files.write_raw_dng
    def tiff(path, cfa, **kw):
        got["cfa"] = np.array(cfa, dtype=float)
        return raw(path, cfa, **kw)
    _image_files.write_raw_dng = tiff
    keep = cli.write_psf_png
    def psf_png(path, psf):
        got["psf"] = np.array(psf, dtype=float)
        return keep(path, psf)
    cli.write_psf_png = psf_png

    out = {"devices": jax.device_count()}
    scene = sys.argv[1] + "/spectral.json"
    with open(scene, "w") as f:
        json.dump(spectral_doc(), f)
    res = {}
    for tag, extra in (("one", []), ("two", ["--devices", "2"])):
        rc = cli.main(["--x64", "predict", scene, "--out", sys.argv[1] + "/" + tag] + extra)
        out["rc_" + tag] = rc
        res[tag] = dict(got)
    for name in ("cfa", "psf"):
        a, b = res["one"][name], res["two"][name]
        out[name] = float(np.abs(a - b).max() / np.abs(a).max())
    print("RESULT " + json.dumps(out))
''')


@pytest.mark.slow
def test_spectral_predict_on_two_host_devices_equals_one(tmp_path):
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    env.pop("DIFSTAR_DEVICES", None)
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    p = subprocess.run([sys.executable, "-c", CHILD, str(tmp_path)], cwd=root, env=env,
                       capture_output=True, text=True, timeout=300)
    line = [x for x in p.stdout.splitlines() if x.startswith("RESULT ")]
    assert p.returncode == 0 and line, p.stderr[-3000:]
    r = json.loads(line[-1][7:])
    assert r["devices"] == 2 and r["rc_one"] == 0 and r["rc_two"] == 0, r
    assert "sharded over the devices" in p.stderr and "wavelengths 3/3 done" in p.stderr
    assert r["cfa"] < 1e-12 and r["psf"] < 1e-12, r


def _sensor(**edit) -> dict:
    doc = spectral_doc()
    sd = doc["camera"]["sensor"]
    for k, v in edit.items():
        if v is None:
            sd.pop(k, None)
        else:
            sd[k] = v
    return doc


WL = WAVELENGTHS
BAD = [
    ("ragged", dict(wavelengths=[WL[0][:2], WL[1], WL[2]]),
     "camera/sensor/wavelengths:", "2, 3, 3 wavelengths (ragged)"),
    ("two channels", dict(wavelengths=WL[:2]), "camera/sensor/wavelengths:", "3 lists of K"),
    ("numbers and lists", dict(wavelengths=[WL[0], 530e-9, WL[2]]),
     "camera/sensor/wavelengths:", "mixes numbers and lists"),
    ("nanometres", dict(wavelengths=[[580, 610, 640], WL[1], WL[2]]),
     "camera/sensor/wavelengths/0/0", "<= 0.001"),
    ("negative", dict(wavelengths=[WL[0], [500e-9, -5e-7, 560e-9], WL[2]]),
     "camera/sensor/wavelengths/1/1", "> 0"),
    ("not a number", dict(wavelengths=[WL[0], WL[1], [430e-9, "450", 470e-9]]),
     "camera/sensor/wavelengths/2/1", "not a number"),
    ("empty channel", dict(wavelengths=[[], WL[1], WL[2]], spectral_weights=None),
     "camera/sensor/wavelengths/0", "give 1 to"),
    ("weights ragged", dict(spectral_weights=[[1, 1], [1, 1, 1], [1, 1, 1]]),
     "camera/sensor/spectral_weights:", "(ragged)"),
    ("weights of another K", dict(spectral_weights=[[1, 1]] * 3),
     "camera/sensor/spectral_weights:", "2 weights per channel for 3 wavelengths"),
    ("weight negative", dict(spectral_weights=[[1, -1, 1], [1, 1, 1], [1, 1, 1]]),
     "camera/sensor/spectral_weights/0/1", ">= 0"),
    ("channel all zero", dict(spectral_weights=[[1, 1, 1], [0, 0, 0], [1, 1, 1]]),
     "camera/sensor/spectral_weights/1", "weight > 0"),
    ("weights, trichromatic", dict(wavelengths=[600e-9, 530e-9, 450e-9]),
     "camera/sensor/spectral_weights:", "3 lists of K"),
    ("NaN wavelength", dict(wavelengths="NAN"), "camera/sensor/wavelengths/0/1", "NaN"),
    ("Infinity weight", dict(spectral_weights="INF"),
     "camera/sensor/spectral_weights/2/0", "Infinity"),
]


@pytest.mark.parametrize("name,edit,field,words", BAD, ids=[b[0] for b in BAD])
def test_bad_spectral_scene_is_refused(tmp_path, capsys, name, edit, field, words):
    text = json.dumps(_sensor(**edit))
    text = text.replace('"NAN"', "[[5e-7, NaN, 6e-7], [5e-7, 5e-7, 5e-7], [4e-7, 4e-7, 4e-7]]")
    text = text.replace('"INF"', "[[1, 1, 1], [1, 1, 1], [Infinity, 1, 1]]")
    scene = tmp_path / "bad.json"
    scene.write_text(text)
    assert cli.main(["predict", str(scene), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.startswith("difstar: error: ")
    assert f"field {field}" in err and words in err and "give" in err, err
    assert not (tmp_path / "o").exists()
    if "NAN" not in text and "INF" not in text:  # the Python entry point: the same error
        with pytest.raises(SceneError, match=field):
            scene_from_dict(json.loads(text))


# ------------------------------------------------------------ point sources (issue 34)

POINT = {"type": "point", "position": [1e-3, -2e-3], "intensity": [1e-7, 2e-7, 3e-7]}


def point_doc(crop=(32, 32)) -> dict:
    """The paper's focused scene with a point source beside its disc."""
    doc = cli.example_document("paper-focused", crop=crop)
    doc["scene"]["sources"][0]["radius"] = 0.3e-3
    doc["scene"]["sources"].append(copy.deepcopy(POINT))
    return doc


def test_point_sources_load_and_roundtrip():
    camera, scene, _ = scene_from_dict(point_doc())
    disc, point = scene.sources
    assert isinstance(disc, difstar.DiscSource) and isinstance(point, difstar.PointSource)
    np.testing.assert_allclose(point.position, POINT["position"], rtol=1e-15)
    np.testing.assert_allclose(point.intensity, POINT["intensity"], rtol=1e-15)
    doc = scene_to_dict(camera, scene)
    assert doc["scene"]["sources"][1] == {**POINT}
    assert doc["scene"]["sources"][0]["type"] == "disc"
    again = scene_from_dict(doc)[1].sources
    assert [type(s) for s in again] == [difstar.DiscSource, difstar.PointSource]
    # a point's position may be left out (on the axis); a disc's type may be left out
    d = point_doc()
    del d["scene"]["sources"][1]["position"], d["scene"]["sources"][0]["type"]
    s = scene_from_dict(d)[1].sources
    np.testing.assert_array_equal(s[1].position, [0.0, 0.0])
    assert isinstance(s[0], difstar.DiscSource)


BAD_POINTS = [
    ("negative", dict(POINT, intensity=[-1e-7, 1e-7, 1e-7]),
     "field scene/sources/1/intensity/0", ">= 0"),
    ("all zero", dict(POINT, intensity=[0, 0, 0]), "scene.sources[1].intensity", "> 0"),
    ("no intensity", {"type": "point", "position": [0, 0]}, "field scene/sources/1",
     "'intensity' is a required property"),
    ("a radius", dict(POINT, radius=1e-3), "field scene/sources/1", "'radius' was unexpected"),
    ("unknown type", dict(POINT, type="star"), "field scene/sources/1/type",
     "not one of ['disc', 'point']"),
    ("NaN", "NAN", "field scene/sources/1/intensity/0", "not a finite number"),
    ("3-D position", dict(POINT, position=[0, 0, 0]), "field scene/sources/1/position",
     "at most 2"),
    ("a word", dict(POINT, intensity="bright"), "field scene/sources/1/intensity",
     "not of type 'array'"),
    ("a disc with intensity", {"radius": 1e-3, "intensity": [1, 1, 1]},
     "field scene/sources/1", "'intensity' was unexpected"),
]


@pytest.mark.parametrize("name,source,field,words", BAD_POINTS, ids=[b[0] for b in BAD_POINTS])
def test_bad_point_source_is_refused(tmp_path, capsys, name, source, field, words):
    doc = point_doc()
    doc["scene"]["sources"][1] = source
    text = json.dumps(doc).replace('"NAN"', '{"type": "point", "intensity": [NaN, 1, 1]}')
    with pytest.raises(SceneError) as exc:
        scene_from_dict(json.loads(text))
    assert field in str(exc.value) and words in str(exc.value), str(exc.value)
    scene = tmp_path / "bad.json"
    scene.write_text(text)
    assert cli.main(["predict", str(scene), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.startswith("difstar: error: ") and field in err, err
    assert not (tmp_path / "o").exists()


def test_predict_of_a_point_source_scene(tmp_path):
    """A scene file with a point source predicts end to end (the windows sized from it)."""
    doc = point_doc()
    doc["scene"]["sources"] = [dict(POINT, position=[2e-5, 0.0])]
    scene = tmp_path / "point.json"
    scene.write_text(json.dumps(doc))
    assert cli.main(["predict", str(scene), "--out", str(tmp_path / "out")]) == 0
    written = json.loads((tmp_path / "out" / "scene.json").read_text())
    assert written["scene"]["sources"][0]["type"] == "point"


def test_a_detector_blur_in_a_scene_file_loads_roundtrips_and_is_refused_when_wrong():
    """camera.sensor.blur (a jitter and named halos, pixels) is the sensor's difstar.Blur,
    written back the same; predicting through it blurs the image (less peak, the same
    light); a fraction above 1 and two halos of one name are refused naming the field."""
    import equinox as eqx

    doc = cli.example_document("paper-focused", crop=(24, 24))
    doc["scene"]["sources"][0]["radius"] = 0.3e-3
    blur = {"jitter": 1.2, "halos": [{"name": "scatter", "fraction": 0.05, "width": 3.0}]}
    doc["camera"]["sensor"]["blur"] = copy.deepcopy(blur)
    camera, scene, opts = scene_from_dict(copy.deepcopy(doc))
    b = camera.sensor.blur
    assert [type(layer).__name__ for layer in b.layers] == ["Jitter", "Halo"]
    assert float(b.values["scatter"]) == 0.05 and b.reach == 18  # 6 × the 3 px halo
    assert scene_to_dict(camera, scene)["camera"]["sensor"]["blur"] == blur
    sharp = difstar.Camera(camera.lens, difstar.Sensor(
        pixel_pitch=camera.sensor.pixel_pitch, wavelengths=camera.sensor.wavelengths))
    blurred = difstar.Camera(camera.lens, difstar.Sensor(
        pixel_pitch=camera.sensor.pixel_pitch, wavelengths=camera.sensor.wavelengths, blur=b))
    sim = eqx.filter_jit(difstar.simulate)  # compiled: op by op, each took 3x as long
    img = [np.asarray(sim(c, scene, difstar.choose_grid(
        c, scene, crop=(24, 24), raw_only=True)).image) for c in (sharp, blurred)]
    assert img[1].max() < 0.99 * img[0].max()
    np.testing.assert_allclose(img[1].sum(), img[0].sum(), rtol=2e-2)  # the crop's light
    bad = copy.deepcopy(doc)
    bad["camera"]["sensor"]["blur"]["halos"][0]["fraction"] = 1.5
    with pytest.raises(SceneError, match="camera/sensor/blur/halos/0/fraction"):
        scene_from_dict(bad)
    bad = copy.deepcopy(doc)
    bad["camera"]["sensor"]["blur"]["halos"] *= 2
    with pytest.raises(SceneError, match="\\['scatter', 'scatter_width'\\] belong to two"):
        scene_from_dict(bad)
