"""``difstar design`` sweeps (issue 17): many designs measured at once, sharded over
devices; equal to the designs measured one at a time; bad sweeps refused field by field.

Several host CPU devices need ``XLA_FLAGS`` set before JAX starts, so the 4-device check
runs in a child Python that prints its measured differences as JSON.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from difstar import _batch as B
from difstar._design_study import curvature_grid, parse_sweep
from difstar._validate import InputError
from difstar.cli import main

ROOT = Path(__file__).resolve().parents[1]

SWEEP = {
    "designs": [
        {"name": "straight", "curvature": 0.0},
        {"name": "wobbly", "curvature": 0.3, "angular": 0.004,
         "radial": [0.01, -0.01, 0.005, 0.0, 0.0, 0.002, -0.003, 0.0, 0.001]},
        {"name": "disc", "curvature": 1.0},
    ],
    "grid": {"curvature": [0.15, 0.45, 0.6]},
}

CHILD = textwrap.dedent('''
    import json, sys
    import jax, numpy as np
    jax.config.update("jax_enable_x64", True)
    from difstar._design_study import measurer, parse_sweep, study_setup, sweep_designs
    sweep = json.loads(sys.argv[1])
    designs = parse_sweep(sweep, blades=9)
    family, setup, opts = study_setup(blades=9, quick=True)
    # one design at a time, by the study's own measure (compiled once for all six)
    measure_one = measurer(family, setup, opts)
    one = []
    for i in range(len(designs)):
        d = designs[i]
        p = family.params(d["curvature"], radial=d["radial"], angular=d["angular"])
        one.append(measure_one(p)[0])
    out = {"devices": jax.device_count(), "n": len(designs)}
    for d in (1, 4):
        plans = []
        got = sweep_designs(designs, blades=9, quick=True, devices=d, chunk=8,
                            plan_out=plans)["rows"]
        out[f"per_device_{d}"] = plans[0].per_device
        out[f"names_{d}"] = [r["name"] for r in got]
        # relative error, on a scale of at least 1e-4 (measures that are differences of
        # nearly equal numbers, such as a disc's wedge excess, 2e-7, or the area error,
        # 1e-16, carry the rounding of the terms they cancel)
        err = {k: max(abs(r[k] - q[k]) / max(abs(q[k]), 1e-4) for r, q in zip(got, one))
               for k in one[0]}
        out[f"err_{d}"] = max(err.values())
        out[f"worst_{d}"] = max(err, key=err.get)
    out["spread"] = float(np.ptp([q["halo_anisotropy"] for q in one]))
    print("RESULT " + json.dumps(out))
''')


@pytest.mark.slow
def test_sweep_on_1_and_4_host_devices_equals_one_design_at_a_time():
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4 "
               "--xla_cpu_multi_thread_eigen=false")
    env.pop(B.ENV_DEVICES, None)
    limit = 500
    p = subprocess.run([sys.executable, "-c", CHILD, json.dumps(SWEEP)], cwd=ROOT, env=env,
                       capture_output=True, text=True, timeout=limit)
    line = [x for x in p.stdout.splitlines() if x.startswith("RESULT ")]
    assert p.returncode == 0 and line, p.stderr[-3000:]
    r = json.loads(line[-1][7:])
    assert r["devices"] == 4 and r["n"] == 6
    assert r["per_device_1"] == 6 and r["per_device_4"] == 2  # 6 designs padded to 8
    names = ["straight", "wobbly", "disc", "curvature=0.15", "curvature=0.45",
             "curvature=0.6"]
    assert r["names_1"] == names and r["names_4"] == names
    assert r["spread"] > 1e-3  # the designs differ: a mix-up would show
    for d in (1, 4):  # float64 rounding only
        assert r[f"err_{d}"] < 1e-11, r


def _run(argv, capsys):
    try:
        code = main([str(a) for a in argv])
    except SystemExit as exc:  # argparse
        code = exc.code
    return code, capsys.readouterr()


@pytest.mark.slow
def test_sweep_cli_writes_whole_and_never_overwrites_user_files(tmp_path, capsys):
    f = tmp_path / "sweep.json"
    f.write_text(json.dumps({"designs": [{"name": "a", "curvature": 0.2}]}))
    out = tmp_path / "out"
    argv = ["design", "--quick", "--sweep", f, "--sweep-curvature", "0", "0.5", "2",
            "--devices", "1", "--out", out]
    code, cap = _run(argv, capsys)
    assert code == 0, cap.err
    assert "1/3 designs" in cap.err or "3/3 designs" in cap.err  # progress per chunk
    assert sorted(p.name for p in out.iterdir()) == [".difstar-output", "sweep.json",
                                                     "sweep.md"]
    doc = json.loads((out / "sweep.json").read_text())
    assert [r["name"] for r in doc["rows"]] == ["a", "curvature=0", "curvature=0.5"]
    assert doc["devices"] == 1 and doc["config"]["blades"] == 9
    assert doc["rows"][0]["curvature"] == pytest.approx(0.2)
    assert doc["rows"][1]["halo_anisotropy"] > doc["rows"][2]["halo_anisotropy"] > 0
    assert "| a |" in cap.out
    before = (out / "sweep.json").read_bytes()
    code, cap = _run(argv, capsys)  # exists: refused, untouched
    assert code == 2 and "--overwrite" in cap.err and cap.err.count("\n") == 1
    assert (out / "sweep.json").read_bytes() == before
    code, cap = _run(argv + ["--overwrite"], capsys)  # difstar's own folder: replaced
    assert code == 0, cap.err
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep")
    code, cap = _run(argv[:-1] + [mine, "--overwrite"], capsys)
    assert code == 2 and "not made by difstar" in cap.err
    assert sorted(p.name for p in mine.iterdir()) == ["notes.txt"]
    assert not [p for p in tmp_path.iterdir() if "difstar-tmp" in p.name]


BAD = [  # (sweep document, words the one-line error must hold: the field, the fix)
    ({"designs": [{"curvature": float("nan")}]}, ["designs/0/curvature", "finite"]),
    ({"designs": [{"curvature": 1.5}]}, ["designs[0].curvature", "<= 1"]),
    ({"designs": [{"name": "x"}]}, ["designs[0].curvature: missing", "[0, 1]"]),
    ({"designs": [{"curvature": 0.2, "radial": [0.0] * 7}]},
     ["designs[0].radial", "7 values for a 9-blade", "one per vertex"]),
    ({"designs": [{"curvature": 0.2, "radial": [0.0] * 8 + [0.7]}]},
     ["designs[0].radial[8]", "< 0.5"]),
    ({"designs": [{"curvature": 0.2, "curvatrue": 0.1}]},
     ["designs[0].curvatrue: unknown field", "curvature"]),
    ({"designs": [{"name": "a", "curvature": 0.2}, {"name": "a", "curvature": 0.3}]},
     ["designs[1].name", "its own name"]),
    ({"designs": []}, ["no design"]),
    ({"desings": []}, ["desings: unknown field", "designs"]),
    ({"grid": {"curvature": [0.1, -0.2]}}, ["grid.curvature[1]", ">= 0"]),
    ({"grid": {"radial": [0.1]}}, ["grid", '"curvature"']),
    ({"designs": [{"name": "bent", "curvature": 0.9, "radial": [0.3, -0.3] * 4 + [0.3]}]},
     ["design 0 ('bent')", "not convex", "reduce its curvature"]),
    ([1, 2], ["expected a JSON object"]),
]


@pytest.mark.parametrize("doc,words", BAD, ids=[str(i) for i in range(len(BAD))])
def test_bad_sweep_is_refused_naming_the_field(tmp_path, capsys, doc, words):
    f = tmp_path / "sweep.json"
    f.write_text(json.dumps(doc))
    code, cap = _run(["design", "--quick", "--sweep", f, "--out", tmp_path / "out"], capsys)
    err = cap.err.strip().splitlines()[-1]
    assert code == 2 and err.startswith("difstar: error:"), cap.err
    assert "Traceback" not in cap.err
    for w in words:
        assert w in err, (w, err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sweep.json"]


def test_bad_sweep_flags_are_refused(tmp_path, capsys):
    out = tmp_path / "out"
    for argv, words in (
        (["--sweep-curvature", "0.6", "0.1", "3"], ["--sweep-curvature", "LO <= HI"]),
        (["--sweep-curvature", "0", "2", "3"], ["--sweep-curvature HI", "<= 1"]),
        (["--sweep-curvature", "0", "0.5", "2.5"], ["--sweep-curvature N", "integer"]),
        (["--sweep-curvature", "0", "0.5", "0"], ["--sweep-curvature N", ">= 1"]),
        (["--sweep-curvature", "0", "0.5", "2", "--devices", "0"], ["--devices: 0"]),
        (["--sweep-curvature", "0", "0.5", "2", "--chunk", "-1"], ["--chunk", ">= 1"]),
        (["--devices", "1"], ["--devices", "only a sweep"]),
        (["--sweep", tmp_path / "missing.json"], ["missing.json", "cannot read"]),
    ):
        code, cap = _run(["design", "--quick", *argv, "--out", out], capsys)
        err = cap.err.strip()
        assert code == 2 and err.count("\n") == 0 and "Traceback" not in err, (argv, err)
        for w in words:
            assert w in err, (w, err)
        assert not out.exists()
    (tmp_path / "bad.json").write_text("{\"designs\": [")
    code, cap = _run(["design", "--sweep", tmp_path / "bad.json", "--out", out], capsys)
    assert code == 2 and "not valid JSON" in cap.err and not out.exists()


def test_parse_sweep_and_grid():
    d = parse_sweep(SWEEP, blades=9)
    assert [x["name"] for x in d][:3] == ["straight", "wobbly", "disc"]
    assert d[1]["radial"].shape == (9,) and np.all(d[1]["angular"] == 0.004)
    g = curvature_grid("0", "0.6", "4", blades=5)
    assert [x["curvature"] for x in g] == pytest.approx([0, 0.2, 0.4, 0.6])
    assert g[0]["radial"].shape == (5,)
    with pytest.raises(InputError, match=r"^sweep: designs\[0\]\.angular: 3 values"):
        parse_sweep({"designs": [{"curvature": 0, "angular": [0, 0, 0]}]}, blades=5)


def test_sweep_schema_accepts_the_example_and_names_the_fields():
    import jsonschema

    schema = json.loads((ROOT / "data_schemas" / "design_sweep.schema.json").read_text())
    jsonschema.validate(SWEEP, schema)
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate({"designs": [{"curvature": 2}]}, schema)


def test_bad_optimiser_flag_is_refused_before_computing(tmp_path, capsys, monkeypatch):
    import difstar.cli._design as cli

    def reached(*a, **k):
        raise AssertionError("computing started before the input was refused")

    monkeypatch.setattr(cli, "iris_study", reached)
    out = tmp_path / "out"
    code, cap = _run(["design", "--quick", "--optimiser", "bfgs", "--out", out], capsys)
    assert code == 2 and cap.err.count("\n") == 1, cap.err
    assert "--optimiser: 'bfgs' is not one of adam, lbfgsb" in cap.err
    # a sweep optimises nothing: the flag is refused there too
    code, cap = _run(["design", "--quick", "--sweep-curvature", "0", "1", "2", "--optimiser",
                      "lbfgsb", "--out", out], capsys)
    assert code == 2 and "--optimiser: a sweep measures its designs as given" in cap.err
    assert not out.exists()


def test_study_hands_lbfgsb_and_its_bounds_to_design(monkeypatch):
    """iris_study with optimiser="lbfgsb" gives :func:`difstar._design.design` the
    optimiser and the study's boxes: curvature in [0, max_curvature], then the vertices
    within ± vertex_bound (fixed at 0 in the first). That L-BFGS-B then stays within its
    bounds and reaches a bound exactly is tested on ``design`` itself (test_design.py:
    a bounded quadratic, scipy's L-BFGS-B, an iris recovered from its starburst); the
    study end to end runs in notebooks/03 (Adam). Recorded, not computed: two L-BFGS-B
    compilations of the study's objective cost 3 minutes of CI."""
    import types

    import difstar._design as D
    import difstar._design_study as S

    calls = []

    def recorder(objective, start, *, constraints, optimiser, steps, progress):
        assert progress is None  # no progress asked for
        calls.append((constraints, optimiser, steps))
        return types.SimpleNamespace(best_params=start,
                                     history={"value": [1.0], "evaluations": [1]})

    monkeypatch.setattr(D, "design", recorder)
    monkeypatch.setattr(S, "measurer", lambda family, setup, opts: lambda p: (
        {}, np.zeros((2, 2)), np.zeros((2, 2)), np.zeros((3, 2))))
    r = S.iris_study(quick=True, steps=8, optimiser="lbfgsb", max_curvature=0.4,
                     vertex_bound=0.01, log=lambda m: None)
    assert r["config"]["optimiser"] == "lbfgsb" and len(calls) == 2
    ((lo1, hi1), opt1, steps1), ((lo2, hi2), opt2, steps2) = calls  # bounds (lower, upper)
    assert opt1 == opt2 == "lbfgsb" and steps1 == steps2 == 8
    assert float(lo1.curvature) == 0.0 and float(hi1.curvature) == 0.4
    np.testing.assert_array_equal(np.asarray(lo1.radial), 0.0)
    np.testing.assert_array_equal(np.asarray(hi1.radial), 0.0)
    assert float(hi2.curvature) == 0.4
    for part in ("radial", "angular"):
        np.testing.assert_allclose(np.asarray(getattr(lo2, part)), -0.01)
        np.testing.assert_allclose(np.asarray(getattr(hi2, part)), 0.01)


def test_study_progress_names_the_step_the_objective_and_what_moved(monkeypatch, capsys):
    """With ``progress``, each optimisation shows a bar on stderr ticking once a step,
    with the objective and the parameter that moved most since the last step (here the
    vertices' radial deviations, moved by 0.02 against 0.01 for the curvature); quiet
    (``log=None``, no ``progress``), stderr stays empty. The optimiser is a stand-in
    that steps through :func:`difstar._progress.ticking` as ``design`` does."""
    import types

    import difstar._design as D
    import difstar._design_study as S
    from difstar._progress import step_bar, ticking

    def stepping(objective, start, *, constraints, optimiser, steps, progress):
        p = start
        with step_bar(progress, steps) as tick:
            callback = None if tick is None else ticking(None, tick, start)
            for i in range(2):
                p = type(start)(start.curvature + 0.01 * (i + 1),
                                start.radial + 0.02 * (i + 1), start.angular)
                if callback is not None:
                    assert callback(i, p, 0.5 - 0.1 * i, {}) is False  # does not stop it
        return types.SimpleNamespace(best_params=p,
                                     history={"value": [1.0], "evaluations": [1]})

    monkeypatch.setattr(D, "design", stepping)
    monkeypatch.setattr(S, "measurer", lambda family, setup, opts: lambda p: (
        {}, np.zeros((2, 2)), np.zeros((2, 2)), np.zeros((3, 2))))
    S.iris_study(quick=True, steps=2, progress=True)
    err = capsys.readouterr().err
    assert "optimising the curvature" in err and "curvature and vertices" in err
    assert "objective 0.4" in err and "moved most: radial (0.02)" in err
    assert "2/2" in err
    S.iris_study(quick=True, steps=2, log=None)
    assert capsys.readouterr().err == ""
