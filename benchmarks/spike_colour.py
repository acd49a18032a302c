"""Why the spikes render warm: the colour of the paper-focused example, measured.

    python benchmarks/spike_colour.py [--crop 1250]

Predicts the paper's focused example (`difstar predict --example paper-focused`: a 10.5 mm
disc lit 5000 K-neutral, 7 blades at f/22, one wavelength per channel: 600, 530, 450 nm)
and prints

1. the mean 8-bit sRGB R:G:B in the core (the disc's image), in the spikes' mid-tones and
   in the spikes far out;
2. the light each channel's PSF puts into rings about the axis, as a fraction of the
   power through the pupil, against the channel's wavelength: a straight edge's
   far-field streak has, at a distance r, an intensity L²/(4π² r² A) whatever λ (L the
   edge's length, A the pupil's area) and a width across of about λ z / L, so the light
   it carries grows in proportion to λ: far out, the red channel's rings hold
   600/450 = 1.33 times the blue's, while the streaks' centres are nearly grey;
3. the chain's per-channel gains (1/φ0 × white balance, equal here, so that the core
   renders neutral) and the colour matrix, which widens a camera-RGB tint about twice.

"Spike" pixels are, in each annulus, those in the brightest 5 % (the 14 streaks of a
7-blade iris cover a few per cent of a ring); "mid-tones" are spike pixels whose sRGB
luminance lies in 0.25–0.75, "far out" those beyond 80 % of the window's half-width.
"""

from __future__ import annotations

import argparse

import numpy as np


def _rings(h: int, w: int):
    y, x = np.mgrid[:h, :w]
    return np.hypot(y - h // 2, x - w // 2)


def _spike_mask(img: np.ndarray, r: np.ndarray, r_min: float, r_max: float, top=0.05):
    """Pixels in the brightest ``top`` fraction of each 4 px annulus between r_min, r_max."""
    mask = np.zeros(img.shape, bool)
    for r0 in np.arange(r_min, r_max, 4.0):
        ring = (r >= r0) & (r < r0 + 4)
        if ring.sum() < 50:
            continue
        cut = np.quantile(img[ring], 1 - top)
        mask |= ring & (img >= cut)
    return mask


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--crop", type=int, default=1250, help="window side, px (default 1250)")
    a = ap.parse_args(argv)

    import equinox as eqx

    import difstar

    camera, scene = difstar.paper_camera("focused")
    grid = difstar.choose_grid(camera, scene, crop=(a.crop, a.crop))
    pred = eqx.filter_jit(difstar.simulate)(camera, scene, grid)
    srgb = np.asarray(pred.srgb, dtype=np.float64)             # (3, h, w), 0..1
    psf = np.asarray(pred.psf, dtype=np.float64)               # (3, h, w), power fraction
    _, h, w = srgb.shape
    r = _rings(h, w)
    lum = srgb.mean(axis=0)

    disc_px = float(pred.geometry.magnification) * difstar.paper_camera()[1].sources[0].radius \
        / camera.sensor.pixel_pitch
    core = r < 0.8 * abs(disc_px)
    spikes = _spike_mask(lum, r, 1.3 * abs(disc_px), 0.98 * min(h, w) / 2)
    mid = spikes & (lum > 0.25) & (lum < 0.75)
    far = spikes & (r > 0.8 * min(h, w) / 2)

    def rgb(m):
        v = 255 * srgb[:, m].mean(axis=1)
        return f"{v[0]:5.1f} : {v[1]:5.1f} : {v[2]:5.1f}   (G = 100: " \
               f"{100 * v[0] / v[1]:.0f} : 100 : {100 * v[2] / v[1]:.0f})   {m.sum():7d} px"

    lam = np.asarray(camera.sensor.wavelengths, dtype=np.float64).reshape(3, -1).mean(axis=1)
    print(f"paper-focused, {h}x{w} px, disc radius {abs(disc_px):.1f} px, "
          f"wavelengths R G B = {', '.join(f'{x * 1e9:.0f}' for x in lam)} nm")
    print("mean 8-bit sRGB R : G : B")
    print(f"  core (r < {0.8 * abs(disc_px):.0f} px)            {rgb(core)}")
    print(f"  spikes, mid-tones (0.25..0.75)   {rgb(mid)}")
    print(f"  spikes, far out (r > {0.8 * min(h, w) / 2:.0f} px)   {rgb(far)}")

    # the physics: PSF power per channel in rings about the axis, against lambda
    psf_lum = psf.mean(axis=0)
    print("PSF power per channel (fraction of the pupil's power); R:G:B relative to G")
    print(f"  (the wavelengths' own ratios: {lam[0] / lam[1]:.3f} : 1 : {lam[2] / lam[1]:.3f})")
    for lo, hi in ((100, 200), (200, 400), (400, 0.98 * min(h, w) / 2)):
        ring = (r >= lo) & (r < hi)
        centres = _spike_mask(psf_lum, r, lo, hi) & ring
        for label, sel in (("whole ring", ring), ("spike centres", centres)):
            frac = psf[:, sel].sum(axis=1)
            rel = frac / frac[1]
            print(f"  r {lo:4.0f}..{hi:4.0f} px, {label:13s}: R {frac[0]:.3e}  G {frac[1]:.3e}"
                  f"  B {frac[2]:.3e}   R:G:B = {rel[0]:.3f} : 1 : {rel[2]:.3f}")
    m = np.asarray(camera.sensor.colour_matrix, np.float64)
    print("colour matrix camera RGB -> linear sRGB (rows R, G, B): diagonal "
          f"{m[0, 0]:.2f}, {m[1, 1]:.2f}, {m[2, 2]:.2f}; camera RGB 1.10 : 1 : 0.86 becomes "
          + " : ".join(f"{x:.2f}" for x in m @ np.array([1.10, 1.0, 0.86])))
    gain = np.asarray(camera.sensor.white_balance, np.float64) / np.asarray(
        camera.sensor.phi0, np.float64)
    print(f"chain gains 1/phi0 x white balance, R:G:B = "
          f"{gain[0] / gain[1]:.2f} : 1 : {gain[2] / gain[1]:.2f} (the same for core and spikes)")


if __name__ == "__main__":
    main()
