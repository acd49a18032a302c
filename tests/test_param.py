"""difstar.Param and the one bound map (``_param.py``), used by the RAW fit, the image
fit and design: values, bounds, round trips, gradients and refused input."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import difstar
from difstar._design import IrisFamily
from difstar._param import START_MARGIN, bound_map, bound_map_inverse, bound_map_slope
from difstar.raw_fit import Param


def test_the_bound_map_is_the_logistic_and_its_inverse_the_logit():
    # independent truth: the closed forms lo + (hi − lo)/(1 + e^−u) and log(t/(1 − t))
    u = np.linspace(-6, 6, 13)
    np.testing.assert_allclose(np.asarray(bound_map(jnp.asarray(u), 2.0, 5.0)),
                               2.0 + 3.0 / (1.0 + np.exp(-u)), rtol=1e-14)
    x = np.array([2.3, 3.5, 4.9])
    t = (x - 2.0) / 3.0
    np.testing.assert_allclose(bound_map_inverse(x, 2.0, 5.0), np.log(t / (1 - t)),
                               rtol=1e-13)
    # a start on a bound is moved START_MARGIN of the range inside
    np.testing.assert_allclose(bound_map(bound_map_inverse(5.0, 2.0, 5.0), 2.0, 5.0),
                               5.0 - 3.0 * START_MARGIN, rtol=1e-12)


def test_gradient_of_the_map_matches_finite_differences_and_is_finite_far_out():
    f = jax.jit(jax.grad(lambda u: bound_map(u, -1.0, 3.0)))
    for u in (-3.0, 0.0, 2.5):
        fd = (bound_map(u + 1e-6, -1.0, 3.0) - bound_map(u - 1e-6, -1.0, 3.0)) / 2e-6
        np.testing.assert_allclose(float(f(u)), float(fd), rtol=1e-6)
    assert np.isfinite(float(f(800.0))) and np.isfinite(float(f(-800.0)))
    j = jax.jacfwd(lambda u: bound_map(u, np.zeros(3), np.array([1.0, 2.0, 4.0])))(
        jnp.zeros(3))
    np.testing.assert_allclose(np.diag(np.asarray(j)), [0.25, 0.5, 1.0], rtol=1e-14)


def test_the_bound_maps_slope_in_numpy_is_its_derivative_and_never_overflows():
    # independent truth: the logistic's derivative (hi − lo) e^−u / (1 + e^−u)², and
    # JAX's own derivative of the map
    g = jax.jit(jax.grad(lambda u: bound_map(u, -1.0, 3.0)))
    for u in (-30.0, -3.0, 0.0, 2.5, 30.0):
        want = 4.0 * np.exp(-u) / (1.0 + np.exp(-u)) ** 2
        assert bound_map_slope(u, -1.0, 3.0) == pytest.approx(want, rel=1e-14)
        assert bound_map_slope(u, -1.0, 3.0) == pytest.approx(float(g(u)), rel=1e-12)
    with np.errstate(over="raise"):
        assert bound_map_slope(-800.0, -1.0, 3.0) == 0.0
        assert bound_map_slope(800.0, -1.0, 3.0) == 0.0


@pytest.mark.parametrize("value, bounds", [
    (0.7, (0.0, 2.0)),                                           # a number (image fit)
    (np.array([0.1, -0.2, 0.05]), (-0.5, 0.5)),                 # an array (RAW fit)
    (np.array([0.1, 0.2]), (np.array([0.0, 0.1]), np.array([1.0, 0.3]))),
])
def test_round_trip_for_numbers_and_arrays(value, bounds):
    p = Param(value, True, bounds)
    x = p.from_unconstrained(p.to_unconstrained())
    np.testing.assert_allclose(np.asarray(x), value, rtol=1e-12, atol=1e-15)
    assert p.shape == np.shape(value) and p.size == np.size(value)
    assert p.contains(x)


def test_a_design_pytree_with_a_fixed_leaf():
    fam = IrisFamily(7, 1.0)
    start = fam.params(0.2, radial=0.003)
    p = Param(start, True, fam.bounds(curvature=(0.0, 0.5), radial=0.01))
    u = p.to_unconstrained()
    np.testing.assert_array_equal(np.asarray(u.angular), 0.0)  # angular's range is 0 wide
    back = p.from_unconstrained(u)
    np.testing.assert_allclose(float(back.curvature), 0.2, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(back.radial), 0.003, rtol=1e-12)
    g = jax.grad(lambda w: p.from_unconstrained(w).angular.sum())(u)
    np.testing.assert_array_equal(np.asarray(g.angular), 0.0)


def test_unbounded_parameter_moves_by_its_scale():
    p = Param(200.0, True, scale=5.0)
    np.testing.assert_allclose(float(p.from_unconstrained(2.0)), 210.0)
    assert float(p.to_unconstrained(210.0)) == pytest.approx(2.0)
    q = Param(200.0, True)  # default scale: 10 % of |value|
    np.testing.assert_allclose(float(q.from_unconstrained(1.0)), 220.0)


@pytest.mark.parametrize("make, message", [
    (lambda: Param(float("nan")), "value must be finite"),
    (lambda: Param(1.0, True, (2.0, 1.0)), "lo < hi"),
    (lambda: Param(1.0, True, (0.0, float("inf"))), "lo < hi"),
    (lambda: Param(5.0, True, (0.0, 1.0)), "outside its bounds"),
    (lambda: Param(np.zeros(3), True, (np.ones(3), np.zeros(3))), "lo ≤ hi"),
    (lambda: Param(np.ones(2), True, (0.0, np.array([2.0, np.nan]))), "finite"),
    (lambda: Param(1.0, True, (0.0,)), "pair"),
])
def test_bad_parameters_are_refused_by_name(make, message):
    with pytest.raises(difstar.FitInputError, match=message):
        make()


def test_input_arrays_are_not_modified():
    v = np.array([0.1, 0.2])
    lo = np.zeros(2)
    p = Param(v, True, (lo, 1.0))
    p.value[0] = 0.9  # the Param holds its own copies
    assert v[0] == 0.1 and lo[0] == 0.0


def test_both_fit_models_are_forward_models_with_one_interface():
    """The RAW fit's FitModel and the image fit's ImageModel are the two kinds of
    ForwardModel: the free names in the solver's order, the values, the units, and a
    copy at other values (bounds kept; ``free`` leaves only those free) the same way;
    ``FitModel.fixed_at`` fixes every parameter (the truth of a synthetic campaign)."""
    from test_fit import _model

    from difstar._param import ForwardModel
    from difstar.fitting import ImageModel, Light, obstructed_circle_pupil

    raw = _model()
    img = ImageModel(obstructed_circle_pupil(), {
        "rotation": Param(0.0, True, (-5.0, 5.0)), "x0": Param(0.0, True, (-2.0, 2.0))},
        light=Light.monochromatic(3.6e-6))
    for m, name, unit in ((raw, "rotation", "rad"), (img, "rotation", "deg")):
        assert isinstance(m, ForwardModel)
        assert list(m.free) == [k for k, p in m.params.items() if p.free]
        assert set(m.values()) == set(m.params) and m.units[name].startswith(unit)
        keep = [k for k in m.free if k != name]
        moved = m.with_values({name: 0.1}, free=keep)
        assert name not in moved.free and list(moved.free) == keep
        assert float(np.asarray(moved.params[name].value)) == pytest.approx(0.1)
        assert moved.params[name].bounds == m.params[name].bounds
        assert list(m.with_values({name: 0.1}).free) == list(m.free)  # free as it was
    fixed = raw.fixed_at({"rotation": 0.2})
    assert list(fixed.free) == [] and float(fixed.params["rotation"].value) == 0.2
