"""Bad design sweeps and bad ``difstar design`` arguments (issue 31): refused before
anything is computed, each with one line naming the field (the JSON path, or the flag)
and the fix, exit status 2, no traceback, the inputs unchanged and nothing written.

Every case is refused before a PSF is computed: the study and the sweep's measures are
replaced by functions that fail the test if they are called. Only the convexity check
computes (the outlines of the designs, no PSF).
"""

from __future__ import annotations

import json
import math

import pytest
from test_bad_input import refused, run, snapshot, work  # noqa: F401 - work: a fixture

from difstar._validate import InputError

SWEEP = {"designs": [{"name": "straight", "curvature": 0.0},
                     {"name": "wobbly", "curvature": 0.3,
                      "radial": [0.01, -0.01, 0.005, 0, 0, 0.002, -0.003, 0, 0.001],
                      "angular": 0.004}],
         "grid": {"curvature": [0.15, 0.45]}}


@pytest.fixture
def no_compute(monkeypatch):
    """The study and the sweep's measures fail the test if reached."""
    import difstar._design_study as study
    import difstar.cli._design as cli

    def reached(*a, **k):
        raise AssertionError("computing started before the input was refused")

    for name in ("iris_study", "sweep_designs"):
        monkeypatch.setattr(cli, name, reached)
    for name in ("iris_study", "sweep_designs", "measures_fn"):
        monkeypatch.setattr(study, name, reached)


def _one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    return lines[0]


def _last_line(err: str) -> str:
    """argparse prints its usage first; the error is the last line."""
    return err.strip().splitlines()[-1]


# ------------------------------------------------------------------ sweep files

# (the file's text, what the one-line message must hold: the field and the fix)
BAD_SWEEPS = [
    ('{"designs": [{"curvature": NaN}]}', ["designs/0/curvature", "finite"]),
    ('{"designs": [{"curvature": 0.2, "radial": [0, 0, 0, 0, 0, 0, 0, 0, Infinity]}]}',
     ["designs/0/radial/8", "finite"]),
    ('{"grid": {"curvature": [1e999]}}', ["grid/curvature/0", "finite"]),
    ('{"grid": {"curvature": [123456789012345678901234567890]}}',
     ["grid/curvature/0", "too large"]),
    ('{"designs": [{"curvature": "0.3"}]}', ["designs[0].curvature", "without quotes"]),
    ('{"designs": [{"curvature": 0.3, "angular": "0.1"}]}',
     ["designs[0].angular", "without quotes"]),
    ('{"designs": [{"curvature": true}]}', ["designs[0].curvature", "not a number"]),
    ('{"designs": [{"curvature": null}]}', ["designs[0].curvature", "not a number"]),
    ('{"designs": [{"curvature": 0.2, "name": "  "}]}', ["designs[0].name", "non-empty"]),
    ('{"designs": [{"curvature": 0.2, "name": 7}]}', ["designs[0].name", "string"]),
    ('{"designs": [{"curvature": -0.1}]}', ["designs[0].curvature", ">= 0"]),
    ('{"designs": [{"curvature": 0.2, "angular": 0.5}]}', ["designs[0].angular", "< 0.5"]),
    ('{"designs": [{"curvature": 0.2, "radial": [0.01, 0.02, 0.03]}]}',
     ["designs[0].radial", "3 values for a 9-blade", "--blades"]),
    ('{"designs": [{"curvature": 0.2, "radial": {"0": 0.1}}]}',
     ["designs[0].radial", "not a number"]),
    ('{"designs": [{"curvature": 0.2, "Radial": 0.1}]}',
     ["designs[0].Radial: unknown field", "radial"]),
    ('{"$comment": "fine", "design": [{"curvature": 0.2}]}',
     ["design: unknown field", "designs"]),
    ('{"designs": {"curvature": 0.2}}', ["designs", "list of designs"]),
    ('{"designs": [0.2]}', ["designs[0]", "expected an object"]),
    ('{"designs": []}', ["no design"]),
    ('{}', ["no designs", '"grid"']),
    ('{"grid": {"curvature": []}}', ["grid.curvature", "non-empty"]),
    ('{"grid": {"curvature": 0.3}}', ["grid.curvature", "list"]),
    ('{"grid": {"curvature": [0.3], "radial": [0.1]}}', ["grid", '"curvature"']),
    ('{"designs": [{"name": "curvature=0.5", "curvature": 0.1}], "grid": {"curvature": '
     '[0.5]}}', ["'curvature=0.5'", "its own name"]),
    ('[]', ["expected a JSON object"]),
    ('"designs"', ["expected a JSON object"]),
    ('', ["not valid JSON", "line 1"]),
    ('{"designs": [{"curvature": 0.2},]}', ["not valid JSON"]),
    ('{"designs": ' + "[" * 100 + "]" * 100 + "}", ["nested"]),
]


@pytest.mark.parametrize("text,words", BAD_SWEEPS, ids=[str(i) for i in range(len(BAD_SWEEPS))])
def test_bad_sweep_file_is_refused(work, capsys, no_compute, text, words):
    f = work / "sweep.json"
    f.write_text(text)
    err = refused(["design", "--quick", "--sweep", f, "--out", work / "out"], capsys, work,
                  *words)
    line = _one_line(err)
    assert line.startswith("difstar: error: ") and "sweep.json" in line, line


def test_non_convex_design_is_refused_before_any_psf(work, capsys, no_compute):
    doc = {"designs": [{"name": "ok", "curvature": 0.2},
                       {"name": "wavy", "curvature": 0.8,
                        "radial": [0.35, -0.35, 0.35, -0.35, 0.35, -0.35, 0.35, -0.35, 0.35]}]}
    f = work / "sweep.json"
    f.write_text(json.dumps(doc))
    err = refused(["design", "--quick", "--sweep", f, "--out", work / "out"], capsys, work,
                  "design 1 ('wavy')", "not convex", "reduce its curvature")
    _one_line(err)


def test_sweep_files_that_are_not_json_text(work, capsys, no_compute):
    argv = ["design", "--quick", "--out", work / "out", "--sweep"]
    (work / "bin.json").write_bytes(b"\xff\xfe{\x00")
    _one_line(refused(argv + [work / "bin.json"], capsys, work, "bin.json", "UTF-8"))
    (work / "folder").mkdir()
    _one_line(refused(argv + [work / "folder"], capsys, work, "--sweep", "folder"))
    _one_line(refused(argv + [work / "missing.json"], capsys, work, "--sweep",
                      "missing.json", "does not exist"))


def test_too_many_designs_are_refused_up_front(work, capsys, no_compute, monkeypatch):
    import difstar.cli._design as cli

    _one_line(refused(["design", "--sweep-curvature", "0", "1", "100001", "--out",
                       work / "out"], capsys, work, "--sweep-curvature N", "<= 100000"))
    # the file's designs and the flag's together (the limit made small to keep this cheap)
    monkeypatch.setattr(cli, "MAX_SWEEP_DESIGNS", 10)
    f = work / "sweep.json"
    f.write_text(json.dumps({"grid": {"curvature": [0.05 * k for k in range(6)]}}))
    _one_line(refused(["design", "--sweep", f, "--sweep-curvature", "0.5", "1", "5",
                       "--out", work / "out"], capsys, work, "11 designs", "at most 10"))
    f.write_text(json.dumps({"designs": [{"curvature": 0.1}] * 6,
                             "grid": {"curvature": [0.1, 0.2, 0.3, 0.4, 0.5]}}))
    _one_line(refused(["design", "--sweep", f, "--out", work / "out"], capsys, work,
                      "11 designs", "at most 10"))
    monkeypatch.setattr(cli, "MAX_SWEEP_BYTES", 100)
    f.write_text(json.dumps(SWEEP))
    _one_line(refused(["design", "--sweep", f, "--out", work / "out"], capsys, work,
                      "--sweep", "MiB", "split it"))


def test_a_fine_curvature_grid_has_distinct_names():
    from difstar._design_study import curvature_grid, parse_sweep

    names = [d["name"] for d in curvature_grid("0.1", "0.1001", "11", blades=5)]
    assert len(set(names)) == 11 and names[0] == "curvature=0.1", names
    with pytest.raises(InputError, match=r"grid\.curvature\[2\]: 0\.2 repeats "
                       r"grid\.curvature\[0\]"):
        parse_sweep({"grid": {"curvature": [0.2, 0.3, 0.2]}}, blades=9)


def test_the_sweep_file_is_never_the_output(work, capsys, no_compute):
    (work / "in").mkdir()
    f = work / "in" / "sweep.json"
    f.write_text(json.dumps(SWEEP))
    for out in (work / "in", f):
        _one_line(refused(["design", "--sweep", f, "--out", out, "--overwrite"], capsys,
                          work, "input"))


# (extra arguments after `design --sweep FILE --out OUT`, what the message must hold)
BAD_SWEEP_FLAGS = [
    (["--steps", "5"], ["--steps", "nothing is optimised"]),
    (["--max-curvature", "0.5"], ["--max-curvature", "nothing is optimised"]),
    (["--vertex-bound", "0.01"], ["--vertex-bound", "nothing is optimised"]),
    (["--bokeh-weight", "1"], ["--bokeh-weight", "nothing is optimised"]),
    (["--chunk", "0"], ["--chunk", ">= 1"]),
    (["--chunk", "nan"], ["--chunk", ">= 1"]),
    (["--chunk", "1e400"], ["--chunk", ">= 1"]),
    (["--chunk", "two"], ["--chunk", "not a number"]),
    (["--devices", "0"], ["--devices", ">= 1"]),
    (["--devices", "2.5"], ["--devices", ">= 1"]),
    (["--devices", "1e400"], ["--devices", "finite"]),
    (["--devices", "many"], ["--devices", "not a number"]),
    (["--devices", "100000"], ["--devices", "available"]),
    (["--blades", "4"], ["designs[1].radial", "9 values for a 4-blade"]),
    (["--sweep-curvature", "nan", "1", "3"], ["--sweep-curvature LO", "finite"]),
    (["--sweep-curvature", "0", "2", "3"], ["--sweep-curvature HI", "<= 1"]),
    (["--sweep-curvature", "0.6", "0.2", "3"], ["--sweep-curvature", "LO <= HI"]),
    (["--sweep-curvature", "0", "1", "0"], ["--sweep-curvature N", ">= 1"]),
    (["--sweep-curvature", "0", "1", "-5"], ["--sweep-curvature N", ">= 1"]),
    (["--sweep-curvature", "0", "1", "2.5"], ["--sweep-curvature N", "integer"]),
    (["--sweep-curvature", "0", "1", "1e400"], ["--sweep-curvature N", "finite"]),
    (["--sweep-curvature", "0", "0.45", "2"], ["'curvature=0.45'", "own name"]),
]


@pytest.mark.parametrize("extra,words", BAD_SWEEP_FLAGS,
                         ids=[" ".join(e) for e, _ in BAD_SWEEP_FLAGS])
def test_bad_sweep_flags_are_refused(work, capsys, no_compute, extra, words):
    f = work / "sweep.json"
    f.write_text(json.dumps(SWEEP))
    err = refused(["design", "--quick", "--sweep", f, "--out", work / "out", *extra], capsys,
                  work, *words)
    _one_line(err)


# -------------------------------------------------------------- study arguments

# (arguments after `design --out OUT`, the flag the message must name, more words)
BAD_STUDY_ARGS = [
    (["--f-number", "nan"], "--f-number", []),
    (["--f-number", "inf"], "--f-number", []),
    (["--f-number", "-8"], "--f-number", [">= 1"]),
    (["--f-number", "0"], "--f-number", [">= 1"]),
    (["--f-number", "0.5"], "--f-number", [">= 1"]),
    (["--f-number", "1e9"], "--f-number", ["<= 128"]),
    (["--f-number", "f/8"], "--f-number", ["not a number"]),
    (["--steps", "0"], "--steps", [">= 1"]),
    (["--steps", "-3"], "--steps", [">= 1"]),
    (["--steps", "2.5"], "--steps", ["integer"]),
    (["--steps", "10001"], "--steps", ["<= 10000"]),
    (["--steps", "99999999999999999999999"], "--steps", ["<= 10000"]),
    (["--blades", "2"], "--blades", [">= 3"]),
    (["--blades", "65"], "--blades", ["<= 64"]),
    (["--blades", "9.5"], "--blades", ["integer"]),
    (["--blades", "nan"], "--blades", []),
    (["--max-curvature", "0"], "--max-curvature", ["> 0"]),
    (["--max-curvature", "1.01"], "--max-curvature", ["<= 1"]),
    (["--max-curvature", "nan"], "--max-curvature", []),
    (["--vertex-bound", "-0.01"], "--vertex-bound", [">= 0"]),
    (["--vertex-bound", "0.5"], "--vertex-bound", ["< 0.5"]),
    (["--vertex-bound", "nan"], "--vertex-bound", []),
    (["--bokeh-weight", "-1"], "--bokeh-weight", [">= 0"]),
    (["--bokeh-weight", "inf"], "--bokeh-weight", []),
    (["--bokeh-weight", "1e7"], "--bokeh-weight", ["<= 1e+06"]),
]


@pytest.mark.parametrize("args,flag,words", BAD_STUDY_ARGS,
                         ids=[" ".join(a) for a, _, _ in BAD_STUDY_ARGS])
def test_bad_study_arguments_are_refused(work, capsys, no_compute, args, flag, words):
    err = refused(["design", "--quick", "--out", work / "out", *args], capsys, work, flag,
                  *words)
    assert "Traceback" not in err
    assert flag in _last_line(err) and "error" in _last_line(err), err


# arguments each fine alone, refused together: a box of designs that are not all convex
# (was: the curvature optimised for minutes, then a ValueError naming convex=False)
BAD_STUDY_COMBINATIONS = [
    (["--blades", "12"], ["--vertex-bound: 0.015", "--blades 12", "<= 0.011"]),
    (["--blades", "64"], ["--vertex-bound", "<= 0.00046"]),
    (["--max-curvature", "1", "--vertex-bound", "0.01"], ["--vertex-bound 0", "smaller "
                                                          "--max-curvature"]),
    (["--vertex-bound", "0.4"], ["--vertex-bound: 0.4", "non-convex"]),
    (["--devices", "2"], ["--devices", "only a sweep"]),
    (["--chunk", "4"], ["--chunk", "only a sweep"]),
]


@pytest.mark.parametrize("args,words", BAD_STUDY_COMBINATIONS,
                         ids=[" ".join(a) for a, _ in BAD_STUDY_COMBINATIONS])
def test_bad_study_combinations_are_refused_up_front(work, capsys, no_compute, args, words):
    _one_line(refused(["design", "--quick", "--out", work / "out", *args], capsys, work,
                      *words))


def test_the_suggested_vertex_bound_is_accepted():
    from difstar._design_study import check_study_args

    for blades in (3, 9, 12, 30, 64):
        for mc in (0.2, 0.6, 0.95):
            try:
                check_study_args(blades=blades, max_curvature=mc, vertex_bound=0.45)
            except InputError as exc:
                ok = float(str(exc).split("<= ")[1].split(" ")[0])
                check_study_args(blades=blades, max_curvature=mc, vertex_bound=ok)


# ------------------------------------------------------------------ Python API


def test_python_api_refuses_before_computing():
    from difstar._design import IrisFamily, design
    from difstar._design_study import check_convex, iris_study, parse_sweep, study_setup

    for kw, field in ((dict(blades=12), "vertex_bound"), (dict(f_number=0.5), "f_number"),
                      (dict(f_number=math.inf), "f_number"), (dict(steps=10**6), "steps"),
                      (dict(bokeh_weight=math.nan), "bokeh_weight"),
                      (dict(learning_rate=-1.0), "learning_rate"),
                      (dict(max_curvature=1.0, vertex_bound=0.1), "vertex_bound")):
        with pytest.raises(InputError, match=field):
            iris_study(quick=True, **kw)
    with pytest.raises(InputError, match="f_number"):
        study_setup(f_number=200.0)
    with pytest.raises(InputError, match=r"^sweep: designs\[0\]\.curvature: '0\.3' is a string"):
        parse_sweep({"designs": [{"curvature": "0.3"}]}, blades=9)
    with pytest.raises(InputError, match="blades"):
        parse_sweep(SWEEP, blades=2)
    with pytest.raises(InputError, match=r"designs\[0\]\.curvature: nan is not a finite"):
        parse_sweep({"designs": [{"curvature": math.nan}]}, blades=9)
    designs = parse_sweep({"designs": [{"name": "x", "curvature": 1.0, "radial": 0.2}]},
                          blades=9)
    check_convex(parse_sweep(SWEEP, blades=9), blades=9)  # convex: no error
    with pytest.raises(InputError, match=r"^sweep: design 0 \('x'\): the iris is not convex"):
        check_convex(designs, blades=9)
    for args, field in (((2, 1e-5), "IrisFamily.n"), ((9, -1e-5), "IrisFamily.area"),
                        ((9, math.nan), "IrisFamily.area"), ((65, 1e-5), "IrisFamily.n")):
        with pytest.raises(InputError, match=field):
            IrisFamily(*args)
    fam = IrisFamily(9, 1e-5)
    with pytest.raises(InputError, match="steps"):
        design(lambda p: p.curvature, fam.params(0.1), steps=-1)


def test_the_schema_and_the_checks_agree_on_the_repository_sweep():
    """The sweep of the docs and the schema's example pass both, for their blade count."""
    from difstar._design_study import parse_sweep
    from difstar.io._scene import load_schema

    for doc in (SWEEP, *load_schema("design_sweep")["examples"]):
        assert len(parse_sweep(doc, blades=9)) >= 3
