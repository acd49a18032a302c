"""``difstar fit-image`` (difstar.cli._fit_image) end to end on a manifest of two
captures (an exposure bracket of a disc source, one shared flux) made by the
independent NumPy generator of tests/test_fitting.py: the manifest validates against
its schema, the fit recovers the generator's values, the outputs are written whole,
nothing is overwritten without --overwrite, and bad requests exit 2 with a message."""

from __future__ import annotations

import json
from pathlib import Path

import jsonschema
import numpy as np
import pytest
from test_fitting import LAM, TRUE, P, _numpy_star

from difstar.cli._fit_image import main
from difstar.fitting import ImageModel, Light
from difstar.fitting._model import parameter_unit
from difstar.fitting._parts import BUILDERS

ROOT = Path(__file__).resolve().parents[1]
RADIUS = 1.3  # disc source, data pixels


def _manifest(name, data, stages, **top):
    """A manifest of the generator's star (obstructed circle, struts, at LAM; centre,
    flux and background free), with ``data``, ``stages`` and other top-level keys."""
    return {
        "name": name, "data": data, **top,
        "pupil": {"builder": "circle", "radius": 0.425},
        "light": {"wavelength": LAM},
        "detector": {"pad": 4},
        "accuracy": 3e-3,
        "params": {
            "rotation": TRUE["rotation"], "pixel_scale": P, "obstruction": 0.16,
            "strut_width": 0.06,
            "x0": {"value": 0.0, "free": True, "bounds": [-2, 2]},
            "y0": {"value": 0.0, "free": True, "bounds": [-2, 2]},
            "flux": {"value": 900.0, "free": True, "scale": 100.0},
            "background": {"value": 0.0, "free": True, "scale": 1.0},
        },
        "stages": stages,
    }


@pytest.fixture(scope="module")
def bracket(tmp_path_factory):
    d = tmp_path_factory.mktemp("bracket")
    lin = _numpy_star(**dict(TRUE, background=0.0), disc=RADIUS)
    rng = np.random.default_rng(4)
    caps = []
    for i, t in enumerate((1.0, 4.0)):
        img = t * lin + TRUE["background"]
        sigma = 2e-3 * lin.max()
        np.save(d / f"cap{i}.npy", img + rng.normal(0, sigma, img.shape))
        caps.append({"path": f"cap{i}.npy", "sigma": sigma, "exposure": t})
    man = _manifest("bracket", caps, [{"free": "all", "max_steps": 30}],
                    per_capture=["background"], source="disc")
    man["params"]["source_radius"] = {"value": 1.0, "free": True, "bounds": [0.0, 3.0]}
    path = d / "manifest.json"
    path.write_text(json.dumps(man))
    return path


def test_manifest_validates_against_the_schema(bracket):
    schema = json.loads((ROOT / "data_schemas" / "image_fit_manifest.schema.json").read_text())
    jsonschema.validate(json.loads(bracket.read_text()), schema)
    for m in ("jwst-nircam", "spitzer-irac"):
        jsonschema.validate(json.loads((ROOT / "fit" / m / "manifest.json").read_text()),
                            schema)
    from difstar.fitting._manifest import manifest_document

    variants = sorted((ROOT / "fit").glob("*/variants/*.json"))
    assert variants
    for path in variants:  # as the reader sees them: merged with what they extend
        jsonschema.validate(manifest_document(path)[0], schema)
    typo = json.loads(bracket.read_text())
    typo["stages"][0]["noise_from_residual"] = {"floor": 0.03}  # the fit refuses it too
    with pytest.raises(jsonschema.ValidationError, match="noise_from_residual"):
        jsonschema.validate(typo, schema)


@pytest.mark.slow
def test_fit_image_cli_bracket_end_to_end(bracket, capsys):
    out = bracket.parent / "out"
    assert main([str(bracket), "--out", str(out)]) == 0
    shown = capsys.readouterr()
    assert "stage 0" in shown.err and "step" in shown.err  # progress of the solver's steps
    assert "moved most: " in shown.err  # ... and the parameter each step moved most
    assert "wall time" in shown.out
    res = json.loads((out / "result.json").read_text())
    v = res["values"]
    assert abs(v["x0"] - TRUE["x0"]) < 0.02 and abs(v["y0"] - TRUE["y0"]) < 0.02
    assert abs(v["flux"] / TRUE["flux"] - 1) < 0.01
    assert abs(v["source_radius"] - RADIUS) < 0.05
    assert "background@1" in res["free"] and "flux@1" not in res["free"]
    assert res["chi2_dof"] < 2.0
    assert res["units"].keys() == v.keys() and all(res["units"].values())  # every one
    assert res["units"]["background@1"] == "data units"
    assert np.load(out / "model.npy").shape == (2, 19, 19)
    assert (out / "fit.png").stat().st_size > 10_000
    spikes = res["spike_angles_deg"]  # the model's, one per data spike (null: no peak)
    assert len(spikes["measured_in_model"]) == len(spikes["measured_in_data"])
    assert all(a is None or 0 <= a < 180 for a in spikes["measured_in_model"])
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    # nothing is overwritten without --overwrite; a bracket cannot make fainter copies
    assert main([str(bracket), "--out", str(out), "--quiet"]) == 2
    assert "overwrite" in capsys.readouterr().err
    assert main([str(bracket), "--out", str(bracket.parent / "o2"), "--quiet",
                 "--fainter", "4"]) == 2
    assert "one capture" in capsys.readouterr().err
    assert not (bracket.parent / "o2").exists()
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_console_spike_angles_name_a_missing_peak():
    from difstar.fitting._run import _degrees

    assert _degrees([1.6770, None, 150.4648]) == "1.68°, no peak, 150.46°"


def test_bad_manifests_exit_2_with_the_field_named(tmp_path, capsys):
    bad = tmp_path / "m.json"
    bad.write_text(json.dumps({"data": [], "pupil": {"builder": "circle"},
                               "light": {"wavelength": LAM}, "params": {}}))
    assert main([str(bad), "--out", str(tmp_path / "o")]) == 2
    assert "empty list" in capsys.readouterr().err
    bad.write_text(json.dumps({"data": [{"sigma": 1.0}], "pupil": {"builder": "circle"},
                               "light": {"wavelength": LAM}, "params": {}}))
    assert main([str(bad), "--out", str(tmp_path / "o")]) == 2
    assert "data[0]" in capsys.readouterr().err
    np.save(tmp_path / "img.npy", np.ones((9, 9)))
    bad.write_text(json.dumps({"data": {"path": "img.npy", "sigma": 1.0},
                               "pupil": {"builder": "circle"}, "source": {"file": "x"},
                               "light": {"wavelength": LAM}, "params": {}}))
    assert main([str(bad), "--out", str(tmp_path / "o")]) == 2
    assert "source" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


@pytest.mark.slow
def test_rough_starts_about_the_result(bracket):
    """--robustness 1 --rough-about result: one refit from every free parameter moved
    within ± 20 % of the main fit's value lands back on it."""
    out = bracket.parent / "rough"
    assert main([str(bracket), "--out", str(out), "--quiet", "--robustness", "1",
                 "--rough-about", "result", "--seed", "3"]) == 0
    study = json.loads((out / "robustness.json").read_text())
    main_fit = json.loads((out / "result.json").read_text())["values"]
    (row,) = study["starts"]
    assert study["about"] == "result"
    for k, v in row["start"].items():  # per-capture ones about the first capture's
        ref = main_fit.get(f"{k}@0", main_fit[k])
        assert abs(v - ref) <= 0.2 * abs(ref) + 1e-12, k
    assert row["max_deviation"] < 1.0
    assert "value in the main fit" in (out / "robustness.md").read_text()


@pytest.mark.slow
def test_fainter_copies_end_to_end(tmp_path, capsys):
    """--fainter 4 on one capture with noise in electrons (gain 50): the main fit and the
    copy 4 times fainter both recover the generator's centre, and the copy its flux / 4;
    difstar.fitting.fit_fainter_copy (one copy, from a result folder) fits the same copy."""
    from difstar.fitting import fit_fainter_copy

    lin = _numpy_star((31, 31), **dict(TRUE, background=0.0))
    gain, read = 50.0, 0.05
    rng = np.random.default_rng(7)
    img = lin + TRUE["background"]
    img = img + rng.normal(0, 1, img.shape) * np.sqrt(read**2 + lin / gain)
    np.save(tmp_path / "star.npy", img)
    man = _manifest("one star", {"path": "star.npy", "noise": {"read": read, "gain": gain}},
                    [{"free": "all", "max_steps": 30},
                     {"free": "all", "max_steps": 30, "noise_from_residuals": {"floor": 0.0}}])
    path = tmp_path / "manifest.json"
    # without a noise_from_residuals stage: refused before any fitting, nothing written
    path.write_text(json.dumps(dict(man, stages=man["stages"][:1])))
    assert main([str(path), "--out", str(tmp_path / "o"), "--quiet", "--fainter", "4"]) == 2
    assert not (tmp_path / "o").exists() and "noise_from_residuals" in capsys.readouterr().err
    path.write_text(json.dumps(man))
    out = tmp_path / "out"
    assert main([str(path), "--out", str(out), "--quiet", "--fainter", "4", "--seed", "5"]) == 0
    res = json.loads((out / "result.json").read_text())
    study = json.loads((out / "fainter.json").read_text())
    assert abs(res["values"]["x0"] - TRUE["x0"]) < 0.02
    # the gain, estimated from the faint pixels' residual, scatters from 40 to 99 (10th to
    # 90th percentile over 20 noise draws of this image, with the true model)
    assert 0.4 < res["noise"]["gain"] / gain < 2.5
    (copy,) = study["copies"]
    assert copy["factor"] == 4.0 and study["seed"] == 5
    assert "(fixed)" in (out / "fainter.md").read_text()  # the rotation is held
    assert abs(copy["values"]["x0"] - TRUE["x0"]) < 0.05
    assert abs(copy["values"]["y0"] - TRUE["y0"]) < 0.05
    assert abs(copy["values"]["flux"] / (TRUE["flux"] / 4) - 1) < 0.03
    again = fit_fainter_copy(path, res, np.load(out / "model.npy"), 4.0, 5)
    assert again.values["x0"] == pytest.approx(copy["values"]["x0"], abs=1e-4)
    assert again.values["flux"] == pytest.approx(copy["values"]["flux"], rel=1e-4)


def test_fits_outputs_subtract_from_the_input_fits(tmp_path):
    """A FITS input with a WCS and a window (roi) inside a larger frame: model.fits lies
    in the input's own layout (its rows bottom-up, its full frame, its header and WCS),
    so that the input minus model.fits is residual.fits, whose RMS over the fitted
    pixels / the peak is result.json's residual_rms_over_peak."""
    from astropy.io import fits

    star = _numpy_star(**TRUE)  # 19 × 19, rows down
    frame = np.full((40, 36), TRUE["background"])
    r0, c0 = 13, 7
    frame[r0:r0 + 19, c0:c0 + 19] = star
    hdr = fits.Header({"CTYPE1": "RA---TAN", "CTYPE2": "DEC--TAN", "CRPIX1": 18.0,
                       "CRPIX2": 20.0, "CRVAL1": 150.0, "CRVAL2": 2.0,
                       "CDELT1": -P / 3600, "CDELT2": P / 3600, "BUNIT": "counts"})
    fits.PrimaryHDU(frame[::-1].copy(), header=hdr).writeto(tmp_path / "star.fits")  # FITS
    man = _manifest("fits", {"path": "star.fits", "sigma": 0.01,
                             "roi": [r0, r0 + 19, c0, c0 + 19]},
                    [{"free": "all", "max_steps": 8}])
    (tmp_path / "m.json").write_text(json.dumps(man))
    out = tmp_path / "out"
    assert main([str(tmp_path / "m.json"), "--out", str(out), "--quiet"]) == 0
    res = json.loads((out / "result.json").read_text())
    data = fits.getdata(tmp_path / "star.fits")
    model, mh = fits.getdata(out / "model.fits", header=True)
    resid = fits.getdata(out / "residual.fits")
    assert model.shape == data.shape == resid.shape
    assert mh["CRPIX1"] == 18.0 and mh["CTYPE2"] == "DEC--TAN" and mh["BUNIT"] == "counts"
    assert mh["HIERARCH DIFSTAR ROTATION"] == pytest.approx(res["values"]["rotation"])
    inside = np.isfinite(model)
    assert inside.sum() == 19 * 19
    np.testing.assert_allclose((data - model)[inside], resid[inside], rtol=0, atol=1e-12)
    # the star where the input has it (the rows were not flipped twice, or never)
    assert np.unravel_index(np.nanargmax(model), model.shape) == \
        np.unravel_index(np.argmax(data), data.shape)
    rms = np.sqrt(np.mean(resid[inside] ** 2)) / np.max(data[inside])
    assert rms == pytest.approx(res["residual_rms_over_peak"], rel=1e-9)


@pytest.mark.parametrize("kind", sorted(BUILDERS))
def test_every_parameter_has_a_unit(kind):
    """result.json's "units" and the FITS comments: every parameter any model of a
    builder can have (Zernike terms, a disc source, the response curve, per-capture
    copies) has one, and the documented ones are right (ImageModel's and the builders'
    docstrings: z<j> nm RMS, angles in degrees, lengths in metres, fractions 1)."""
    model = ImageModel(BUILDERS[kind](), {}, light=Light.monochromatic(LAM),
                       zernike=(4, 11), source="disc", response=True,
                       halos=["halo", "diffusion"])
    names = [*model.params, "x0@1", "z4@2", "diffusion@1"]
    assert all(parameter_unit(k, model) for k in names), [
        k for k in names if not parameter_unit(k, model)]
    documented = {"z4": "nm RMS", "z11@2": "nm RMS", "rotation": "deg", "halo": "1",
                  "strut_spread": "deg", "strut_tilt": "deg", "flat_to_flat": "m",
                  "gap": "m", "incoherent": "1", "diffusion": "1", "iris_radius": "m",
                  "radius": "m", "pixel_scale": "arcsec per data px",
                  "diffusion_width": "data px"}
    for k, unit in documented.items():
        assert parameter_unit(k, model).split(",")[0] == unit, k
    with pytest.raises(KeyError, match="no unit for 'bogus'"):
        parameter_unit("bogus")
