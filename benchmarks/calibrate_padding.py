"""The calibration behind ``choose_grid(accuracy=..., method="fft")`` (the paper's n × n
grid; the PSF engine plans its own period): the paper's grid's error outside the core
against padding, float64, for the paper's focused scene (against the exact polygon
transform) and defocused scene (against the PSF engine at accuracy 1e-4 on the period of
padding 10, convolved with the exact source coverage: speed_vs_error.difstar_reference)
on a CROP px crop.

    python benchmarks/calibrate_padding.py [CROP]      (default 256; minutes on 2 cores)
"""

import sys
from pathlib import Path

import equinox as eqx
import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

sys.path.insert(0, str(Path(__file__).resolve().parent))  # speed_vs_error.py beside this
import speed_vs_error as b  # noqa: E402

from difstar import choose_grid, simulate  # noqa: E402

crop = (int(sys.argv[1]) if len(sys.argv) > 1 else 256,) * 2
print("| scene | padding | N | N/crop | lin. err outside core |")
print("|---|---|---|---|---|")
for cfg in ("focused", "defocused"):
    cam, sc = b.paper_case(cfg, source_radius=None if crop[0] > 300 else 1.5e-3)
    mask = b.core_mask(crop, b._source_radius_px(cam, sc))
    ref = (b.exact_focused_image(cam, sc, crop) if cfg == "focused"
           else b.difstar_reference(cam, sc, crop, 10.0))
    for pad in (0.1, 0.25, 0.5, 1, 1.5, 2, 3, 4, 6):
        g = choose_grid(cam, sc, crop=crop, padding=pad, raw_only=True, method="fft")
        img = np.asarray(eqx.filter_jit(simulate)(cam, sc, g).image)  # the paper's grid
        print(f"| {cfg} | {pad} | {g.n} | {g.n / crop[0]:.2f} | {b.rel_rms(img, ref, mask):.2e} |",
              flush=True)
