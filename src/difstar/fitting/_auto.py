""":func:`auto_stages`: the stages of a fit chosen from the model and the data, for a
manifest (or a call of :func:`fit`) that gives none of its own."""

from __future__ import annotations

import math
from collections.abc import Sequence

from ._data import FitData
from ._model import ImageModel
from ._params import ARCSEC

#: the parameters that place the star and shape its core, fitted first on a small window
#: (and each halo's fraction)
CORE = ("x0", "y0", "flux", "background", "jitter")
#: the relative mismatch of the model that σ carries once the noise is estimated from
#: the residual (the spike stages' weights): 3 % of the intensity
MISMATCH_FLOOR = 0.03
#: how far a pixel must lie from the model (in σ) to be taken for something else (a
#: neighbour, a cosmic ray, a hot pixel) and masked
REJECT_ABOVE = 20.0


def resolution_px(model: ImageModel) -> float:
    """λ/D in data pixels at the band's longest wavelength (D: the pupil's largest
    diameter the fit allows): the size of the core's features."""
    lam = max(float(x) for x in model.light.wavelengths)
    ang = model.params["pixel_scale"].value * ARCSEC
    return lam / (2.0 * float(model.pupil.max_radius)) / ang


def noise_unknown(data: FitData) -> bool:
    """Whether ``data``'s σ says nothing about the signal's own noise: made from the
    default :class:`Noise` (the border's read noise, a gain of 1 and no floor), not a σ
    map or a gain or floor the user gave. Such data are in units that are not
    electrons (a gain of 1 then weights the bright pixels far too much)."""
    return data.noise is not None and data.noise.gain == 1.0 and data.noise.floor == 0.0


def _nice(x: float) -> float:
    """``x`` rounded down to two significant digits (a grid step a reader can check)."""
    e = 10.0 ** math.floor(math.log10(x) - 1)
    return math.floor(x / e) * e


def auto_stages(model: ImageModel, data) -> list[dict]:
    """The stages of a fit that needs no recipe, chosen from ``model`` (its free
    parameters, pupil, band, pixel scale and bounds) and ``data`` (a :class:`FitData` or
    a list of captures: their smallest window). Ordinary stages, so :func:`fit` checks
    and runs them like hand-written ones and its log shows them; copy them into a
    manifest to change one.

    With ``r_edge`` the largest radius inside the window and ``core`` = 10 λ/D (at least
    8 pixels, at most r_edge / 2):

    1. the star's place, flux, background and blur (those of :data:`CORE` and the
       halos' fractions that are free)
       on the central (2 core + 1)² pixels, where the spikes weigh little — only where
       the window is larger than that;
    2. everything else free on all pixels, the rotation held; if ``rotation`` is free,
       first a scan of it over its bounds (± 20° where it has none) in steps that move
       a spike at ``r_edge`` by a quarter pixel (the grid finds the basin the spikes'
       fine structure makes), and the rotation held at the scan's best (stage 3 measures
       it; a solve of the rotation alone right after the scan cost a compiled program of
       its own: without it the Spitzer star's answer is the same, and the JWST star's
       falls in its other rotation basin at a χ² lower by 6, BENCHMARKS.md);

    and if ``rotation`` is free, the rotation measured on its spikes in turn with the rest:

    3. where the data's σ says nothing of the signal's noise (:func:`noise_unknown`),
       σ re-estimated from the residual (read noise and gain, and a 3 % floor for the
       model's own mismatch, :data:`MISMATCH_FLOOR`); pixels more than 20 σ off beyond
       the core masked (a neighbour, a cosmic ray); then the rotation alone on the
       pixels within ± 8° of the model's spikes between ``core`` and ``r_edge``;
    4. everything but the rotation on all pixels again;
    5. a hop of the rotation by ± 2 scan steps (stages 3–4 re-run from each; the lowest
       χ² kept): out of a neighbouring basin that the other parameters' adaptation made
       self-consistent;
    6. stages 3–4 repeated until the rotation moves by less than what moves a spike at
       ``r_edge`` by 1/250 pixel over a round (at most 8 rounds).

    This is the procedure the JWST campaign was found to need (docs/fitting.md), with its
    numbers taken from the data and the model instead of one star."""
    datas = data if isinstance(data, (list, tuple)) else [data]
    n = min(min(d.image.shape) for d in datas)
    r_edge = (n - 1) // 2
    free = set(model.free)
    res = resolution_px(model)
    core = int(min(max(8, math.ceil(10 * res)), max(r_edge // 2, 1)))
    stages: list[dict] = []
    core_free = [q for q in (*CORE, *(h.name for h in model.halos)) if q in free]
    if core_free and 2 * core + 1 < n:
        stages.append({"free": core_free, "half": core})
    rotation = "rotation" in free
    if not rotation:
        stages.append({"free": "all", "half": None})
        return stages
    step = round(_nice(math.degrees(0.25 / r_edge)), 12)
    b = model.params["rotation"].bounds
    # the whole of the bounds from any start (the grid is clipped to them)
    half_range = (b[1] - b[0]) if b is not None else 20.0
    half_range = min(half_range, 200 * step)  # at most 400 grid points
    scan = {"name": "rotation", "half_range": round(half_range, 6), "step": step}
    rest = {"free": "all", "fix": ["rotation"], "half": None}
    stages.append(dict(rest, scan=scan, max_steps=25))
    spikes = {"r_min": float(core), "r_max": float(r_edge), "half_width": 8.0,
              "profiles": False, "directions": "model"}
    spike_stage = {"free": ["rotation"], "half": None}
    if all(noise_unknown(d) for d in datas):
        spike_stage["noise_from_residuals"] = {"floor": MISMATCH_FLOOR, "intensity": "data"}
    spike_stage |= {"reject": {"above": REJECT_ABOVE, "r_min": float(core), "grow": 2},
                    "spikes": spikes, "max_steps": 30, "rtol": 1e-4}
    stages.append(spike_stage)
    stages.append(dict(rest, max_steps=80, rtol=1e-5))
    hop = round(2 * step, 12)
    stages.append({"hop": {"name": "rotation", "offsets": [-hop, hop], "stages": 2}})
    settle = float(f"{math.degrees(0.004 / r_edge):.2g}")
    stages.append({"repeat": {"until": {"rotation": settle}, "stages": 2, "max_rounds": 8}})
    return stages


def stages_text(stages: Sequence[dict]) -> str:
    """The stages, one line each, as the command line shows the procedure it chose."""
    return "\n".join(f"  {i}: {st}" for i, st in enumerate(stages))
