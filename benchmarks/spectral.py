"""Spectral mode against trichromatic: speed and error (issue 14).

The paper's focused scene (7 blades, f/22, a 5000 K disc through the Nikon D7000's
measured sensitivities shipped with difstar) rendered three ways:

- trichromatic: one wavelength per channel (the paper's model, difstar's default path);
- spectral: each channel's wavelengths and weights from ``difstar.choose_wavelengths`` at
  an accuracy target (error against the number of wavelengths);
- reference: every 5 nm over the sensitivities' band with the channel's weights (source ×
  measured sensitivity × 5 nm), in float64.

Error: relative RMS of the linear image against the reference, both in float64 (in float32
the convolution's rounding alone is ~1e-3 of the faint spikes), over the crop and outside
the source's core (beyond its image radius + 20 px, where the spikes are). Time: the jitted
forward in float32, best of ``--repeats`` after compiling.

    python benchmarks/spectral.py [--crop 512] [--repeats 3]
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np


def _sensor(sensor, wavelengths, weights):
    import difstar

    return difstar.Sensor(
        pixel_pitch=sensor.pixel_pitch, pattern=sensor.pattern, wavelengths=wavelengths,
        spectral_weights=weights, phi0=sensor.phi0, response=sensor.response,
        white_balance=sensor.white_balance, colour_matrix=sensor.colour_matrix)


def _dense(sens):
    """Every 5 nm over the sensitivities' band (within 380–780 nm), per channel:
    wavelengths and normalised weights (3, n)."""
    from difstar import dense_weights

    cw = dense_weights(5000.0, sens)
    w = np.asarray(cw.normalised)
    return np.broadcast_to(np.asarray(cw.wavelengths), w.shape).copy(), w


def main(argv=None, prog=None) -> int:
    ap = argparse.ArgumentParser(prog=prog, description=__doc__.splitlines()[0])
    ap.add_argument("--crop", type=int, default=512, help="crop side in pixels (default 512)")
    ap.add_argument("--repeats", type=int, default=3, help="timed runs (default 3)")
    ap.add_argument("--accuracy", type=float, action="append",
                    help="wavelength-choice targets (default 1e-2, 1e-3, 3e-4, 1e-4)")
    args = ap.parse_args(argv)
    accs = args.accuracy or [1e-2, 1e-3, 3e-4, 1e-4]

    import equinox as eqx
    import jax

    import difstar
    from difstar import paper_sensitivities

    crop = (args.crop, args.crop)
    camera, scene = difstar.paper_camera("focused")
    sens = paper_sensitivities()

    def image(cam, x64: bool):
        """(the image in float64, for the error; the best float32 forward time; grid)."""
        grid = difstar.choose_grid(cam, scene, crop=crop, raw_only=True)
        fn = eqx.filter_jit(lambda c, s: difstar.simulate(c, s, grid).image)
        out = np.asarray(fn(cam, scene).block_until_ready(), float)
        best = float("inf")
        if not x64:
            def f32(tree):
                return jax.tree.map(lambda a: a.astype(np.float32) if eqx.is_array(a) else a,
                                    tree)

            cam32, sc32 = f32(cam), f32(scene)
            fn(cam32, sc32).block_until_ready()
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                fn(cam32, sc32).block_until_ready()
                best = min(best, time.perf_counter() - t0)
        return out, best, grid

    jax.config.update("jax_enable_x64", True)
    wl, w = _dense(sens)
    t0 = time.perf_counter()
    ref, _, _ = image(difstar.Camera(camera.lens, _sensor(camera.sensor, wl, w)), True)
    t_ref = time.perf_counter() - t0
    g = difstar.geometry_of(camera, scene)
    rad = float(scene.sources[0].radius) * abs(float(g.magnification)) / camera.sensor.pixel_pitch
    yy, xx = np.mgrid[: crop[0], : crop[1]]
    outside = np.hypot(yy - crop[0] // 2, xx - crop[1] // 2) > rad + 20

    def err(img, mask=None):
        m = np.ones(crop, bool) if mask is None else mask
        return float(np.sqrt(np.mean((img[:, m] - ref[:, m]) ** 2) / np.mean(ref[:, m] ** 2)))

    # trichromatic: the channel's weighted mean wavelength (the K = 1 rule)
    rows = []
    tri = difstar.choose_wavelengths(5000.0, sens, 1.0, max_wavelengths=1)
    twl, tw = tri.padded()
    img, t_tri, grid = image(difstar.Camera(camera.lens, _sensor(camera.sensor, twl[:, :1], tw[:, :1])), False)
    img3, t_tri3, grid3 = image(camera, False)
    rows.append(("trichromatic (paper: 600/530/450 nm)", "1/1/1", grid3.method, t_tri3, err(img3),
                 err(img3, outside)))
    rows.append(("trichromatic (mean wavelengths)", "1/1/1", grid.method, t_tri, err(img),
                 err(img, outside)))
    for a in accs:
        ch = difstar.choose_wavelengths(5000.0, sens, a)
        cwl, cw = ch.padded()
        img, t, grid = image(difstar.Camera(camera.lens, _sensor(camera.sensor, cwl, cw)), False)
        ks = "/".join(str(len(x)) for x in ch.wavelengths)
        rows.append((f"spectral, target {a:g}", ks, grid.method, t, err(img), err(img, outside)))
    print(f"# Spectral mode (issue 14): paper focused scene, {crop[0]}² crop, 5000 K, D7000; "
          f"{os.cpu_count()} CPUs, jax {jax.__version__}")
    print(f"# reference: {wl.shape[1]} wavelengths (5 nm, {wl[0, 0] * 1e9:.0f}–"
          f"{wl[0, -1] * 1e9:.0f} nm) per channel, float64, {t_ref:.1f} s")
    print("| model | wavelengths R/G/B | method | forward (s) | × paper trichromatic | "
          "error (crop) | error (spikes) |")
    print("|---|---|---|---|---|---|---|")
    for name, ks, method, t, e, eo in rows:
        print(f"| {name} | {ks} | {method} | {t:.3f} | {t / t_tri3:.2f} | {e:.2e} | {eo:.2e} |")
    print("\ncommand: " + (prog or "python benchmarks/spectral.py") + " "
          + " ".join(argv or []))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
