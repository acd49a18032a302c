"""Cost bounded up front, for every request, on the command line and in the Python API
(issue 31).

Memory and work are estimated from the shapes, the wavelengths' count, the blades' and
vertices' counts before anything is allocated or compiled; what is out of bounds is
refused with an ``InputError`` (a ``ValueError``) naming the setting and the fix. Every
case here is cheap because it is refused before any allocation: a case that regressed
would allocate hundreds of GB or run for minutes instead.
"""

from __future__ import annotations

import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_bad_input import run, snapshot

import difstar
from difstar._validate import (
    MAX_BUILD_EDGES,
    MAX_EDGES,
    MAX_EXACT_EDGES,
    MAX_WAVELENGTHS,
    InputError,
    memory_budget,
    parse_memory_limit,
)

R = 51.5e-3 / 44  # the paper's f/22 exit pupil radius, metres
GOOD = dict(wavelength=530e-9, z_image=51.5e-3, pixel_pitch=3.917e-6, shape=(32, 32))


def pupil():
    return difstar.RegularPolygon(7, R, 0.0)


def refused(fn, *fields):
    """``fn()`` raises InputError (a ValueError) naming every one of ``fields``."""
    with pytest.raises(InputError) as e:
        fn()
    assert isinstance(e.value, ValueError)
    for f in fields:
        assert f in str(e.value), (f, str(e.value))
    assert "\n" not in str(e.value)
    return str(e.value)


# ----------------------------------------------------------------------- shapes, memory


def test_huge_psf_window_is_refused_before_allocation():
    msg = refused(lambda: difstar.psf(pupil(), **{**GOOD, "shape": (200000, 200000)}),
                  "difstar.psf", "200000 x 200000", "memory", "DIFSTAR_MEMORY_LIMIT",
                  "smaller shape")
    assert "GB" in msg
    refused(lambda: difstar.plan_psf(pupil(), **{**GOOD, "shape": (200000, 200000)}),
            "memory")
    # a window that fits alone but not with the closed form's per-pixel nodes
    refused(lambda: difstar.psf(pupil(), **{**GOOD, "shape": (30000, 30000)}),
            "memory", "smaller shape")


def test_huge_psf_window_with_a_given_plan_is_refused():
    plan = difstar.plan_psf(pupil(), **GOOD)
    refused(lambda: difstar.psf(pupil(), **{**GOOD, "shape": (100000, 100000)}, plan=plan),
            "difstar.psf", "memory")


def test_memory_limit_is_honoured(monkeypatch):
    monkeypatch.setenv("DIFSTAR_MEMORY_LIMIT", "1M")
    assert memory_budget() == 2**20
    refused(lambda: difstar.psf(pupil(), **{**GOOD, "shape": (512, 512)}), "memory",
            "1.05 MB")
    cam, sc = difstar.paper_camera("focused")
    with pytest.raises(ValueError, match="memory"):
        difstar.choose_grid(cam, sc, crop=(512, 512))


@pytest.mark.parametrize("shape,bad", [
    ((8.5, 8), "8.5"), ((8, 8.5), "8.5"), ((True, 8), "True"), ((0, 8), "0"),
    ((-4, 8), "-4"), ((8, 1), "1"), ((8,), "(8,)"), ("88", "'88'"), ((8, 8, 8), "(8, 8, 8)"),
    ((8, None), "None"), ((8, float("nan")), "nan"), ((8, "8"), "'8'"),
])
def test_bad_shapes_are_refused_naming_shape(shape, bad):
    refused(lambda: difstar.psf(pupil(), **{**GOOD, "shape": shape}), "shape", bad)
    refused(lambda: difstar.plan_psf(pupil(), **{**GOOD, "shape": shape}), "shape")


def test_whole_number_shapes_are_accepted():
    a = difstar.psf(pupil(), **{**GOOD, "shape": (np.int64(8), 8.0)})
    assert a.shape == (8, 8)


def test_huge_simulate_grid_is_refused_before_allocation():
    cam, sc = difstar.paper_camera("focused")
    refused(lambda: difstar.simulate(cam, sc, difstar.Grid(n=200000, crop=(16, 16))),
            "difstar.simulate", "200000", "memory")
    with pytest.raises(ValueError, match="crop of at most"):
        difstar.choose_grid(cam, sc, crop=(200000, 200000))


# --------------------------------------------------------------- blades, vertices, vanes


def test_too_many_blades_are_refused():
    # built: beyond MAX_BUILD_EDGES at once
    refused(lambda: difstar.RegularPolygon(100000, R), "RegularPolygon.n", "100000",
            str(MAX_BUILD_EDGES), "Circle")
    refused(lambda: difstar.Spiders(100000, 1e-5), "Spiders.n", "100000")
    refused(lambda: difstar.Struts(np.zeros(100000), 1e-5), "Struts.angles", "100000")
    refused(lambda: difstar.CurvedIris(100000, R), "CurvedIris.n")
    refused(lambda: difstar.CurvedIris(9, R, segments=1000), "CurvedIris.n x segments")
    v = np.zeros((100000, 2))  # not even looked at: refused on the count
    refused(lambda: difstar.Polygon(v), "Polygon.vertices", "100000")
    # difstar.psf: beyond MAX_EDGES per outline
    many = difstar.RegularPolygon(MAX_EDGES + 1, R)
    refused(lambda: difstar.psf(many, **GOOD), "difstar.psf", "pupil.n",
            str(MAX_EDGES), "use Circle")
    curved = difstar.CurvedIris(100, R, segments=16)
    refused(lambda: difstar.psf(curved, **GOOD), "pupil.n x segments")
    obs = difstar.Obstructed(difstar.Circle(R), None, difstar.Spiders(MAX_EDGES + 1, 1e-6))
    refused(lambda: difstar.psf(obs, **GOOD), "pupil.spiders.n", "vanes")
    union = difstar.Union([difstar.RegularPolygon(6, R / 4),
                           difstar.RegularPolygon(MAX_EDGES + 1, R / 4).transformed(
                               0.0, (R, 0.0))], check_overlap=False)
    refused(lambda: difstar.psf(union, **GOOD), "pupil.members[1].vertices")


def test_too_many_blades_in_a_camera_are_refused():
    cam, sc = difstar.paper_camera("focused")
    big = difstar.Camera(difstar.Lens(difstar.RegularPolygon(2000, R), focal_length=51.5e-3,
                                      focus_distance=1.0), cam.sensor)
    refused(lambda: difstar.choose_grid(big, sc, crop=(16, 16)), "camera.lens.pupil.n")
    g = difstar.choose_grid(cam, sc, crop=(16, 16))
    refused(lambda: difstar.simulate(big, sc, g), "difstar.simulate",
            "camera.lens.pupil.n")


def test_the_closed_form_is_bounded_and_sampling_takes_over():
    many = difstar.RegularPolygon(MAX_EXACT_EDGES + 1, R)
    assert difstar.plan_psf(many, **GOOD).method in ("mft", "fft")
    refused(lambda: difstar.plan_psf(many, **GOOD, method="exact"), "method='exact'",
            str(MAX_EXACT_EDGES))
    exact = difstar.plan_psf(pupil(), **GOOD)
    assert exact.method == "exact"
    refused(lambda: difstar.psf(many, **GOOD, plan=exact), "plan.method")
    cam, sc = difstar.paper_camera("focused")
    cam = difstar.Camera(difstar.Lens(many, focal_length=51.5e-3, focus_distance=1.0),
                         cam.sensor)
    assert difstar.choose_grid(cam, sc, crop=(16, 16)).psf_plan.method in ("mft", "fft")
    refused(lambda: difstar.choose_grid(cam, sc, crop=(16, 16), method="exact"),
            "method='exact'")


# ----------------------------------------------------------------------- wavelengths


def test_too_many_wavelengths_are_refused():
    lams = np.linspace(400e-9, 700e-9, 10000)
    refused(lambda: difstar.psf(pupil(), **{**GOOD, "wavelength": lams}),
            "difstar.psf: wavelength", "10000", str(MAX_WAVELENGTHS))
    refused(lambda: difstar.plan_psf(pupil(), **{**GOOD, "wavelength": lams}), "wavelength")
    cam, sc = difstar.paper_camera("focused")
    k = MAX_WAVELENGTHS + 1
    wl = np.stack([np.linspace(560e-9, 640e-9, k), np.linspace(490e-9, 570e-9, k),
                   np.linspace(410e-9, 490e-9, k)])
    spectral = difstar.Camera(cam.lens, difstar.Sensor(pixel_pitch=3.917e-6, wavelengths=wl,
                                                       spectral_weights=np.ones_like(wl)))
    refused(lambda: difstar.choose_grid(spectral, sc, crop=(16, 16)),
            "camera.sensor.wavelengths")


def test_spectrum_sizes_are_bounded():
    from difstar._spectrum import dense_weights, gauss_nodes

    refused(lambda: difstar.choose_wavelengths(5000.0, None, 1e-3, max_wavelengths=10**6),
            "max_wavelengths")
    refused(lambda: dense_weights(5000.0, None, step=1e-18), "step")
    with pytest.raises(ValueError, match="step"):
        dense_weights(5000.0, None, step=0.0)
    refused(lambda: difstar.channel_weights(5000.0, None, np.linspace(4e-7, 7e-7, 10**6)),
            "wavelengths", "1000000")
    refused(lambda: difstar.error_table(5000.0, None, ks=[1, 10**5]), "ks[1]")
    refused(lambda: gauss_nodes(np.linspace(0, 1, 10), np.ones(10), 10**5), "k")


# ------------------------------------------------------------------ under jit and grad


def test_checks_are_static_and_pass_tracers():
    """The counts and shapes are static: the checks run while tracing, on traced pupils
    and wavelengths, and refuse there as outside."""
    plan = difstar.plan_psf(pupil(), **GOOD)

    def total(r, lam):
        kw = {**GOOD, "wavelength": lam}
        return jnp.sum(difstar.psf(difstar.RegularPolygon(7, r, 0.0), plan=plan, **kw))

    g = jax.jit(jax.grad(total))(R, 530e-9)
    assert np.isfinite(float(g))
    lams = jnp.full(MAX_WAVELENGTHS + 1, 530e-9)
    with pytest.raises(InputError, match="wavelength"):
        jax.jit(total)(R, lams)

    @jax.jit
    def huge(r):
        kw = {**GOOD, "shape": (100000, 100000)}
        return difstar.psf(difstar.RegularPolygon(7, r, 0.0), plan=plan, **kw)

    with pytest.raises(InputError, match="memory"):
        huge(R)


# ------------------------------------------------------------------ DIFSTAR_MEMORY_LIMIT


@pytest.mark.parametrize("text,value", [
    ("8000000000", 8000000000), ("512M", 512 * 2**20), ("8G", 8 * 2**30), ("8g", 8 * 2**30),
    ("8GiB", 8 * 2**30), ("8GB", 8 * 10**9), ("1.5G", int(1.5 * 2**30)), (" 64K ", 64 * 2**10),
])
def test_memory_limit_forms(text, value):
    assert parse_memory_limit(text) == value


@pytest.mark.parametrize("text", ["abc", "0", "-5", "1.5", "8X", "1e9", "8 G B", "inf",
                                  "nan", "9" * 40, "0M"])
def test_bad_memory_limit_is_refused(monkeypatch, text):
    refused(lambda: parse_memory_limit(text), "DIFSTAR_MEMORY_LIMIT", "512M")
    monkeypatch.setenv("DIFSTAR_MEMORY_LIMIT", text)
    refused(memory_budget, "DIFSTAR_MEMORY_LIMIT")
    refused(lambda: difstar.psf(pupil(), **GOOD), "DIFSTAR_MEMORY_LIMIT")
    from difstar._batch import device_memory

    if not (jax.devices()[0].memory_stats() or {}).get("bytes_limit"):
        refused(device_memory, "DIFSTAR_MEMORY_LIMIT")


def test_empty_memory_limit_means_unset(monkeypatch):
    monkeypatch.setenv("DIFSTAR_MEMORY_LIMIT", "")
    assert memory_budget() > 2**20


def test_batch_uses_the_same_parser(monkeypatch):
    from difstar._batch import device_memory

    if (jax.devices()[0].memory_stats() or {}).get("bytes_limit"):
        pytest.skip("this device (a GPU) reports its own memory limit, which device_memory "
                    "uses instead of DIFSTAR_MEMORY_LIMIT: the parser is tested on CPU hosts")
    monkeypatch.setenv("DIFSTAR_MEMORY_LIMIT", "8G")
    assert device_memory() == 8 * 2**30 // jax.local_device_count()


def test_cli_refuses_a_bad_memory_limit(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("DIFSTAR_MEMORY_LIMIT", "abc")
    before = snapshot(tmp_path)
    code, err = run(["predict", "--example", "paper-focused", "--crop", 16, 16,
                     "--out", tmp_path / "out"], capsys)
    assert code == 2, (code, err)
    assert "DIFSTAR_MEMORY_LIMIT" in err and "'abc'" in err and "512M" in err
    assert "Traceback" not in err and err.count("\n") == 1
    assert snapshot(tmp_path) == before


def test_cli_honours_the_memory_limit(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("DIFSTAR_MEMORY_LIMIT", "1M")
    before = snapshot(tmp_path)
    code, err = run(["predict", "--example", "paper-focused", "--crop", 1024, 1024,
                     "--out", tmp_path / "out"], capsys)
    assert code == 2, (code, err)
    assert "memory" in err and "Traceback" not in err
    assert snapshot(tmp_path) == before


# -------------------------------------------------------------- a real interpreter


def test_huge_psf_is_a_python_exception_not_an_abort():
    """Was: an XLA check failure that aborted the interpreter (SIGABRT, -6 / 134)."""
    code = ("import difstar; difstar.psf(difstar.RegularPolygon(7, 1e-3), "
            "wavelength=530e-9, z_image=0.05, pixel_pitch=4e-6, shape=(200000, 200000))")
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    env.pop("DIFSTAR_MEMORY_LIMIT", None)
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 1, (proc.returncode, proc.stderr[-2000:])
    assert "InputError" in proc.stderr and "memory" in proc.stderr
