"""The compiled programs a fit keeps between stages (difstar.fitting._programs): a stage
run again on other values and other data reuses its program and gets the answer a
freshly traced one gives; whatever changes a trace (bounds, the free parameters, the
model, the PSF plan, the target) gets a program of its own; at most MAX_PROGRAMS are
kept. The stars are the independent NumPy generator's of tests/test_fitting.py."""

from __future__ import annotations

import numpy as np
import pytest
from test_fitting import TRUE, _model, _numpy_star

from difstar.fitting import FitData, Param, _programs, _solve, fit


@pytest.fixture(scope="module")
def stars():
    """Two noisy captures of the generator's star (other noise, other σ, one with a
    masked column), and a third star elsewhere."""
    clean = _numpy_star(**TRUE)
    other = _numpy_star(**(TRUE | {"x0": -0.4, "y0": 0.5, "rotation": 2.0, "flux": 700.0}))
    rng = np.random.default_rng(7)
    s1, s2 = 2e-3 * clean.max(), 5e-3 * clean.max()
    mask = np.ones(clean.shape, bool)
    mask[:, 3] = False
    return (FitData.from_array(clean + rng.normal(0, s1, clean.shape), sigma=s1),
            FitData.from_array(clean + rng.normal(0, s2, clean.shape), sigma=s2, mask=mask),
            FitData.from_array(other + rng.normal(0, s1, clean.shape), sigma=s1))


@pytest.fixture()
def traces(monkeypatch):
    """The number of residual functions built (one per program traced anew)."""
    _programs.release_programs()
    count = [0]
    real = _solve._residual_fn

    def counted(*a, **k):
        count[0] += 1
        return real(*a, **k)

    monkeypatch.setattr(_solve, "_residual_fn", counted)
    yield count
    _programs.release_programs()


def _values(res):
    return np.array([res.values[k] for k in ("rotation", "x0", "y0", "flux", "background")])


def test_a_stage_run_again_reuses_its_program_and_sees_the_new_data(stars, traces):
    a, b, c = stars
    stage = [{"free": "all"}]
    model = _model()
    fit(model, a, stages=stage, max_steps=30)
    built = traces[0]
    assert built >= 1
    # other data (σ, mask, star) and another start (a copy of the model, as a rough
    # start makes): the same program, not traced again
    start = model.with_values({"rotation": 1.0, "flux": 600.0})
    again = [fit(start, d, stages=stage, max_steps=30) for d in (b, c)]
    assert traces[0] == built, "a stage of the same shapes was traced again"
    # … and each answer is the one a freshly traced program gives
    for d, res in zip((b, c), again):
        _programs.release_programs()
        fresh = fit(_model().with_values({"rotation": 1.0, "flux": 600.0}), d,
                    stages=stage, max_steps=30)
        np.testing.assert_allclose(_values(res), _values(fresh), rtol=1e-9, atol=1e-9)
        assert res.chi2 == pytest.approx(fresh.chi2, rel=1e-9)
    # the third star's own values, not the first's
    assert again[1].values["rotation"] == pytest.approx(2.0, abs=0.5)
    assert again[1].values["x0"] == pytest.approx(-0.4, abs=0.05)


def test_a_stage_with_other_tolerances_shares_the_program(stars, traces):
    """The solver's tolerances are arguments of its program: a stage with another rtol
    is not traced again, and its answer is the one a freshly traced program with that
    rtol gives (a looser rtol stops no later)."""
    a = stars[0]
    model = _model()
    tight = fit(model, a, stages=[{"free": "all", "rtol": 1e-8}], max_steps=40)
    n = traces[0]
    loose = fit(model, a, stages=[{"free": "all", "rtol": 1e-2}], max_steps=40)
    assert traces[0] == n, "another rtol traced the stage again"
    assert loose.steps <= tight.steps
    _programs.release_programs()
    fresh = fit(_model(), a, stages=[{"free": "all", "rtol": 1e-2}], max_steps=40)
    np.testing.assert_allclose(_values(loose), _values(fresh), rtol=1e-9, atol=1e-9)
    assert loose.steps == fresh.steps


def test_what_changes_a_trace_gets_a_program_of_its_own(stars, traces):
    a = stars[0]
    stage = [{"free": "all"}]
    base = fit(_model(), a, stages=stage, max_steps=30)
    assert base.values["rotation"] == pytest.approx(TRUE["rotation"], abs=0.5)
    n = traces[0]
    # bounds that hold the rotation below the truth: the answer at the new bound
    held = fit(_model(rotation=Param(0.0, True, (-20, 3.0))), a, stages=stage,
               max_steps=30)
    assert traces[0] > n and held.values["rotation"] <= 3.0
    # another set of free parameters
    n = traces[0]
    fit(_model(), a, stages=[{"free": ["x0", "y0", "flux", "background"]}], max_steps=30)
    assert traces[0] > n
    # another model of the same parameters (a wider obstruction): its own program
    n = traces[0]
    wide = fit(_model(obstruction=Param(0.4)), a, stages=stage, max_steps=30)
    assert traces[0] > n and wide.chi2 > base.chi2
    # a spike-profile stage on the same window
    n = traces[0]
    fit(_model(), a, stages=[{"free": ["x0", "y0", "flux", "background"]},
                             {"free": ["rotation"], "spikes": {"r_min": 3, "r_max": 9,
                                                               "n_spikes": 3}}],
        max_steps=30)
    assert traces[0] > n


def test_a_plan_made_for_other_values_that_comes_out_the_same_shares_a_program():
    m = _model()
    key1, _ = _programs.trace_key(m, [FitData.from_array(np.ones((19, 19)), sigma=1.0)],
                                  [_solve._PixelTarget(FitData.from_array(
                                      np.ones((19, 19)), sigma=1.0))])
    d = FitData.from_array(np.ones((19, 19)), sigma=1.0)
    moved = m.with_values({"rotation": 7.0, "x0": 0.3})
    key2, _ = _programs.trace_key(moved, [d], [_solve._PixelTarget(d)])
    assert key1 == key2
    d2 = FitData.from_array(np.ones((21, 19)), sigma=1.0)
    key3, _ = _programs.trace_key(moved, [d2], [_solve._PixelTarget(d2)])
    assert key3 != key1


def test_kept_programs_are_bounded(monkeypatch):
    _programs.release_programs()
    monkeypatch.setattr(_programs, "MAX_PROGRAMS", 2)
    made = [_programs.program(("k", i), lambda i=i: i) for i in range(5)]
    assert made == list(range(5))
    assert len(_programs._PROGRAMS) <= 2
    # a kept one is found, not made again
    assert _programs.program(("k", 4), lambda: "made again") == 4
    _programs.release_programs()
    assert len(_programs._PROGRAMS) == 0


def test_a_spike_stages_errors_come_from_its_solvers_last_linearisation(monkeypatch):
    """The standard error of a spike stage is the one the Jacobian program gives at its
    answer, without compiling that program (the solver's last linearisation, mapped
    from its unconstrained coordinate to degrees)."""
    true = dict(TRUE, rotation=7.3, flux=1e5)
    clean = _numpy_star((41, 41), **true)
    sigma = 1e-4 * clean.max()
    data = FitData.from_array(clean + np.random.default_rng(4).normal(0, sigma, clean.shape),
                              sigma=sigma)
    held = {k: Param(true[k]) for k in ("x0", "y0", "flux", "background")}
    stage = [{"free": ["rotation"], "spikes": {"r_min": 6, "r_max": 20, "n_spikes": 6,
                                               "half_width": 6, "bin_width": 0.5}}]
    jacobians = []
    real = _solve._jacobian
    monkeypatch.setattr(_solve, "_jacobian",
                        lambda *a, **k: jacobians.append(1) or real(*a, **k))
    res = fit(_model(**held), data, stages=stage, max_steps=30)
    spike_errors = res.stages[0]["errors"]
    assert len(jacobians) == 1  # the final errors' only, on all pixels
    # the same stage with the Jacobian program: the same standard error
    monkeypatch.setattr(_solve, "_linearised", lambda *a: None)
    again = fit(_model(**held), data, stages=stage, max_steps=30)
    assert len(jacobians) == 3
    assert again.values["rotation"] == pytest.approx(res.values["rotation"], abs=1e-12)
    assert spike_errors["rotation"] == pytest.approx(again.stages[0]["errors"]["rotation"],
                                                     rel=1e-6)
    assert res.errors["rotation"] == pytest.approx(again.errors["rotation"], rel=1e-6)


def test_the_standard_errors_jacobian_compiles_while_a_hop_runs(monkeypatch):
    """As a procedure's first hop (or repeat) begins, the Jacobian of the standard
    errors at its end is compiled on the background thread, for the shapes the end will
    have: the end runs that program, and the errors are those of the same fit that
    compiled its Jacobian at the end."""
    from difstar._ahead import Ahead
    from difstar.fitting import _procedure

    clean = _numpy_star((21, 21), **TRUE)
    sigma = 1e-3 * clean.max()
    data = FitData.from_array(clean + np.random.default_rng(5).normal(0, sigma, clean.shape),
                              sigma=sigma)
    stages = [{"free": ["x0", "y0", "flux", "background"], "max_steps": 30},
              {"hop": {"name": "x0", "offsets": [-0.4, 0.4], "stages": 1}}]
    model = _model(rotation=Param(TRUE["rotation"]))
    used = []
    real_call = Ahead.__call__

    def spy(self, *args):
        if self.started:  # the program compiled ahead takes these arguments (else raises)
            self._program()(*args)
            used.append(self)
        return real_call(self, *args)

    monkeypatch.setattr(Ahead, "__call__", spy)
    _programs.release_programs()
    ahead = fit(model, data, stages=stages)
    jac = [v[0] for k, v in _programs._PROGRAMS.items() if k[0] == "jacobian"]
    assert len(jac) == 1 and used == jac  # compiled ahead, and the end ran it
    _programs.release_programs()
    monkeypatch.setattr(_procedure, "compile_errors_ahead", lambda *a: None)
    used.clear()
    late = fit(model, data, stages=stages)
    assert used == []
    assert ahead.values == late.values
    for k in ahead.errors:
        assert ahead.errors[k] == pytest.approx(late.errors[k], rel=1e-12), k
