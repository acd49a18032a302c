"""Speed against error for the paper's scenes: the benchmark behind BENCHMARKS.md.

    python benchmarks/speed_vs_error.py [--quick] [--config focused] [--json out.json] ...

Outer layer (times, prints progress, spawns a float64 subprocess for the references); it
only *calls* the core. What it measures, for the paper's focused and defocused scenes:

- error against a converged reference (a) on the linear image outside the source's core
  (relative RMS beyond ``CORE_MARGIN_PX`` pixels from the source image's edge) and (b) on
  the final sRGB image (MSE) at the capture's exposure (DESIGN.md, "Measuring error");
- wall time (best of a few runs) with the compile time apart, for a plain NumPy
  implementation of the paper's method on its 3750² grid, difstar's default and difstar at
  tighter accuracy targets; forward and reverse-mode (gradient) time; peak memory;
- the FFT floor: the FFTs the chain needs on the grid it chose, timed in the same run;
- the in-focus 7-blade PSF from prysm (matrix DFT), against difstar and the exact
  polygon transform (Lee & Mittra 1983).

References. Focused: the exact polygon transform of the pupil, linearly convolved with
the geometric image (no grid, no wrap: an independent truth). Defocused: the PSF engine
(checked against quadrature and the exact transform in ``tests/test_psf_truths.py``) in
float64 at accuracy 1e-4, its field's period a much larger grid (``REF_PADDING``),
convolved linearly with the exact source coverage; its convergence is shown by pushing
the period further and reporting the change, and by the same reference's agreement with
the exact one in focus.

Rows: the paper's method in NumPy; difstar's default (``choose_grid``: the closed form in
focus, the PSF engine otherwise) and the engine at a tighter accuracy; and the paper's
own n × n grid in difstar (``method="fft"``) at its default padding and others.
"""

from __future__ import annotations

import json
import math
import os
import platform
import subprocess
import sys
import time
import tracemalloc
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

CORE_MARGIN_PX = 20.0
REF_PADDING = (3.0, 5.0)  # reference and its convergence check (defocused scene)
REF_ACCURACY = 1e-4  # the reference's PSF engine (its sub-cells)
BASELINE_N = 3750
ENGINE_TIGHT = 1e-4  # the engine's tighter row (defocused)


def _log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


# --------------------------------------------------------------------------- scenes


def paper_case(config: str, *, source_radius: float | None = None):
    """The paper's camera and scene; ``source_radius`` (object plane, metres) overrides
    the 5.25 mm disc (the quick benchmark uses a smaller one)."""
    import equinox as eqx

    import difstar

    camera, scene = difstar.paper_camera(config)
    if source_radius is not None:
        scene = eqx.tree_at(lambda s: s.sources, scene, (difstar.DiscSource(source_radius),))
    return camera, scene


def _source_radius_px(camera, scene) -> float:
    from difstar.stages import scene_extent

    return scene_extent(camera, scene)["object_radius_px"]


def core_mask(crop: tuple[int, int], radius_px: float, margin: float = CORE_MARGIN_PX):
    """True where a pixel lies more than ``margin`` px beyond the source's edge (the source
    image centred at the crop's centre pixel)."""
    h, w = crop
    yy, xx = np.mgrid[:h, :w]
    return np.hypot(yy - h // 2, xx - w // 2) > radius_px + margin


def rel_rms(a, ref, mask) -> float:
    a = np.asarray(a, float)
    ref = np.asarray(ref, float)
    m = np.broadcast_to(mask, ref.shape)
    return float(np.sqrt(np.sum((a - ref)[m] ** 2) / np.sum(ref[m] ** 2)))


def render(camera, scene, image) -> np.ndarray:
    """The same post-processing for every method's linear image (3, h, w): sensor
    response at the capture's exposure, CFA, demosaic, colour → sRGB (3, h, w)."""
    import jax.numpy as jnp

    from difstar.stages import mosaic, render_srgb, sensor

    sen = camera.sensor
    img = jnp.asarray(image, dtype=sen.phi0.dtype) + scene.background[:, None, None]
    zeta = sensor(img, exposure_time=scene.exposure_time, phi0=sen.phi0, response=sen.response)
    cfa = mosaic(zeta, sen.pattern)
    return np.asarray(
        render_srgb(cfa, sen.pattern, white_balance=sen.white_balance, matrix=sen.colour_matrix)
    )


# --------------------------------------------------------------------------- references


def polygon_ft(vertices: np.ndarray, kx: np.ndarray, ky: np.ndarray) -> np.ndarray:
    """Exact ∫_P exp(−i k·x) dA of a polygon (Lee & Mittra 1983): the test suite's
    independent reference, ``tests/references.py`` (this benchmark needs a clone)."""
    tests = Path(__file__).resolve().parents[1] / "tests"
    if str(tests) not in sys.path:
        sys.path.insert(0, str(tests))
    from references import polygon_ft as exact  # noqa: PLC0415

    return exact(vertices, kx, ky)


def exact_polygon_psf(vertices, *, wavelength, z, pixel_pitch, shape) -> np.ndarray:
    """Point-sampled in-focus PSF of a polygon, centred at (H//2, W//2), normalised so the
    sum over the infinite pixel grid is 1 (Parseval)."""
    h, w = shape
    u = (np.arange(w) - w // 2) * pixel_pitch
    v = -(np.arange(h) - h // 2) * pixel_pitch
    s = 2 * np.pi / (wavelength * z)
    amp = polygon_ft(vertices, s * u[None, :], s * v[:, None])
    v0 = np.asarray(vertices, float)
    v1 = np.roll(v0, -1, axis=0)
    area = 0.5 * np.sum(v0[:, 0] * v1[:, 1] - v1[:, 0] * v0[:, 1])
    return np.abs(amp) ** 2 * pixel_pitch**2 / ((wavelength * z) ** 2 * area)


def exact_focused_image(camera, scene, crop: tuple[int, int]) -> np.ndarray:
    """The in-focus linear image (3, h, w) with no grid: the exact polygon PSF linearly
    convolved with the geometric image (every source pixel, every PSF offset it needs)."""
    import scipy.signal

    import difstar

    g = difstar.geometry_of(camera, scene)
    p = camera.sensor.pixel_pitch
    rad = int(math.ceil(_source_radius_px(camera, scene))) + 2
    light = difstar.radiometry(camera, scene, g)  # the light the pupil passes
    b = np.asarray(
        difstar.geometric_image(scene.sources, magnification=g.magnification, pixel_pitch=p,
                                shape=(2 * rad + 1, 2 * rad + 1),
                                extended_scale=light.extended_scale,
                                point_scale=light.point_scale),
        float,
    )
    verts = np.asarray(camera.lens.pupil.vertices, float)
    out = []
    for c, lam in enumerate(np.asarray(camera.sensor.wavelengths, float)):
        k = (crop[0] + 2 * rad + 1, crop[1] + 2 * rad + 1)
        h = exact_polygon_psf(verts, wavelength=lam, z=float(g.z_exit_pupil), pixel_pitch=p,
                              shape=k)
        full = scipy.signal.fftconvolve(h, b[c], mode="full")
        out.append(full[2 * rad : 2 * rad + crop[0], 2 * rad : 2 * rad + crop[1]])
    return np.stack(out)


def difstar_reference(camera, scene, crop: tuple[int, int], padding: float) -> np.ndarray:
    """difstar's linear image (3, h, w) through the PSF engine (verified against
    quadrature: ``tests/test_psf_truths.py``) at accuracy ``REF_ACCURACY``, its field's
    period the n × n grid of ``padding``, convolved linearly with the exact source
    coverage. Run in float64 (the ``reference`` subcommand of this module sets
    JAX_ENABLE_X64)."""
    import equinox as eqx
    import jax

    import difstar
    from difstar.stages import choose_grid

    n = choose_grid(camera, scene, crop=crop, padding=padding, method="fft").n
    grid = choose_grid(camera, scene, crop=crop, n=n, accuracy=REF_ACCURACY, raw_only=True,
                       method="engine")
    return np.asarray(jax.block_until_ready(
        eqx.filter_jit(difstar.simulate)(camera, scene, grid).image))


def reference_images(config: str, crop, source_radius, paddings, cache: Path | None):
    """{padding: image} from a float64 subprocess (cached on disk when ``cache``)."""
    key = f"ref_{config}_{crop[0]}x{crop[1]}_{source_radius}_{'_'.join(map(str, paddings))}"
    path = (cache or Path(os.environ.get("TMPDIR", "/tmp"))) / f"difstar_bench_{key}.npz"
    if cache is None or not path.exists():
        _log(f"  reference ({config}, float64, padding {paddings}) in a subprocess ...")
        env = dict(os.environ, JAX_ENABLE_X64="1")
        args = [sys.executable, str(Path(__file__).resolve()), "reference", config, str(crop[0]),
                str(crop[1]), str(source_radius), ",".join(map(str, paddings)), str(path)]
        subprocess.run(args, check=True, env=env)
    with np.load(path) as z:
        return {float(k): z[k] for k in z.files}


# --------------------------------------------------------------------------- baseline


def paper_baseline(camera, scene, *, n: int, crop: tuple[int, int]):
    """The paper's method as a reader would write it in plain NumPy (complex128): binary
    pupil raster on the n × n frequency grid, defocus phase exp(i k W) (Eq. 2–4, in the
    Fresnel scaling the reference uses, so the difference is numerical only),
    PSF = |IFFT(ATF)|², OTF = FFT(PSF), C = IFFT(OTF · FFT(B)), crop.

    The geometric image B is difstar's, with the light the pupil passes
    (``difstar.radiometry``; the same object for every method; computed before the clock
    starts). Returns (image (3, h, w), seconds, peak bytes by tracemalloc).
    """
    import difstar
    from difstar.stages import defocus_phase_coefficient

    g = difstar.geometry_of(camera, scene)
    p = camera.sensor.pixel_pitch
    z_r = float(g.z_exit_pupil)
    dz = float(g.defocus)
    use_dz = difstar.needs_defocus(camera, scene)
    rad = difstar.radiometry(camera, scene, g)  # the light the pupil passes, as simulate's
    b = np.asarray(difstar.geometric_image(scene.sources, magnification=g.magnification,
                                           pixel_pitch=p, shape=(n, n),
                                           extended_scale=rad.extended_scale,
                                           point_scale=rad.point_scale), float)
    verts = np.asarray(camera.lens.pupil.vertices, float)
    lams = np.asarray(camera.sensor.wavelengths, float)
    r0, c0 = n // 2 - crop[0] // 2, n // 2 - crop[1] // 2
    tracemalloc.start()
    t0 = time.perf_counter()
    f = (np.arange(n) - n // 2) / (n * p)
    out = []
    for c, lam in enumerate(lams):
        x = lam * z_r * f[None, :]
        y = -lam * z_r * f[:, None]
        inside = np.ones((n, n), bool)
        for a, e in zip(verts, np.roll(verts, -1, axis=0)):  # CCW: left of every edge
            inside &= (e[0] - a[0]) * (y - a[1]) - (e[1] - a[1]) * (x - a[0]) >= 0
        atf = inside.astype(complex)
        if use_dz:
            k = defocus_phase_coefficient(lam, z_r, dz)
            atf *= np.exp(1j * k * (f[None, :] ** 2 + f[:, None] ** 2))
        h = np.fft.fftshift(np.fft.ifft2(np.fft.ifftshift(atf)))
        psf = np.abs(h) ** 2
        psf /= psf.sum()
        otf = np.fft.fft2(np.fft.ifftshift(psf))
        img = np.real(np.fft.ifft2(otf * np.fft.fft2(b[c])))
        out.append(img[r0 : r0 + crop[0], c0 : c0 + crop[1]].copy())
    seconds = time.perf_counter() - t0
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return np.stack(out), seconds, peak


# --------------------------------------------------------------------------- difstar timing


@dataclass
class Timing:
    compile_s: float
    forward_s: float
    grad_compile_s: float
    grad_s: float
    fft_floor_s: float
    peak_bytes: int
    grad_peak_bytes: int


def _best(fn, repeats: int) -> float:
    import jax

    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn())
        best = min(best, time.perf_counter() - t0)
    return best


def _mem(compiled) -> int:
    """XLA's peak memory estimate of a compiled program (arguments, outputs and
    temporaries), -1 where the backend gives none. ``compiled`` is a JAX ``Compiled`` or
    equinox's wrapper of one (which holds it as ``.compiled``)."""
    compiled = getattr(compiled, "compiled", compiled)
    try:
        m = compiled.memory_analysis()
        return int(m.temp_size_in_bytes + m.argument_size_in_bytes + m.output_size_in_bytes)
    except Exception:  # backend without memory analysis
        return -1


def fft_floor(grid, dtype, pixel_pitch: float, repeats: int = 3) -> float:
    """Seconds for exactly the FFTs ``simulate`` does on ``grid``. Full FFT path: per
    channel one complex (nq)² inverse FFT (the field), one real n² FFT (the OTF) and one
    real inverse FFT (the image), plus the real FFT of the three-channel geometric image.
    The PSF engine's path and the exact path: the transforms they do instead
    (``pixel_pitch``: the sensor's, which turns the engine's period into samples)."""
    import jax
    import jax.numpy as jnp

    key = jax.random.PRNGKey(0)
    if grid.method == "exact":
        # the exact path's only FFTs: the convolution of PSF and geometric image
        from difstar.stages import conv_size, window_rfft2

        hb = grid.source_window
        (nh, nw), _ = conv_size(grid.crop, (hb, hb))
        p = jax.random.normal(key, (3, nh, nw), dtype)

        @jax.jit
        def conv(p):
            spec = jnp.fft.rfft2(p) * window_rfft2(p[:, :hb, :hb], (nh, nw))
            return jnp.fft.irfft2(spec, s=(nh, nw))

        jax.block_until_ready(conv(p))
        return _best(lambda: conv(p), repeats)
    if grid.method == "engine":
        # the PSF engine's pruned FFTs, per channel: the field's first pass over the
        # pupil window's rows (length L/p), its second pass over the window's columns,
        # then the linear convolution (real FFTs of a fast size ≥ window + source − 1)
        from difstar.stages import fast_length

        plan, q, hb = grid.psf_plan, grid.oversample, grid.source_window * grid.oversample
        nf = round(plan.period * q / pixel_pitch)
        wp = plan.pupil_window
        kh = grid.crop[0] * q + hb - 1  # the PSF's offsets a side
        lh = fast_length(kh + hb - 1)
        cdt = jnp.result_type(dtype, jnp.complex64)
        a = jax.random.normal(key, (3, wp, wp), dtype).astype(cdt)
        p = jax.random.normal(key, (3, lh, lh), dtype)

        @jax.jit
        def engine(a, p):
            g = jnp.fft.ifft(a, n=nf, axis=2)[:, :, :kh]
            field = jnp.fft.ifft(jnp.swapaxes(g, 1, 2), n=nf, axis=2)[:, :, :kh]
            spec = jnp.fft.rfft2(p) * jnp.fft.rfft2(p[:, :hb, :hb], s=(lh, lh))
            return field, jnp.fft.irfft2(spec, s=(lh, lh))

        jax.block_until_ready(engine(a, p))
        return _best(lambda: engine(a, p), repeats)
    n, m = grid.n, grid.n * grid.oversample
    cdt = jnp.result_type(dtype, jnp.complex64)
    a = jax.random.normal(key, (3, m, m), dtype).astype(cdt)
    b = jax.random.normal(key, (3, n, n), dtype)
    c = jax.random.normal(key, (3, n, n), dtype)

    @jax.jit
    def ffts(a, b, c):
        field = jnp.fft.ifft2(a)
        spec = jnp.fft.rfft2(b) * jnp.fft.rfft2(c)
        return field, jnp.fft.irfft2(spec, s=(n, n))

    jax.block_until_ready(ffts(a, b, c))
    return _best(lambda: ffts(a, b, c), repeats)


def time_difstar(camera, scene, grid, repeats: int = 3):
    """(prediction, Timing): forward and gradient (reverse mode, all parameters), compile
    times apart, XLA's peak memory, and the FFT floor for this grid."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    import difstar

    fwd = eqx.filter_jit(difstar.simulate)
    t0 = time.perf_counter()
    compiled = fwd.lower(camera, scene, grid).compile()
    t_compile = time.perf_counter() - t0
    pred = jax.block_until_ready(compiled(camera, scene, grid))
    t_fwd = _best(lambda: compiled(camera, scene, grid), repeats)

    target = jax.lax.stop_gradient(pred.cfa) * 0.9

    def loss(cs):
        out = difstar.simulate(cs[0], cs[1], grid)
        return jnp.mean((out.cfa - target) ** 2)

    vg = eqx.filter_jit(eqx.filter_value_and_grad(loss))
    t0 = time.perf_counter()
    gcompiled = vg.lower((camera, scene)).compile()
    t_gcompile = time.perf_counter() - t0
    jax.block_until_ready(gcompiled((camera, scene)))
    t_grad = _best(lambda: gcompiled((camera, scene)), repeats)
    dtype = camera.sensor.phi0.dtype
    floor = fft_floor(grid, dtype, camera.sensor.pixel_pitch, repeats)
    timing = Timing(t_compile, t_fwd, t_gcompile, t_grad, floor, _mem(compiled), _mem(gcompiled))
    return pred, timing


def prysm_comparison(*, crop: int = 256, npup: int = 1024, wavelength: float = 530e-9,
                     repeats: int = 3) -> dict:
    """The paper's in-focus 7-blade f/22 PSF from prysm (matrix DFT to the pixel grid) and
    from difstar, each against the exact polygon transform over a ``crop`` window."""
    import jax

    import difstar

    camera, scene = difstar.paper_camera("focused")
    g = difstar.geometry_of(camera, scene)
    z = float(g.z_exit_pupil)
    p = camera.sensor.pixel_pitch
    r = float(camera.lens.pupil.circumradius)
    verts = np.asarray(camera.lens.pupil.vertices, float)
    exact = exact_polygon_psf(verts, wavelength=wavelength, z=z, pixel_pitch=p,
                              shape=(crop, crop))
    mask = core_mask((crop, crop), 0.0)
    out: dict = {"crop": crop, "wavelength_nm": wavelength * 1e9}
    try:
        import prysm
        from prysm.coordinates import make_xy_grid
        from prysm.geometry import regular_polygon
        from prysm.propagation import Wavefront

        def run_prysm():
            dx_mm = 2 * r * 1e3 * 1.02 / npup
            x, y = make_xy_grid(npup, dx=dx_mm)
            amp = regular_polygon(7, r * 1e3, x, y, rotation=0).astype(float)
            wf = Wavefront.from_amp_and_phase(amp, None, wavelength * 1e6, dx_mm)
            field = wf.focus_fixed_sampling(z * 1e3, p * 1e6, crop).data
            inten = np.abs(field) ** 2
            area = amp.sum() * (dx_mm * 1e-3) ** 2
            return inten / inten[crop // 2, crop // 2] * area * p**2 / (wavelength * z) ** 2

        run_prysm()
        t = math.inf
        for _ in range(repeats):
            t0 = time.perf_counter()
            pr = run_prysm()
            t = min(t, time.perf_counter() - t0)
        # prysm's image axes may be flipped relative to difstar's; take its best orientation
        cands = [pr, pr[::-1], pr[:, ::-1], pr[::-1, ::-1], pr.T]
        errs = [rel_rms(c, exact, mask) for c in cands]
        pr = cands[int(np.argmin(errs))]
        out["prysm"] = {"version": prysm.__version__, "pupil_samples": npup, "seconds": t,
                        "err_vs_exact": min(errs)}
    except ImportError:
        out["prysm"] = None
        pr = None

    # difstar: the PSF engine on exactly this window (point samples, as prysm gives),
    # planned outside jit, timed jitted
    lens = camera.lens
    n = crop
    kw = dict(wavelength=wavelength, z_image=z, pixel_pitch=p, shape=(crop, crop),
              sampling="point")
    plan = difstar.plan_psf(lens.pupil, **kw)
    fn = jax.jit(lambda pup: difstar.psf(pup, plan=plan, **kw))
    t0 = time.perf_counter()
    jax.block_until_ready(fn(lens.pupil))
    t_c = time.perf_counter() - t0
    t = _best(lambda: fn(lens.pupil), repeats)
    ds = np.asarray(fn(lens.pupil), float)
    out["difstar"] = {"n": n, "seconds": t, "compile_s": t_c,
                      "err_vs_exact": rel_rms(ds, exact, mask)}
    if pr is not None:
        out["prysm_vs_difstar"] = rel_rms(pr, ds, mask)
    return out


# --------------------------------------------------------------------------- the run


@dataclass
class Row:
    config: str
    method: str
    n: int
    oversample: int
    padding: float | None
    lin_err: float
    srgb_mse: float
    forward_s: float
    compile_s: float | None = None
    grad_s: float | None = None
    grad_compile_s: float | None = None
    fft_floor_s: float | None = None
    peak_mb: float | None = None
    grad_peak_mb: float | None = None
    extra: dict = field(default_factory=dict)


def machine() -> dict:
    import jax

    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"cpu": cpu, "cores": os.cpu_count(), "python": platform.python_version(),
            "jax": jax.__version__, "numpy": np.__version__, "backend": jax.default_backend(),
            "devices": [str(d) for d in jax.devices()]}


def run(*, quick: bool = False, configs=("focused", "defocused"), accuracies=None,
        paddings=None, baseline_n: int | None = None, cache: Path | None = None,
        repeats: int = 3, with_prysm: bool = True) -> dict:
    """The whole benchmark; returns a JSON-able dict (rows, machine, references)."""
    import difstar
    from difstar.stages import DEFAULT_ACCURACY, choose_grid, padding_for_accuracy

    if quick:
        crop, src_r = (128, 128), 0.5e-3
        baseline_n = baseline_n or 3 * 128
        accuracies = accuracies or (DEFAULT_ACCURACY, 3e-3)
        paddings = paddings if paddings is not None else ()
        repeats = min(repeats, 2)
    else:
        crop, src_r = (1250, 1250), None
        baseline_n = baseline_n or BASELINE_N
        accuracies = accuracies or (DEFAULT_ACCURACY, 5e-3)
        paddings = paddings if paddings is not None else (0.25,)
    result: dict = {"machine": machine(), "crop": list(crop), "rows": [], "references": {},
                    "quick": quick}
    rows: list[Row] = []
    for config in configs:
        _log(f"speed_vs_error: {config} scene, crop {crop[0]}×{crop[1]}")
        camera, scene = paper_case(config, source_radius=src_r)
        mask = core_mask(crop, _source_radius_px(camera, scene))
        refs = reference_images(config, crop, src_r, REF_PADDING, cache)
        ref_big = refs[REF_PADDING[-1]]
        ref_info = {"difstar_f64_padding": list(REF_PADDING),
                    "difstar_f64_change_lin": rel_rms(refs[REF_PADDING[0]], ref_big, mask)}
        if config == "focused" or not difstar.needs_defocus(camera, scene):
            _log("  exact polygon-transform reference ...")
            ref = exact_focused_image(camera, scene, crop)
            ref_info["kind"] = "exact polygon transform ⊛ geometric image"
            ref_info["difstar_f64_vs_exact_lin"] = rel_rms(ref_big, ref, mask)
        else:
            ref = ref_big
            ref_info["kind"] = (f"the PSF engine in float64 (accuracy {REF_ACCURACY:g}) on the "
                                f"period of padding {REF_PADDING[-1]}")
        ref_srgb = render(camera, scene, ref)
        ref_info["difstar_f64_change_srgb_mse"] = float(
            np.mean((render(camera, scene, refs[REF_PADDING[0]]) - ref_srgb) ** 2))
        result["references"][config] = ref_info

        def errors(img):
            return rel_rms(img, ref, mask), float(np.mean((render(camera, scene, img)
                                                           - ref_srgb) ** 2))

        _log(f"  NumPy paper baseline on {baseline_n}² ...")
        img, secs, peak = paper_baseline(camera, scene, n=baseline_n, crop=crop)
        le, se = errors(img)
        rows.append(Row(config, f"numpy paper method N={baseline_n}", baseline_n, 1, None, le,
                        se, secs, peak_mb=peak / 2**20))
        _log(f"    {secs:.2f} s, lin err {le:.3g}, sRGB MSE {se:.3g}")

        camera32 = _to_float32(camera)
        scene32 = _to_float32(scene)
        settings = [("paper's grid (method='fft')" if a == DEFAULT_ACCURACY else
                     f"paper's grid accuracy={a:g}", padding_for_accuracy(a), a)
                    for a in accuracies]
        settings += [(f"paper's grid padding={pd:g}", pd, None) for pd in paddings]
        grids = [(name, pad, acc, choose_grid(camera, scene, crop=crop, padding=pad,
                                              method="fft")) for name, pad, acc in settings]
        if config != "focused" and difstar.needs_defocus(camera, scene):
            grids = [(f"default (PSF engine{'' if a is None else f', accuracy={a:g}'})",
                      None, a, choose_grid(camera, scene, crop=crop, accuracy=a))
                     for a in (None, ENGINE_TIGHT)] + grids
        for name, pad, acc, grid in grids:
            n_eff = (round(grid.psf_plan.period / camera.sensor.pixel_pitch)
                     if grid.method == "engine" else grid.n)
            _log(f"  difstar {name}: n = {n_eff}, q = {grid.oversample} ...")
            pred, t = time_difstar(camera32, scene32, grid, repeats)
            le, se = errors(np.asarray(pred.image, float))
            rows.append(Row(config, f"difstar {name}", n_eff, grid.oversample, pad, le, se,
                            t.forward_s, t.compile_s, t.grad_s, t.grad_compile_s, t.fft_floor_s,
                            t.peak_bytes / 2**20, t.grad_peak_bytes / 2**20,
                            {"accuracy": acc}))
            _log(f"    fwd {t.forward_s:.3f} s (compile {t.compile_s:.1f}), grad "
                 f"{t.grad_s:.3f} s, FFT floor {t.fft_floor_s:.3f} s, lin err {le:.3g}, "
                 f"sRGB MSE {se:.3g}")
        default = choose_grid(camera, scene, crop=crop)
        if default.method == "exact":  # in focus: the default is the closed-form path
            _log("  difstar default: exact in-focus path (no grid) ...")
            pred, t = time_difstar(camera32, scene32, default, repeats)
            le, se = errors(np.asarray(pred.image, float))
            from difstar.stages import conv_size

            (n_conv, _), _ = conv_size(default.crop, (default.source_window,) * 2)
            rows.append(Row(config, "difstar default (exact in-focus path)", n_conv, 1, None, le, se,
                            t.forward_s, t.compile_s, t.grad_s, t.grad_compile_s,
                            t.fft_floor_s, t.peak_bytes / 2**20, t.grad_peak_bytes / 2**20))
            _log(f"    fwd {t.forward_s:.3f} s, grad {t.grad_s:.3f} s, FFT floor "
                 f"{t.fft_floor_s:.3f} s, lin err {le:.3g}, sRGB MSE {se:.3g}")
    result["rows"] = [asdict(r) for r in rows]
    if with_prysm:
        _log("speed_vs_error: prysm comparison (in-focus 7-blade PSF) ...")
        result["prysm"] = prysm_comparison(crop=128 if quick else 256,
                                           npup=512 if quick else 1024)
    return result


def _to_float32(tree):
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    def cast(x):
        if eqx.is_array(x) and jnp.issubdtype(x.dtype, jnp.floating):
            return x.astype(jnp.float32)
        return x

    return jax.tree_util.tree_map(cast, tree)


# --------------------------------------------------------------------------- report


def table(result: dict) -> str:
    """Markdown tables of a ``run`` result."""
    lines = []
    hdr = ("| scene | method | N | q | lin. err (outside core) | sRGB MSE | forward s | "
           "grad s | grad/fwd | FFT floor s | fwd/floor | compile s (fwd+grad) | peak MiB "
           "(fwd / grad) | speed-up vs NumPy |")
    for config in dict.fromkeys(r["config"] for r in result["rows"]):
        rows = [r for r in result["rows"] if r["config"] == config]
        base = next((r for r in rows if r["method"].startswith("numpy")), None)
        lines += [hdr, "|" + "|".join(["---"] * (hdr.count("|") - 1)) + "|"]
        for r in rows:
            def f(x, fmt="{:.3f}"):
                return "–" if x is None else fmt.format(x)

            ratio = None if r["grad_s"] is None else r["grad_s"] / r["forward_s"]
            floor = None if r["fft_floor_s"] is None else r["forward_s"] / r["fft_floor_s"]
            comp = None if r["compile_s"] is None else f"{r['compile_s']:.1f}+{r['grad_compile_s']:.1f}"
            mem = (f"{r['peak_mb']:.0f}" if r["grad_peak_mb"] is None
                   else f"{r['peak_mb']:.0f} / {r['grad_peak_mb']:.0f}")
            speed = None if base is None else base["forward_s"] / r["forward_s"]
            lines.append(
                f"| {config} | {r['method']} | {r['n']} | {r['oversample']} | "
                f"{r['lin_err']:.2e} | {r['srgb_mse']:.2e} | {f(r['forward_s'])} | "
                f"{f(r['grad_s'])} | {f(ratio, '{:.2f}')} | {f(r['fft_floor_s'])} | "
                f"{f(floor, '{:.2f}')} | {comp or '–'} | {mem} | {f(speed, '{:.1f}×')} |")
        lines.append("")
    refs = result.get("references", {})
    for config, info in refs.items():
        s = f"- {config} reference: {info['kind']}. difstar float64 padding " \
            f"{info['difstar_f64_padding'][0]} → {info['difstar_f64_padding'][1]} changes the " \
            f"linear image by {info['difstar_f64_change_lin']:.2e} (sRGB MSE " \
            f"{info['difstar_f64_change_srgb_mse']:.2e})"
        if "difstar_f64_vs_exact_lin" in info:
            s += f"; difstar float64 (padding {info['difstar_f64_padding'][1]}) against the " \
                 f"exact reference: {info['difstar_f64_vs_exact_lin']:.2e}"
        lines.append(s + ".")
    pr = result.get("prysm")
    if pr:
        lines.append("")
        lines.append(f"In-focus 7-blade f/22 PSF, {pr['crop']}² window, "
                     f"λ = {pr['wavelength_nm']:.0f} nm, relative RMS outside the centre:")
        lines.append("")
        lines.append("| package | setting | time s | error vs exact polygon transform |")
        lines.append("|---|---|---|---|")
        d = pr["difstar"]
        lines.append(f"| difstar | psf engine on the {d['n']}² window (point, defaults) | "
                     f"{d['seconds']:.4f} | "
                     f"{d['err_vs_exact']:.2e} |")
        if pr.get("prysm"):
            q = pr["prysm"]
            lines.append(f"| prysm {q['version']} | matrix DFT, {q['pupil_samples']}² binary "
                         f"pupil | {q['seconds']:.4f} | {q['err_vs_exact']:.2e} |")
            lines.append("")
            lines.append(f"prysm against difstar: {pr['prysm_vs_difstar']:.2e}.")
    m = result["machine"]
    lines.append("")
    lines.append(f"Machine: {m['cpu']}, {m['cores']} cores, {m['backend']} backend; "
                 f"python {m['python']}, jax {m['jax']}, numpy {m['numpy']}.")
    return "\n".join(lines)


def _reference_main(argv) -> int:
    config, h, w, src_r, pads, out = argv
    import jax

    jax.config.update("jax_enable_x64", True)
    camera, scene = paper_case(config, source_radius=None if src_r == "None" else float(src_r))
    imgs = {}
    for pad in pads.split(","):
        t0 = time.perf_counter()
        imgs[pad] = difstar_reference(camera, scene, (int(h), int(w)), float(pad))
        _log(f"    padding {pad}: {time.perf_counter() - t0:.1f} s")
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(str(out) + ".tmp.npz")
    np.savez(tmp, **imgs)
    tmp.replace(out)
    return 0


def _number(what: str, *, integer: bool = False, **limits):
    """An argparse type: a finite number (a whole one if ``integer``) within ``limits``
    (gt, ge, le), else an error naming what was wanted."""
    import argparse

    def parse(text: str):
        try:
            v = int(text) if integer else float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a {what} number") from None
        ok = math.isfinite(v) and all(
            {"gt": v > b, "ge": v >= b, "le": v <= b}[k] for k, b in limits.items())
        if not ok:
            bounds = ", ".join(f"{k} {b}" for k, b in limits.items())
            raise argparse.ArgumentTypeError(f"{text!r}: give a finite {what} number ({bounds})")
        return v

    return parse


def main(argv=None) -> int:
    """The command line (BENCHMARKS.md gives the commands): a Markdown table on stdout,
    progress on stderr; ``--json FILE`` also writes the full result."""
    import argparse

    from difstar.io import OutputError, write_file_atomic

    positive = _number("positive", gt=0)
    nonnegative = _number("non-negative", ge=0)
    ap = argparse.ArgumentParser(
        prog="python benchmarks/speed_vs_error.py",
        description="Time and measure the error of the paper's method (NumPy, 3750² grid) "
        "and difstar at several accuracy settings, on the paper's focused and defocused "
        "scenes; prints a Markdown table (progress on stderr).")
    ap.add_argument("--quick", action="store_true",
                    help="128 px crop, small source, few settings (about a minute)")
    ap.add_argument("--config", choices=("focused", "defocused"), action="append",
                    help="scene(s) to run (default both)")
    ap.add_argument("--accuracy", type=positive, action="append",
                    help="difstar accuracy target(s) to time (default: the default and one "
                    "tighter)")
    ap.add_argument("--padding", type=nonnegative, action="append",
                    help="extra difstar padding settings for the speed-against-error curve "
                    "(default: none)")
    ap.add_argument("--baseline-n", type=_number("whole", integer=True, ge=8, le=65536),
                    help="grid of the NumPy baseline, 8 to 65536 (default 3750)")
    ap.add_argument("--repeats", type=_number("whole", integer=True, ge=1), default=3,
                    help="timed runs per setting (best kept)")
    ap.add_argument("--cache", default=".bench_cache",
                    help="directory caching the float64 references (default .bench_cache)")
    ap.add_argument("--no-prysm", action="store_true", help="skip the prysm comparison")
    ap.add_argument("--json", help="also write the full result as JSON to this file (its "
                    "folder must exist; an existing file is replaced)")
    a = ap.parse_args(argv)
    cache = Path(a.cache)
    if cache.exists() and not cache.is_dir():
        raise OutputError(f"--cache {cache} is a file; give a folder.")
    if a.json:
        j = Path(a.json)
        if j.is_dir() or not j.parent.is_dir():
            raise OutputError(f"--json {j}: give a file in an existing folder.")
    cache.mkdir(parents=True, exist_ok=True)
    result = run(
        quick=a.quick, configs=tuple(a.config or ("focused", "defocused")),
        accuracies=tuple(a.accuracy) if a.accuracy else None,
        paddings=tuple(a.padding) if a.padding else None, baseline_n=a.baseline_n,
        cache=cache, repeats=a.repeats, with_prysm=not a.no_prysm,
    )
    result["command"] = "python benchmarks/speed_vs_error.py " + " ".join(
        sys.argv[1:] if argv is None else argv)
    sys.stdout.write(table(result) + "\n")
    if a.json:
        write_file_atomic(a.json, json.dumps(result, indent=1, default=str) + "\n",
                          overwrite=True, what="--json")
    return 0


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "reference":
        sys.exit(_reference_main(sys.argv[2:]))
    sys.exit(main())
