"""Looking at a fit: χ² at given values and along one parameter, rough starts, spike
angles measured from an image or a model."""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Mapping

import jax.numpy as jnp
import numpy as np

from .._progress import step_bar
from ._data import FitData, _angle_from, _polar
from ._model import ImageModel
from ._params import PERTURB, FitInputError, _finite
from ._residuals import SpikeProfiles, _as_list, _PixelTarget
from ._solve import model_images

#: the most grid points a stage's ``scan`` may try (each one a model image: a scan step
#: of 1e-7 ran for minutes)
MAX_SCAN_POINTS = 1000

def _scan_problem(model: ImageModel, name, half_range, step) -> str | None:
    """Why a scan of ``name`` over ± ``half_range`` by ``step`` cannot run, or None."""
    if not isinstance(name, str) or name not in model.params:
        return (f"name {name!r} is not a parameter of the model; known: "
                f"{sorted(model.params)}")
    for q, x in (("half_range", half_range), ("step", step)):
        if not (_finite(x) and x > 0):
            return f"{q} must be a finite number > 0 (in {name}'s units); got {x!r}"
    if step > 2 * half_range:
        return (f"step {step:g} is wider than the range (2 × half_range = "
                f"{2 * half_range:g}): give step <= 2 half_range")
    ratio = 2 * half_range / step
    if not ratio < MAX_SCAN_POINTS:  # (a ratio of inf: the same)
        return (f"half_range {half_range:g} / step {step:g} makes {ratio:.3g} grid points, "
                f"each a model image; at most {MAX_SCAN_POINTS}: raise step or lower "
                "half_range")
    return None

def _scan(model: ImageModel, data, target, values, *, name: str, half_range,
          step) -> dict:
    """``values`` with ``name`` moved to the lowest χ² of ``target`` on a grid of
    ``step`` over ± ``half_range`` about its value (inside its bounds): a coarse search
    that puts the local solver in the right basin when the objective has several (the
    rotation, against spikes whose fine structure repeats every fraction of a degree).
    The grid is the whole multiples of ``step`` in that range, not the value plus
    multiples: starts that differ by less than a step search the same points, so the
    basin chosen does not depend on where inside a step the start happened to be."""
    grid, cost = scan_grid(model, data, target, values, name=name, half_range=half_range,
                           step=step)
    if grid.size == 0:  # no grid point inside the bounds: nothing better to move to
        return dict(values)
    return {**values, name: float(grid[int(np.argmin(cost))])}

def scan_grid(model: ImageModel, data, target, values, *, name: str, half_range,
              step, progress: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The grid :func:`_scan` searches (inside the bounds; possibly empty) and χ² at each
    of its points. ``progress``: a label for a bar on stderr that counts the points (a
    scan of a few hundred model images takes seconds); None: quiet."""
    why = _scan_problem(model, name, half_range, step)
    if why:
        raise FitInputError(f"scan: {why}.")
    p = model.params[name]
    v = float(values[name])
    grid = step * np.arange(math.ceil((v - half_range) / step - 1e-9),
                            math.floor((v + half_range) / step + 1e-9) + 1)
    if p.bounds is not None:
        grid = grid[(grid > p.bounds[0]) & (grid < p.bounds[1])]
    if grid.size == 0:
        return grid, np.zeros(0)
    with step_bar(progress, grid.size) as tick:
        lowest = [math.inf]

        def each(x, c):
            lowest[0] = min(lowest[0], c)
            tick(f"{name} {x:.6g}: χ² {c:.6g}, lowest {lowest[0]:.6g}")

        return grid, chi2_slice(model, data, values, name, grid, target=target,
                                each=None if tick is None else each)

def scan_rivals(grid, cost, *, within: float) -> list[tuple[float, float]]:
    """The other minima of a scan that the data hardly tell from its lowest: grid points
    lower than their neighbours (an end counts against its one neighbour), more than one
    step from the lowest, whose χ² exceeds the lowest by less than ``within``; as
    (value, Δχ²), lowest first."""
    grid, cost = np.asarray(grid, float), np.asarray(cost, float)
    if grid.size < 3:
        return []
    best = int(np.argmin(cost))
    left = np.concatenate([[np.inf], cost[:-1]])
    right = np.concatenate([cost[1:], [np.inf]])
    minima = [i for i in np.flatnonzero((cost < left) & (cost <= right))
              if abs(int(i) - best) > 1 and cost[i] - cost[best] < within]
    return sorted(((float(grid[i]), float(cost[i] - cost[best])) for i in minima),
                  key=lambda x: x[1])

def chi2_slice(model: ImageModel, data, values: Mapping[str, float], name: str, grid,
               *, target=None, each=None) -> np.ndarray:
    """χ² of ``model`` on ``data`` (a FitData or a list of captures; on all their used
    pixels unless ``target`` says otherwise) with ``name`` at each value of ``grid`` and
    every other parameter held at ``values``: a slice through the objective, to see
    whether it has one minimum along that parameter or several (the rotation of a
    pupil whose spikes the model matches only in part). One compile, then one model
    image per grid value. ``each(value, χ²)``, if given, is called after each grid
    value (a progress bar). Raises :class:`FitInputError` for a name the model lacks or
    a grid that is empty or not finite."""
    if name not in model.params:
        raise FitInputError(f"chi2_slice: {name!r} is not a parameter of the model; known: "
                            f"{sorted(model.params)}.")
    g = np.asarray(grid, float).ravel()
    if g.size == 0 or not np.all(np.isfinite(g)):
        raise FitInputError(f"chi2_slice: grid must be a non-empty list of finite values; "
                            f"got {grid!r}.")
    out = []
    for x in g:
        out.append(chi2_at(model, data, {**values, name: float(x)}, target))
        if each is not None:
            each(float(x), out[-1])
    return np.array(out)

def spike_target(data: FitData, values: Mapping[str, float], *, n_spikes=8, r_min=12.0,
                 r_max=45.0, half_width=4.0, bin_width=0.25, profiles=True,
                 directions="data", model_image=None):
    """The residuals of the spikes about the star at the model's ``values`` (x0, y0 from
    the window's centre pixel; background), around the directions :func:`spike_angles`
    measures in the data (``directions="data"``) or in ``model_image``, the model at the
    values reached (``"model"``: noise-free, so a faint star's noise cannot put a window
    where there is no spike): their angular profiles (:class:`SpikeProfiles`), or with
    ``profiles=False`` the pixels themselves within ± ``half_width`` degrees of each
    direction and between ``r_min`` and ``r_max`` pixels."""
    h, w = data.image.shape
    centre = (w // 2 + values["x0"], h // 2 + values["y0"])
    if directions == "data":
        img = np.where(data.mask, data.image - values["background"], np.nan)
    elif directions == "model" and model_image is not None:
        img = np.asarray(model_image, float) - values["background"]
    else:
        raise FitInputError(f"spikes: directions must be 'data' or 'model' (with the model "
                            f"image); got {directions!r}.")
    dirs = spike_angles(img, centre, r_min=r_min, r_max=r_max, n_spikes=n_spikes)
    if profiles:
        return SpikeProfiles(data, centre, values["background"], dirs, r_min=r_min,
                             r_max=r_max, half_width=half_width, bin_width=bin_width)
    r, th = _polar((h, w), centre)
    near = np.zeros((h, w), bool)
    for phi in dirs:
        near |= np.abs(_angle_from(th, phi)) <= half_width
    t = _PixelTarget(dataclasses.replace(data, mask=data.mask & near & (r >= r_min)
                                         & (r <= r_max)))
    t.kind = "spike pixels"
    t.directions = [float(d) for d in dirs]
    return t

def perturbed_starts(model: ImageModel, n, *, rel=PERTURB, seed=0) -> list[dict[str, float]]:
    """``n`` rough starts: every free parameter's start moved by a uniform random
    fraction within ± ``rel`` of its value (of half its bounds' width, or of its
    ``scale``, where the start is 0), kept inside its bounds. For checking that a fit
    converges to the same answer from anywhere near (the issue's ±20 %)."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(int(n)):
        start = {}
        for k in model.free:
            p = model.params[k]
            size = abs(p.value)
            if size == 0:
                size = (0.5 * (p.bounds[1] - p.bounds[0]) if p.bounds is not None
                        else (p.scale or 1e-3))
            v = p.value + rel * size * rng.uniform(-1, 1)
            if p.bounds is not None:
                lo, hi = p.bounds
                v = min(max(v, lo + 1e-3 * (hi - lo)), hi - 1e-3 * (hi - lo))
            start[k] = float(v)
        out.append(start)
    return out

def chi2_at(model: ImageModel, data, values: Mapping[str, float], target=None) -> float:
    """χ² = Σ ((data − model) / σ)² over the used pixels of ``data`` (a :class:`FitData`
    or a list of them) at ``values``; ``model`` as the fit had it (its own values are
    replaced by ``values``). ``target``: a spike stage's target instead of the pixels."""
    datas = _as_list(data)
    targets = [_PixelTarget(d) for d in datas] if target is None else _as_list(target)
    # the model images from the one program that makes them (model_images: the values
    # its arguments, kept in ._programs), the residuals of the targets on the host
    images = model_images(model, values, datas)
    return float(sum(np.sum(np.asarray(t(jnp.asarray(m), model.capture_values(values, i)))
                            ** 2) for i, (t, m) in enumerate(zip(targets, images))))

def spike_angles(image, centre=None, *, r_min=15.0, r_max=40.0, n_spikes=6, bins=720,
                 symmetric=True, near=None, window=8.0):
    """Angles (degrees, counter-clockwise from +x, y up, in [0, 180) when ``symmetric``)
    of the ``n_spikes`` brightest spikes of an image, from the azimuthal profile of
    r² I between ``r_min`` and ``r_max`` pixels of ``centre`` (x, y in pixel units from
    the top-left pixel's centre; default: the intensity-weighted centre of the brightest
    3 × 3 pixels). Each peak is refined by a parabola through its three bins. With
    ``symmetric`` the profile is folded (θ and θ + 180° are one spike).

    ``near`` (angles in degrees): instead, for each of them the brightest peak within
    ± ``window`` degrees, in the same order (NaN where the profile there has no peak,
    only a slope: its maximum at the window's edge). This measures a second image's
    spikes where the first image's are, e.g. a model's where the data's were found."""
    img = np.asarray(image, float)
    h, w = img.shape
    if centre is None:
        r, c = np.unravel_index(np.nanargmax(img), img.shape)
        sub = img[r - 1:r + 2, c - 1:c + 2]
        yy, xx = np.mgrid[r - 1:r + 2, c - 1:c + 2]
        centre = (float((sub * xx).sum() / sub.sum()), float((sub * yy).sum() / sub.sum()))
    period = 180.0 if symmetric else 360.0
    rr, th = _polar((h, w), centre, period)
    sel = (rr >= r_min) & (rr <= r_max) & np.isfinite(img)
    nb = bins // 2 if symmetric else bins
    edges = np.linspace(0, period, nb + 1)
    idx = np.clip(np.digitize(th[sel], edges) - 1, 0, nb - 1)
    prof = np.bincount(idx, weights=(rr[sel] ** 2 * img[sel]), minlength=nb)
    cnt = np.bincount(idx, minlength=nb)
    prof = np.where(cnt > 0, prof / np.maximum(cnt, 1), 0)
    # smooth a little (circularly)
    k = np.array([1, 2, 3, 2, 1], float)
    k /= k.sum()
    prof = np.convolve(np.concatenate([prof[-2:], prof, prof[:2]]), k, "valid")
    width = period / nb

    def refined(i):
        a, b, c = prof[i - 1], prof[i], prof[(i + 1) % nb]
        den = a - 2 * b + c
        off = 0.5 * (a - c) / den if den != 0 else 0.0
        return ((i + 0.5 + off) * width) % period

    if near is not None:
        near = np.asarray(near, float).ravel()
        if not (np.all(np.isfinite(near)) and 2 * width < window < period / 2):
            raise FitInputError(f"spike_angles: near must be finite angles and window between "
                                f"{2 * width:g} and {period / 2:g} degrees; got {near}, {window}.")
        centres = (np.arange(nb) + 0.5) * width
        out = []
        for t in near:
            gap = np.abs((centres - t + period / 2) % period - period / 2)
            inside = np.flatnonzero(gap <= window)
            i = int(inside[np.argmax(prof[inside])])
            edge = gap[i] > window - width
            out.append(float("nan") if edge else refined(i))
        return out
    peaks = []
    p = prof.copy()
    for _ in range(n_spikes // (2 if symmetric else 1)):
        i = int(np.argmax(p))
        peaks.append(refined(i))
        lo, hi = i - int(8 / width), i + int(8 / width)
        for j in range(lo, hi + 1):
            p[j % nb] = -np.inf
    return sorted(peaks)

def model_spike_angles(values: Mapping[str, float], builder: str = "jwst") -> dict:
    """The spike directions (degrees, [0, 180), counter-clockwise from +x in the image,
    y up) a fitted model implies: perpendicular to the hexagons' edges and to the struts,
    then through the image distortion (``shear``, ``aspect``). For the ``jwst``
    builder: the six hexagon spikes (three directions) at 90° + rotation + k·60° and the
    strut spikes."""
    rot = values.get("rotation", 0.0)
    d = np.array([[1.0, 0.0], [values.get("shear", 0.0), 1.0 + values.get("aspect", 0.0)]])

    def seen(angles):
        a = np.deg2rad(np.asarray(angles, float) + rot)
        u = d @ np.stack([np.cos(a), np.sin(a)])
        return sorted(float(t) for t in np.degrees(np.arctan2(u[1], u[0])) % 180.0)

    out = {}
    if builder == "jwst":
        out["hexagon"] = seen([90.0 + 60 * k for k in range(3)])
        sp = values.get("strut_spread", 30.0)
        up = 90.0 + values.get("strut_tilt", 0.0)
        out["struts"] = seen([a + 90.0 for a in (up, 270 - sp, 270 + sp)])
    else:
        out["struts"] = seen([a + 90.0 for a in (90.0, 210.0, 330.0)])
    return out

def _nowarn():
    warnings.simplefilter("ignore")
