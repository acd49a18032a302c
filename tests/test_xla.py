"""difstar._xla: the compiler options of the solvers' programs.

The options change how XLA generates code, never what it computes: a solve compiled
with them must end where a solve compiled without them ends (float64, to rounding),
and a jaxlib that does not know them must compile as usual instead of failing."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from difstar import _lm, _xla


@pytest.fixture
def fresh_options():
    _xla.solver_jit_options.cache_clear()
    yield
    _xla.solver_jit_options.cache_clear()


def test_on_a_cpu_the_solver_programs_use_the_older_fusion_code_generator(fresh_options):
    """... and no YNNPACK fusions."""
    if jax.default_backend() != "cpu":
        assert _xla.solver_jit_options() == {}
        return
    assert _xla.solver_jit_options() == {"compiler_options": _xla.SOLVER_CPU_OPTIONS}


def test_an_option_this_jaxlib_does_not_know_falls_back_to_plain_compiles(
        fresh_options, monkeypatch):
    monkeypatch.setattr(_xla, "SOLVER_CPU_OPTIONS", {"xla_no_such_option_here": True})
    assert _xla.solver_jit_options() == {}


def test_an_unknown_option_is_left_out_and_the_known_ones_kept(fresh_options, monkeypatch):
    monkeypatch.setattr(_xla, "SOLVER_CPU_OPTIONS", {"xla_no_such_option_here": True,
                                                     "xla_cpu_use_fusion_emitters": False})
    if jax.default_backend() == "cpu":
        assert _xla.solver_jit_options() == {
            "compiler_options": {"xla_cpu_use_fusion_emitters": False}}


def test_with_the_options_a_product_summed_under_vmap_is_computed_right(fresh_options):
    """A product of a (14, 13122) array with a batch of 5 such, summed over its 14
    rows, under jit and vmap, in float32, against NumPy: jaxlib 0.10.2's YNNPACK fusion
    got this wrong (by about the values themselves; jax#39103), which the options turn
    off."""
    rng = np.random.default_rng(0)
    v = rng.random((5, 14, 13122)).astype(np.float32)
    c = rng.random((14, 13122)).astype(np.float32)
    f = jax.jit(jax.vmap(lambda v, c: jnp.sum(c * v, axis=0), in_axes=(0, None)),
                **_xla.solver_jit_options())
    want = np.einsum("bgn,gn->bn", v.astype(float), c.astype(float))
    np.testing.assert_allclose(f(v, c), want, rtol=1e-5)


def test_a_jax_whose_jit_takes_no_compiler_options_falls_back_too(fresh_options,
                                                                 monkeypatch):
    plain_jit = jax.jit

    def old_jit(fn, **kwargs):
        if "compiler_options" in kwargs:
            raise TypeError("jit() got an unexpected keyword argument 'compiler_options'")
        return plain_jit(fn, **kwargs)

    monkeypatch.setattr(jax, "jit", old_jit)
    if jax.default_backend() == "cpu":
        assert _xla.solver_jit_options() == {}


def _decay_fit(monkeypatch, options):
    """A three-parameter exponential decay fitted to 60 exact samples from (0, 0, 0)."""
    monkeypatch.setattr(_lm, "solver_jit_options", lambda: options)
    t = jnp.linspace(0.0, 3.0, 60)
    truth = 2.0 * jnp.exp(-1.3 * t) + 0.25

    def residuals(u, y):
        return u[0] * jnp.exp(-u[1] * t) + u[2] - y

    sol = _lm.LMStepper(residuals, rtol=1e-12, atol=1e-12).solve(
        jnp.zeros(3), truth, max_steps=200, ftol=1e-14)
    return np.asarray(sol.u), sol.result


def test_a_solve_compiled_with_the_options_ends_where_one_without_them_ends(monkeypatch):
    jax.config.update("jax_enable_x64", True)
    on_cpu = jax.default_backend() == "cpu"
    with_options, r1 = _decay_fit(
        monkeypatch, {"compiler_options": dict(_xla.SOLVER_CPU_OPTIONS)} if on_cpu else {})
    without, r2 = _decay_fit(monkeypatch, {})
    assert r1 == r2 == "converged"
    # the independent truth: the parameters the samples were made with
    np.testing.assert_allclose(with_options, [2.0, 1.3, 0.25], rtol=1e-9)
    np.testing.assert_allclose(with_options, without, rtol=1e-12, atol=1e-14)


_CHILD = """
import os, sys
import numpy as np
import difstar
import jax, jax.numpy as jnp
v = np.random.default_rng(0).random((5, 14, 13122)).astype(np.float32)
c = np.random.default_rng(1).random((14, 13122)).astype(np.float32)
f = jax.jit(jax.vmap(lambda v, c: jnp.sum(c * v, axis=0), in_axes=(0, None)))
err = np.abs(np.asarray(f(v, c)) - np.einsum("bgn,gn->bn", v.astype(float), c.astype(float)))
print(repr(os.environ.get("XLA_FLAGS", "")), float(err.max() / 14))
"""


def _child(**env):
    import os
    import subprocess
    import sys

    run = dict(os.environ, **env)
    for k in ("XLA_FLAGS", _xla.KEEP_FLAGS_ENV):
        if k not in env:
            run.pop(k, None)
    out = subprocess.run([sys.executable, "-c", _CHILD], env=run, capture_output=True,
                         text=True, check=True, timeout=300).stdout.split()
    return out[0], float(out[1])


def _in_range():
    import jaxlib

    lo, hi = _xla.YNN_JAXLIBS
    return lo <= tuple(int(p) for p in jaxlib.__version__.split(".")[:3]) < hi


@pytest.mark.skipif(jax.default_backend() != "cpu",
                    reason="YNNPACK fusions are XLA's CPU backend's: on a GPU there is "
                    "nothing to turn off")
def test_import_difstar_turns_off_the_ynn_fusions_so_a_users_jit_is_right_too():
    """``import difstar`` (before any JAX computation) adds the flag to XLA_FLAGS where
    jaxlib is one that fuses with YNNPACK by default; a plain ``jax.jit`` of the
    product that jaxlib 0.10.2 got wrong then agrees with NumPy (float32's rounding of
    a sum of 14 products). DIFSTAR_KEEP_XLA_FLAGS leaves XLA_FLAGS alone, and a flag
    the user set is kept as it is."""
    flags, err = _child()
    if _in_range():
        assert _xla.YNN_OFF_FLAG in flags
    assert err < 1e-5
    flags, _ = _child(**{_xla.KEEP_FLAGS_ENV: "1"})
    assert _xla.YNN_OFF_FLAG not in flags
    flags, _ = _child(XLA_FLAGS="--xla_cpu_experimental_ynn_fusion_type=reduce")
    assert flags.count("ynn_fusion_type") == 1 and "=reduce" in flags


def test_the_flag_is_added_once_and_only_before_jax_starts(monkeypatch):
    from jax._src import xla_bridge

    monkeypatch.setattr(xla_bridge, "backends_are_initialized", lambda: False)
    env = {"XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
    assert _xla.turn_off_ynn_fusions(env) == _in_range()
    if _in_range():
        assert env["XLA_FLAGS"] == ("--xla_force_host_platform_device_count=2 "
                                    + _xla.YNN_OFF_FLAG)
    assert not _xla.turn_off_ynn_fusions(env)  # already there
    monkeypatch.setattr(xla_bridge, "backends_are_initialized", lambda: True)
    assert not _xla.turn_off_ynn_fusions({})  # too late: XLA read its flags
