"""Render the README picture: the paper's two configurations side by side (sRGB) and the
in-focus PSF on a log scale with its colour bar, axes in millimetres on the sensor.

    python docs/make_figure.py            # writes docs/starburst.png
"""

from __future__ import annotations

import sys
from pathlib import Path

import equinox as eqx
import numpy as np

import difstar


def render(config: str, crop=(1250, 1250)):
    camera, scene = difstar.paper_camera(config)
    grid = difstar.choose_grid(camera, scene, crop=crop)
    return eqx.filter_jit(difstar.simulate)(camera, scene, grid)


def main(out="docs/starburst.png"):
    """Three panels with axes in millimetres on the sensor from the optical axis: the
    focused and the defocused sRGB images, and the in-focus PSF of the green channel as
    log10 of the fraction of the power per pixel, with its colour bar."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    f = render("focused")
    d = render("defocused")
    pitch_mm = difstar.paper_camera("focused")[0].sensor.pixel_pitch * 1e3

    def extent(h, w):  # pixel k of a centred crop sits k − size//2 pixels from the axis
        return ((-(w // 2) - 0.5) * pitch_mm, (w - w // 2 - 0.5) * pitch_mm,
                (-(h - h // 2) + 0.5) * pitch_mm, (h // 2 + 0.5) * pitch_mm)

    fig = Figure(figsize=(13.0, 4.3), dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, 3)
    for ax, pred, title in ((axes[0], f, "focused (sRGB)"),
                            (axes[1], d, "defocused by 4.78 mm (sRGB)")):
        img = np.clip(np.moveaxis(np.asarray(pred.srgb, float), 0, -1), 0, 1)
        ax.imshow(img, extent=extent(*img.shape[:2]), interpolation="antialiased")
        ax.set_title(title)
        ax.set_xlabel("x on the sensor (mm)")
    axes[0].set_ylabel("y on the sensor (mm)")
    psf = np.asarray(f.psf, float)[1]  # green channel, 530 nm
    c = psf.shape[-1] // 2
    psf = psf[c - 150 : c + 150, c - 150 : c + 150]
    hi = float(np.log10(psf.max()))
    im = axes[2].imshow(np.log10(np.clip(psf, 10.0 ** (hi - 7), None)), cmap="magma",
                        vmin=hi - 7, vmax=hi, extent=extent(*psf.shape),
                        interpolation="antialiased")
    axes[2].set_title("in-focus PSF, green channel (530 nm)")
    axes[2].set_xlabel("x on the sensor (mm)")
    bar = fig.colorbar(im, ax=axes[2], shrink=0.9)
    bar.set_label("log10(fraction of the power per pixel)")
    tmp = Path(out).with_suffix(".tmp.png")
    fig.savefig(tmp, format="png")
    tmp.replace(out)
    print(f"wrote {out}", file=sys.stderr)


if __name__ == "__main__":
    main(*sys.argv[1:])
