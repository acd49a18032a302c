"""Render the README picture: the paper's two configurations side by side (sRGB) and the
in-focus PSF on a log scale.

    python docs/make_figure.py            # writes docs/starburst.png
"""

from __future__ import annotations

import sys
from pathlib import Path

import equinox as eqx
import numpy as np
from PIL import Image

import difstar


def render(config: str, crop=(1250, 1250)):
    camera, scene = difstar.paper_camera(config)
    grid = difstar.choose_grid(camera, scene, crop=crop)
    return eqx.filter_jit(difstar.simulate)(camera, scene, grid)


def to_image(a, size):
    a = np.clip(np.moveaxis(np.asarray(a, float), 0, -1), 0, 1)
    return Image.fromarray(np.round(a * 255).astype(np.uint8)).resize((size, size), Image.LANCZOS)


def main(out="docs/starburst.png", size=400):
    f = render("focused")
    d = render("defocused")
    psf = np.asarray(f.psf)
    c = psf.shape[-1] // 2
    psf = psf[:, c - 150 : c + 150, c - 150 : c + 150]
    logp = (np.log10(np.clip(psf / psf.max(), 1e-7, None)) + 7) / 7
    canvas = Image.new("RGB", (3 * size, size))
    for i, im in enumerate([to_image(f.srgb, size), to_image(d.srgb, size), to_image(logp, size)]):
        canvas.paste(im, (i * size, 0))
    tmp = Path(out).with_suffix(".tmp.png")
    canvas.save(tmp)
    tmp.replace(out)
    print(f"wrote {out}", file=sys.stderr)


if __name__ == "__main__":
    main(*sys.argv[1:])
