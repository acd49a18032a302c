"""The sampling rules of ``simulate``'s grids, in one place (the PSF engine's own plan is
in :mod:`._psf_engine`): the n × n grid's rules with their fixes (:func:`sampling_report`,
:func:`check_sampling`), the windows that hold the pupil and the sources, whether the
defocus phase matters, and the PSF offsets a crop needs; and the grid's cost
(:func:`check_cost`: wavelengths, edges and memory from static shapes, before anything is
allocated).

For pixel pitch p, oversampling q, n pixels a side and the shortest wavelength λ:
1. the pupil fits the frequency grid: p/q ≤ λ N_w;
2. the grid holds the crop, the object and its blur (checked by the grid chooser);
3. the defocus phase steps by less than π between pupil samples (the blur fits the grid);
4. enough samples across the pupil.
"""

from __future__ import annotations

import math

import jax
import numpy as np

from ._atf import pupil_scale
from ._geometry import check_geometry
from ._model import Camera, Grid, Scene, geometry_of
from ._psf import _bytes, _edges, psf_bytes
from ._psf_engine import SamplingError
from ._validate import (
    MAX_EXACT_EDGES,
    InputError,
    check_memory,
    check_pupil_cost,
    check_wavelength_count,
)


def _concrete(x):
    """A Python float of ``x``, or None when ``x`` is a tracer (inside jit/grad)."""
    try:
        return float(np.asarray(x))
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError, TypeError):
        return None


def scene_extent(camera: Camera, scene: Scene) -> dict:
    """Sizes on the sensor, in pixels: the object's image radius (including its offset),
    the geometric blur diameter and the PSF's core scale λ N_w."""
    g = geometry_of(camera, scene)
    p = camera.sensor.pixel_pitch
    m = abs(float(g.magnification))
    obj = max(
        (float(np.hypot(*np.asarray(s.position, float))) + float(s.radius)) * m / p
        for s in scene.sources
    )
    r = float(camera.lens.pupil.max_radius())
    blur = 2 * r * abs(float(g.defocus)) / float(g.z_in_focus) / p
    return {"object_radius_px": obj, "blur_diameter_px": blur}


def sampling_report(
    *,
    pupil_radius,
    wavelength,
    z_image,
    defocus,
    pixel_pitch,
    oversample: int,
    n: int,
    scaling: str = "fresnel",
    min_pupil_samples: float = 16.0,
) -> list[str]:
    """The DESIGN.md sampling rules that fail, each as a message with the fix (empty = ok).

    Rule 1, pupil in the grid: grid pitch p/q ≤ λ N_w (the ATF's support, the pupil scaled
    to frequencies, fits in the grid; the PSF is then exact at the grid's samples, and
    ``simulate`` takes them at the pixel centres).
    Rule 3, defocus phase: phase step between pupil samples < π, i.e. the field N p/q
    exceeds the geometric blur 2 r |Δz| / z_i.
    Rule 4, pupil resolution: at least ``min_pupil_samples`` samples across the pupil.
    (Rule 2, the field holding the scene, is checked by the grid chooser.)
    """
    r = float(pupil_radius)
    lam = float(wavelength)
    z_r = float(z_image)
    dz = float(defocus)
    p = float(pixel_pitch)
    q = int(oversample)
    scale = float(pupil_scale(lam, z_r, dz, scaling))
    dx = p / q
    fails = []
    nw = scale / lam / (2 * r)
    if dx > lam * nw * (1 + 1e-12):
        need = math.ceil(p / (lam * nw))
        fails.append(
            f"rule 1 (pupil in the grid): grid pitch p/q = {dx * 1e6:.4g} µm exceeds "
            f"λ·N_w = {lam * nw * 1e6:.4g} µm (λ = {lam * 1e9:.4g} nm, working f-number "
            f"{nw:.4g}); the pupil would wrap around the frequency grid. Use oversample >= "
            f"{need}."
        )
    z_i = z_r - dz
    blur = 2 * r * abs(dz) / z_i
    field = n * dx
    if blur >= field:
        need_n = math.ceil(blur / dx) + 1
        fails.append(
            f"rule 3 (defocus phase): the geometric blur {blur * 1e3:.4g} mm does not fit in "
            f"the grid's field {field * 1e3:.4g} mm, so the defocus phase steps by more than π "
            f"between pupil samples. Use a grid of at least {need_n} samples a side "
            f"(shape x oversample)."
        )
    samples = 2 * r * field / scale
    if samples < min_pupil_samples:
        need_n = math.ceil(min_pupil_samples * scale / (2 * r * dx))
        fails.append(
            f"rule 4 (pupil resolution): only {samples:.3g} samples across the pupil "
            f"(minimum {min_pupil_samples:g}). Use a grid of at least {need_n} samples a side."
        )
    return fails


#: complex (n·q)² arrays counted as a grid's least memory (choose_grid and simulate)
_WORKING_ARRAYS = 1


def _grid_bytes(side: int) -> int:
    """Lower bound on the memory of a (side × side) sample grid: one complex array."""
    item = 16 if jax.config.jax_enable_x64 else 8
    return _WORKING_ARRAYS * item * int(side) ** 2


def simulate_bytes(camera: Camera, grid: Grid) -> int:
    """Lower estimate of the bytes :func:`difstar.simulate` holds for this grid, from
    static shapes only (the grid, the wavelengths' count, the pupil's edges): the n·q
    grid (fft); the crop's offsets and the closed form's plane per edge (exact); the
    engine's PSF (:func:`difstar._psf.psf_bytes`) and the crop's offsets, with the
    sensor blur's reach around it (engine)."""
    if grid.method == "fft":
        return _grid_bytes(grid.n * grid.oversample)
    if grid.method == "engine":  # its sub-grid at pitch p/q, the blur's reach around
        q = grid.oversample
        kh, kw = engine_psf_shape(engine_fine_crop(engine_crop(grid.crop, grid.blur_reach), q),
                                  grid.source_window * q)
    else:
        kh, kw = engine_psf_shape(grid.crop, grid.source_window)
    edges = _edges(camera.lens.pupil)
    if grid.method == "exact":
        return _grid_bytes(max(kh, kw)) + 3 * edges * kh * kw * _bytes()
    k = int(np.shape(camera.sensor.wavelengths)[-1]) if np.ndim(camera.sensor.wavelengths) == 2 \
        else 1
    return _grid_bytes(max(kh, kw)) + psf_bytes(grid.psf_plan, (kh, kw), k, edges,
                                                float(camera.sensor.pixel_pitch) / q)


def check_cost(camera: Camera, grid: Grid, where: str = "difstar.simulate") -> None:
    """Refuse (``InputError``, naming the setting and the fix) what cannot run in
    reasonable time and memory, from static shapes (so also while tracing): more than
    ``MAX_WAVELENGTHS`` wavelengths per channel, an outline of more than ``MAX_EDGES``
    edges (``MAX_EXACT_EDGES`` on the closed form), or :func:`simulate_bytes` above the
    memory budget (``DIFSTAR_MEMORY_LIMIT``, else the device's or machine's memory)."""
    sen = camera.sensor
    k = int(np.shape(sen.wavelengths)[-1]) if np.ndim(sen.wavelengths) == 2 else 1
    check_wavelength_count(k, f"{where}: camera.sensor.wavelengths (per channel)")
    check_pupil_cost(camera.lens.pupil, f"{where}: camera.lens.pupil")
    edges = _edges(camera.lens.pupil)
    if grid.method == "exact" and edges > MAX_EXACT_EDGES:
        raise InputError(
            f"{where}: Grid.method='exact' with a pupil of {edges} edges; the closed form "
            f"takes at most {MAX_EXACT_EDGES} (its compile time and memory grow with each "
            "edge); use method='fft' (difstar.choose_grid picks it).")
    side = grid.n * grid.oversample
    check_memory(simulate_bytes(camera, grid), where=where,
                 what=(f"the {grid.method} grid ({grid.n} px a side, oversample "
                       f"{grid.oversample}: {side} samples a side)" if grid.method == "fft"
                       else f"the {grid.method} method on a {grid.crop[0]} x {grid.crop[1]} "
                            f"px crop (source window {grid.source_window} px"
                            + (f", the blur's reach {grid.blur_reach} px"
                               if grid.blur_reach else "") + ")"),
                 fix="use a smaller crop, grid, padding or blur (difstar.choose_grid sizes "
                     "them).")


def check_sampling(camera: Camera, scene: Scene, grid: Grid) -> None:
    """Raise SamplingError when the grid breaks a sampling rule (concrete inputs only),
    and ``InputError`` when its cost is out of bounds (:func:`check_cost`, from static
    shapes: also inside jit)."""
    check_cost(camera, grid)
    lens = camera.lens
    r_f = _concrete(lens.focus_distance)
    r_o = _concrete(scene.object_distance)
    f = _concrete(lens.focal_length)
    if f is None or r_o is None or r_f is None:
        return
    check_geometry(
        focal_length=f, object_distance=r_o, focus_distance=r_f,
        principal_separation=float(lens.principal_separation),
    )
    g = geometry_of(camera, scene)
    vals = [_concrete(v) for v in (lens.pupil.max_radius(), g.z_exit_pupil, g.defocus)]
    try:  # traced wavelengths (a spectral render sharded over them): nothing to check
        lams = [float(v) for v in np.ravel(np.asarray(camera.sensor.wavelengths))]
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError,
            TypeError):
        return
    if any(v is None for v in vals + lams):
        return
    r, z_r, dz = vals
    fails = []
    for lam in sorted(set(lams)):
        fails += [
            f"[λ = {lam * 1e9:.4g} nm] {m}"
            for m in sampling_report(
                pupil_radius=r, wavelength=lam, z_image=z_r, defocus=dz,
                pixel_pitch=camera.sensor.pixel_pitch, oversample=grid.oversample,
                n=grid.n * grid.oversample, scaling=grid.scaling,
            )
            # the exact path has no grid (the closed form at the pixel centres)
            if grid.method == "fft"
        ]
    if grid.method == "fft" and grid.pupil_window:
        need = max(pupil_window_for(r, lam, z_r, camera.sensor.pixel_pitch, grid.n)
                   for lam in lams)
        if need > grid.pupil_window:
            fails.append(
                f"Grid.pupil_window = {grid.pupil_window} samples cannot hold the pupil "
                f"({r * 1e3:.4g} mm radius spans {need} samples at the shortest wavelength); "
                f"use pupil_window >= {need}, or 0 for the whole grid."
            )
    if grid.method == "fft" and 0 < grid.source_window < grid.n:
        need_w = source_window_for(scene_extent(camera, scene)["object_radius_px"])
        if need_w > grid.source_window:
            fails.append(
                f"Grid.source_window = {grid.source_window} px cannot hold the sources' "
                f"image; use source_window >= {need_w} (odd), or 0 for the whole grid."
            )
    if grid.method == "exact" and abs(dz) > 0:
        peak = math.pi * r * r * abs(dz) / (min(lams) * z_r * (z_r - dz))
        if peak > 1e-2:
            fails.append(
                f"Grid.method='exact' is for in-focus scenes, but Δz = {dz * 1e3:.4g} mm "
                f"gives {peak:.3g} rad of defocus phase; use method='fft'."
            )
    if grid.method == "fft" and not grid.use_defocus and abs(dz) > 0:
        # Without the phase the model is wrong by the defocus's peak phase; allow only
        # a negligible amount (< 0.01 rad at the pupil edge).
        peak = math.pi * r * r * abs(dz) / (min(lams) * z_r * (z_r - dz))
        if peak > 1e-2:
            fails.append(
                f"Grid.use_defocus is False but Δz = {dz * 1e3:.4g} mm gives "
                f"{peak:.3g} rad of defocus phase; set use_defocus=True."
            )
    if fails:
        raise SamplingError("difstar.simulate: " + " ".join(fails))


def pupil_window_for(pupil_radius: float, wavelength: float, z_image: float,
                     pixel_pitch: float, n: int) -> int:
    """Even number of frequency samples (a side, of the n·q grid) holding a pupil of this
    radius, with 2 samples to spare each side: 2 r n p / (λ z_R) + 4."""
    span = 2 * pupil_radius * n * pixel_pitch / (wavelength * z_image)
    m = math.ceil(span) + 4
    return m + m % 2


def source_window_for(object_radius_px: float) -> int:
    """Odd number of pixels holding the sources' image (its radius plus one pixel)."""
    return 2 * math.ceil(object_radius_px + 1) + 1


def shortest_wavelength(camera: Camera) -> float:
    """The sensor's shortest wavelength in metres (concrete; NumPy, no JAX operation):
    the one that samples the pupil most finely and spreads the intensity least."""
    return float(np.min(np.asarray(camera.sensor.wavelengths, float)))


def needs_defocus(camera: Camera, scene: Scene, *, tolerance: float = 1e-2) -> bool:
    """Whether the defocus phase is worth computing (peak phase above ``tolerance`` rad)."""
    g = geometry_of(camera, scene)
    r = float(camera.lens.pupil.max_radius())
    dz = float(g.defocus)
    z_r = float(g.z_exit_pupil)
    lam = shortest_wavelength(camera)
    return math.pi * r * r * abs(dz) / (lam * z_r * (z_r - dz)) > tolerance


def engine_fine_crop(crop: tuple[int, int], q: int) -> tuple[int, int]:
    """The crop of the engine's sub-grid at pitch p/q (q odd): pixel k's samples are
    kq … kq + q − 1 and the crop's centre sample (index n//2, on the axis) is the centre
    pixel's centre, so an even side gains q − 1 samples."""
    return tuple(int(n) * q + (q - 1) * (1 - int(n) % 2) for n in crop)


def engine_oversample(bandwidth_cycles_per_pixel: float) -> int:
    """The odd sub-sampling q of the engine's grid that samples the intensity (bandwidth
    2 r p/(λ z_R) cycles per pixel) at or above its Nyquist rate: 1 where the pixels do."""
    q = max(1, math.ceil(2.0 * float(bandwidth_cycles_per_pixel) - 1e-9))
    return q if q % 2 else q + 1


def engine_crop(crop: tuple[int, int], reach: int) -> tuple[int, int]:
    """The pixels the engine computes for ``crop``: the crop and ``reach`` pixels more on
    every side (a sensor blur's, :attr:`Grid.blur_reach`: the light it moves into the
    crop)."""
    return int(crop[0]) + 2 * reach, int(crop[1]) + 2 * reach


def engine_psf_shape(crop: tuple[int, int], source_window: int) -> tuple[int, int]:
    """The PSF offsets a crop needs from a centred source window: (h + s − 1, w + s − 1)."""
    return crop[0] + source_window - 1, crop[1] + source_window - 1
