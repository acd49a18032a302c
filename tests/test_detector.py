"""The detector's blur in the camera chain (difstar._detector: Blur of Jitter and Halo
layers, Sensor.blur): against SciPy's Gaussian filter of the unblurred image, jit, grad
and jacfwd against central differences, flux kept, and the refusals."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.ndimage as ndi

import difstar
from difstar._sampling import choose_grid

sim = eqx.filter_jit(difstar.simulate)


def _scene(config="focused"):
    camera, scene = difstar.paper_camera(config)
    return camera, eqx.tree_at(lambda s: s.sources, scene, (difstar.DiscSource(0.5e-3),))


def _with_blur(camera, blur):
    sensor = eqx.tree_at(lambda s: s.blur, camera.sensor, blur, is_leaf=lambda x: x is None)
    return eqx.tree_at(lambda c: c.sensor, camera, sensor)


def _scipy_blur(a, layers, values):
    """SciPy's sampled Gaussians (truncated at 10 σ, zero outside) one after the other:
    the jitter, then each halo moving its fraction into its Gaussian."""
    for layer in layers:
        if isinstance(layer, difstar.Jitter):
            a = ndi.gaussian_filter(a, values["jitter"], mode="constant", truncate=10)
        else:
            f, s = values[layer.name], values.get(f"{layer.name}_width", layer.width)
            a = (1 - f) * a + f * ndi.gaussian_filter(a, s, mode="constant", truncate=10)
    return a


@pytest.mark.parametrize("layers, values", [
    ((difstar.Jitter(),), {"jitter": 2.5}),
    ((difstar.Halo("halo", 3.0),), {"halo": 0.3}),
    ((difstar.Jitter(), difstar.Halo("scatter", 2.6)), {"jitter": 2.5, "scatter": 0.2}),
])
def test_the_blurred_image_is_scipys_gaussian_filter_of_the_unblurred_one(layers, values):
    """In focus (the engine's closed-form PSF: no sampling error of its own), one sample
    per pixel: the blurred crop equals SciPy's Gaussian filter applied to the unblurred
    image on a crop wider by more than the blur's reach, then cut to the same pixels, to
    1e-11 of the peak in float64 (widths ≥ 2.5 px, where a sampled Gaussian's spectrum is
    the continuous one's to 1e-13). The light the blur moves into the crop from beyond it
    is there: the chain computes the image ``reach`` pixels beyond the crop."""
    camera, scene = _scene()
    crop = (40, 40)
    blur = difstar.Blur(layers, values)
    blurred = _with_blur(camera, blur)
    grid = choose_grid(blurred, scene, crop=crop, raw_only=True)
    assert grid.method == "engine" and grid.oversample == 1
    got = np.asarray(sim(blurred, scene, grid).image)
    big = crop[0] + 2 * blur.reach + 40
    plain = sim(camera, scene, choose_grid(camera, scene, crop=(big, big), raw_only=True,
                                           method="engine"))
    o = (big - crop[0]) // 2
    ref = np.stack([_scipy_blur(np.asarray(plain.image[c]), layers, values)[o:o + crop[0],
                                                                              o:o + crop[1]]
                    for c in range(3)])
    assert np.abs(got - ref).max() < 1e-11 * ref.max()
    # the blur moved light: far from the unblurred image (a test that can fail)
    assert np.abs(got - np.asarray(plain.image)[:, o:o + crop[0], o:o + crop[1]]).max() \
        > 1e-3 * ref.max()


def test_a_blur_keeps_the_flux_with_sub_pixel_samples_and_defocus():
    """Defocused (the sampled pupil) with 3 × 3 samples a pixel: a Gaussian moves light
    without losing any, so on a crop that holds the blurred image the sum is unchanged
    (to the light the crop misses: 1e-4 of it)."""
    camera, scene = _scene("defocused")
    blur = difstar.Blur([difstar.Jitter(), difstar.Halo()], {"jitter": 1.0, "halo": 0.2,
                                                            "halo_width": 2.0})
    crop = (96, 96)
    blurred = _with_blur(camera, blur)
    grid = choose_grid(blurred, scene, crop=crop, raw_only=True, oversample=3)
    plain = sim(camera, scene, choose_grid(camera, scene, crop=crop, raw_only=True,
                                           oversample=3)).image
    got = sim(blurred, scene, grid).image
    np.testing.assert_allclose(np.asarray(got).sum(axis=(1, 2)),
                               np.asarray(plain).sum(axis=(1, 2)), rtol=1e-4)
    assert float(jnp.max(got)) < 0.99 * float(jnp.max(plain))  # the core spread


def test_jit_grad_and_jacfwd_of_the_blurs_values_match_central_differences():
    """d/d(jitter, halo, halo_width) of a weighted sum of the mosaic: jit equals eager,
    jax.grad and jax.jacfwd equal central differences (rel. 1e-5), all finite."""
    camera, scene = _scene()
    layers = (difstar.Jitter(), difstar.Halo())
    grid = choose_grid(_with_blur(camera, difstar.Blur(layers, {"jitter": 2.0, "halo": 0.2,
                                                                "halo_width": 3.0})),
                       scene, crop=(24, 24), raw_only=True)
    w = jnp.linspace(0.5, 1.5, 24)

    def loss(v):
        blur = difstar.Blur(layers, {"jitter": v[0], "halo": v[1], "halo_width": v[2]},
                            reach=18)
        pred = difstar.simulate(_with_blur(camera, blur), scene, grid)
        return jnp.sum(pred.cfa * w[None, :])

    v0 = jnp.asarray([1.5, 0.2, 2.5])
    f = jax.jit(loss)
    assert float(f(v0)) == pytest.approx(float(loss(v0)), rel=1e-12)
    g = jax.jit(jax.grad(loss))(v0)
    jf = jax.jit(jax.jacfwd(loss))(v0)
    assert np.all(np.isfinite(np.asarray(g)))
    for i in range(3):
        e = jnp.zeros(3).at[i].set(1e-5)
        fd = (float(f(v0 + e)) - float(f(v0 - e))) / 2e-5
        assert float(g[i]) == pytest.approx(fd, rel=1e-5)
        assert float(jf[i]) == pytest.approx(fd, rel=1e-5)
    assert abs(float(g[0])) > 0 and abs(float(g[1])) > 0 and abs(float(g[2])) > 0


def test_bad_blurs_are_refused_naming_the_field_and_the_fix():
    with pytest.raises(difstar.FitInputError, match="layers\\[0\\].*Jitter and Halo"):
        difstar.Blur([difstar.fitting.NativePixel(2.0)])
    with pytest.raises(difstar.FitInputError, match="\\['halo'\\] belong to no layer"):
        difstar.Blur([difstar.Jitter()], {"halo": 0.1})
    with pytest.raises(difstar.FitInputError, match="reach"):
        difstar.Blur([difstar.Jitter()], {"jitter": 1.0}, reach=-1)
    with pytest.raises(difstar.FitInputError, match="give reach"):
        jax.jit(lambda s: difstar.Blur([difstar.Jitter()], {"jitter": s}).reach)(1.0)
    with pytest.raises(ValueError, match="Sensor.blur must be a difstar.Blur"):
        difstar.Sensor(pixel_pitch=4e-6, blur={"jitter": 1.0})
    camera, scene = _scene()
    blurred = _with_blur(camera, difstar.Blur([difstar.Jitter()], {"jitter": 1.0}))
    for method in ("exact", "fft"):
        with pytest.raises(ValueError, match="blur"):
            choose_grid(blurred, scene, crop=(32, 32), method=method)
        with pytest.raises(ValueError, match="Sensor.blur"):
            difstar.simulate(blurred, scene, choose_grid(camera, scene, crop=(32, 32),
                                                         method=method))
    # the default reach: 6 σ of the widest Gaussian; a halo with no light reaches nowhere
    assert difstar.Blur([difstar.Jitter(), difstar.Halo()], {"jitter": 1.2}).reach == 8
    assert difstar.Blur([difstar.Jitter(), difstar.Halo()],
                        {"jitter": 1.2, "halo": 0.1}).reach == 24


def test_a_grid_holds_the_blurs_reach_and_a_huge_blur_is_refused_before_any_work():
    """The grid records the reach it was planned for (Grid.blur_reach, from choose_grid):
    a blurred camera on a grid planned without its blur is refused naming the fix, and a
    blur whose reach needs more memory than the machine has is refused when the grid is
    planned, before anything is computed."""
    camera, scene = _scene()
    blurred = _with_blur(camera, difstar.Blur([difstar.Jitter()], {"jitter": 1.0}))
    grid = choose_grid(blurred, scene, crop=(16, 16), raw_only=True)
    assert grid.blur_reach == 6
    plain = choose_grid(camera, scene, crop=(16, 16), raw_only=True, method="engine")
    assert plain.blur_reach == 0
    with pytest.raises(ValueError, match="reaches 6 px.*plan the grid with this camera"):
        difstar.simulate(blurred, scene, plain)
    # a sharp camera on a grid with room for a blur: the same image as on its own grid
    np.testing.assert_allclose(np.asarray(sim(camera, scene, grid).image),
                               np.asarray(sim(camera, scene, plain).image), rtol=1e-12,
                               atol=1e-15)
    huge = _with_blur(camera, difstar.Blur([difstar.Jitter()], {"jitter": 1e5}))
    with pytest.raises(ValueError, match="memory"):
        choose_grid(huge, scene, crop=(16, 16), raw_only=True)
