"""The one solver loop (difstar._lm): its stopping rule, and a solve to a known
minimum."""

import jax
import jax.numpy as jnp
import numpy as np

from difstar._lm import MAX_REJECTED, LMStepper, StopRule, with_batched_jacobian


def test_rejections_at_the_start_do_not_stop_a_solve():
    rule = StopRule(1e-6)
    assert not rule.update(10.0, 1)  # the start, accepted
    for _ in range(5):  # the trust region shrinks: rejected, the loss stays
        assert not rule.update(10.0, 1)
    assert not rule.update(5.0, 2)


def test_plateau_over_accepted_steps_and_a_run_of_rejections_stop():
    rule = StopRule(1e-6)
    stops = [rule.update(loss, k) for k, loss in
             enumerate([10.0, 5.0, 5.0 - 1e-7, 5.0 - 2e-7, 5.0 - 3e-7], start=1)]
    assert stops[-1] and not any(stops[:-1])
    rule = StopRule(1e-6)
    rule.update(10.0, 1)
    rule.update(5.0, 2)
    stops = [rule.update(5.0, 2) for _ in range(MAX_REJECTED)]
    assert stops[-1] and not any(stops[:-1])


def test_solve_reaches_the_rosenbrock_minimum():
    jax.config.update("jax_enable_x64", True)

    def fn(u, _):
        return jnp.stack([10.0 * (u[1] - u[0] ** 2), 1.0 - u[0]])

    res = LMStepper(fn, rtol=1e-10, atol=1e-12).solve(jnp.array([-1.2, 1.0]), None,
                                                         max_steps=200, ftol=1e-14)
    assert res.result == "converged"
    np.testing.assert_allclose(np.asarray(res.u), [1.0, 1.0], atol=1e-6)
    assert res.loss < 1e-12 and res.loss_start > 1.0


def test_a_rejected_gauss_newton_step_is_shortened_until_one_is_accepted():
    """Many residuals (a loss of 10⁴–10⁵ at the start, so JᵀJ ≈ 10⁵) of a wiggly misfit
    in one parameter: the Gauss–Newton step from the start overshoots into a higher
    loss. Each rejection must shorten the next step to at most half its length
    (difstar._lm.ShrinkingTrustRegion): the solve leaves the start and ends where the
    loss's derivative, by central differences of the residuals in float64, is zero
    (< 1e-4 of the start's), at a loss far below the start's. optimistix's own
    update quarters 1/λ from 1, which leaves the step as it was until λ reaches JᵀJ:
    the same test with it stops at the start after ten rejections."""
    jax.config.update("jax_enable_x64", True)
    x = jnp.linspace(-1.0, 1.0, 200)

    def fn(u, _):
        return 30.0 * (jnp.sin(3.0 * (u[0] - 0.7)) + 0.2 * jnp.sin(40.0 * u[0])) * (1 + 0.1 * x)

    def loss(u):
        return 0.5 * float(np.sum(np.asarray(fn(jnp.asarray([u]), None)) ** 2))

    def slope(u, h=1e-6):
        return (loss(u + h) - loss(u - h)) / (2 * h)

    stepper = LMStepper(fn, rtol=1e-8, atol=1e-10)
    res = stepper.solve(jnp.asarray([0.0]), None, max_steps=100, ftol=1e-12)
    assert res.result == "converged" and res.accepted > 1
    u = float(res.u[0])
    assert u != 0.0 and res.loss < 0.8 * loss(0.0)
    assert abs(slope(u)) < 1e-4 * abs(slope(0.0)), (u, slope(u), slope(0.0))
    assert abs(res.loss - loss(u)) < 1e-9 * loss(u)


def test_aux_of_the_answer_rides_with_the_batched_jacobian():
    """A solve whose residuals carry an aux (values made on the way, not differentiated):
    the result's aux is the aux at its answer, and the batched Jacobian with the aux is
    jax.jacfwd's of the residuals alone."""
    t = jnp.linspace(0.0, 1.0, 40)
    data = 3.0 * jnp.exp(-1.7 * t) + 0.5

    def raw(u, args):
        shape = jnp.exp(-u[0] * t)
        a = jnp.stack([shape, jnp.ones_like(t)], axis=1)  # amplitude, offset: closed form
        beta = jnp.linalg.solve(a.T @ a, a.T @ args)
        return a @ beta - args, beta

    fn = jax.jit(with_batched_jacobian(raw, has_aux=True, batch=1))
    u0 = jnp.asarray([0.5])
    r, beta = fn(u0, data)
    assert np.allclose(r, raw(u0, data)[0]) and np.allclose(beta, raw(u0, data)[1])
    jac = jax.jacfwd(lambda u: fn(u, data)[0])(u0)
    assert np.allclose(jac, jax.jacfwd(lambda u: raw(u, data)[0])(u0), rtol=1e-10)
    sol = LMStepper(fn, has_aux=True, rtol=1e-10, atol=1e-12).solve(u0, data, max_steps=50)
    assert abs(float(sol.u[0]) - 1.7) < 1e-6
    assert np.allclose(sol.aux, raw(sol.u, data)[1], rtol=1e-10)
    assert np.allclose(sol.aux, [3.0, 0.5], rtol=1e-6)


def _blocks(u, t):
    # three blocks (stars) of 5 residuals each: block c is u0 exp(-u1 t) + u[2 + 2c] t
    # + u[3 + 2c], and a 2-vector output per block (its mean and its first value)
    rs, firsts = [], []
    for c in range(3):
        r = u[0] * jnp.exp(-u[1] * t) + u[2 + 2 * c] * t + u[3 + 2 * c] * (c + 1.0)
        rs.append(r)
        firsts.append(jnp.stack([jnp.mean(r), r[0]]))
    return jnp.concatenate(rs), firsts


def test_blocks_of_the_batched_jacobian_equal_the_analytic_jacobian():
    """``blocks``: 2 shared parameters and 2 per block over 3 blocks computed in 4
    compressed directions (not 8); every column is the closed form's, the rows of other
    blocks exactly 0, for a flat residual and for a list of per-block outputs."""
    t = jnp.linspace(0.0, 1.0, 5)
    owners = [-1, -1, 0, 0, 1, 1, 2, 2]
    rows = (np.repeat(np.arange(3), 5), [np.int32(c) for c in range(3)])
    fn = jax.jit(with_batched_jacobian(_blocks, batch=2, blocks=(owners, rows)))
    u0 = jnp.asarray([1.3, 0.7, 0.2, -0.4, 0.5, 0.1, -0.3, 0.9])
    jac_r, jac_f = jax.jacfwd(lambda u: fn(u, t))(u0)
    e = jnp.exp(-u0[1] * t)
    want = np.zeros((15, 8))
    for c in range(3):
        want[5 * c:5 * c + 5, 0] = e
        want[5 * c:5 * c + 5, 1] = -u0[0] * t * e
        want[5 * c:5 * c + 5, 2 + 2 * c] = t
        want[5 * c:5 * c + 5, 3 + 2 * c] = c + 1.0
    np.testing.assert_allclose(jac_r, want, rtol=1e-12, atol=0)
    for c in range(3):
        np.testing.assert_allclose(jac_f[c][1], want[5 * c], rtol=1e-12, atol=0)
        np.testing.assert_allclose(jac_f[c][0], want[5 * c:5 * c + 5].mean(0), rtol=1e-12,
                                   atol=1e-15)
    # a parameter said to be block 0's that moves block 1 too is the caller's error: the
    # compressed Jacobian then differs (the test can fail)
    bad = jax.jit(with_batched_jacobian(lambda u, t: _blocks(u, t)[0], batch=2,
                                        blocks=([-1, 0, 0, 0, 1, 1, 2, 2], rows[0])))
    assert not np.allclose(jax.jacfwd(lambda u: bad(u, t))(u0), want)


def test_compressed_jacobian_under_jit_and_vmap_equals_the_matrix():
    """A linear residual A u whose matrix has a block structure (two blocks of 6561
    rows, 12 shared columns and 2 per block: 14 compressed directions), its rows in
    blocks one after the other and, again, interleaved: the linearisation that
    :func:`with_batched_jacobian` keeps (the directions' derivatives, weighted by the
    tangent on each block's rows) applied to 5 directions at once under ``jit`` and
    ``vmap``, and its transpose, against A itself (NumPy's products in float64), to
    float32's rounding: in float32, at these sizes, jaxlib 0.10.2's CPU compiler
    computed a product summed over the directions wrongly (and slowly) under ``vmap``
    (its YNNPACK fusion); the rule contracts over them instead."""
    rng = np.random.default_rng(5)
    owners = np.array([0, 1, 0, 1] + [-1] * 12)
    for rows in (np.repeat(np.arange(2), 6561), np.tile(np.arange(2), 6561)):
        a = rng.normal(size=(rows.size, owners.size))
        own = owners >= 0
        a[:, own] *= rows[:, None] == owners[own][None, :]  # a star's columns on its rows
        mat = jnp.asarray(a, jnp.float32)
        fn = with_batched_jacobian(lambda u, _: mat @ u, blocks=(owners, rows))
        u0 = jnp.asarray(rng.normal(size=owners.size), jnp.float32)
        seeds = rng.normal(size=(5, owners.size)).astype(np.float32)
        r = rng.normal(size=rows.size).astype(np.float32)

        @jax.jit
        def both(u, seeds, r):
            lin = jax.linearize(lambda v: fn(v, None), u)[1]
            return jax.vmap(lin)(seeds), jax.linear_transpose(lin, u)(r)[0]

        jv, jtr = both(u0, jnp.asarray(seeds), jnp.asarray(r))
        a32 = a.astype(np.float32).astype(float)
        np.testing.assert_allclose(jv, seeds.astype(float) @ a32.T, rtol=0, atol=1e-5)
        np.testing.assert_allclose(jtr, a32.T @ r.astype(float), rtol=0, atol=1e-3)


def test_a_solve_on_block_normal_equations_reaches_the_dense_minimum():
    """A Levenberg–Marquardt solve on the normal equations of a Jacobian with a block
    structure (:class:`NormalDescent`) reaches the dense QR solve's minimum of a
    nonlinear three-block problem, in float64; its last state holds the normal
    equations of its last accepted point (the stopping rule's Gauss–Newton gain reads
    them there after a rejected step), equal to the dense JᵀJ and Jᵀr at that point."""
    from difstar._normal_equations import BlockColumns, normal_equations

    owners = [-1, -1, 0, 0, 1, 1, 2, 2]
    rows = np.repeat(np.arange(3), 5)
    structure = BlockColumns.of((owners, rows))
    rng = np.random.default_rng(3)
    t = jnp.linspace(0.0, 1.0, 5)
    truth = np.array([1.3, 0.7, 0.2, -0.4, 0.5, 0.1, -0.3, 0.9])
    data = _blocks(jnp.asarray(truth), t)[0] + 0.01 * jnp.asarray(rng.normal(size=15))

    def residual(u, t):
        return _blocks(u, t)[0] - data

    fn = jax.jit(with_batched_jacobian(residual, batch=2, blocks=(owners, rows)))
    u0 = jnp.asarray([0.8, 1.5, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    plain = LMStepper(fn, rtol=1e-12, atol=1e-14).solve(u0, t, max_steps=200, ftol=1e-15)
    blocked = LMStepper(fn, rtol=1e-12, atol=1e-14, structure=structure).solve(
        u0, t, max_steps=200, ftol=1e-15)
    assert plain.result == blocked.result == "converged"
    # the same minimum, to where each solve's stopping rule left it (the parameters'
    # noise-limited errors here are about 1e-2)
    np.testing.assert_allclose(blocked.u, plain.u, rtol=0, atol=1e-6)
    assert abs(blocked.loss - plain.loss) <= 1e-10 * plain.loss
    jac = np.asarray(jax.jacfwd(lambda u: residual(u, t))(blocked.u))
    r = np.asarray(residual(blocked.u, t))
    jtj, g = blocked.state.descent_state.jtj, blocked.state.descent_state.g
    np.testing.assert_allclose(jtj, jac.T @ jac, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(g, jac.T @ r, rtol=1e-8, atol=1e-14)
    np.testing.assert_allclose(normal_equations(blocked.state.f_info)[0], jtj, rtol=1e-10,
                               atol=1e-12)


def _items(u, args, i):
    # item i of a stacked residual: exp(-(i + 1) u0 t) u1 - data_i, with its aux
    scale = (i + 1.0) * u[0]
    return u[1] * jnp.exp(-scale * args[0]) - args[1][i], scale


def test_items_of_the_batched_jacobian_are_one_map_with_the_analytic_jacobian():
    """``items``: the items' residuals stacked, each linearised inside one lax.map; the
    values and the Jacobian are the closed form's (d/du0 = −(i+1) t u1 e^{−(i+1) u0 t},
    d/du1 = e^{−(i+1) u0 t}), with 5 parameters padded to whole batches of 2, and the
    aux rides along."""
    t = jnp.linspace(0.0, 1.0, 7)
    data = jnp.stack([jnp.sin(t), jnp.cos(t), t])
    u = jnp.asarray([0.7, 1.3, 0.0, 0.0, 0.0])  # three parameters the items ignore
    fn = jax.jit(with_batched_jacobian(_items, items=3, batch=2, has_aux=True))
    r, aux = fn(u, (t, data))
    k = jnp.arange(1.0, 4.0)[:, None]
    e = np.exp(-k * 0.7 * t)
    np.testing.assert_allclose(r, 1.3 * e - data, rtol=1e-13)
    np.testing.assert_allclose(aux, 0.7 * k[:, 0], rtol=1e-13)
    jac = jax.jacfwd(lambda v: fn(v, (t, data))[0])(u)
    assert jac.shape == (3, 7, 5)
    np.testing.assert_allclose(jac[..., 0], -k * t * 1.3 * e, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(jac[..., 1], e, rtol=1e-12)
    assert not np.asarray(jac[..., 2:]).any()


ITEMS_CHILD = """
import sys
import jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
sys.path.insert(0, "tests")
from test_lm import _items
from difstar._batch import device_mesh
from difstar._lm import with_batched_jacobian
t = jnp.linspace(0.0, 1.0, 7)
args = (t, jnp.stack([jnp.sin(t), jnp.cos(t), t]))
u = jnp.asarray([0.7, 1.3, 0.2])
one = with_batched_jacobian(lambda v, a, i: _items(v, a, i)[0], items=3, batch=1)
two = with_batched_jacobian(lambda v, a, i: _items(v, a, i)[0], items=3, batch=1,
                            mesh=device_mesh(2))
j1, j2 = (np.asarray(jax.jit(jax.jacfwd(f))(u, args)) for f in (one, two))
print("RESULT", jax.device_count(), float(np.abs(j1 - j2).max()), float(np.abs(j1).max()))
"""


def test_items_of_the_batched_jacobian_shared_out_over_two_devices():
    """The items' Jacobian with its columns shared out over 2 host devices (3 columns,
    padded to 4) is the one device's."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    env.pop("DIFSTAR_DEVICES", None)
    p = subprocess.run([sys.executable, "-c", ITEMS_CHILD],
                       cwd=Path(__file__).resolve().parents[1], env=env,
                       capture_output=True, text=True, timeout=300)
    line = [x for x in p.stdout.splitlines() if x.startswith("RESULT ")]
    assert p.returncode == 0 and line, p.stderr[-3000:]
    _, devices, diff, size = line[-1].split()
    assert int(devices) == 2 and float(size) > 0.1 and float(diff) <= 1e-12 * float(size)


def test_a_step_compiled_ahead_gives_the_same_solve_and_other_shapes_still_solve():
    """LMStepper.compile_ahead: the next solve of those shapes runs the program compiled
    on the background thread (the same steps and answer as a stepper without it); a
    solve of other shapes falls back to the jitted step."""
    jax.config.update("jax_enable_x64", True)

    traces = []

    def fn(u, _):
        traces.append(u.shape)  # Python runs only while a program is traced
        return jnp.concatenate([10.0 * (u[1:] - u[:-1] ** 2), 1.0 - u[:-1]])

    u0 = jnp.array([-1.2, 1.0, 0.5])
    plain = LMStepper(fn, rtol=1e-10, atol=1e-12).solve(u0, None, max_steps=200, ftol=1e-14)
    assert traces  # the plain stepper traced its programs in its solve
    ahead = LMStepper(fn, rtol=1e-10, atol=1e-12)
    ahead.compile_ahead(u0, None)
    program = ahead._step_with._program()  # compiled on the background thread
    ahead.compile_ahead(u0, None)  # a second call keeps the first program
    assert program is not None and ahead._step_with._program() is program
    traces.clear()
    res = ahead.solve(u0, None, max_steps=200, ftol=1e-14)
    assert traces == []  # the solve ran the programs made ahead: nothing traced again
    assert (res.steps, res.result) == (plain.steps, plain.result) == (res.steps, "converged")
    np.testing.assert_array_equal(np.asarray(res.u), np.asarray(plain.u))
    u1 = jnp.array([-1.2, 1.0, 0.5, 0.2])
    other = ahead.solve(u1, None, max_steps=300, ftol=1e-14)
    same = LMStepper(fn, rtol=1e-10, atol=1e-12).solve(u1, None, max_steps=300, ftol=1e-14)
    assert other.result == same.result == "converged" and other.steps == same.steps
    np.testing.assert_array_equal(np.asarray(other.u), np.asarray(same.u))
