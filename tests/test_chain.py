"""The composed chain: energy, geometry of the image, jit, gradients at the hard points,
and the paper's example end to end (small crop)."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import difstar
from difstar._sampling import choose_grid, fast_length


sim = eqx.filter_jit(difstar.simulate)


def _small(config="focused", crop=(64, 64), **kw):
    camera, scene = difstar.paper_camera(config)
    # a small source so a small grid holds it
    scene = eqx.tree_at(lambda s: s.sources, scene, (difstar.DiscSource(0.5e-3),))
    return camera, scene, choose_grid(camera, scene, crop=crop, **kw)


def test_energy_conserved_sum_image_equals_sum_object():
    """The circular convolution conserves energy: Σ image = Σ object × Σ PSF over the
    period. The PSF is normalised by the pupil's energy (Parseval), so Σ PSF over the
    period falls short of 1 by the energy diffracted beyond the grid, which shrinks
    about as 1/n (float64)."""
    camera, scene, _ = _small()
    grid = difstar.Grid(n=128, crop=(128, 128), use_defocus=False)
    pred = sim(camera, scene, grid)
    g = pred.geometry
    b = difstar.geometric_image(scene.sources, magnification=g.magnification,
                                pixel_pitch=camera.sensor.pixel_pitch, shape=(128, 128))
    b = b * difstar.irradiance_scale(camera, scene)  # the light the pupil passes
    psf_sum = np.asarray(pred.psf).sum(axis=(1, 2))
    np.testing.assert_allclose(np.asarray(pred.image).sum(axis=(1, 2)),
                               np.asarray(b).sum(axis=(1, 2)) * psf_sum, rtol=1e-12)
    deficit = 1 - psf_sum
    assert np.all(deficit > 0) and np.all(deficit < 0.015)
    p1024 = sim(camera, scene, difstar.Grid(n=1024, crop=(1024, 1024), use_defocus=False)).psf
    deficit_big = 1 - np.asarray(p1024).sum(axis=(1, 2))
    assert np.all(deficit_big > 0) and np.all(deficit_big < deficit / 4), (deficit, deficit_big)
    # and the object's image area equals π (|M| r / p)² (area coverage is exact-ish)
    area = float(b[1].sum() / difstar.irradiance_scale(camera, scene))
    expect = np.pi * (abs(float(g.magnification)) * 0.5e-3 / camera.sensor.pixel_pitch) ** 2
    assert area == pytest.approx(expect, rel=1e-3)


def test_point_source_image_is_the_psf():
    camera, scene, _ = _small()
    scene = eqx.tree_at(lambda s: s.sources, scene, (difstar.DiscSource(1e-6),))
    grid = difstar.Grid(n=128, crop=(128, 128), use_defocus=False)
    pred = sim(camera, scene, grid)
    for c in range(3):
        img = np.asarray(pred.image[c]) / float(pred.image[c].sum())
        psf = np.asarray(pred.psf[c]) / float(pred.psf[c].sum())
        np.testing.assert_allclose(img, psf, atol=2e-3 * float(psf.max()))


def test_off_axis_source_lands_inverted_at_M_times_position():
    camera, scene, _ = _small()
    x_obj = 3e-3  # 3 mm off axis → about −41 px with M ≈ −0.054
    scene = eqx.tree_at(lambda s: s.sources, scene,
                        (difstar.DiscSource(1e-4, position=(x_obj, 0.0)),))
    grid = difstar.Grid(n=256, crop=(256, 256), use_defocus=False)
    pred = sim(camera, scene, grid)
    img = np.asarray(pred.image[1])
    # centroid in a window around the peak (the PSF is centrosymmetric; a whole-grid
    # centroid would be pulled inwards by the periodic grid's wrapped tails)
    r0, c0 = np.unravel_index(np.argmax(img), img.shape)
    win = img[r0 - 12 : r0 + 13, c0 - 12 : c0 + 13]
    col = (win.sum(axis=0) * np.arange(c0 - 12, c0 + 13)).sum() / win.sum() - 128
    expect = float(pred.geometry.magnification) * x_obj / camera.sensor.pixel_pitch
    assert col == pytest.approx(expect, abs=0.05)


def test_defocus_switch_and_rules():
    camera, scene, grid = _small("focused")
    assert grid.use_defocus is False  # Δz = 0: no phase computed
    camera, scene, grid = _small("defocused")
    assert grid.use_defocus is True and grid.psf_plan.use_defocus is True
    camera, scene, grid = _small("defocused", method="fft")  # the paper's grid: its switch
    assert grid.use_defocus is True
    with pytest.raises(difstar.SamplingError, match="use_defocus is False"):
        difstar.simulate(camera, scene, dataclasses.replace(grid, use_defocus=False))


def test_undersampled_grid_override_errors_with_fix():
    camera, scene = difstar.paper_camera("focused")
    lens = difstar.Lens(difstar.RegularPolygon(7, 51.5e-3 / (2 * 1.8)), focal_length=51.5e-3,
                        focus_distance=1.0, principal_separation=-3e-3)
    camera = difstar.Camera(lens, camera.sensor)
    # λN_w = 0.45 µm × 1.9 = 0.86 µm at 450 nm: the pupil fits the grid with q = 5
    with pytest.raises(difstar.SamplingError, match=r"rule 1.*oversample >= 5"):
        difstar.simulate(camera, scene, difstar.Grid(n=64, crop=(32, 32), oversample=1))
    assert choose_grid(camera, scene, crop=(32, 32), method="fft").oversample == 5
    # by default the pixels, which undersample the intensity (4.9 cycles per pixel in
    # blue), are integrated on the engine's odd sub-grid at the intensity's Nyquist rate
    grid = choose_grid(camera, scene, crop=(32, 32))
    assert grid.method == "engine" and grid.oversample == 11


def test_fast_length():
    assert fast_length(1250) == 1250  # 2 · 5⁴
    assert fast_length(1251) == 1260  # 2² · 3² · 5 · 7
    assert fast_length(1024) == 1024
    assert fast_length(2401) == 2401  # 7^4


def _loss_fn(grid):
    def loss(params, camera, scene):
        dz, rot, phi0, toe = params
        pupil = difstar.RegularPolygon(7, camera.lens.pupil.circumradius, rot)
        lens = difstar.Lens(pupil, focal_length=camera.lens.focal_length,
                            focus_distance=camera.lens.focus_distance,
                            principal_separation=camera.lens.principal_separation, defocus=dz)
        sensor = eqx.tree_at(lambda s: (s.phi0, s.response.toe), camera.sensor,
                             (phi0, jnp.broadcast_to(toe, (3,))))
        pred = difstar.simulate(difstar.Camera(lens, sensor), scene, grid)
        w = jnp.linspace(0.0, 1.0, grid.crop[1])
        return jnp.sum(pred.cfa * w[None, :]) + jnp.sum(pred.srgb)
    return loss


@pytest.mark.parametrize("dz", [0.0, 0.2e-3])
def test_chain_jit_and_grad_match_fd(dz):
    # Δz = 0 (with the phase on), φ0 small enough that the core saturates (a hard point)
    camera, scene, _ = _small("focused")
    grid = difstar.Grid(n=96, crop=(32, 32), use_defocus=True)
    eager = _loss_fn(grid)
    loss = jax.jit(eager)
    params = (jnp.asarray(dz), jnp.asarray(0.1), jnp.asarray([0.02, 0.02, 0.03]), jnp.asarray(0.02))
    v = loss(params, camera, scene)
    if dz == 0.0:  # jit equals no-jit (once: eager evaluation of the chain is slow)
        assert float(eager(params, camera, scene)) == pytest.approx(float(v), rel=1e-10)
    g = jax.jit(jax.grad(eager))(params, camera, scene)
    leaves = jax.tree_util.tree_leaves(g)
    assert all(np.all(np.isfinite(np.asarray(x))) for x in leaves)
    steps = [1e-7, 1e-6, 1e-7, 1e-6]
    for i, eps in enumerate(steps):
        p = params[i]
        idx = (0,) if p.ndim else ()
        e = jnp.zeros_like(p).at[idx].set(eps)
        hi = list(params)
        lo = list(params)
        hi[i] = p + e
        lo[i] = p - e
        fd = (loss(tuple(hi), camera, scene) - loss(tuple(lo), camera, scene)) / (2 * eps)
        gi = g[i][idx]
        assert float(gi) == pytest.approx(float(fd), rel=2e-4, abs=1e-6 * abs(float(v)))


def test_saturated_pixels_have_finite_gradients():
    camera, scene, _ = _small()
    grid = difstar.Grid(n=64, crop=(32, 32), use_defocus=False, raw_only=True)
    def f(phi0):
        sensor = eqx.tree_at(lambda s: s.phi0, camera.sensor, phi0)
        return jnp.sum(difstar.simulate(difstar.Camera(camera.lens, sensor), scene, grid).cfa)
    phi0 = jnp.asarray([1e-4, 1e-4, 1e-4])  # everything near the core is deep in saturation
    g = jax.jit(jax.grad(f))(phi0)
    assert np.all(np.isfinite(np.asarray(g)))
    pred = sim(camera, eqx.tree_at(lambda s: s.exposure_time, scene, 2.5), grid)
    assert pred.srgb is None  # raw_only: no demosaic


def test_paper_example_small_crop_end_to_end():
    for config in ("focused", "defocused"):
        camera, scene = difstar.paper_camera(config)
        grid = choose_grid(camera, scene, crop=(192, 192), padding=0.25)
        pred = sim(camera, scene, grid)
        assert pred.cfa.shape == (192, 192)
        assert pred.srgb.shape == (3, 192, 192)
        cfa = np.asarray(pred.cfa)
        assert 0.0 <= cfa.min() and cfa.max() <= 1.0
        assert cfa[96, 96] > 0.99  # the core saturates
        assert np.all(np.isfinite(np.asarray(pred.srgb)))
    assert float(pred.geometry.defocus) == pytest.approx(4.78e-3, abs=1e-5)


def test_exact_path_chosen_in_focus_and_agrees_with_converged_fft():
    camera, scene, grid = _small("focused", crop=(64, 64))
    assert grid.method == "exact"
    assert _small("defocused")[2].method == "engine"
    exact = np.asarray(sim(camera, scene, grid).image)
    fft_grid = choose_grid(camera, scene, crop=(64, 64), method="fft", padding=12.0)
    ref = np.asarray(sim(camera, scene, fft_grid).image)
    # the FFT path's error falls as ~2e-2/padding outside the core (BENCHMARKS.md)
    yy, xx = np.mgrid[:64, :64] - 32
    m = np.broadcast_to(np.hypot(yy, xx) > 12, ref.shape)
    err = np.sqrt(np.sum((exact - ref)[m] ** 2) / np.sum(ref[m] ** 2))
    assert err < 5e-3
    np.testing.assert_allclose(exact.sum(), ref.sum(), rtol=2e-2)  # energy lost off-crop only


def test_exact_path_refuses_defocus_and_has_finite_gradients():
    camera, scene, grid = _small("focused", crop=(32, 32))
    cam_d, scene_d, _ = _small("defocused", crop=(32, 32))
    with pytest.raises(difstar.SamplingError, match="method='exact' is for in-focus"):
        difstar.simulate(cam_d, scene_d, grid)

    def f(rot):
        pupil = difstar.RegularPolygon(7, camera.lens.pupil.circumradius, rot)
        lens = eqx.tree_at(lambda l: l.pupil, camera.lens, pupil)
        return jnp.sum(difstar.simulate(difstar.Camera(lens, camera.sensor), scene, grid).cfa)

    g = jax.jit(jax.grad(f))(0.1)
    eps = 1e-6
    fd = (jax.jit(f)(0.1 + eps) - jax.jit(f)(0.1 - eps)) / (2 * eps)
    assert np.isfinite(float(g)) and float(g) == pytest.approx(float(fd), rel=1e-4, abs=1e-8)
