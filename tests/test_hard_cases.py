"""Hard cases: each checked for finite output, finite gradients and, where it has one, its
error against an independent truth: the NumPy camera of ``tests/raw_generator.py`` (which
shares no code with difstar's model), an analytic integral or the exact polygon transform
(small crops and grids: the full-size benchmark is ``difstar bench``).

Errors against the independent camera outside the source's core, relative (measured
2026-11-28 at the cases' accuracy target 3e-2): f/64 2.2e-2, saturated f/22 1.6e-2, the
million-times-brighter source 2.3e-2; at difstar's default accuracy 1e-3 the same
comparisons read 1.8e-3, 3.9e-3 and 3.7e-3 (the two cameras' floor: the generator's
period and point-tested pupil, and at f/22 difstar's PSF sampled at the pixel centres
where the generator integrates), and the image turned by 180° is 0.15–0.24 off.
"""

import dataclasses
import json
import os
import subprocess
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import raw_generator as G
from helpers import polygon_psf_exact

import difstar
from difstar._mft import focused_image, polygon_psf
from difstar._sampling import choose_grid, scene_extent

F = 51.5e-3
P = 3.917e-6


def _camera(f_number=22.0, *, defocus=None, blades=7, phi0=None):
    cam, _ = difstar.paper_camera("focused")
    lens = difstar.Lens(difstar.RegularPolygon(blades, F / (2 * f_number), 0.1), focal_length=F,
                        focus_distance=1.0, principal_separation=-3e-3, defocus=defocus)
    sensor = cam.sensor
    if phi0 is not None:
        sensor = eqx.tree_at(lambda s: s.phi0, sensor, jnp.asarray(phi0, float))
    return difstar.Camera(lens, sensor)


def _scene(src=0.3e-3, background=0.0, exposure=2.5):
    return difstar.Scene(object_distance=1.0, sources=(difstar.DiscSource(src),),
                         exposure_time=exposure, background=(background,) * 3)


def _err(a, ref, crop, radius_px, margin=None):
    if margin is None:
        margin = min(20.0, max(crop) / 2 - radius_px - 4)
    yy, xx = np.mgrid[: crop[0], : crop[1]]
    m = np.broadcast_to(np.hypot(yy - crop[0] // 2, xx - crop[1] // 2) > radius_px + margin,
                        ref.shape)
    return float(np.sqrt(np.sum((a - ref)[m] ** 2) / np.sum(ref[m] ** 2)))


def _loss(camera, scene, grid):
    pred = difstar.simulate(camera, scene, grid)
    w = jnp.linspace(0.0, 1.0, grid.crop[1])
    return jnp.sum(pred.cfa * w) + jnp.sum(pred.image[1] * w)


#: the chain as users run it: one compiled program per grid (not op by op)
simulate = eqx.filter_jit(difstar.simulate)


def _generator_image(camera, scene, crop, *, fft_size: int = 1024):
    """The linear image (3, h, w) of ``camera`` and ``scene`` (a straight iris in focus, one
    disc on the axis, no background) by the independent NumPy camera
    (``tests/raw_generator.py``: point-tested pupil, one zero-padded FFT, pixels summed
    over a 4² sub-grid), scaled per channel to difstar's totals later (the radiometry is
    checked apart, in test_independent_camera.py)."""
    lens, pupil, sen = camera.lens, camera.lens.pupil, camera.sensor
    cfg = G.Configuration("focused", float(lens.focus_distance), float(scene.object_distance),
                          (), (crop[0] // 2, crop[1] // 2))
    iris = G.Iris(n=pupil.n, circumradius=float(pupil.circumradius), curvature=0.0,
                  rotation=float(pupil.rotation), spherical=0.0)
    camp = G.Campaign(
        lens=G.Lens(float(lens.focal_length), float(lens.principal_separation),
                    float(lens.pupil_magnification)),
        iris=iris, sensor=G.Sensor(pixel_pitch=float(sen.pixel_pitch),
                                   wavelengths=tuple(float(w) for w in sen.wavelengths)),
        source_radius=float(scene.sources[0].radius), frame=crop, configurations=(cfg,),
        fft_size=fft_size)
    return np.stack([G.channel_image(camp, cfg, c) for c in range(3)])


def _check_case(camera, scene, crop, *, accuracy, tol, fft_size=None):
    """Finite output and gradients on the default grid; with ``fft_size``, also the
    error outside the core against the independent camera (:func:`_generator_image`
    with that FFT), after one constant per channel; and the image turned by 180° must be
    at least 3× farther off (the comparison can tell orientation). None: no such
    comparison."""
    grid = choose_grid(camera, scene, crop=crop, accuracy=accuracy)
    pred = eqx.filter_jit(simulate)(camera, scene, grid)  # compiled, not op by op
    for a in (pred.image, pred.cfa, pred.srgb, pred.psf):
        assert np.all(np.isfinite(np.asarray(a)))
    g = eqx.filter_jit(eqx.filter_grad(lambda cs: _loss(cs[0], cs[1], grid)))((camera, scene))
    leaves = [x for x in jax.tree_util.tree_leaves(g) if eqx.is_array(x)]
    assert leaves and all(np.all(np.isfinite(np.asarray(x))) for x in leaves)
    if fft_size is None:
        return grid, pred
    # the background is a uniform radiance (the PSF sums to 1): taken off before the
    # comparison with the generator's disc alone
    bg = np.asarray(difstar.irradiance_scale(camera, scene)) * np.asarray(scene.background)
    img = np.asarray(pred.image) - bg[:, None, None]
    gen = _generator_image(camera, scene, crop, fft_size=fft_size)
    gen = gen * img.sum(axis=(1, 2), keepdims=True) / gen.sum(axis=(1, 2), keepdims=True)
    rad = scene_extent(camera, scene)["object_radius_px"]
    err = _err(img, gen, crop, rad)
    assert err < tol, err
    assert _err(img, gen[:, ::-1, ::-1], crop, rad) > 3 * tol
    return grid, pred


def test_f1_8_undersampled_pixels_get_oversampled():
    """f/1.8 with 3.9 µm pixels: the pixel grid undersamples the intensity, so the chain
    runs on the engine's sub-pixel grid, with finite output and gradients. Its accuracy
    is checked against the independent camera, which integrates true pixels
    (tests/test_independent_camera.py, f/1.8 in focus: within 3e-4 of the peak). The fft grid
    at finer padding is no reference here: it samples the PSF at the pixel centres, 9 %
    off beyond the core."""
    camera = _camera(1.8)
    grid, _ = _check_case(camera, _scene(), (32, 32), accuracy=3e-2, tol=None)
    assert grid.method == "engine" and grid.oversample >= 9  # 2 × 4.9 cycles/px at 450 nm


@pytest.mark.slow
def test_large_defocus_5mm_at_f2_8():
    # About 150 waves of defocus, single channel through psf(): the blur (~510 px) fits
    # the window; reference: the geometric disc's encircled energy (test_psf style).
    lam = 600e-9
    r = F / (2 * 2.8)
    dz = 5e-3
    z_r = F
    waves = r * r * dz / (2 * lam * (z_r - dz) * z_r)
    assert waves > 100
    blur_px = 2 * r * dz / (z_r - dz) / P
    n = int(blur_px * 1.15) + 2
    n += n % 2
    pup = difstar.Circle(r)
    kw = dict(wavelength=lam, z_image=z_r, pixel_pitch=P, shape=(n, n), sampling="point")
    plan = difstar.plan_psf(pup, defocus=dz, accuracy=3e-2, **kw)  # Δz is traced below

    def f(dz_):
        return difstar.psf(pup, defocus=dz_, plan=plan, **kw)

    p = np.asarray(f(dz))
    assert np.all(np.isfinite(p))
    yy, xx = np.mgrid[:n, :n] - n // 2
    rad = np.hypot(yy, xx) * P
    r_geo = r * dz / (z_r - dz)
    for frac in (0.3, 0.6, 0.9):
        inside = rad <= frac * r_geo
        assert p[inside].sum() == pytest.approx(inside.sum() * P**2 / (np.pi * r_geo**2),
                                                abs=0.015)
    g = jax.jit(jax.grad(lambda d: jnp.sum(f(d)[n // 2, n // 2 : n // 2 + 40])))(
        jnp.asarray(dz))
    assert np.isfinite(float(g))


def test_f64_psf_spans_hundreds_of_pixels():
    camera = _camera(64.0)
    grid, pred = _check_case(camera, _scene(), (96, 96), accuracy=3e-2, tol=3e-2,
                             fft_size=2048)
    assert grid.oversample == 1  # no oversampling where the pixel grid suffices
    # spikes reach the crop's edge: well above zero there
    assert float(pred.psf[1, 48, 95]) > 1e-7 * float(pred.psf[1].max())


def test_sliver_polygon_close_to_degenerate():
    # A triangle 1000 times longer than wide: exact transform vs FFT path and fast path.
    r = F / (2 * 22)
    v = np.array([[-r, -r / 2000], [r, 0.0], [-r, r / 2000]])
    pup = difstar.Polygon(v)
    n = 64
    exact = polygon_psf_exact(v, wavelength=530e-9, z=F, pixel_pitch=P, shape=(n, n))
    fast = np.asarray(polygon_psf(jnp.asarray(v), wavelength=530e-9, z_image=F, pixel_pitch=P,
                                  shape=(n, n)))
    np.testing.assert_allclose(fast, exact, rtol=1e-7, atol=1e-12 * exact.max())

    kw = dict(wavelength=530e-9, z_image=F, pixel_pitch=P, shape=(n, n), sampling="point")
    plan = difstar.plan_psf(pup, **kw)  # the vertices are traced below

    def f(vv):
        return jnp.sum(difstar.psf(difstar.Polygon(vv), plan=plan, **kw)[:, ::3])

    got = np.asarray(difstar.psf(pup, **kw))
    np.testing.assert_allclose(got, exact, rtol=1e-7, atol=1e-12 * exact.max())
    # the sampled-pupil method sees a sliver 1/1000 of a cell wide: finite, and its
    # window holds no more than all the power
    mft = np.asarray(difstar.psf(pup, method="mft", accuracy=1e-2, **kw))
    assert np.all(np.isfinite(mft)) and 0 < mft.sum() <= 1.0
    for fn in (f, lambda vv: jnp.sum(polygon_psf(vv, wavelength=530e-9, z_image=F,
                                                 pixel_pitch=P, shape=(n, n))[:, ::3])):
        g = np.asarray(jax.jit(jax.grad(fn))(jnp.asarray(v)))  # compiled: op by op, 2.5x
        assert np.all(np.isfinite(g))


def test_closed_form_intensity_gradient_matches_autodiff_and_fd():
    # polygon_intensity's hand-written VJP against JAX autodiff of the same forward and
    # against central differences, float64, on a grid holding k = 0 and offsets along
    # an edge (the series branch) as well as the general case
    from difstar._mft import _intensity_plain, polygon_intensity

    rng = np.random.default_rng(3)
    ang = np.sort(rng.uniform(0, 2 * np.pi, 7))
    w0 = np.stack([np.cos(ang), np.sin(ang)], 1) * 0.6 * (1 + 0.2 * rng.uniform(size=(7, 1)))
    d = (w0[1] - w0[0]) / np.linalg.norm(w0[1] - w0[0])
    u = np.concatenate([np.arange(-20.0, 21.0), [d[0] * 1e-3, d[0] * 0.5]])
    t = np.concatenate([np.arange(-15.0, 1.0), [d[1] * 1e-3, d[1] * 0.5]])
    weights = jnp.asarray(rng.uniform(size=(t.size, u.size)))

    def loss(intensity):
        return lambda w: jnp.sum(weights * jnp.sqrt(intensity(w, u, t)))

    w = jnp.asarray(w0)
    np.testing.assert_allclose(np.asarray(polygon_intensity(w, u, t)),
                               np.asarray(_intensity_plain(w, u, t)), rtol=1e-14)
    g = np.asarray(jax.jit(jax.grad(loss(polygon_intensity)))(w))
    g_auto = np.asarray(jax.jit(jax.grad(loss(_intensity_plain)))(w))
    np.testing.assert_allclose(g, g_auto, rtol=1e-10, atol=1e-12 * np.abs(g_auto).max())
    f = jax.jit(loss(polygon_intensity))  # the differences: compiled, not op by op
    eps = 1e-6
    for j, c in ((0, 0), (2, 1), (5, 0)):
        e = np.zeros_like(w0)
        e[j, c] = eps
        fd = (float(f(w + e)) - float(f(w - e))) / (2 * eps)
        assert g[j, c] == pytest.approx(fd, rel=1e-6)
    assert np.all(np.isfinite(g))


def test_defocus_exactly_zero_has_finite_gradient():
    camera = _camera(22.0, defocus=0.0)
    scene = _scene()
    grid = choose_grid(camera, scene, crop=(32, 32), accuracy=3e-2)
    assert grid.use_defocus is False  # no phase computed at Δz = 0
    g_on = dataclasses.replace(  # the same grid with the phase computed (it is 0)
        grid, use_defocus=True, psf_plan=dataclasses.replace(grid.psf_plan, use_defocus=True))

    def loss(dz):
        cam = eqx.tree_at(lambda c: c.lens.defocus, camera, dz)
        return _loss(cam, scene, g_on)

    d = jax.jit(jax.grad(loss))(jnp.asarray(0.0))
    assert np.isfinite(float(d))
    eps = 2e-6
    loss = jax.jit(loss)
    fd = (loss(jnp.asarray(eps)) - loss(jnp.asarray(-eps))) / (2 * eps)
    assert float(d) == pytest.approx(float(fd), rel=1e-3, abs=1e-6 * abs(float(fd)) + 1e-9)
    a = simulate(camera, scene, grid).image
    b = simulate(camera, scene, g_on).image
    np.testing.assert_allclose(a, b, atol=1e-12)


def test_saturated_sensor_has_finite_gradients():
    camera = _camera(22.0, phi0=(1e-6, 1e-6, 1e-6))
    scene = _scene()
    grid, pred = _check_case(camera, scene, (32, 32), accuracy=3e-2, tol=3e-2, fft_size=1024)
    assert float(jnp.min(pred.cfa)) > 0.99  # saturated everywhere


def test_source_a_million_times_brighter_than_surroundings():
    camera = _camera(22.0)
    scene = _scene(background=1e-6)
    grid, pred = _check_case(camera, scene, (64, 64), accuracy=3e-2, tol=3e-2,
                             fft_size=1024)
    img = np.asarray(pred.image)
    assert img.max() / 1e-6 > 1e5
    assert img.min() >= 1e-6 * (1 - 1e-3) - 1e-12  # background not swamped by ringing


def test_fast_in_focus_path_is_exact_and_beats_the_grid():
    camera = _camera(22.0)
    scene = _scene()
    crop = (64, 64)
    g = difstar.geometry_of(camera, scene)
    rad = int(np.ceil(scene_extent(camera, scene)["object_radius_px"])) + 2
    b = difstar.geometric_image(scene.sources, magnification=g.magnification, pixel_pitch=P,
                                shape=(2 * rad + 1, 2 * rad + 1))
    _, img = focused_image(camera.lens.pupil.vertices, b, camera.sensor.wavelengths,
                           z_image=g.z_exit_pupil, pixel_pitch=P, crop=crop)
    ref = []  # exact PSF (helpers) linearly convolved, brute force over the source pixels
    bb = np.asarray(b)
    k = crop[0] + 2 * rad + 1
    for c, lam in enumerate(np.asarray(camera.sensor.wavelengths)):
        h = polygon_psf_exact(np.asarray(camera.lens.pupil.vertices), wavelength=lam,
                              z=float(g.z_exit_pupil), pixel_pitch=P, shape=(k, k))
        acc = np.zeros(crop)
        for i, j in zip(*np.nonzero(bb[c])):
            r0, c0 = k // 2 - crop[0] // 2 - (i - rad), k // 2 - crop[1] // 2 - (j - rad)
            acc += bb[c, i, j] * h[r0 : r0 + crop[0], c0 : c0 + crop[1]]
        ref.append(acc)
    ref = np.stack(ref)
    np.testing.assert_allclose(np.asarray(img), ref, rtol=1e-9, atol=1e-12 * ref.max())


def test_float32_against_float64():
    # The chain in float32 (default precision) in a subprocess, against float64 here.
    code = (
        "import json, numpy as np, equinox as eqx, difstar\n"
        "from difstar._sampling import choose_grid\n"
        "cam, sc = difstar.paper_camera('defocused')\n"
        "sc = eqx.tree_at(lambda s: s.sources, sc, (difstar.DiscSource(0.3e-3),))\n"
        "g = choose_grid(cam, sc, crop=(64, 64), accuracy=3e-2)\n"
        "p = difstar.simulate(cam, sc, g)\n"
        "print(json.dumps({'dtype': str(p.image.dtype), 'n': g.n,"
        " 'image': np.asarray(p.image).tolist(), 'srgb': np.asarray(p.srgb).tolist()}))\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "JAX_ENABLE_X64"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env=env, check=True)
    r = json.loads(out.stdout.strip().splitlines()[-1])
    assert r["dtype"] == "float32"
    camera, scene = difstar.paper_camera("defocused")
    scene = eqx.tree_at(lambda s: s.sources, scene, (difstar.DiscSource(0.3e-3),))
    grid = choose_grid(camera, scene, crop=(64, 64), accuracy=3e-2)
    assert grid.n == r["n"]
    pred = simulate(camera, scene, grid)
    rad = scene_extent(camera, scene)["object_radius_px"]
    assert _err(np.asarray(r["image"]), np.asarray(pred.image), (64, 64), rad) < 1e-3
    assert float(np.mean((np.asarray(r["srgb"]) - np.asarray(pred.srgb)) ** 2)) < 1e-8


@pytest.mark.parametrize("shape, centre, q", [((9, 12), None, 1), ((8, 7), (2, 5), 2)])
def test_polygon_psf_gradient_folded_by_symmetry(shape, centre, q):
    # polygon_psf evaluates the whole window but runs its gradient on a half-plane (the
    # cotangent folded by I(k) = I(−k)); against autodiff of a plain whole-window
    # evaluation and central differences, float64, with the window off-centre so that
    # the two halves differ in size
    from difstar._mft import _area, _intensity_plain

    rng = np.random.default_rng(5)
    ang = np.sort(rng.uniform(0, 2 * np.pi, 6))
    r = F / (2 * 22)
    v = jnp.asarray(np.stack([np.cos(ang), np.sin(ang)], 1) * r * (1 + 0.1 * rng.uniform(size=(6, 1))))
    weights = jnp.asarray(rng.uniform(size=shape))
    kw = dict(wavelength=530e-9, z_image=F, pixel_pitch=P, shape=shape, oversample=q,
              centre=centre)

    def plain(vv):  # the same PSF, no symmetry, plain autodiff
        h, w = shape
        ch, cw = (h // 2, w // 2) if centre is None else centre
        dx = P / q
        beta = 2 * np.pi * dx / (530e-9 * F)
        t = ((2 * ch * q + q - 1) - 2 * np.arange(h * q)) * 0.5
        u = (2 * np.arange(w * q) - (2 * cw * q + q - 1)) * 0.5
        inten = _intensity_plain(vv * beta, u, t) / (4 * np.pi**2 * _area(vv * beta))
        return inten.reshape(h, q, w, q).sum(axis=(1, 3))

    np.testing.assert_allclose(np.asarray(polygon_psf(v, **kw)), np.asarray(plain(v)), rtol=1e-12)
    loss = lambda fn: lambda vv: jnp.sum(weights * jnp.sqrt(fn(vv)))  # noqa: E731
    g = np.asarray(jax.jit(jax.grad(loss(lambda vv: polygon_psf(vv, **kw))))(v))
    g_auto = np.asarray(jax.jit(jax.grad(loss(plain)))(v))
    np.testing.assert_allclose(g, g_auto, rtol=1e-9, atol=1e-12 * np.abs(g_auto).max())
    f = jax.jit(loss(lambda vv: polygon_psf(vv, **kw)))  # compiled, not op by op
    eps = 1e-6 * r
    for j, c in ((0, 0), (3, 1)):
        e = np.zeros(v.shape)
        e[j, c] = eps
        fd = (float(f(v + e)) - float(f(v - e))) / (2 * eps)
        assert g[j, c] == pytest.approx(fd, rel=1e-6)


def test_closed_form_gradient_in_float32_matches_float64():
    # float32 uses the series for |q| < 0.5 (float64: 1e-2), so the series' truncation
    # and the general form's cancellation are both exercised: against the float64
    # gradient, on offsets along an edge at |q| from 1e-4 to 2 and a general grid
    from difstar._mft import polygon_intensity

    rng = np.random.default_rng(7)
    ang = np.sort(rng.uniform(0, 2 * np.pi, 7))
    w0 = np.stack([np.cos(ang), np.sin(ang)], 1) * 0.6 * (1 + 0.2 * rng.uniform(size=(7, 1)))
    d = w0[1] - w0[0]
    s = np.array([1e-4, 0.05, 0.2, 0.45, 0.55, 1.0, 2.0]) / np.dot(d, d)  # q = s |d|²
    u = np.concatenate([np.arange(-12.0, 13.0), d[0] * s])
    t = np.concatenate([np.arange(-9.0, 1.0), d[1] * s])
    weights = rng.uniform(size=(t.size, u.size))

    def grad(dtype):
        uu, tt, ww = u.astype(dtype), t.astype(dtype), jnp.asarray(weights, dtype)
        f = lambda w: jnp.sum(ww * jnp.sqrt(polygon_intensity(w, uu, tt)))  # noqa: E731
        return np.asarray(jax.jit(jax.grad(f))(jnp.asarray(w0, dtype)), np.float64)

    g32, g64 = grad(np.float32), grad(np.float64)
    assert np.all(np.isfinite(g32))
    np.testing.assert_allclose(g32, g64, rtol=0, atol=2e-5 * np.abs(g64).max())
