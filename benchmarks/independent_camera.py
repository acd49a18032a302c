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

import difstar  # noqa: E402

FRAME = 64
PEAK_E = 17000.0
READ_E2 = 40.0


def difstar_image(camp, cfg, *, q: int | None, source_scale: float = 1.0) -> np.ndarray:
    """difstar's linear image of the campaign's scene through ``simulate`` on the grid
    ``choose_grid`` makes, its sub-sampling q forced (None: choose_grid's own)."""
    iris, sen = camp.iris, camp.sensor
    wave = difstar.Zernike({11: iris.spherical}, radius=iris.zernike_radius)
    lens = difstar.Lens(
        difstar.CurvedIris(iris.n, iris.circumradius, iris.curvature, rotation=iris.rotation),
        focal_length=camp.lens.focal_length, focus_distance=cfg.focus_distance,
        principal_separation=camp.lens.principal_separation,
        pupil_magnification=camp.lens.pupil_magnification, wavefront=wave)
    camera = difstar.Camera(lens, difstar.Sensor(pixel_pitch=sen.pixel_pitch,
                                                 pattern=sen.pattern,
                                                 wavelengths=sen.wavelengths))
    scene = difstar.Scene(object_distance=cfg.object_distance,
                          sources=(difstar.DiscSource(camp.source_radius * source_scale),),
                          exposure_time=0.01)
    grid = difstar.choose_grid(camera, scene, crop=(FRAME, FRAME), oversample=q)
    return np.asarray(difstar.simulate(camera, scene, grid).image), grid.oversample


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
            img, used = difstar_image(camp, cfg, q=q, source_scale=scale)
            dt = time.perf_counter() - t0
            print(f"| {label} | {used} | {scale:.2f} × true | {chi2(gen, img):.1f} | {dt:.1f} |")

if __name__ == "__main__":
    main()
