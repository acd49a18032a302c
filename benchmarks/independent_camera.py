"""How far difstar's linear image is from the independent NumPy camera's
(``tests/raw_generator.py``), in noise units, for the curved-iris campaign's scene in
focus, and how much of it is the pixel grid on which the chain convolves the source
with the PSF.

On the pixel grid, ``simulate`` would convolve the source's pixel coverage with the PSF
sampled at the pixel centres. At f/11 with 3.9 µm pixels the intensity's bandwidth is
0.72 cycles per pixel in blue, above the pixel grid's Nyquist limit (0.5), so that sum
is not the pixel integral of the source convolved with the PSF. ``choose_grid`` now
samples the engine's grid q times finer where the pixels undersample the intensity
(``Grid.oversample``: q = 3 here) and ``simulate`` averages
each pixel's q × q samples. The generator integrates on a 4 × 4 sub-pixel grid. Rows:
q forced to 1 (the chain before the rule), choose_grid's own q, and q forced to 5.

chi2: Σ ((generator − k·difstar)/σ)² over a 64² window and the three channels, k the
best radiometric constant per channel, σ the noise of a capture whose peak holds 17,000
electrons (the campaign's brightest unclipped exposure) plus 40 e⁻ of read noise.
Noiseless images: chi2 = 0 is perfect agreement; the campaign's fit has about 28,000
pixels per configuration, so chi2 of a few hundred here biases the fitted parameters by
several standard errors.

Second table: the grid ``choose_grid`` picks by default for a straight 9-blade iris
without aberration (the camera the exact and fft paths serve), from f/22, where the
pixels sample the intensity (bandwidth under 0.5 cycles per pixel) and the pixel-centre
paths stay, to f/1.8 (4.6 cycles per pixel), where it now picks the engine's sub-pixel
grid; error: RMS difference over the window relative to the peak, worst channel, after
one radiometric constant per channel; the generator's sub-grid is at or under the
intensity's Nyquist rate (4², 5² at f/4, 11² at f/1.8).

    python benchmarks/independent_camera.py
"""

from __future__ import annotations

import dataclasses
import sys
import time
from pathlib import Path

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import raw_generator as G  # noqa: E402
from generator_twins import shape_error, twin_image  # noqa: E402

FRAME = 64
PEAK_E = 17000.0
READ_E2 = 40.0


def chi2(gen: np.ndarray, model: np.ndarray) -> float:
    scale = PEAK_E / gen.max()
    w = 1.0 / np.sqrt(gen * scale + READ_E2)
    out = 0.0
    for c in range(3):
        k = np.sum(w[c] ** 2 * gen[c] * model[c]) / np.sum(w[c] ** 2 * model[c] ** 2)
        out += float(np.sum((w[c] * (gen[c] - k * model[c]) * scale) ** 2))
    return out


def main() -> None:
    cfg = G.Configuration("focused", 1.5, 1.5, (), (FRAME // 2, FRAME // 2))
    camp = dataclasses.replace(G.CURVED_IRIS, frame=(FRAME, FRAME), configurations=(cfg,))
    t0 = time.perf_counter()
    gen = np.stack([G.channel_image(camp, cfg, c) for c in range(3)])
    print(f"independent camera: {time.perf_counter() - t0:.1f} s "
          f"(pixels on a {camp.pixel_supersample}² sub-grid, FFT {camp.fft_size}²)\n")
    print("| grid | q (sub-pixels a side) | source radius | chi2 vs the independent camera "
          "| difstar s |")
    print("|---|---:|---:|---:|---:|")
    for label, q in (("pixel grid (before the sub-pixel rule)", 1),
                     ("choose_grid's own", None), ("finer", 5)):
        for scale in (1.0, 0.95):
            t0 = time.perf_counter()
            img, grid, _ = twin_image(camp, cfg, oversample=q, source_scale=scale)
            dt = time.perf_counter() - t0
            print(f"| {label} | {grid.oversample} | {scale:.2f} × true "
                  f"| {chi2(gen, img):.1f} | {dt:.1f} |")


def f_number_table() -> None:
    """The default grid against the pixel-centre paths, straight 9-blade iris, no
    aberration, from f/22 (pixels sample the intensity) to f/1.8 (4.9 cycles per pixel)."""

    print("\n| f-number | focus | bandwidth, cycles/px (blue) | pixel centres (exact or fft) "
          "| error | default grid | error | ratio |")
    print("|---:|---|---:|---|---:|---|---:|---:|")
    for f_number, names, frame, ss in ((22.0, ("focused", "near", "far"), 64, 4),
                                       (11.0, ("focused", "near", "far"), 64, 4),
                                       (4.0, ("focused", "near", "far"), 64, 5),
                                       (1.8, ("focused",), 32, 11)):
        cfgs = {c.name: dataclasses.replace(c, source_position=(frame // 2, frame // 2))
                for c in G.CURVED_IRIS.configurations}
        iris = G.Iris(circumradius=G.CURVED_IRIS.lens.focal_length / (2 * f_number),
                      curvature=0.0, spherical=0.0)
        for name in names:
            cfg = cfgs[name]
            camp = G.Campaign(frame=(frame, frame), configurations=(cfg,), iris=iris,
                              fft_size=1024, pixel_supersample=ss)
            gen = np.stack([G.channel_image(camp, cfg, c) for c in range(3)])
            old, og, _ = twin_image(camp, cfg, straight=True,
                                    method="exact" if name == "focused" else "fft")
            new, ng, _ = twin_image(camp, cfg, straight=True)
            e_old, e_new = shape_error(gen, old), shape_error(gen, new)
            bw = _bandwidth(camp, cfg)
            print(f"| {f_number:g} | {name} | {bw:.2f} | {og.method} (q = {og.oversample}) "
                  f"| {e_old:.2e} | {ng.method} (q = {ng.oversample}) | {e_new:.2e} "
                  f"| {e_old / e_new:.1f} |", flush=True)


def _bandwidth(camp, cfg) -> float:
    """2 r p / (λ_blue z_R) for the campaign's lens at this focus (the generator's own
    geometry)."""
    g = G.lens_geometry(camp.lens, cfg.focus_distance, cfg.object_distance)
    return 2 * camp.iris.circumradius * camp.sensor.pixel_pitch / (
        min(camp.sensor.wavelengths) * g["z_R"])


if __name__ == "__main__":
    main()
    f_number_table()
