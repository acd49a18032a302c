"""The PSF engine's figures (issue 13, "Done means"), side by side in one run.

    python benchmarks/psf_engine.py [--only accuracy|speed] [--repeats 3]

Prints Markdown tables (progress on stderr):

a. accuracy of ``difstar.psf`` at its defaults (float64) against independent NumPy truths
   from ``tests/references.py``: the exact polygon transform (point, and integrated over
   each pixel by Gauss–Legendre), quadrature of the Fresnel integral over the polygon at
   sampled pixels, the Hankel integral for a defocused circle;
b. speed and spike-region error of ``difstar.psf`` (float32, as users run it by default)
   against the paper's method in plain NumPy (complex128, binary pupil raster, FFT on a
   3750² grid, |IFFT|² normalised to unit sum on its grid, centre 1250² crop) on the
   paper's 1250² window, in focus and defocused (530 nm, point samples);
c. the machine and the command.

Needs a clone of the repository (it imports ``tests/references.py``).
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
TESTS = ROOT / "tests"


def _references():
    if not (TESTS / "references.py").is_file():
        raise SystemExit(
            f"benchmarks/psf_engine.py: {TESTS / 'references.py'} not found. This benchmark "
            "needs a clone of the difstar repository (git clone, then run it from there); it "
            "is not part of the installed package.")
    if str(TESTS) not in sys.path:
        sys.path.insert(0, str(TESTS))
    import references  # noqa: PLC0415

    return references


LAM = 530e-9
SPIKE_R = 20  # px: the spike region is r > SPIKE_R from the centre pixel


def _log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def _spike_mask(shape, r_px=SPIKE_R):
    h, w = shape
    yy, xx = np.mgrid[:h, :w]
    return np.hypot(yy - h // 2, xx - w // 2) > r_px


def _time_psf(pupil, *, repeats: int, **kw):
    """difstar.psf jitted (pupil and wavelength traced, the plan made outside): (result as
    float64 NumPy, compile+first run seconds, best of ``repeats`` seconds after compile)."""
    import jax  # noqa: PLC0415

    import difstar  # noqa: PLC0415

    lam = kw.pop("wavelength")
    plan = difstar.plan_psf(pupil, wavelength=lam, **kw)
    f = jax.jit(lambda pup, lm: difstar.psf(pup, wavelength=lm, plan=plan, **kw))
    lam_a = jax.numpy.asarray(lam)
    t0 = time.perf_counter()
    out = jax.block_until_ready(f(pupil, lam_a))
    first = time.perf_counter() - t0
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(f(pupil, lam_a))
        best = min(best, time.perf_counter() - t0)
    return np.asarray(out, dtype=float), first, best, plan


def _plan_str(plan) -> str:
    if plan.method == "exact":
        return f"exact, {plan.nodes}² nodes/px"
    return (f"{plan.method}, {plan.nodes}² nodes/px, pupil {plan.pupil_window}², "
            f"{plan.subcells}² sub-cells, L = {plan.period * 1e3:.3g} mm")


def _fmt_s(s: float) -> str:
    return f"{s * 1e3:.3g} ms" if s < 1 else f"{s:.3g} s"


# --- a. accuracy at the defaults (float64) -------------------------------------------------


def accuracy(R, repeats: int) -> list[dict]:
    import difstar  # noqa: PLC0415

    rows = []
    cam, scene = difstar.paper_camera("focused")
    g = difstar.geometry_of(cam, scene)
    z_r = float(g.z_exit_pupil)
    p = float(cam.sensor.pixel_pitch)
    pup = cam.lens.pupil
    pupil = difstar.RegularPolygon(pup.n, float(pup.circumradius), float(pup.rotation))
    v = R.regular_polygon_vertices(pup.n, float(pup.circumradius), float(pup.rotation))
    shape = (256, 256)
    mask = _spike_mask(shape)
    for sampling in ("pixel", "point"):
        _log(f"a. in focus, {sampling}: exact transform (NumPy) ...")
        truth = R.polygon_psf_exact(v, wavelength=LAM, z=z_r, pixel_pitch=p, shape=shape,
                                    sampling=sampling)
        _log(f"a. in focus, {sampling}: difstar.psf ...")
        got, _, best, plan = _time_psf(pupil, repeats=repeats, wavelength=LAM, z_image=z_r,
                                       pixel_pitch=p, shape=shape, sampling=sampling)
        what = f"in focus, 7 blades f/22, 256², sampling=\"{sampling}\""
        e_all = R.rel_rms(got, truth)
        e_spk = R.rel_rms(got[mask], truth[mask])
        e_en = abs(got.sum() - truth.sum()) / truth.sum()
        for metric, err, tgt in (("shape (window)", e_all, 1e-4),
                                 (f"spikes (r > {SPIKE_R} px)", e_spk, 1e-3),
                                 ("window energy", e_en, 1e-4)):
            rows.append(dict(case=what, metric=metric, err=err, target=tgt, time=best,
                             plan=_plan_str(plan), truth="exact transform" + (
                                 ", Gauss–Legendre per pixel" if sampling == "pixel" else "")))

    # the paper's defocused case on 96²: Fresnel quadrature at sampled pixels
    cam, scene = difstar.paper_camera("defocused")
    g = difstar.geometry_of(cam, scene)
    z_r, dz = float(g.z_exit_pupil), float(g.defocus)
    pup = cam.lens.pupil
    pupil = difstar.RegularPolygon(pup.n, float(pup.circumradius), float(pup.rotation))
    v = R.regular_polygon_vertices(pup.n, float(pup.circumradius), float(pup.rotation))
    shape = (96, 96)
    rr, cc = R.sample_pixels(shape, spokes_deg=(0, 180 / 7, 90, 180, 257),
                             radii_px=(4, 12, 20, 26, 32, 47), n_random=40, seed=13)
    _log(f"a. paper defocused 96²: Fresnel quadrature at {len(rr)} pixels ...")
    truth = R.polygon_fresnel_psf(v, rr, cc, wavelength=LAM, z_image=z_r, defocus=dz,
                                  pixel_pitch=p, shape=shape, sampling="pixel")
    _log("a. paper defocused 96²: difstar.psf ...")
    got, _, best, plan = _time_psf(pupil, repeats=repeats, wavelength=LAM, z_image=z_r,
                                   defocus=dz, pixel_pitch=p, shape=shape)
    rows.append(dict(case=f"paper defocused, Δz = {dz * 1e3:.3g} mm, 96², sampling=\"pixel\"",
                     metric=f"shape ({len(rr)} sampled px)", err=R.rel_rms(got[rr, cc], truth),
                     target=1e-3, time=best, plan=_plan_str(plan),
                     truth="Fresnel quadrature over the polygon, Gauss–Legendre per pixel"))

    # circle at f/8 with 10 waves of defocus: the Hankel integral
    z8 = 51.5e-3
    r8 = z8 / 16
    waves = 10.0
    n = 128
    dz = R.defocus_from_waves(waves, wavelength=LAM, radius=r8, z_image=z8)
    blur_px = 2 * r8 * dz / (z8 - dz) / p
    _log("a. circle f/8, 10 waves: Hankel integral ...")
    truth = R.circle_psf(radius=r8, wavelength=LAM, z=z8, pixel_pitch=p, shape=(n, n),
                         sampling="pixel",
                         phase=R.radial_phase(wavelength=LAM, radius=r8, waves=waves))
    _log("a. circle f/8, 10 waves: difstar.psf ...")
    got, _, best, plan = _time_psf(difstar.Circle(r8), repeats=repeats, wavelength=LAM,
                                   z_image=z8, defocus=dz, pixel_pitch=p, shape=(n, n))
    rows.append(dict(case=f"circle f/8, 10 waves (blur {blur_px:.0f} px across), {n}², "
                     "sampling=\"pixel\"", metric="shape (window)", err=R.rel_rms(got, truth),
                     target=1e-3, time=best, plan=_plan_str(plan),
                     truth="Hankel integral, Gauss–Legendre per pixel"))
    return rows


def accuracy_table(rows) -> str:
    out = ["| case | metric | error | target | met | difstar.psf | plan | truth |",
           "|---|---|---:|---:|:---:|---:|---|---|"]
    for r in rows:
        met = "yes" if r["err"] <= r["target"] else "**NO**"
        out.append(f"| {r['case']} | {r['metric']} | {r['err']:.2e} | {r['target']:.0e} | "
                   f"{met} | {_fmt_s(r['time'])} | {r['plan']} | {r['truth']} |")
    out.append("")
    out.append("Float64, `difstar.psf` at its defaults (accuracy 1e-3; in focus the plan is "
               "the closed form, defocused the sampled pupil). Errors: relative RMS "
               "‖psf − truth‖₂/‖truth‖₂ over the window (or the sampled pixels, or the pixels "
               f"r > {SPIKE_R} px from the centre); window energy |Σ psf − Σ truth|/Σ truth. "
               "Time: jitted, best of the repeats after compile (float64).")
    return "\n".join(out)


# --- b. speed against the paper's NumPy method ----------------------------------------------


def numpy_paper_psf(vertices, *, wavelength, z_image, defocus, pixel_pitch, n, crop):
    """The paper's method for one PSF in plain NumPy (complex128): binary pupil raster on
    the n × n frequency grid (spacing 1/(n p)), defocus phase exp(i k W) in the Fresnel
    form, PSF = |IFFT(ATF)|² normalised to unit sum on the n × n grid, centre crop."""
    p = float(pixel_pitch)
    f = (np.arange(n) - n // 2) / (n * p)
    x = wavelength * z_image * f[None, :]
    y = -wavelength * z_image * f[:, None]
    inside = np.ones((n, n), bool)
    for a, e in zip(vertices, np.roll(vertices, -1, axis=0)):  # CCW: left of every edge
        inside &= (e[0] - a[0]) * (y - a[1]) - (e[1] - a[1]) * (x - a[0]) >= 0
    atf = inside.astype(complex)
    if defocus:
        # φ = k ½ (1/z_i − 1/z_R) |ξ|², ξ = λ z_R f
        z_i = z_image - defocus
        c = math.pi * wavelength * z_image**2 * (1 / z_i - 1 / z_image)
        atf *= np.exp(1j * c * (f[None, :] ** 2 + f[:, None] ** 2))
    h = np.fft.fftshift(np.fft.ifft2(np.fft.ifftshift(atf)))
    psf = h.real**2 + h.imag**2
    psf /= psf.sum()
    r0, c0 = n // 2 - crop[0] // 2, n // 2 - crop[1] // 2
    return psf[r0:r0 + crop[0], c0:c0 + crop[1]].copy()


def paper_numpy_psf(config: str, runs: int, crop=(1250, 1250)):
    """The NumPy paper method on the paper's ``config`` scene ("focused" or "defocused"),
    530 nm, on a grid 3 × the ``crop``: (the best of ``runs`` timings in seconds, its PSF
    on ``crop``). The speed yardstick of every benchmark that compares with the paper."""
    import difstar  # noqa: PLC0415

    R = _references()
    cam, scene = difstar.paper_camera(config)
    g = difstar.geometry_of(cam, scene)
    pup = cam.lens.pupil
    v = R.regular_polygon_vertices(pup.n, float(pup.circumradius), float(pup.rotation))
    best, ref = math.inf, None
    for _ in range(runs):
        t0 = time.perf_counter()
        ref = numpy_paper_psf(v, wavelength=LAM, z_image=float(g.z_exit_pupil),
                              defocus=float(g.defocus) if config == "defocused" else 0.0,
                              pixel_pitch=float(cam.sensor.pixel_pitch), n=3 * crop[0],
                              crop=crop)
        best = min(best, time.perf_counter() - t0)
    return best, ref


def _spike_sample(shape, r_min, n_spokes=28, n_random=120):
    """Pixels in the spike region: rays every 180/(2·7)° (along the 14 spikes of a 7-gon
    and between them) at radii from just outside r_min to the window's edge, and random
    pixels; those with r <= r_min dropped."""
    import references as R  # noqa: PLC0415

    h, w = shape
    radii = [int(round(x)) for x in np.geomspace(r_min + 4, min(h, w) // 2 - 2, 8)]
    rr, cc = R.sample_pixels(shape, spokes_deg=[k * 360 / n_spokes for k in range(n_spokes)],
                             radii_px=radii, n_random=n_random, seed=13, core=0)
    keep = np.hypot(rr - h // 2, cc - w // 2) > r_min
    return rr[keep], cc[keep]


def speed(R, repeats: int, numpy_runs: int) -> list[dict]:
    import difstar  # noqa: PLC0415

    crop = (1250, 1250)
    n_np = 3 * crop[0]
    rows = []
    for config in ("focused", "defocused"):
        cam, scene = difstar.paper_camera(config)
        g = difstar.geometry_of(cam, scene)
        z_r = float(g.z_exit_pupil)
        dz = float(g.defocus) if config == "defocused" else 0.0
        p = float(cam.sensor.pixel_pitch)
        pup = cam.lens.pupil
        v = R.regular_polygon_vertices(pup.n, float(pup.circumradius), float(pup.rotation))
        _log(f"b. {config}: difstar.psf 1250², point, float32 ...")
        got, first, best, plan = _time_psf(pup, repeats=repeats, wavelength=LAM, z_image=z_r,
                                           defocus=dz, pixel_pitch=p, shape=crop,
                                           sampling="point")
        _log(f"   {_fmt_s(best)} (compile+first {_fmt_s(first)})")
        extra = None
        if plan.method == "mft":
            # the sampled pupil by pruned FFTs instead: shown beside the default's plan
            _log("b. same, method='fft' (not the default plan) ...")
            extra = _time_psf(pup, repeats=repeats, wavelength=LAM, z_image=z_r, defocus=dz,
                              pixel_pitch=p, shape=crop, sampling="point", method="fft")
            _log(f"   {_fmt_s(extra[2])} (compile+first {_fmt_s(extra[1])})")
        _log(f"b. {config}: NumPy paper method {n_np}² ...")
        t_np, ref = paper_numpy_psf(config, numpy_runs, crop)
        _log(f"   {_fmt_s(t_np)}; truth ...")
        t0 = time.perf_counter()
        if config == "focused":
            truth = R.polygon_psf_exact(v, wavelength=LAM, z=z_r, pixel_pitch=p, shape=crop,
                                        sampling="point")
            m = _spike_mask(crop)
            d, b, t = got[m], ref[m], truth[m]
            sel = m
            where = f"every pixel r > {SPIKE_R} px ({m.sum()} px)"
            truth_name = "exact transform (Lee–Mittra) at every pixel"
        else:
            rr, cc = _spike_sample(crop, SPIKE_R)
            t = R.polygon_fresnel_psf(v, rr, cc, wavelength=LAM, z_image=z_r, defocus=dz,
                                      pixel_pitch=p, shape=crop, sampling="point")
            d, b = got[rr, cc], ref[rr, cc]
            sel = (rr, cc)
            where = f"{len(rr)} sampled px, r > {SPIKE_R} px"
            truth_name = "Fresnel quadrature over the polygon at sampled pixels"
        _log(f"   truth {_fmt_s(time.perf_counter() - t0)}")
        e_d, e_np = R.rel_rms(d, t), R.rel_rms(b, t)
        speed_tgt, err_tgt = (20, 1 / 10) if config == "focused" else (10, 1 / 3)
        rows.append(dict(config=config, dz=dz, t_difstar=best, t_compile=first, t_numpy=t_np,
                         e_difstar=e_d, e_numpy=e_np, speed_tgt=speed_tgt, err_tgt=err_tgt,
                         where=where, truth=truth_name, plan=_plan_str(plan),
                         np_sum=float(ref.sum()), d_sum=float(got.sum()), label=""))
        if extra is not None:
            g2, first2, best2, plan2 = extra
            rows.append(dict(rows[-1], t_difstar=best2, t_compile=first2,
                             e_difstar=R.rel_rms(g2[sel], t), plan=_plan_str(plan2),
                             d_sum=float(g2.sum()), label=", method=\"fft\" (not the default)"))
    return rows


def speed_table(rows) -> str:
    out = ["| case | difstar.psf (float32) | NumPy paper method (3750², complex128) | "
           "NumPy / difstar | target | met | spike error difstar | NumPy | difstar / NumPy | "
           "target | met |",
           "|---|---:|---:|---:|---:|:---:|---:|---:|---:|---:|:---:|"]
    for r in rows:
        ratio_t = r["t_numpy"] / r["t_difstar"]
        ratio_e = r["e_difstar"] / r["e_numpy"]
        met_t = "yes" if ratio_t >= r["speed_tgt"] else "**NO**"
        met_e = "yes" if ratio_e <= r["err_tgt"] else "**NO**"
        name = ("in focus" if r["config"] == "focused"
                else f"defocused (Δz = {r['dz'] * 1e3:.3g} mm)") + r["label"]
        out.append(
            f"| {name} | {_fmt_s(r['t_difstar'])} | {_fmt_s(r['t_numpy'])} | {ratio_t:.3g}× | "
            f"≥ {r['speed_tgt']}× | {met_t} | {r['e_difstar']:.2e} | {r['e_numpy']:.2e} | "
            f"{ratio_e:.2g} | ≤ 1/{round(1 / r['err_tgt'])} | {met_e} |")
    out.append("")
    out.append("Paper's 7-blade f/22 iris, 530 nm, 1250² window, `sampling=\"point\"`, "
               "`difstar.psf` at its defaults (accuracy 1e-3) in float32, jitted, best of the "
               "repeats after compile; NumPy: binary pupil raster, FFT on 3750² "
               "(N = 3 × 1250), |IFFT|², centre 1250² crop, best of its runs."
               + (" A row marked method=\"fft\" forces the pruned-FFT path of the sampled "
                  "pupil (same plan otherwise) for comparison; it is not the default."
                  if any(r["label"] for r in rows) else ""))
    for r in rows:
        out.append(f"- {r['config']}{r['label']}: plan {r['plan']}; compile + first run "
                   f"{_fmt_s(r['t_compile'])}. Truth: {r['truth']} ({r['where']}). Window sums: "
                   f"difstar {r['d_sum']:.6f}, NumPy crop {r['np_sum']:.6f}.")
    out.append("- Spike error: relative RMS ‖psf − truth‖₂/‖truth‖₂ over those pixels. "
               "Normalisation as each method's contract says: difstar's value is the fraction "
               "of the power through the pupil on the pixel (I(centre)·p² here), as is the "
               "truth's; the NumPy PSF sums to 1 over its 3750² grid, which is the same "
               "quantity up to the light beyond that grid (folded back in by the FFT's "
               "period).")
    return "\n".join(out)


# --- c. the machine --------------------------------------------------------------------------


def machine(argv) -> str:
    import jax  # noqa: PLC0415

    try:
        avail = len(os.sched_getaffinity(0))
    except AttributeError:
        avail = os.cpu_count()
    dev = ", ".join(sorted({d.platform for d in jax.devices()}))
    return (f"Machine: {platform.machine()}, {os.cpu_count()} CPUs ({avail} available), "
            f"jax {jax.__version__} on {dev}, NumPy {np.__version__}, Python "
            f"{platform.python_version()}. Load average {_load()}.\n"
            f"Command: `{' '.join(argv)}`")


def _load() -> str:
    try:
        return "/".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:
        return "n/a"


def main(argv: list[str] | None = None, prog: str = "python benchmarks/psf_engine.py") -> int:
    ap = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", choices=("accuracy", "speed"),
                    help="run one part (default both)")
    ap.add_argument("--repeats", type=int, default=3,
                    help="timed difstar runs after compile, best kept (default 3)")
    ap.add_argument("--numpy-runs", type=int, default=2,
                    help="runs of the NumPy paper method, best kept (default 2)")
    args = ap.parse_args(argv)
    if args.repeats < 1 or args.numpy_runs < 1:
        ap.error("--repeats and --numpy-runs must be >= 1")
    R = _references()
    import jax  # noqa: PLC0415

    cmd = [prog, *(sys.argv[1:] if argv is None else argv)]
    load0 = _load()
    t0 = time.perf_counter()
    parts = []
    if args.only in (None, "speed"):
        with jax.enable_x64(False):  # float32, as users run it by default
            rows = speed(R, args.repeats, args.numpy_runs)
        parts.append("### Speed against the paper's NumPy method (1250² window)\n\n"
                     + speed_table(rows))
    if args.only in (None, "accuracy"):
        with jax.enable_x64(True):
            rows = accuracy(R, args.repeats)
        parts.insert(0, "### Accuracy at the defaults (float64)\n\n" + accuracy_table(rows))
    total = time.perf_counter() - t0
    parts.append(machine(cmd) + f" (load before: {load0}); whole run {total:.0f} s.")
    print("\n\n".join(parts))
    return 0


if __name__ == "__main__":
    sys.exit(main())
