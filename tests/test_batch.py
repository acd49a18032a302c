"""Sharding over devices (issue 17): the batch helpers, their errors, and sharded results
against one-device results in float64.

Several host CPU devices need ``XLA_FLAGS=--xla_force_host_platform_device_count=4`` set
before JAX starts, so those checks run in a child Python (:data:`CHILD`) that prints its
measured differences as JSON; this process asserts on them.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from difstar import _batch as B

from difstar import _batch_fits as BF

from difstar import _distributed as DI
from difstar._validate import InputError

#: several host devices, their Eigen operations single-threaded (so that 4 devices on 2
#: cores do not oversubscribe them)
HOST_FLAGS = "--xla_force_host_platform_device_count=4 --xla_cpu_multi_thread_eigen=false"


def test_device_count_refuses_bad_values_naming_the_flag(monkeypatch):
    monkeypatch.delenv(B.ENV_DEVICES, raising=False)
    have = jax.device_count()
    assert B.device_count() == have and B.device_count(1) == 1
    for bad, words in ((0, ">= 1"), ("nan", "not a finite number"), (1.5, ">= 1"),
                       ("two", "not a number"), (have + 1, "available")):
        with pytest.raises(InputError) as e:
            B.device_count(bad)
        msg = str(e.value)
        assert msg.startswith("--devices:") and words in msg and "give a whole number" in msg
        assert "\n" not in msg
    monkeypatch.setenv(B.ENV_DEVICES, "-3")
    with pytest.raises(InputError, match=r"^DIFSTAR_DEVICES: -3 .*>= 1"):
        B.device_count()
    monkeypatch.setenv(B.ENV_DEVICES, "1")
    assert B.device_count() == 1


def test_chunks_follow_memory_and_padding():
    # 10 items on 4 devices: 3 per device at most; 1000 bytes free, 200 per item
    p = B.plan_chunks(10, 4, item_bytes=200, free_bytes=1000)
    assert (p.per_device, p.chunk, p.chunks) == (3, 12, 1)  # FILL·1000/200 = 3
    p = B.plan_chunks(10, 4, item_bytes=400, free_bytes=1000)
    assert (p.per_device, p.chunk, p.chunks) == (1, 4, 3)
    p = B.plan_chunks(10, 4, item_bytes=10**6, free_bytes=1000)  # never below one
    assert p.per_device == 1
    assert B.plan_chunks(10, 4).per_device == 3  # nothing known: one chunk
    assert B.plan_chunks(10, 4, chunk=5).per_device == 2  # rounded up to the devices
    with pytest.raises(InputError, match="whole number >= 1"):
        B.plan_chunks(10, 4, chunk=0)


def test_map_batch_one_device_equals_vmap_and_reports_progress():
    def f(item):
        return {"s": jnp.sum(jnp.sin(item["a"]) ** 2) * item["b"], "v": 2 * item["a"]}

    rng = np.random.default_rng(0)
    batch = {"a": rng.random((7, 5)), "b": np.arange(7.0)}
    seen = []
    out = B.map_batch(f, batch, devices=1, chunk=3,
                      progress=lambda d, n, s: seen.append((d, n)))
    ref = jax.vmap(f)(batch)
    assert seen == [(3, 7), (6, 7), (7, 7)]
    assert out["v"].shape == (7, 5)
    np.testing.assert_allclose(out["s"], np.asarray(ref["s"]), rtol=1e-14)  # chunks of 3: rounding
    with pytest.raises(ValueError, match="same leading"):
        B.map_batch(f, {"a": np.ones((3, 2)), "b": np.ones(4)}, devices=1)


def test_simulate_spectral_refuses_a_trichromatic_camera():
    import difstar

    camera, scene = difstar.paper_camera("focused")
    grid = difstar.choose_grid(camera, scene, crop=(16, 16), raw_only=True)
    with pytest.raises(ValueError, match="trichromatic"):
        B.simulate_spectral(camera, scene, grid, devices=1)


CHILD = textwrap.dedent('''
    import json, sys
    import jax, numpy as np
    jax.config.update("jax_enable_x64", True)
    import equinox as eqx
    import difstar
    from difstar import _batch as B
    from difstar import _batch_fits as BF
    from difstar import _distributed as DI
    sys.path.insert(0, "tests")
    out = {"devices": jax.device_count()}

    # many wavelengths: difstar.psf per wavelength, sharded, against psf's own lax.map
    pupil = difstar.RegularPolygon(7, 1.0e-3, 0.1)
    lams = np.linspace(450e-9, 650e-9, 6)
    wts = np.linspace(1.0, 2.0, 6)
    kw = dict(z_image=0.05, defocus=2e-4, pixel_pitch=4e-6, shape=(24, 24))
    plan = difstar.plan_psf(pupil, wavelength=lams, **kw)
    one = lambda lam: difstar.psf(pupil, wavelength=lam, plan=plan, **kw)
    ref = np.asarray(difstar.psf(pupil, wavelength=lams, weights=wts, plan=plan, **kw))
    for d in (1, 2, 4):
        mono = B.map_batch(one, lams, devices=d)
        got = np.einsum("l,lhw->hw", wts / wts.sum(), mono)
        out[f"psf_{d}"] = float(np.abs(got - ref).max() / ref.max())

    # a spectral simulate, wavelengths sharded, against simulate itself
    from difstar._examples import paper_sensitivities
    camera, scene = difstar.paper_camera("focused")
    ch = difstar.choose_wavelengths(5000.0, paper_sensitivities(), 1e-3)
    wl, w = ch.padded()
    s = camera.sensor
    cam = difstar.Camera(camera.lens, difstar.Sensor(
        pixel_pitch=s.pixel_pitch, pattern=s.pattern, wavelengths=wl, spectral_weights=w,
        phi0=s.phi0, response=s.response, white_balance=s.white_balance))
    grid = difstar.choose_grid(cam, scene, crop=(32, 32), raw_only=True)
    ref = eqx.filter_jit(difstar.simulate)(cam, scene, grid)
    for d in (1, 4):
        got = B.simulate_spectral(cam, scene, grid, devices=d)
        out[f"image_{d}"] = float(np.abs(got.image - np.asarray(ref.image)).max()
                                  / np.abs(np.asarray(ref.image)).max())
        out[f"cfa_{d}"] = float(np.abs(got.cfa - np.asarray(ref.cfa)).max())
    out["k"] = int(wl.shape[1])

    # many fits: solve_many's lockstep against Fitter.solve, one after another
    from test_fit import F, _data, _model, _start
    model = _model()
    fitter, data = _data(model, noise_sigma=1e-3)
    u0s = np.stack([np.asarray(_start(model, 0.1, seed=s)) for s in range(3)])
    args = [F.make_args(model, data, u) for u in u0s]
    seq = [fitter.solve(u, a, max_steps=6) for u, a in zip(u0s, args)]
    stacked = jax.tree_util.tree_map(lambda *x: np.stack([np.asarray(v) for v in x]), *args)
    for d in (1, 3):
        res = BF.solve_many(fitter, u0s, stacked, devices=d, max_steps=6)
        out[f"fit_du_{d}"] = max(float(np.abs(r.u - np.asarray(q.u)).max())
                                 for r, q in zip(res, seq))
        out[f"fit_loss_{d}"] = max(abs(r.loss - q.loss) / q.loss for r, q in zip(res, seq))
    out["fit_du_start"] = max(float(np.abs(np.asarray(q.u) - u).max())
                              for q, u in zip(seq, u0s))
    print("RESULT " + json.dumps(out))
''')


@pytest.mark.slow
def test_sharded_equals_one_device_on_four_host_devices():
    env = dict(os.environ, XLA_FLAGS=HOST_FLAGS)
    env.pop(B.ENV_DEVICES, None)
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    p = subprocess.run([sys.executable, "-c", CHILD], cwd=root, env=env, capture_output=True,
                       text=True, timeout=600)
    line = [x for x in p.stdout.splitlines() if x.startswith("RESULT ")]
    assert p.returncode == 0 and line, p.stderr[-3000:]
    r = json.loads(line[-1][7:])
    assert r["devices"] == 4
    for d in (1, 2, 4):  # the same wavelengths on 1, 2 or 4 devices: rounding only
        assert r[f"psf_{d}"] < 1e-13, r
    assert r["k"] > 1
    for d in (1, 4):
        assert r[f"image_{d}"] < 1e-12 and r[f"cfa_{d}"] < 1e-12, r
    # lockstep fits end where one fit after another ends: the starts moved by O(0.1) in
    # u, the sharded and sequential ends agree to the solver's rounding
    assert r["fit_du_start"] > 1e-3
    for d in (1, 3):
        assert r[f"fit_du_{d}"] < 1e-7 and r[f"fit_loss_{d}"] < 1e-9, r


def test_cli_devices_errors_exit_2_with_one_line(tmp_path, capsys):
    from difstar.cli import main

    rc = main(["predict", "--example", "paper-focused", "--crop", "16", "16",
               "--out", str(tmp_path / "out"), "--devices", "0"])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and err.count("\n") == 0 and "--devices: 0" in err
    assert not (tmp_path / "out").exists()


def test_fit_devices_for_a_single_fit_are_checked_first(tmp_path, capsys):
    """``fit --devices N`` without a study shares one fit's Jacobian out (tested in
    test_fit.py); a bad count is refused before anything is read or written."""
    from difstar.cli import main

    manifest = Path(__file__).resolve().parents[1] / "fit" / "synthetic-paper-camera" / \
        "manifest.json"
    for bad in ("0", "2.5", "999"):
        rc = main(["fit", str(manifest), "--out", str(tmp_path / "out"), "--devices", bad])
        err = capsys.readouterr().err.strip()
        assert rc == 2 and err.count("\n") == 0 and "--devices" in err, err
        assert not (tmp_path / "out").exists()


HANG_CHILD = textwrap.dedent('''
    import faulthandler, json, sys, time
    faulthandler.dump_traceback_later(float(sys.argv[1]), exit=True)  # a hang fails loudly
    import jax, numpy as np
    jax.config.update("jax_enable_x64", True)
    from difstar import _batch as B
    from difstar import _batch_fits as BF
    from difstar import _distributed as DI
    sys.path.insert(0, "tests")
    from test_fit import F, _data, _model, _start
    model = _model()
    fitter, data = _data(model, noise_sigma=1e-3)
    u0 = np.stack([np.asarray(_start(model, 0.1, seed=s)) for s in range(8)])
    arg = [F.make_args(model, data, u) for u in u0]
    args = jax.tree_util.tree_map(lambda *x: np.stack([np.asarray(v) for v in x]), *arg)
    out = {"devices": jax.device_count()}
    t0 = time.perf_counter()
    plans = []
    many = BF.solve_many(fitter, u0, args, devices=4, max_steps=3, chunk=8, plan_out=plans)
    out["seconds_4"] = time.perf_counter() - t0
    out["per_device"] = plans[0].per_device
    one = BF.solve_many(fitter, u0, args, devices=1, max_steps=3)
    out["du"] = max(float(np.abs(a.u - b.u).max()) for a, b in zip(many, one))
    out["moved"] = max(float(np.abs(a.u - u).max()) for a, u in zip(one, u0))

    # the recovery study's path: ordinary one-fit code in threads, two solves each,
    # gathered into batched rounds on 4 devices
    def job(i):
        def run(f):
            r = f.solve(u0[i], arg[i], max_steps=2)
            return f.solve(r.u, arg[i], max_steps=1)
        return run
    got = BF.FitBatcher(fitter, devices=4).run([job(i) for i in range(8)])
    two = BF.solve_many(fitter, u0, args, devices=1, max_steps=2)
    two = BF.solve_many(fitter, np.stack([t.u for t in two]), args, devices=1, max_steps=1)
    out["batcher_du"] = max(float(np.abs(np.asarray(g.u) - o.u).max())
                            for g, o in zip(got, two))
    print("RESULT " + json.dumps(out), flush=True)
''')


@pytest.mark.slow
def test_many_fits_on_host_cpu_devices_finish():
    """The hang of issue 17: jaxlib's CPU LAPACK kernels split a batch of matrices over
    XLA's CPU thread pool and block the pool thread waiting; several host devices each
    solving a batch of fits at once took every pool thread and stopped for ever.
    ``NPROC=2`` fixes the pool at 2 threads on any machine, 4 devices with 2 fits each
    reach their solves together: this hung before solve_many took a device's fits in
    turn on CPU. The child dumps its stacks and exits if it runs past the limit."""
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4", NPROC="2")
    env.pop(B.ENV_DEVICES, None)
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    limit = 400
    try:
        p = subprocess.run([sys.executable, "-c", HANG_CHILD, str(limit)], cwd=root, env=env,
                           capture_output=True, text=True, timeout=limit + 60)
    except subprocess.TimeoutExpired as e:
        pytest.fail(f"many fits on 4 host devices hung (no result in {limit + 60} s): "
                    f"{(e.stderr or b'')[-3000:]!r}")
    line = [x for x in p.stdout.splitlines() if x.startswith("RESULT ")]
    assert p.returncode == 0 and line, (
        f"many fits on 4 host devices did not finish (exit {p.returncode}; a "
        f"'Timeout' traceback means it hung):\n{p.stderr[-3000:]}")
    r = json.loads(line[-1][7:])
    assert r["devices"] == 4 and r["per_device"] == 2, r
    assert r["moved"] > 1e-3, r  # the fits did step
    # the same per-fit code on 4 devices and on 1: the same numbers
    assert r["du"] < 1e-12 and r["batcher_du"] < 1e-12, r
