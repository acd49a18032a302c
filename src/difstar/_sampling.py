"""Choosing the grid from the scene (DESIGN.md sampling rules).

Runs outside jit, on concrete values: it decides the static shapes that ``simulate``
compiles for. Rule 1 sets the oversampling q; rules 2–4 set the grid size n; the defocus
phase is switched off when its peak phase is negligible ("model only what the scene
needs").
"""

from __future__ import annotations

import math

import numpy as np

from ._atf import intensity_bandwidth
from ._fft_size import fast_length as fast_length
from ._model import Camera, Grid, Scene, geometry_of
from ._psf import _edges, _plan
from ._psf_engine import SamplingError
from ._pupil import Polygon, RegularPolygon
from ._sampling_rules import (
    _grid_bytes,
    check_cost,
    check_sampling,
    engine_crop,
    engine_fine_crop,
    engine_oversample,
    engine_psf_shape,
    needs_defocus,
    pupil_window_for,
    scene_extent,
    shortest_wavelength,
    source_window_for,
)
from ._validate import (
    MAX_EXACT_EDGES,
    InputError,
    check_camera_scene,
    check_crop,
    fmt_bytes,
    fmt_count,
    memory_budget,
)

#: Accuracy target used when neither ``accuracy`` nor ``padding`` is given: relative RMS
#: error of the linear image outside the source's core (DESIGN.md, "Measuring error").
DEFAULT_ACCURACY = 1e-2

# Calibration (BENCHMARKS.md, "Calibration"): relative RMS error outside the core against
# padding (the guard band beyond the scene and blur, as a fraction of the crop), measured
# in float64 for the paper's focused scene (against the exact polygon transform) and
# defocused scene (against padding 10) on a 256 px crop. The envelope of both is bounded
# by err ≤ _CAL_A · padding^(−_CAL_ALPHA) for padding in [0.1, 6], with a margin for
# smaller crops (a 96 px crop measured 4.2e-3 at padding 4) (the FFT path's
# spikes wrap around, so the error falls only about as 1/N);
# padding_for_accuracy inverts it.
_CAL_A = 2e-2
_CAL_ALPHA = 1.0
_MIN_PADDING = 0.05


def _max_side(budget: int) -> int:
    return int(math.isqrt(max(budget // _grid_bytes(1), 0)))


def required_oversample(camera: Camera, scene: Scene) -> int:
    """Rule 1: the smallest q with p/q ≤ λ_min N_w (the pupil fits in the frequency
    grid; the PSF is sampled at the pixel centres, so its own bandwidth sets nothing).
    p/(λ N_w) = 2 r p/(λ z_R) is the intensity's bandwidth, :func:`pixel_bandwidth`."""
    return max(1, math.ceil(pixel_bandwidth(camera, scene) - 1e-9))


def pixel_bandwidth(camera: Camera, scene: Scene, scaling: str = "fresnel") -> float:
    """The intensity's bandwidth at the shortest wavelength, cycles per pixel. Over 0.5
    the pixels undersample it: the PSF at the pixel centres is then not the pixel
    integral, and only the engine's sub-pixel grid (:func:`engine_oversample`) models
    the pixels."""
    g = geometry_of(camera, scene)
    return float(intensity_bandwidth(
        float(camera.lens.pupil.max_radius()), shortest_wavelength(camera),
        float(g.z_exit_pupil), float(g.defocus), float(camera.sensor.pixel_pitch), scaling))


def padding_for_accuracy(accuracy: float | None) -> float:
    """The padding (fraction of the crop added as a guard band) whose measured error on
    the paper's scenes is at most ``accuracy`` (relative RMS outside the core)."""
    acc = DEFAULT_ACCURACY if accuracy is None else float(accuracy)
    if not (acc > 0 and math.isfinite(acc)):
        raise ValueError(f"accuracy must be a finite number > 0; got {accuracy!r}.")
    return max(_MIN_PADDING, (_CAL_A / acc) ** (1.0 / _CAL_ALPHA))


def _engine_grid(camera: Camera, scene: Scene, crop, *, accuracy, raw_only, scaling,
                 oversample=None, n: int | None = None) -> Grid:
    """The grid of ``method="engine"``: the PSF through :func:`difstar.psf`'s engine on the
    offsets the crop needs, planned here (outside jit) for every channel's wavelengths,
    at pitch p/q where the pixels undersample the intensity (``oversample`` q, odd,
    overrides :func:`engine_oversample`'s choice). ``n``: the field's period in pixels
    (the paper's n × n grid, from ``choose_grid``'s ``n`` or ``padding``) in place of the
    engine's own rule, transformed by pruned FFTs of length n q."""
    g = geometry_of(camera, scene)
    ext = scene_extent(camera, scene)
    window = source_window_for(ext["object_radius_px"])
    lams = np.asarray(camera.sensor.wavelengths)
    pitch = float(camera.sensor.pixel_pitch)
    # sub-pixels where the pixels undersample the intensity
    z_r = float(g.z_exit_pupil)
    q = (engine_oversample(pixel_bandwidth(camera, scene, scaling)) if oversample is None
         else oversample)
    if q % 2 == 0:
        raise ValueError(f"choose_grid: oversample = {q} for the PSF engine's grid; give an "
                         "odd number (each pixel's samples are centred on it), e.g. "
                         f"{q + 1}.")
    crop = tuple(int(c) for c in crop)
    reach = 0 if camera.sensor.blur is None else camera.sensor.blur.reach
    shape = engine_psf_shape(engine_fine_crop(engine_crop(crop, reach), q), window * q)
    # one plan for every channel's wavelengths; each channel is one PSF call of its K
    # (their count per channel was checked with the camera)
    plan = _plan(camera.lens.pupil, wavelength=np.ravel(lams), z_image=z_r,
                 defocus=float(g.defocus), pixel_pitch=pitch / q, shape=shape,
                 sampling="point", accuracy=accuracy, wavefront=camera.lens.wavefront,
                 scaling=scaling, method=None if n is None else "fft", max_radius=None,
                 n_eval=lams.shape[-1] if lams.ndim == 2 else 1,
                 period=None if n is None else n * pitch)
    grid = Grid(n=max(crop) if n is None else max(n, *crop), oversample=q, crop=crop,
                use_defocus=plan.use_defocus,
                raw_only=raw_only, scaling=scaling, method="engine", source_window=window,
                psf_plan=plan, blur_reach=reach)
    check_cost(camera, grid, where="choose_grid")
    return grid


def choose_grid(
    camera: Camera,
    scene: Scene,
    *,
    crop: tuple[int, int],
    padding: float | None = None,
    n: int | None = None,
    oversample: int | None = None,
    raw_only: bool = False,
    scaling: str = "fresnel",
    accuracy: float | None = None,
    method: str | None = None,
) -> Grid:
    """A grid satisfying the sampling rules for this camera and scene.

    ``method`` (default: chosen) is "exact" for an in-focus scene with a polygonal
    pupil, no wavefront, no spectral sensor and pixels that sample the intensity, when
    none of ``n``, ``padding`` and ``accuracy`` is given: the closed-form PSF on exactly
    the offsets the crop needs, no grid and no aliasing. Otherwise it is "engine": the PSF
    engine of :func:`difstar.psf` (one planner for both) on the offsets the crop needs,
    convolved linearly with the sources' window. Its period follows ``accuracy`` (the
    engine's relative RMS target, default its own 1e-3), or the n × n grid that ``n`` or
    ``padding`` give (then ``accuracy``, default :data:`DEFAULT_ACCURACY`, sets only the
    pupil's sub-cells). ``oversample`` is the engine's odd number of samples a side per
    pixel (default: the fewest at the intensity's Nyquist rate, 1 where the pixels
    sample it; each pixel is their mean).

    "fft" (only when asked for) is the paper's transform of the whole n × n grid:
    n ≥ crop + object diameter + blur + ``padding`` × crop, rounded up to a fast FFT size,
    so that the aliases of the spikes land ``padding × crop`` away; ``padding`` defaults
    to the one whose measured error outside the source's core is at most ``accuracy``
    (calibration in BENCHMARKS.md), and its oversampling q is the smallest that meets
    rule 1. An override that breaks a rule raises :class:`difstar.SamplingError` naming
    the rule and the value that would satisfy it.
    """
    crop = check_crop(crop, "choose_grid: crop")
    check_camera_scene(camera, scene, where="choose_grid")
    budget = memory_budget()
    if oversample is not None:
        oversample = int(oversample)
        if oversample < 1:
            raise InputError(f"choose_grid: oversample = {oversample}; give an integer >= 1.")

    def refuse(side: int, q: int, fixes: str):
        raise SamplingError(
            f"difstar.choose_grid: the grid ({fmt_count(side // q, 12)} px a side, "
            f"oversample {q}: {fmt_count(side, 12)} samples a side) needs at least "
            f"{fmt_bytes(_grid_bytes(side))} of memory, "
            f"more than the {fmt_bytes(budget)} this machine has (DIFSTAR_MEMORY_LIMIT "
            f"overrides). {fixes}"
        )

    in_focus = not needs_defocus(camera, scene)
    spectral = camera.sensor.spectral_weights is not None
    aberrated = camera.lens.wavefront is not None
    polygon = isinstance(camera.lens.pupil, (Polygon, RegularPolygon))
    # the closed form's cost grows with the edges: above MAX_EXACT_EDGES, the fft grid
    few_edges = _edges(camera.lens.pupil) <= MAX_EXACT_EDGES
    blurred = camera.sensor.blur is not None  # the detector's blur: the engine's alone
    exact_ok = (in_focus and polygon and few_edges and not spectral and not aberrated
                and not blurred)
    # pixels that undersample the intensity: the exact and fft paths sample the PSF at
    # the pixel centres, 15-170x farther from a pixel-integrating camera than the engine's
    # sub-pixel grid (BENCHMARKS.md, "The chain against an independent camera")
    undersampled = pixel_bandwidth(camera, scene, scaling) > 0.5
    if method is None:
        # the closed form where it applies and nothing asks for a grid; every sampled
        # pupil through the PSF engine's one planner
        method = ("exact" if exact_ok and not (spectral or aberrated or undersampled)
                  and n is None and padding is None and accuracy is None else "engine")
    if method == "engine" and n is None and padding is None:
        return _engine_grid(camera, scene, crop, accuracy=accuracy, raw_only=raw_only,
                            scaling=scaling, oversample=oversample)
    if method == "fft" and (spectral or aberrated or blurred):
        raise ValueError(
            f"choose_grid: method={method!r} models one wavelength per channel, no wavefront "
            "error and no detector blur; this camera has a spectral sensor, a lens wavefront "
            "or a Sensor.blur: use method='engine' (the default for it).")
    if method == "exact":
        if polygon and not few_edges:
            raise InputError(
                f"choose_grid: method='exact' with a pupil of {_edges(camera.lens.pupil)} "
                f"edges; the closed form takes at most {MAX_EXACT_EDGES} (its compile time "
                "and memory grow with each edge); use method='fft' or leave method unset.")
        if not exact_ok:
            raise ValueError(
                "choose_grid: method='exact' needs an in-focus scene, a Polygon or "
                "RegularPolygon pupil, one wavelength per channel, no wavefront error and no "
                "Sensor.blur; use method='engine' (or leave method unset)."
            )
        ext = scene_extent(camera, scene)
        q = 1  # the closed form at the pixel centres: no grid, nothing to oversample
        side = (max(crop) + 2 * math.ceil(ext["object_radius_px"]) + 1) * q
        if _grid_bytes(side) > budget:
            fit = _max_side(budget) // q - 2 * math.ceil(ext["object_radius_px"]) - 1
            fit -= fit % 2
            refuse(side, q, f"Use a crop of at most {fit} × {fit} pixels." if fit >= 8 else
                   "The sources' image alone is too large: make them smaller or nearer the "
                   "axis.")
        window = source_window_for(ext["object_radius_px"])
        grid = Grid(n=max(crop), oversample=q, crop=tuple(int(c) for c in crop),
                    use_defocus=False, raw_only=raw_only, scaling=scaling, method="exact",
                    source_window=window)
        if oversample is not None:
            check_sampling(camera, scene, grid)
        check_cost(camera, grid, where="choose_grid")
        return grid
    if method not in ("fft", "engine"):
        raise ValueError(f"choose_grid: method must be 'exact', 'engine', 'fft' or None; got "
                         f"{method!r}.")
    # n or padding: the n × n grid's period, for the paper's transform ("fft") or the
    # engine's pruned one
    if padding is not None and accuracy is not None and method == "fft":
        raise ValueError("choose_grid: give padding or accuracy, not both (on the paper's "
                         "grid the accuracy chooses the padding).")
    if padding is None:
        padding = padding_for_accuracy(accuracy)
    elif not (float(padding) >= 0 and math.isfinite(float(padding))):
        raise ValueError(f"choose_grid: padding must be a finite number >= 0; got {padding!r}.")
    ext = scene_extent(camera, scene)
    need_q = required_oversample(camera, scene)
    q = need_q if oversample is None else int(oversample)
    span = max(crop) + 2 * ext["object_radius_px"] + ext["blur_diameter_px"]
    overridden = n is not None or oversample is not None
    want = n if n is not None else span + padding * max(crop)
    if not math.isfinite(want) or _grid_bytes(math.ceil(want) * q) > budget:
        n_fit = _max_side(budget) // q
        extra = span - max(crop)
        fixes = []
        if n is not None:
            fixes.append(f"Use n <= {n_fit}.")
        pad_fit = (n_fit - span) / max(crop)
        if pad_fit >= _MIN_PADDING and n is None:
            if accuracy is not None:
                fixes.append(f"The tightest accuracy that fits is about "
                             f"{_CAL_A * (1.0 / pad_fit) ** _CAL_ALPHA:.2g} (accuracy >= "
                             f"that, or padding <= {pad_fit:.3g}).")
            else:
                fixes.append(f"Use padding <= {pad_fit:.3g}.")
        crop_fit = int((n_fit - extra) / (1 + (padding if n is None else 0)))
        crop_fit -= crop_fit % 2
        if crop_fit >= 8:
            fixes.append(f"A crop of at most {crop_fit} × {crop_fit} pixels fits.")
        else:
            fixes.append(f"The sources and their blur alone span {extra:.4g} px: make the "
                         "sources smaller or nearer the axis, or the defocus smaller.")
        refuse(math.ceil(want) * q if math.isfinite(want) else 2**62, q, " ".join(fixes))
    if n is None:
        n = fast_length(math.ceil(span + padding * max(crop)))
        n += n % 2
    elif n < math.ceil(span):
        need = math.ceil(span)
        raise SamplingError(
            f"difstar.choose_grid: rule 2 (field): n = {n} pixels cannot hold the crop "
            f"{max(crop)} px plus the object ({2 * ext['object_radius_px']:.4g} px across) "
            f"and its blur ({ext['blur_diameter_px']:.4g} px); the image would wrap around. "
            f"Use n >= {need} (a fast size: {fast_length(need)}), or omit n."
        )
    if method == "engine":
        # the grid's period through the PSF engine: pruned FFTs on the offsets the crop
        # needs, the pupil's sub-cells at the accuracy (given with padding or n, or the
        # grid's default), and the pixels' own sub-samples where they undersample the
        # intensity
        return _engine_grid(camera, scene, crop, raw_only=raw_only, scaling=scaling,
                            accuracy=DEFAULT_ACCURACY if accuracy is None else accuracy,
                            oversample=oversample, n=int(n))
    # the paper's method: the whole n × n grid, transformed twice per channel
    g = geometry_of(camera, scene)
    lam_min = shortest_wavelength(camera)
    m = pupil_window_for(float(camera.lens.pupil.max_radius()), lam_min,
                         float(g.z_exit_pupil), camera.sensor.pixel_pitch, int(n))
    src = source_window_for(ext["object_radius_px"])
    grid = Grid(
        n=int(n), oversample=q, crop=tuple(int(c) for c in crop),
        use_defocus=needs_defocus(camera, scene), raw_only=raw_only, scaling=scaling,
        pupil_window=m if m < int(n) * q else 0, source_window=src if src < int(n) else 0,
    )
    if overridden:
        check_sampling(camera, scene, grid)  # rules 1, 3, 4 with the fix in the message
    check_cost(camera, grid, where="choose_grid")
    return grid
