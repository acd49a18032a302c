"""Fit manifests: the schema, cross-references and errors that name the file and field."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest

from difstar.io._manifest import load_manifest, manifest_from_dict, roi_origin
from difstar.io._scene import SceneError

CAMPAIGN = Path(__file__).resolve().parents[1] / "fit" / "synthetic-paper-camera" / "manifest.json"

BASE = {
    "camera": {"focal_length": 0.0515, "pixel_pitch": 3.917e-6, "blades": 7},
    "configurations": [{"name": "c", "focus_distance": 1.0, "object_distance": 1.0}],
    "captures": [{"file": "a.dng", "configuration": "c", "source_position": [50, 60]}],
    "parameters": {
        "circumradius": {"free": True, "start": 1.2e-3, "bounds": [1e-3, 1.5e-3]},
        "rotation": {"start": 0.1}, "source_radius": {"start": 5e-4},
        "phi0": {"free": True, "start": [0.1, 0.1, 0.1], "bounds": [0.05, 0.2]},
        "toe": {"start": 0.02}, "knee": {"start": 40},
        "defocus/c": {"free": True, "start": 1e-3, "bounds": [-2e-3, 2e-3]},
    },
}


def _err(doc, match):
    with pytest.raises(SceneError, match=match):
        manifest_from_dict(doc, path="/x/m.json")


def test_campaign_manifest_is_valid():
    man = load_manifest(CAMPAIGN)
    assert len(man.captures) == 10 and set(man.configurations) == {"focused", "defocused"}
    assert man.synthetic is not None
    free = [k for k, p in man.parameters.items() if p["free"]]
    assert {"circumradius", "rotation", "phi0", "toe", "knee", "defocus/defocused"} <= set(free)


def test_defaults_and_shapes():
    man = manifest_from_dict(copy.deepcopy(BASE), path="/x/m.json")
    assert man.captures[0].name == "a" and man.captures[0].path == Path("/x/a.dng")
    assert man.captures[0].roi_size == (128, 128)
    assert man.parameters["toe"]["start"].shape == (3,)
    assert man.parameters["phi0"]["lo"].tolist() == [0.05] * 3
    assert man.noise == {"gain_e_per_dn": 1.0, "read_noise_dn": 2.0}
    assert man.solver["method"] == "lm"


def test_schema_errors_name_the_field():
    d = copy.deepcopy(BASE)
    del d["camera"]["blades"]
    _err(d, r"m\.json: field camera: 'blades' is a required property")
    d = copy.deepcopy(BASE)
    d["parameters"]["rotation"] = {"free": True, "start": 0.1}
    _err(d, r"field parameters/rotation: 'bounds' is a required property")
    d = copy.deepcopy(BASE)
    d["parameters"]["aperture"] = {"start": 1}
    _err(d, r"field parameters")
    d = copy.deepcopy(BASE)
    d["captures"][0]["roi_size"] = [65, 64]
    _err(d, r"field captures/0/roi_size/0")
    d = copy.deepcopy(BASE)
    d["grid"] = {"padding": 1.0, "accuracy": 1e-2}  # two answers to one question
    _err(d, r"field grid")
    d["grid"] = {"accuracy": 0.0}
    _err(d, r"field grid/accuracy")


def test_cross_reference_errors():
    d = copy.deepcopy(BASE)
    d["captures"][0]["configuration"] = "nope"
    _err(d, r"field captures/0/configuration: 'nope' is not one of the configurations")
    d = copy.deepcopy(BASE)
    d["parameters"]["defocus/nope"] = {"start": 0.0}
    _err(d, r"field parameters/defocus/nope: 'nope' is not one of the configurations")
    d = copy.deepcopy(BASE)
    d["parameters"]["phi0"]["start"] = [0.1, 0.1]
    _err(d, r"field parameters/phi0/start: expected a number or an array of shape \[3\]")
    d = copy.deepcopy(BASE)
    d["parameters"]["circumradius"]["start"] = 2e-3
    _err(d, r"field parameters/circumradius/start: .* strictly inside bounds")
    d = copy.deepcopy(BASE)
    d["parameters"]["circumradius"]["bounds"] = [2e-3, 1e-3]
    _err(d, r"field parameters/circumradius/bounds: need lo < hi")
    d = copy.deepcopy(BASE)
    d["captures"].append(dict(d["captures"][0]))
    _err(d, r"field captures/1/name: duplicate capture name 'a'")


def test_synthetic_block_errors():
    d = copy.deepcopy(BASE)
    d["synthetic"] = {"truth": {"circumradius": 1.2e-3}, "frame_size": [128, 128]}
    _err(d, r"field synthetic/truth: missing values for")
    d["synthetic"]["truth"] = {k: v["start"] for k, v in BASE["parameters"].items()}
    d["synthetic"]["truth"]["extra"] = 1.0
    _err(d, r"field synthetic/truth/extra: not a parameter")
    del d["synthetic"]["truth"]["extra"]
    d["captures"][0]["source_position"] = [500, 60]
    _err(d, r"field captures/a/source_position: .* outside the synthetic frame")


def test_unreadable_manifest(tmp_path):
    with pytest.raises(SceneError, match="does not exist"):
        load_manifest(tmp_path / "missing.json")
    p = tmp_path / "bad.json"
    p.write_text("{ not json")
    with pytest.raises(SceneError, match=r"bad\.json: not valid JSON at line 1"):
        load_manifest(p)
    p.write_text(json.dumps(BASE))
    assert load_manifest(p).folder == tmp_path


def test_roi_origin_even_and_inside():
    assert roi_origin((96.4, 97.0), (128, 128), (192, 192)) == (32, 32)
    assert roi_origin((33, 31), (48, 48), (64, 64)) == (8, 6)
    assert roi_origin((5, 190), (64, 64), (192, 192)) == (0, 128)
    r, c = roi_origin((77.0, 51.0), (40, 40), (200, 201))
    assert r % 2 == 0 and c % 2 == 0
    with pytest.raises(ValueError, match="does not fit"):
        roi_origin((10, 10), (64, 64), (32, 32))
    assert np.isfinite(r)


def test_curved_iris_and_zernike_parameters():
    """curvature and z<j> are parameters; a z<j> needs camera.zernike_radius."""
    d = copy.deepcopy(BASE)
    d["parameters"]["curvature"] = {"free": True, "start": 0.4, "bounds": [0.0, 1.0]}
    d["parameters"]["z11"] = {"free": True, "start": 50.0, "bounds": [-200.0, 200.0]}
    _err(d, r"field camera/zernike_radius: the Zernike parameters \['z11'\] need")
    d["camera"]["zernike_radius"] = 1.2e-3
    man = manifest_from_dict(d, path="/x/m.json")
    assert man.parameters["curvature"]["shape"] == () and man.parameters["z11"]["shape"] == ()
    d["parameters"]["z1"] = {"start": 0.0}  # piston is not a parameter
    _err(d, r"field parameters")


def test_a_camera_pupil_builder_and_its_parameters():
    """camera.pupil makes the exit pupil one of the image fit's builders (a mirror lens:
    an obstructed circle with struts); its parameters are fit parameters, circumradius
    and the other iris parameters are refused with it, and required without it."""
    from difstar._fit_run import camera_constants

    d = copy.deepcopy(BASE)
    d["camera"]["pupil"] = {"builder": "circle", "radius": 1.2e-3}
    circ = d["parameters"].pop("circumradius")
    d["parameters"]["obstruction"] = {"free": True, "start": 4e-4, "bounds": [1e-4, 7e-4]}
    d["parameters"]["strut_width"] = {"start": 3e-5}
    man = manifest_from_dict(d, path="/x/m.json")
    assert man.parameters["obstruction"]["shape"] == ()
    assert camera_constants(man).pupil.name == "circle"
    d["parameters"]["circumradius"] = circ
    _err(d, r"field parameters/circumradius: 'circumradius' belongs to the blades iris; a "
         r"camera.pupil builder \('circle'\) has obstruction, radius, strut_width")
    del d["parameters"]["circumradius"]
    d["camera"]["pupil"]["builder"] = "lens"
    _err(d, r"field camera/pupil/builder")
    del d["camera"]["pupil"]
    _err(d, r"field parameters/obstruction")
    d["parameters"].pop("obstruction"), d["parameters"].pop("strut_width")
    _err(d, r"field parameters: the blades iris needs circumradius")


def test_truth_block_for_captures_made_elsewhere():
    d = copy.deepcopy(BASE)
    d["truth"] = {"made_by": "elsewhere", "values": {"circumradius": 1.25e-3, "defocus/c": 0.0011}}
    man = manifest_from_dict(d, path="/x/m.json")
    assert man.synthetic is None and set(man.truth) == {"circumradius", "defocus/c"}
    d["truth"]["values"]["nope"] = 1.0
    _err(d, r"field truth/values/nope: not a parameter")
    d = copy.deepcopy(BASE)
    d["truth"] = {"values": {"circumradius": [1.0, 2.0]}}
    _err(d, r"field truth/values/circumradius")


def test_a_raw_manifest_extends_another_and_keeps_its_captures(tmp_path):
    """``"extends"`` in a RAW-fit manifest: a variant elsewhere changes a few keys, its
    captures are still the base's files (named from the base's folder, even those not
    yet written), and the base is one of its inputs."""
    base = Path(__file__).resolve().parents[1] / "fit" / "curved-iris-raw" / "manifest.json"
    variant = tmp_path / "elsewhere" / "v.json"
    variant.parent.mkdir()
    variant.write_text(json.dumps({"extends": str(base), "name": "fewer steps",
                                   "solver": {"max_steps": 5}}))
    man = load_manifest(variant)
    ref = load_manifest(base)
    assert man.name == "fewer steps" and man.solver["max_steps"] == 5
    assert man.solver["method"] == ref.solver["method"]  # objects merge key by key
    assert [c.path.resolve() for c in man.captures] == [c.path.resolve() for c in ref.captures]
    assert all(c.path.is_file() for c in man.captures)
    assert man.bases == (base,) and ref.bases == ()


def test_the_detectors_blur_parameters_and_their_refusals():
    """jitter and a halo's fraction and width are parameters (the halos declared in
    detector.halos, default one named halo); the camera constants carry the halos; a
    halo that is not declared, a fraction outside [0, 1], a negative jitter or a width
    <= 0 are refused naming the field."""
    from difstar._fit_run import camera_constants

    d = copy.deepcopy(BASE)
    d["parameters"]["jitter"] = {"free": True, "start": 0.5, "bounds": [0.0, 2.0]}
    d["parameters"]["halo"] = {"start": 0.1}
    man = manifest_from_dict(copy.deepcopy(d), path="/x/m.json")
    assert man.parameters["jitter"]["shape"] == () and man.parameters["halo"]["shape"] == ()
    assert [h.name for h in camera_constants(man).halos] == ["halo"]
    d["parameters"]["scatter"] = {"start": 0.1}
    _err(copy.deepcopy(d), r"field parameters/scatter: unknown fit parameter 'scatter'.*"
         r"the halos' are halo, halo_width")
    d["detector"] = {"halos": ["halo", {"name": "scatter", "width": 2.0}]}
    man = manifest_from_dict(copy.deepcopy(d), path="/x/m.json")
    assert [(h.name, h.width) for h in camera_constants(man).halos] == [
        ("halo", 4.0), ("scatter", 2.0)]
    for name, value, match in (("scatter", 1.5, r"must lie in \[0, 1\]"),
                               ("jitter", -0.5, r"must be >= 0"),
                               ("scatter_width", 0.0, r"must be > 0")):
        bad = copy.deepcopy(d)
        bad["parameters"][name] = {"start": value}
        _err(bad, rf"field parameters/{name}/start: .*{match}")
    bad = copy.deepcopy(d)
    bad["detector"]["halos"] = ["halo", "halo"]
    _err(bad, r"field detector/halos: the names \['halo'\] are given twice")


def test_a_spectral_sensor_in_a_raw_manifest():
    """camera.wavelengths as 3 lists of K with camera.spectral_weights (as a scene's
    sensor) reach the camera constants; ragged lists, weights without spectral
    wavelengths and wavelengths in nanometres are refused naming the field."""
    from difstar._fit_run import camera_constants

    d = copy.deepcopy(BASE)
    d["camera"]["wavelengths"] = [[610e-9, 590e-9], [540e-9, 520e-9], [460e-9, 440e-9]]
    d["camera"]["spectral_weights"] = [[1, 1], [1, 2], [2, 1]]
    cc = camera_constants(manifest_from_dict(copy.deepcopy(d), path="/x/m.json"))
    assert cc.wavelengths[1] == (540e-9, 520e-9) and cc.spectral_weights[2] == (2.0, 1.0)
    bad = copy.deepcopy(d)
    bad["camera"]["wavelengths"][0] = [610e-9]
    _err(bad, r"field camera/wavelengths: the channels' lists have 1, 2, 2 wavelengths")
    bad = copy.deepcopy(d)
    bad["camera"]["wavelengths"] = [600e-9, 530e-9, 450e-9]
    _err(bad, r"field camera/spectral_weights: given, but camera/wavelengths has one")
    bad = copy.deepcopy(d)
    bad["camera"]["wavelengths"][2] = [460, 440]
    _err(bad, r"field camera/wavelengths/2/0: 460 is not a wavelength in metres")
