"""One PSF at the star's centre for a solve that holds the optics
(difstar.fitting._centred): the moved, integrated and blurred image against the
independent NumPy star of tests/test_fitting.py (an FFT of a fine raster, pixels
integrated by a midpoint rule) as well as the PSF engine's own path does, and against
that path at values the generator does not cover (blurs, halos, a disc, native pixels,
a window of even size); its gradients against central differences; a fit that uses it
ends where the engine's path ends."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_fitting import TRUE, _model, _numpy_star

from difstar.fitting import FitData, Param, _solve, fit
from difstar.fitting._centred import (
    centred_psf,
    fine_factor,
    image_from_centred,
    optics_fixed,
)


def _both(model, values, shape):
    vals = {**model.values(), **values}
    v = {k: jnp.asarray(x, float) for k, x in vals.items()}
    direct = np.asarray(model.image(v, shape))
    c = jnp.asarray(centred_psf(model, vals, shape))
    cen = np.asarray(image_from_centred(model, v, shape, c, fine_factor(model)))
    return direct, cen


def test_against_the_independent_star():
    truth = _numpy_star(**TRUE)
    direct, cen = _both(_model(), TRUE, truth.shape)
    peak = truth.max()
    err_direct = np.abs(direct - truth).max() / peak
    err_cen = np.abs(cen - truth).max() / peak
    # the generator's own midpoint rule limits both (about 5e-3 of the peak); the
    # centred path may not add to it by more than a tenth
    assert err_direct < 1e-2
    assert err_cen < 1.1 * err_direct, (err_cen, err_direct)


@pytest.mark.parametrize("values,over,shape", [
    ({"x0": 1.7, "y0": -2.4, "jitter": 0.4}, {}, (19, 19)),
    ({"x0": -0.45, "y0": 0.3, "jitter": 0.3, "halo": 0.1, "halo_width": 2.5}, {},
     (20, 18)),
    ({"x0": 0.2, "y0": 0.1}, {"oversample": 2.0}, (19, 19)),
    ({"x0": 0.2, "y0": -0.6, "source_radius": 0.8}, {"source": "disc"}, (19, 19)),
])
def test_agrees_with_the_engine_where_the_generator_does_not_reach(values, over, shape):
    m = _model()
    if over:
        from difstar.fitting import ImageModel, Light, obstructed_circle_pupil

        m = ImageModel(obstructed_circle_pupil(0.425), m.params | {},
                       light=Light.monochromatic(3.6e-6), pad=4, accuracy=3e-3, **over)
    vals = TRUE | values
    direct, cen = _both(m, vals, shape)
    # both within the engine's accuracy target (3e-3 relative RMS) of each other
    assert np.abs(cen - direct).max() < 1e-3 * direct.max()
    rms = np.sqrt(np.mean((cen - direct) ** 2)) / np.sqrt(np.mean(direct**2))
    assert rms < 3e-3


def test_gradients_match_central_differences():
    m = _model()
    shape = (19, 19)
    vals = {**m.values(), **TRUE, "jitter": 0.4, "halo": 0.1, "halo_width": 2.0}
    c = jnp.asarray(centred_psf(m, vals, shape))
    q = fine_factor(m)
    names = ["x0", "y0", "jitter", "halo", "halo_width", "flux", "background"]
    base = {k: jnp.asarray(x, float) for k, x in vals.items()}

    def img(x):
        v = dict(base)
        for i, k in enumerate(names):
            v[k] = x[i]
        return image_from_centred(m, v, shape, c, q)

    x0 = jnp.asarray([float(vals[k]) for k in names])
    jac = np.asarray(jax.jit(jax.jacfwd(img))(x0))
    jrev = np.asarray(jax.jacrev(lambda x: jnp.sum(img(x) ** 2))(x0))
    assert np.all(np.isfinite(jac)) and np.all(np.isfinite(jrev))
    for i in range(len(names)):
        h = 1e-5 * max(1.0, abs(float(x0[i])))
        e = jnp.zeros(len(names)).at[i].set(h)
        fd = (np.asarray(img(x0 + e)) - np.asarray(img(x0 - e))) / (2 * h)
        scale = np.abs(fd).max() + 1e-12
        assert np.abs(jac[..., i] - fd).max() < 1e-6 * max(scale, 1.0), names[i]


def test_which_solves_hold_the_optics():
    m = _model()
    assert optics_fixed(m, ["x0", "y0", "flux", "background", "jitter", "x0@1"])
    assert not optics_fixed(m, ["x0", "rotation"])
    assert not optics_fixed(m, [])
    assert not optics_fixed(m.with_resampling("lanczos3"), ["x0"])


def test_a_fit_that_holds_the_optics_ends_where_the_engines_path_ends(monkeypatch):
    # a blurred star, so that the jitter's minimum lies inside its bounds: both solves
    # reach their minima (with no blur the jitter creeps to its bound at 0 for 50–150
    # steps, and two solves stopped short of it differ by their paths)
    clean = _numpy_star(**TRUE, blur=0.5)
    sig = 2e-3 * clean.max()
    rng = np.random.default_rng(3)
    d = FitData.from_array(clean + rng.normal(0, sig, clean.shape), sigma=sig)
    m = _model(rotation=Param(TRUE["rotation"]), jitter=Param(0.3, True, (0, 2)))
    used = []
    real = _solve.centred_psf
    monkeypatch.setattr(_solve, "centred_psf", lambda *a, **k: used.append(1) or real(*a, **k))
    cen = fit(m, d, max_steps=60)
    assert used, "the solve did not use the centred PSF"
    monkeypatch.setattr(_solve, "optics_fixed", lambda *a: False)
    eng = fit(m, d, max_steps=60)
    assert cen.converged and eng.converged
    assert abs(eng.values["jitter"] - 0.5) < 4 * eng.errors["jitter"]
    # the two paths' minima differ by 0.11 (flux) and 0.14 (background) standard errors,
    # with optimistix's trust-region update as with difstar's: the centred PSF's shift
    # in its spectrum is periodic over the padded window, the engine's tilt is not
    for k in cen.free:
        assert abs(cen.values[k] - eng.values[k]) < 0.2 * eng.errors[k], k
    assert abs(cen.values["x0"] - TRUE["x0"]) < 0.01
    assert abs(cen.values["y0"] - TRUE["y0"]) < 0.01


@pytest.mark.parametrize("pixel_scale,blur", [(1.0, 1.0), (1.0, 0.5), (1.5, 0.7),
                                              (0.2, 0.6)])
def test_blurs_of_undersampled_data_against_the_independent_star(pixel_scale, blur):
    """Data whose pixels undersample the intensity (1.0″ and 1.5″ pixels: bandwidth
    1.1–1.7 cycles a pixel) with a detector's Gaussian blur: the NumPy generator blurs
    its fine grid before its pixels integrate. The model's image (point samples q times
    finer, pixels and blurs in their spectrum) and the centred path both meet it to
    1e-2 of the peak; blurring the pixel-integrated samples instead, as difstar did
    before, missed by 6–12e-2 (a sampled 0.2″ case, q = 1, for contrast)."""
    truth = _numpy_star((25, 25), **TRUE, pixel_scale=pixel_scale, blur=blur)
    m = _model(pixel_scale=Param(pixel_scale))
    assert (fine_factor(m) > 1) == (pixel_scale > 0.5)
    direct, cen = _both(m, TRUE | {"jitter": blur}, truth.shape)
    peak = truth.max()
    assert np.abs(direct - truth).max() < 1e-2 * peak
    assert np.abs(cen - truth).max() < 1e-2 * peak
    assert np.abs(cen - direct).max() < 1e-3 * peak
