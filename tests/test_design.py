"""Design API: objectives (values and gradients), constraints, the optimiser loop."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import difstar
from difstar._design import IrisFamily, PSFSetup, convexity_bound, design
from difstar._design_measures import (
    angular_profile,
    bokeh_nonuniformity,
    core_energy,
    halo_anisotropy,
    image_mismatch,
    spike_energy,
    spike_length,
)

F = 50e-3
AREA = math.pi * (F / 16) ** 2  # f/8 open area
FAM = IrisFamily(9, AREA, segments=8)
# 3.917 µm pixels need 2x oversampling at f/8, 550 nm (rule 1: p/q <= λN/2 = 2.2 µm)
SETUP = PSFSetup(wavelength=550e-9, z_focus=F, pixel_pitch=3.917e-6, shape=(32, 32),
                 defocus=F * 24 * 3.917e-6 / (F / 8), defocus_shape=(32, 32),
                 max_radius=FAM.radius_bound())


def _objective(c, rad):
    p = FAM.params(c, radial=rad)
    pu = FAM.pupil(p)
    img = SETUP.focused(pu)
    bok = SETUP.defocused(pu)
    return (halo_anisotropy(img, core_radius=3)
            + spike_energy(img, pu.chord_normal_angles(), core_radius=3, half_width=0.08)
            + 0.1 * bokeh_nonuniformity(bok, radius=SETUP.blur_radius(AREA)))


@pytest.mark.parametrize("c0", [0.0, 0.5])
def test_objective_gradient_matches_finite_differences(c0):
    rad = jnp.asarray(0.01 * np.sin(np.arange(9.0)))
    g = jax.jit(jax.grad(_objective, argnums=(0, 1)))(jnp.asarray(c0), rad)
    assert np.isfinite(float(g[0])) and np.all(np.isfinite(np.asarray(g[1])))
    f = jax.jit(_objective)
    eps = 1e-5
    fd = (f(c0 + eps, rad) - f(c0 - eps, rad)) / (2 * eps)
    np.testing.assert_allclose(float(g[0]), float(fd), rtol=1e-4, atol=1e-9)
    e = jnp.zeros(9).at[4].set(eps)
    fd_r = (f(c0, rad + e) - f(c0, rad - e)) / (2 * eps)
    np.testing.assert_allclose(float(g[1][4]), float(fd_r), rtol=1e-4, atol=1e-9)


def test_fixed_area_reparametrisation_is_exact():
    rng = np.random.default_rng(0)
    for _ in range(5):
        p = FAM.params(rng.uniform(0, 0.8), radial=0.02 * rng.standard_normal(9),
                       angular=0.02 * rng.standard_normal(9))
        pu = FAM.pupil(p)
        np.testing.assert_allclose(float(pu.area()), AREA, rtol=1e-13)
    # and the area's gradient with respect to the shape is zero
    g = jax.grad(lambda c: FAM.pupil(FAM.params(c)).area())(0.3)
    assert abs(float(g)) < 1e-12 * AREA


def test_bounds_roundtrip_and_fixed_leaves():
    """The one bound map (difstar.Param) on a design's PyTree: a round trip returns the
    value; a zero-width range fixes its leaves (value and gradient)."""
    p = FAM.params(0.3, radial=np.linspace(-0.005, 0.005, 9))
    box = difstar.Param(p, True, FAM.bounds(curvature=(0.0, 0.6), radial=0.01))
    q = box.from_unconstrained(box.to_unconstrained())
    np.testing.assert_allclose(q.curvature, 0.3, rtol=1e-12)
    np.testing.assert_allclose(q.radial, p.radial, atol=1e-15)
    np.testing.assert_array_equal(q.angular, 0.0)  # fixed: zero-width range
    g = jax.grad(lambda u: box.from_unconstrained(u).angular.sum())(box.to_unconstrained())
    np.testing.assert_array_equal(g.angular, 0.0)


def test_convexity_bound_is_a_lower_bound():
    c, r, a = 0.6, 0.015, 0.015
    b = convexity_bound(9, max_curvature=c, max_radial=r, max_angular=a)
    assert b > 0
    rng = np.random.default_rng(1)
    for _ in range(20):
        pu = FAM.pupil(FAM.params(c, radial=rng.choice([-r, r], 9),
                                  angular=rng.choice([-a, a], 9)))
        assert float(pu.convexity_margin()) >= b - 1e-12
    with pytest.raises(ValueError, match="non-convex"):
        FAM.bounds(curvature=(0.0, 0.99), radial=0.05)


def test_design_reduces_the_objective_adam_and_bfgs():
    import optax
    import optimistix as optx

    def obj(p):
        img = SETUP.focused(FAM.pupil(p))
        return halo_anisotropy(img, core_radius=3), {"core": core_energy(img, core_radius=3)}

    box = FAM.bounds(curvature=(0.0, 0.6))
    seen = []
    res = design(obj, FAM.params(0.1), constraints=box, optimiser=optax.adam(0.3), steps=4,
                 callback=lambda i, p, v, aux: seen.append(v) and False)
    v = res.history["value"]
    assert len(v) == 5 and len(seen) == 4 and res.history["aux"]["core"].shape == (5,)
    assert v[-1] < v[0] and float(res.best_value) == v.min()
    assert 0 <= float(res.params.curvature) <= 0.6
    res2 = design(obj, FAM.params(0.1), constraints=box,
                  optimiser=optx.BFGS(rtol=1e-6, atol=1e-9), steps=3)
    assert res2.history["value"].min() < res2.history["value"][0]


def test_objectives_on_known_images():
    h = w = 41
    yy, xx = np.mgrid[:h, :w]
    r = np.hypot(yy - h // 2, xx - w // 2)
    iso = jnp.asarray(1.0 / (1 + r**3))
    dirs = jnp.asarray([0.3, 1.5])
    # an isotropic halo has no spike excess and no anisotropy
    assert abs(float(spike_energy(iso, dirs, core_radius=3, half_width=0.1, excess=True))) < 2e-3
    assert float(halo_anisotropy(iso, core_radius=3)) < 1e-12
    # a line along +x (and −x) is a spike at direction 0
    line = iso.at[h // 2, :].add(0.05)
    e0 = spike_energy(line, jnp.asarray([0.0]), core_radius=3, half_width=0.1)
    e1 = spike_energy(line, jnp.asarray([math.pi / 2]), core_radius=3, half_width=0.1)
    assert float(e0) > 3 * float(e1)
    assert float(halo_anisotropy(line, core_radius=3)) > 0.01
    assert float(spike_length(line, jnp.asarray([0.0]), half_width=0.1, level=1e-3)) > 10
    prof = angular_profile(line, core_radius=3, bins=36)
    assert int(np.argmax(np.asarray(prof))) in (0, 18, 35)
    delta = jnp.zeros((h, w)).at[h // 2, w // 2].set(1.0)
    assert float(core_energy(delta, core_radius=1)) == 1.0
    flat = jnp.ones((h, w))
    assert float(bokeh_nonuniformity(flat, radius=10)) < 1e-12
    assert float(bokeh_nonuniformity(flat, radius=10, measure="tv")) == 0.0
    assert abs(float(bokeh_nonuniformity(flat, radius=10, measure="peak"))) < 1e-12
    assert float(image_mismatch(iso, iso, log=True)) == 0.0


def test_spikes_lie_along_the_chord_normals():
    pu = FAM.pupil(FAM.params(0.0))
    img = SETUP.focused(pu)
    d = pu.chord_normal_angles()
    on = spike_energy(img, d, core_radius=3, half_width=0.08, excess=True)
    off = spike_energy(img, d + math.pi / 18, core_radius=3, half_width=0.08, excess=True)
    assert float(on) > 1e-3 and float(off) < -1e-3  # measured 1.8e-3 and -1.8e-3
    # curvature fans the spikes out: less anisotropy at the same open area
    curved = SETUP.focused(FAM.pupil(FAM.params(0.6)))
    assert float(halo_anisotropy(curved, core_radius=3)) < 0.7 * float(
        halo_anisotropy(img, core_radius=3))


# --- L-BFGS-B (jaxopt) in the bounded parameters ------------------------------------------

FAM5 = IrisFamily(5, 1.0)


def _within(box, params) -> bool:
    return all(bool(np.all((np.asarray(lo) <= np.asarray(p)) & (np.asarray(p) <= np.asarray(hi))))
               for lo, hi, p in zip(jax.tree.leaves(box[0]), jax.tree.leaves(box[1]),
                                    jax.tree.leaves(params)))


def test_lbfgsb_reaches_a_bounded_quadratic_optimum_exactly_on_its_bounds():
    # separable quadratic: the bounded optimum is the target clipped to the box (analytic)
    box = FAM5.bounds(curvature=(0.0, 0.6), radial=0.01, angular=0.01, convex=False)
    target = FAM5.params(0.9, radial=[0.02, -0.005, 0.0, 0.003, -0.03],
                         angular=[0.0, 0.001, -0.002, 0.02, -0.01])
    weights = FAM5.params(3.0, radial=np.arange(1.0, 6.0), angular=2.0)

    def obj(p):
        return sum(jnp.sum(w * (a - b) ** 2) for w, a, b in
                   zip(jax.tree.leaves(weights), jax.tree.leaves(p), jax.tree.leaves(target)))

    start = FAM5.params(0.1, radial=0.004, angular=-0.004)
    start_copy = jax.tree.map(np.array, start)
    res = design(obj, start, constraints=box, optimiser="lbfgsb", steps=40)
    want = jax.tree.map(jnp.clip, target, *box)
    for got, w in zip(jax.tree.leaves(res.best_params), jax.tree.leaves(want)):
        np.testing.assert_allclose(got, w, atol=1e-9)
    # the active bounds are hit exactly (a sigmoid map can only approach them) and every
    # iterate kept within the box, with no tolerance
    assert float(res.best_params.curvature) == 0.6
    assert float(res.best_params.radial[0]) == 0.01 and float(res.best_params.radial[4]) == -0.01
    assert float(res.best_params.angular[3]) == 0.01
    assert all(_within(box, p) for p in res.history["params"])
    np.testing.assert_allclose(float(res.best_value), float(obj(want)), rtol=1e-12)
    # the input is not touched; evaluations are counted and grow
    for a, b in zip(jax.tree.leaves(start), jax.tree.leaves(start_copy)):
        np.testing.assert_array_equal(a, b)
    ev = res.history["evaluations"]
    assert ev.shape == res.history["value"].shape and np.all(np.diff(ev) > 0)


def test_lbfgsb_agrees_with_scipy_on_a_coupled_bounded_problem():
    from scipy.optimize import minimize

    # a strictly convex, non-separable objective (in each parameter's fraction of its
    # range) whose bounded optimum has some bounds active and some not; scipy's L-BFGS-B,
    # an independent implementation, on the same function
    rng = np.random.default_rng(3)
    a = rng.standard_normal((11, 11))
    hess = a @ a.T / 11 + 0.5 * np.eye(11)
    centre = rng.uniform(-0.6, 1.6, 11)
    box = FAM5.bounds(curvature=(0.0, 0.6), radial=0.01, angular=0.01, convex=False)

    def flat(p):
        return jnp.concatenate([p.curvature[None], p.radial, p.angular])

    lo0, span = flat(box[0]), flat(box[1]) - flat(box[0])

    def f(x):
        d = (x - lo0) / span - centre
        return 0.5 * d @ hess @ d + 0.1 * jnp.sum(d**4)

    res = design(lambda p: f(flat(p)), FAM5.params(0.2), constraints=box,
                 optimiser="lbfgsb", steps=200)
    lo, hi = np.asarray(flat(box[0])), np.asarray(flat(box[1]))
    ref = minimize(lambda x: float(f(jnp.asarray(x))), np.asarray(flat(FAM5.params(0.2))),
                   jac=lambda x: np.asarray(jax.grad(f)(jnp.asarray(x))), method="L-BFGS-B",
                   bounds=list(zip(lo, hi)), options={"ftol": 1e-15, "gtol": 1e-12})
    assert ref.success
    got = np.asarray(flat(res.best_params))
    np.testing.assert_allclose(got, ref.x, atol=1e-7)
    assert float(res.best_value) <= ref.fun + 1e-12
    active = (np.isclose(ref.x, lo, atol=1e-12, rtol=0) | np.isclose(ref.x, hi, atol=1e-12, rtol=0))
    assert 0 < active.sum() < 11  # the test covers both kinds of parameter
    np.testing.assert_array_equal(got[active], ref.x[active])  # exactly on the bound


@pytest.mark.slow
def test_lbfgsb_recovers_the_iris_of_a_target_starburst():
    # the target is the PSF of a known iris inside the box: the objective's minimum (0) is
    # that iris, whatever difstar's PSF accuracy. (Its parameters are not unique: at a
    # fixed area, moving every vertex out alike with a matching curvature gives the same
    # outline, so the outline is compared.)
    box = FAM.bounds(curvature=(0.0, 0.6), radial=0.015)
    truth = FAM.params(0.35, radial=0.01 * np.sin(1.3 * np.arange(9) + 0.4))
    # the target compiled (run op by op it took 9 s of this test, the fit 20 s)
    target = jax.jit(lambda p: SETUP.focused(FAM.pupil(p)))(truth)

    def match(p):
        return image_mismatch(SETUP.focused(FAM.pupil(p)), target, log=True)

    res = design(match, FAM.params(0.1), constraints=box, optimiser="lbfgsb", steps=60)
    assert float(res.best_value) < 1e-20  # measured 1e-28 after 52 iterations
    got, want = FAM.pupil(res.best_params), FAM.pupil(truth)
    np.testing.assert_allclose(got.outline(), want.outline(), rtol=0,
                               atol=1e-9 * float(want.circumradius))
    np.testing.assert_array_equal(res.best_params.angular, 0.0)  # fixed: zero-width range


def test_lbfgsb_compiles_its_step_once_and_takes_a_jitted_objective():
    traced = []

    def obj(p):
        traced.append(1)  # runs only while tracing
        return jnp.sum((p.radial - 0.02) ** 2) + (p.curvature - 0.3) ** 2, {"c": p.curvature}

    box = FAM5.bounds(curvature=(0.0, 0.6), radial=0.01, convex=False)
    design(obj, FAM5.params(0.0), constraints=box, optimiser="lbfgsb", steps=2)
    n_short = len(traced)
    traced.clear()
    res = design(obj, FAM5.params(0.0), constraints=box, optimiser="lbfgsb", steps=30)
    assert len(res.history["value"]) > 3
    assert len(traced) == n_short  # independent of the steps: compiled, not run in Python
    np.testing.assert_allclose(float(res.best_params.curvature), 0.3, atol=1e-6)
    np.testing.assert_array_equal(res.best_params.radial, 0.01)
    # an objective that is itself jitted, with aux, and a callback
    seen = []
    res = design(jax.jit(obj), FAM5.params(0.0), constraints=box, optimiser="lbfgsb",
                 steps=5, callback=lambda i, p, v, aux: seen.append(i) and False)
    assert res.history["aux"]["c"].shape == res.history["value"].shape
    assert len(seen) == len(res.history["value"]) - 1


def test_bad_optimiser_and_constraints_are_refused_by_name():
    from difstar._design import LBFGSB
    from difstar._validate import InputError

    def obj(p):
        return p.curvature**2

    with pytest.raises(InputError, match=r"optimiser: 'lbfgs' is not a known optimiser; "
                       r"give one of 'adam', 'lbfgsb'"):
        design(obj, FAM5.params(0.1), optimiser="lbfgs", steps=1)
    with pytest.raises(InputError, match=r"optimiser: a int is not an optimiser"):
        design(obj, FAM5.params(0.1), optimiser=3, steps=1)

    class Reparam:
        def constrain(self, u):
            return u

        def unconstrain(self, p):
            return p

    with pytest.raises(InputError, match=r"constraints: L-BFGS-B needs the bounds "
                       r"themselves, \(lower, upper\); got a Reparam"):
        design(obj, FAM5.params(0.1), constraints=Reparam(), optimiser="lbfgsb", steps=1)
    with pytest.raises(InputError, match=r"LBFGSB.history"):
        LBFGSB(history=0)
    with pytest.raises(InputError, match=r"LBFGSB.tol"):
        LBFGSB(tol=-1.0)
    with pytest.raises(InputError, match=r"LBFGSB.first_step"):
        LBFGSB(first_step=0.0)


def test_design_progress_bar_ticks_each_step_and_keeps_the_callback(capsys):
    """``progress="label"``: a bar on stderr, one tick a step, with the objective and the
    parameter that moved most; the user's callback still runs and can still stop it."""
    seen = []

    def stop_at_two(step, params, value, aux):
        seen.append(step)
        return step == 1

    difstar.design(lambda p: jnp.sum((p["a"] - 1.0) ** 2) + p["b"] ** 2,
                   {"a": jnp.zeros(2), "b": jnp.asarray(0.0)}, steps=5,
                   callback=stop_at_two, progress="quadratic")
    err = capsys.readouterr().err
    assert seen == [0, 1]  # stopped by the callback after its second step
    assert "quadratic" in err and "1/5" in err and "moved most: a" in err
    difstar.design(lambda p: jnp.sum(p**2), jnp.ones(2), steps=2)
    assert capsys.readouterr().err == ""
