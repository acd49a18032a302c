"""The RAW fit's procedure (difstar._fit_procedure): the stages a manifest's
solver.stages gives, as the image fit's types; the default one; the checks that refuse a
procedure that cannot be right, naming the stage and field; and a written procedure run
on a small synthetic fit, each solve moving only what it frees."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from test_fit import _model

from difstar import _fit as F
from difstar._fit_procedure import (
    default_procedure,
    procedure_of,
    restart_response_curves,
    run_stages,
)
from difstar.fitting import Hop, Repeat, Restart, Solve
from difstar.io._scene import SceneError

FREE = {"circumradius": (0.8e-3, 1.6e-3), "rotation": (0.0, 0.45),
        "source_offset/c": (-2.0, 2.0), "phi0": (0.005, 0.03), "knee": (5.0, 200.0)}


@pytest.fixture(scope="module")
def small():
    model = _model(FREE)
    fitter = F.Fitter(model)
    pred = fitter.predict(F.to_unconstrained(model))
    names = [c.name for c in model.captures]
    caps = {n: {"zeta": np.asarray(pred["c"][i]), "saturated": np.asarray(pred["c"][i]) >= 1.0,
                "full_scale_dn": 16000.0} for i, n in enumerate(names)}
    return model, fitter, caps


def test_the_default_procedure_is_the_one_the_docs_write(small):
    model, _, _ = small
    written = [{"fix": ["toe", "knee"]}, {"sigma": "prediction"},
               {"restart": {"parameter": "knee", "factors": [0.5, 2]}}]
    assert procedure_of(model, {"stages": written}) == default_procedure(model, {})
    assert default_procedure(model, {"reweight": 2})[1:3] == (Solve(sigma="prediction"),) * 2
    held = _model()  # the knee fixed: no restarts
    assert not any(isinstance(s, Restart) for s in default_procedure(held, {}))


@pytest.mark.parametrize("stages, field", [
    ([], "solver/stages"),
    ([{"restart": {"parameter": "knee"}}], "solver/stages/0: a restart needs a solve"),
    ([{"free": "all"}, {"restart": {"parameter": "toe"}}], "solver/stages/1/restart/parameter"),
    ([{"free": "all"}, {"restart": {"parameter": "knee", "factors": [0]}}],
     "solver/stages/1/restart/factors"),
    ([{"fix": ["knee"]}, {"restart": {"parameter": "knee"}}],
     "solver/stages/1/restart/parameter: knee is held"),
    ([{"free": ["circumradius"], "half": 4}], "solver/stages/0: \\['half'\\] apply to image"),
    ([{"free": ["radius"]}], "solver/stages/0/free: 'radius' is not a parameter"),
    ([{"fix": ["knee"], "free": ["knee"]}], "solver/stages/0: frees no free parameter"),
    ([{"sigma": "model"}], "solver/stages/0/sigma"),
    ([{"free": "all", "max_steps": 0}], "solver/stages/0/max_steps"),
    ([Repeat(until={"rotation": 1e-3})], "solver/stages/0/repeat: .*stages=2"),
    ([{"free": "all"}, {"repeat": {"until": {"radius": 1e-3}, "stages": 1}}],
     "solver/stages/1/repeat: .*until.radius"),
    ([{"free": "all"}, {"hop": {"name": "rotation", "offsets": [0.1], "stages": 2}}],
     "solver/stages/1/hop: .*1 <= stages <= 1"),
    ([{"free": "all"}, {"hop": {"flip": ["radius"], "stages": 1}}],
     "solver/stages/1/hop: .*'radius'"),
    ([{"free": "all"}, {"hop": {"set": {"rotation": "x"}, "stages": 1}}],
     "solver/stages/1/hop/set: rotation must be a finite number"),
])
def test_a_procedure_that_cannot_be_right_is_refused_naming_the_field(small, stages, field):
    model, _, _ = small
    with pytest.raises(SceneError, match=field):
        procedure_of(model, {"stages": stages}, "m.json")
    if stages:  # the loop checks a procedure given to it the same way, before any solve
        with pytest.raises(SceneError, match=field.split(":")[0].replace("solver/", "")):
            run_stages(None, model, {}, {}, None, {}, procedure=stages, verbose=False)


def test_a_written_procedure_moves_only_what_each_solve_frees(small):
    """From a start off in every free parameter: a first solve of φ0 alone holds the
    geometry where it started; a second with φ0 fixed, σ from the prediction, moves the
    rest; a restart of the knee is recorded per channel."""
    model, fitter, caps = small
    start = {k: np.asarray(model.params[k].value) for k in model.free}
    start = start | {"circumradius": start["circumradius"] * 1.02, "rotation": 0.22,
                     "phi0": start["phi0"] * 1.1}
    u0 = F.to_unconstrained(model, start)
    noise = {"gain_e_per_dn": 1.5, "read_noise_dn": 2.5}
    procedure = (Solve(free=["phi0"], max_steps=8),
                 Solve(fix=["phi0"], sigma="prediction", max_steps=30),
                 Restart("knee", (0.5,)))
    solved, records, _ = run_stages(fitter, model, caps, noise, u0, {"max_steps": 30},
                                    procedure=procedure, verbose=False)
    one, two, restarts = records
    assert set(one["held"]) == set(model.free) - {"phi0"} and two["held"] == ["phi0"]
    assert one["label"] == "phi0, σ from the data"
    assert two["label"] == "all free parameters except phi0, σ from the prediction"
    assert [t["parameter"] for t in restarts["tries"]] == ["knee[0]", "knee[1]", "knee[2]"]
    assert two["loss_end"] < one["loss_end"] < one["loss_start"]
    x = F.from_unconstrained(model, solved.u)
    assert abs(float(x["circumradius"]) / float(start["circumradius"]) - 1) > 1e-3  # moved
    # restarting a parameter that is not free tries nothing
    assert restart_response_curves(fitter, _model(), solved, None, {}, parameter="toe",
                                   verbose=False) == (solved, [])
    assert jnp.all(jnp.isfinite(solved.u))


def test_a_raw_hop_keeps_the_try_that_ends_lowest_and_a_repeat_records_its_rounds(small):
    """The one stage loop runs a RAW fit's hops and repeats as an image fit's. With the
    rotation held 0.1 rad off its true value by a solve of φ0 alone, a hop that moves it
    by −0.1 and +0.1 and re-solves φ0 keeps the −0.1 try (back at the truth, where the
    loss is lowest) and records every try; a repeat of two alternating solves records
    each round's values and whether they settled."""
    model, fitter, caps = small
    truth = float(model.params["rotation"].value)
    start = {k: np.asarray(model.params[k].value) for k in model.free} | {
        "rotation": truth + 0.1}
    u0 = F.to_unconstrained(model, start)
    noise = {"gain_e_per_dn": 1.5, "read_noise_dn": 2.5}
    procedure = (Solve(free=["phi0"], max_steps=10),
                 Hop(name="rotation", offsets=(0.1, -0.1), stages=1))
    solved, records, _ = run_stages(fitter, model, caps, noise, u0, {"max_steps": 10},
                                    procedure=procedure, verbose=False)
    first, hop = records[0], records[-1]
    tried = {t["change"]: t["loss"] for t in hop["tried"]}
    assert list(tried) == ["none", "rotation +0.1", "rotation -0.1"]
    assert tried["rotation -0.1"] < tried["none"] < tried["rotation +0.1"]
    assert tried["none"] == pytest.approx(first["loss_end"], rel=1e-12)
    rotation = float(F.from_unconstrained(model, solved.u)["rotation"])
    assert rotation == pytest.approx(truth, abs=1e-9)
    assert solved.loss == pytest.approx(tried["rotation -0.1"], rel=1e-12)
    # a repeat of the last two solves, round after round
    procedure = (Solve(free=["phi0"], max_steps=5), Solve(free=["rotation"], max_steps=5),
                 Repeat(until={"rotation": 1e-6, "phi0": 1e-9}, stages=2, max_rounds=2))
    solved, records, _ = run_stages(fitter, model, caps, noise, u0, {"max_steps": 5},
                                    procedure=procedure, verbose=False)
    rounds = records[-1]["rounds"]
    assert 1 <= len(rounds) <= 2 and set(rounds[0]["values"]) == {"rotation", "phi0"}
    assert len(rounds[0]["values"]["phi0"]) == 3  # one per channel
    assert rounds[-1]["values"]["rotation"] == pytest.approx(
        float(F.from_unconstrained(model, solved.u)["rotation"]), rel=1e-12)
    assert abs(rounds[-1]["values"]["rotation"] - truth) < 1e-3
    assert len(records) == 2 + 2 * len(rounds) + 1  # every re-solve is recorded


@pytest.mark.slow
def test_a_manifests_written_procedure_runs_and_every_free_parameter_has_its_error(tmp_path):
    """The synthetic campaign on 64² regions (a manifest that extends it) with its own
    solver.stages, the second of which holds the response curves, then a hop of the
    rotation that re-runs it, and a jitter held (the detector's blur): the fit runs those
    stages and no others, each grid computes the blur's reach beyond its region, the result
    records the hop and validates against its schema, and the standard errors are every
    free parameter's (the held ones' too, from a Jacobian of all of them at the
    answer)."""
    import json
    from pathlib import Path

    from difstar._fit_run import fit_manifest
    from difstar.io._manifest import load_manifest
    from difstar.io._scene import validate

    root = Path(__file__).resolve().parents[1]
    small = tmp_path / "small.json"
    small.write_text(json.dumps({
        "extends": str(root / "fit" / "synthetic-paper-camera" / "manifest.json"),
        "roi_size": [64, 64],
        "parameters": {"jitter": {"start": 0.3}},  # the detector's blur, held
        "synthetic": {"truth": {"jitter": 0.3}},
        "solver": {"stages": [{"free": "all", "max_steps": 3},
                              {"fix": ["toe", "knee"], "sigma": "prediction",
                               "max_steps": 2},
                              {"hop": {"name": "rotation", "offsets": [0.01], "stages": 1}}]}}))
    res, model, *_ = fit_manifest(load_manifest(small), verbose=False)
    validate(res, "fit_result", source="fit_result.json")
    records = res["convergence"]["stages"]
    labels = [s["label"] for s in records if "label" in s]
    assert labels == ["all free parameters, σ from the data",
                      "all free parameters except toe, knee, σ from the prediction",
                      "all free parameters except toe, knee, σ from the prediction "
                      "(again, σ as it was)"]
    assert records[1]["held"] == ["toe", "knee"]
    assert all(c.grid.blur_reach == 2 for c in model.configs)  # 6 × 0.3 px
    assert res["parameters"]["jitter"]["value"] == 0.3
    assert [t["change"] for t in records[-1]["tried"]] == ["none", "rotation +0.01"]
    for name in model.free:
        se = np.asarray(res["parameters"][name]["stderr"])
        assert np.all(np.isfinite(se)) and np.all(se > 0), (name, se)
