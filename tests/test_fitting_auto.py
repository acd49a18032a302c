"""The stages a fit chooses for itself (difstar.fitting._auto): the rules, checked on
their own, and the procedure run on a star made by the independent NumPy generator from a
rough start, against that generator's truth."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from test_fitting import LAM, TRUE, _model, _numpy_star

from difstar.fitting import (
    FitData,
    FitInputError,
    Noise,
    Param,
    auto_stages,
    fit,
    load_manifest,
)
from difstar.fitting._auto import noise_unknown, resolution_px
from difstar.fitting._stages import _check_fit_inputs


def _data(shape):
    return FitData.from_array(np.ones(shape) + np.eye(*shape), sigma=0.1)


def test_resolution_is_lambda_over_d_in_pixels():
    model = _model()
    d = 2 * model.pupil.max_radius
    assert resolution_px(model) == pytest.approx(LAM / d / (0.4 * math.pi / 648000), rel=1e-12)


def test_without_a_free_rotation_the_core_then_everything():
    model = _model(rotation=Param(TRUE["rotation"]))
    # λ/D is 2 px here: the core's 10 λ/D is capped at half the largest radius
    assert resolution_px(model) == pytest.approx(1.98, abs=0.01)
    st = auto_stages(model, _data((41, 41)))
    assert st == [{"free": ["x0", "y0", "flux", "background"], "half": 10},
                  {"free": "all", "half": None}]
    assert auto_stages(model, _data((17, 17)))[0]["half"] == 4
    # nothing of the core free: no core stage
    held = _model(rotation=Param(0.0), x0=Param(0.0), y0=Param(0.0), flux=Param(1.0),
                  background=Param(0.0), jitter=Param(0.5, True, (0, 2)))
    assert auto_stages(held, _data((101, 101)))[0] == {"free": ["jitter"], "half": 20}
    held = _model(rotation=Param(0.0), x0=Param(0.0), y0=Param(0.0), flux=Param(1.0),
                  background=Param(0.0), obstruction=Param(0.16, True, (0.1, 0.2)))
    assert auto_stages(held, _data((101, 101))) == [{"free": "all", "half": None}]


def test_with_a_free_rotation_scan_spikes_hop_and_repeat():
    model = _model()  # rotation free in (-20, 20)
    data = _data((41, 41))
    st = auto_stages(model, data)
    assert [next(iter(s)) if len(s) == 1 else s["free"] for s in st] == [
        ["x0", "y0", "flux", "background"], "all", ["rotation"], "all", "hop", "repeat"]
    r_edge = 20
    scan = st[1]["scan"]  # before the whole image's stage, the rotation held there
    # the step moves a spike at the window's edge by about a quarter pixel (rounded down
    # to two digits); the range covers the bounds from any start inside them
    arc = scan["step"] * math.pi / 180 * r_edge
    assert 0.2 < arc <= 0.25
    assert scan["half_range"] >= 40 and 2 * scan["half_range"] / scan["step"] < 1000
    assert st[2]["spikes"]["r_min"] == 10 and st[2]["spikes"]["r_max"] == r_edge
    assert st[1]["fix"] == ["rotation"] and st[3]["fix"] == ["rotation"]
    assert st[4]["hop"]["offsets"] == [-2 * scan["step"], 2 * scan["step"]]
    assert st[4]["hop"]["stages"] == 2 and st[5]["repeat"]["stages"] == 2  # the spikes, all
    tol = st[5]["repeat"]["until"]["rotation"]
    assert tol * math.pi / 180 * r_edge == pytest.approx(0.004, rel=0.05)
    # ordinary stages: fit's own checks pass them
    _check_fit_inputs(model, [data], st, starts=None, max_steps=100)
    # an unbounded rotation is scanned over ± 20°
    free_rot = _model(rotation=Param(0.0, True))
    assert auto_stages(free_rot, data)[1]["scan"]["half_range"] == 20.0


def test_sigma_is_estimated_from_the_residual_only_where_the_data_say_nothing_of_it():
    img = _numpy_star((41, 41), **TRUE)
    default = FitData.from_array(img)  # the border's read noise, gain 1, no floor
    assert noise_unknown(default)
    for known in (FitData.from_array(img, sigma=1.0),
                  FitData.from_array(img, noise=Noise(gain=50.0)),
                  FitData.from_array(img, noise=Noise(read=1.0, floor=0.02))):
        assert not noise_unknown(known)
    spike = [s for s in auto_stages(_model(), default) if "spikes" in s][0]
    assert spike["noise_from_residuals"] == {"floor": 0.03, "intensity": "data"}
    assert "noise_from_residuals" not in auto_stages(_model(), _data((41, 41)))[2]


def test_fit_refuses_stages_that_are_neither_a_list_nor_auto():
    with pytest.raises(FitInputError, match="'auto'"):
        fit(_model(), _data((19, 19)), stages="automatic")


def test_a_manifest_without_stages_runs_the_chosen_ones(tmp_path):
    img = _numpy_star((41, 41), **TRUE)
    np.save(tmp_path / "star.npy", img)
    man = {"name": "auto", "data": {"path": "star.npy", "sigma": 1.0},
           "pupil": {"builder": "circle", "radius": 0.425}, "light": {"wavelength": LAM},
           "params": {"rotation": {"value": 0.0, "free": True, "bounds": [-20, 20]},
                      "pixel_scale": 0.4, "x0": {"value": 0.0, "free": True},
                      "y0": {"value": 0.0, "free": True}}}
    (tmp_path / "m.json").write_text(json.dumps(man))
    model, data, opts = load_manifest(tmp_path / "m.json")
    assert opts["stages"] == auto_stages(model, data)
    man["stages"] = "auto"
    (tmp_path / "m.json").write_text(json.dumps(man))
    assert load_manifest(tmp_path / "m.json")[2]["stages"] == opts["stages"]
    man["stages"] = "recipe"
    (tmp_path / "m.json").write_text(json.dumps(man))
    with pytest.raises(FitInputError, match="stages"):
        load_manifest(tmp_path / "m.json")


def test_auto_procedure_recovers_the_independent_star_from_a_rough_start():
    """The NumPy generator's star (struts at 4°, noise 0.2 % of the peak), from a start
    with the rotation 14° off (the scan's job), the centre 0.4 px off and the flux 25 %
    low: the chosen stages end at the generator's values."""
    clean = _numpy_star((41, 41), **TRUE)
    sigma = 2e-3 * clean.max()
    noisy = clean + np.random.default_rng(3).normal(0, sigma, clean.shape)
    data = FitData.from_array(noisy, sigma=sigma)
    model = _model(rotation=Param(TRUE["rotation"] - 14.0, True, (-20, 20)),
                   x0=Param(TRUE["x0"] - 0.4, True, (-2, 2)),
                   y0=Param(TRUE["y0"] + 0.4, True, (-2, 2)),
                   flux=Param(0.75 * TRUE["flux"], True, scale=100.0))
    res = fit(model, data, stages="auto", max_steps=40)
    v, e = res.values, res.errors
    assert [s.get("stage") for s in res.stages if "scan" in s] == [1]
    assert abs(v["rotation"] - TRUE["rotation"]) < max(3 * e["rotation"], 0.05), (v, e)
    assert abs(v["x0"] - TRUE["x0"]) < 0.02 and abs(v["y0"] - TRUE["y0"]) < 0.02
    assert abs(v["flux"] / TRUE["flux"] - 1) < 0.01
    assert res.residual_rms_peak < 5e-3
