"""How far difstar's linear image is from the independent NumPy camera's
(``tests/raw_generator.py``), in noise units, for the curved-iris campaign's scene in
focus, and how much of it is the pixel grid on which the chain convolves the source
with the PSF.

``simulate`` convolves the source's pixel coverage with the PSF sampled at the pixel
centres. At f/11 with 3.9 µm pixels the intensity's bandwidth is 0.72 cycles per pixel
in blue, above the pixel grid's Nyquist limit (0.5), so that sum is not the pixel
integral of the source convolved with the PSF. The generator integrates on a 4 × 4
sub-pixel grid. Column ``q``: difstar evaluated on a grid q times finer (pixel pitch
p/q, the source moved so that the sub-pixels of each pixel are centred on it) and
binned q × q. q = 1 is what ``simulate`` does today.

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
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import raw_generator as G  # noqa: E402

import difstar  # noqa: E402

FRAME = 64
PEAK_E = 17000.0
READ_E2 = 40.0


def difstar_image(camp, cfg, *, q: int, source_scale: float = 1.0) -> np.ndarray:
    """difstar's linear image of the campaign's scene, evaluated at pitch p/q, binned."""
    iris, sen = camp.iris, camp.sensor
    geo = G.lens_geometry(camp.lens, cfg.focus_distance, cfg.object_distance)
    wave = difstar.Zernike({11: iris.spherical}, radius=iris.zernike_radius)
    lens = difstar.Lens(
        difstar.CurvedIris(iris.n, iris.circumradius, iris.curvature, rotation=iris.rotation),
        focal_length=camp.lens.focal_length, focus_distance=cfg.focus_distance,
        principal_separation=camp.lens.principal_separation,
        pupil_magnification=camp.lens.pupil_magnification, wavefront=wave)
    camera = difstar.Camera(lens, difstar.Sensor(pixel_pitch=sen.pixel_pitch / q,
                                                 pattern=sen.pattern,
                                                 wavelengths=sen.wavelengths))
    # pixel k's sub-pixels are centred (q − 1)/2 sub-pixels after the fine grid's axis
    off = (q - 1) / 2 * sen.pixel_pitch / q
    m = geo["magnification"]
    src = difstar.DiscSource(camp.source_radius * source_scale,
                             jnp.asarray([off / m, -off / m]))
    scene = difstar.Scene(object_distance=cfg.object_distance, sources=(src,),
                          exposure_time=0.01)
    grid = difstar.choose_grid(camera, scene, crop=(FRAME * q, FRAME * q))
    img = np.asarray(difstar.simulate(camera, scene, grid).image)
    return img.reshape(3, FRAME, q, FRAME, q).sum(axis=(2, 4))


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
    print("| q (sub-pixels a side) | source radius | chi2 vs the independent camera | difstar s |")
    print("|---:|---:|---:|---:|")
    for q in (1, 3):
        for scale in (1.0, 0.95):
            t0 = time.perf_counter()
            img = difstar_image(camp, cfg, q=q, source_scale=scale)
            dt = time.perf_counter() - t0
            print(f"| {q} | {scale:.2f} × true | {chi2(gen, img):.1f} | {dt:.1f} |")


if __name__ == "__main__":
    main()
