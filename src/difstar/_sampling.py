"""Choosing the grid from the scene (DESIGN.md sampling rules).

Runs outside jit, on concrete values: it decides the static shapes that ``simulate``
compiles for. Rule 1 sets the oversampling q; rules 2–4 set the grid size n; the defocus
phase is switched off when its peak phase is negligible ("model only what the scene
needs").
"""

from __future__ import annotations

import math

import jax.numpy as jnp

from ._chain import Camera, Grid, Scene, geometry_of, needs_defocus

_FAST_RADICES = (2, 3, 5, 7)


def fast_length(n: int) -> int:
    """Smallest m ≥ n whose prime factors are all in {2, 3, 5, 7} (fast FFT sizes)."""
    m = max(int(n), 1)
    while True:
        k = m
        for p in _FAST_RADICES:
            while k % p == 0:
                k //= p
        if k == 1:
            return m
        m += 1


def required_oversample(camera: Camera, scene: Scene) -> int:
    """Rule 1: the smallest q with p/q ≤ λ_min N_w / 2."""
    g = geometry_of(camera, scene)
    r = float(camera.lens.pupil.max_radius())
    nw = float(g.z_exit_pupil) / (2 * r)
    lam = float(jnp.min(camera.sensor.wavelengths))
    return max(1, math.ceil(camera.sensor.pixel_pitch / (lam * nw / 2) - 1e-9))


def scene_extent(camera: Camera, scene: Scene) -> dict:
    """Sizes on the sensor, in pixels: the object's image radius (including its offset),
    the geometric blur diameter and the PSF's core scale λ N_w."""
    g = geometry_of(camera, scene)
    p = camera.sensor.pixel_pitch
    m = abs(float(g.magnification))
    obj = max(
        (float(jnp.hypot(*s.position)) + float(s.radius)) * m / p for s in scene.sources
    )
    r = float(camera.lens.pupil.max_radius())
    blur = 2 * r * abs(float(g.defocus)) / float(g.z_in_focus) / p
    return {"object_radius_px": obj, "blur_diameter_px": blur}


def choose_grid(
    camera: Camera,
    scene: Scene,
    *,
    crop: tuple[int, int],
    padding: float = 1.0,
    n: int | None = None,
    oversample: int | None = None,
    raw_only: bool = False,
    scaling: str = "fresnel",
) -> Grid:
    """A grid satisfying the sampling rules for this camera and scene.

    n ≥ crop + object diameter + blur + ``padding`` × crop, rounded up to a fast FFT
    size: the crop's pixels then receive light only from PSF offsets inside the grid,
    and the aliases of the PSF's slowly decaying spikes land ``padding × crop`` away.
    ``n`` and ``oversample`` override the choice; an override that breaks a rule raises
    :class:`difstar.SamplingError` (checked in ``simulate``).
    """
    ext = scene_extent(camera, scene)
    need_q = required_oversample(camera, scene)
    q = need_q if oversample is None else int(oversample)
    if n is None:
        span = max(crop) + 2 * ext["object_radius_px"] + ext["blur_diameter_px"]
        n = fast_length(math.ceil(span + padding * max(crop)))
        n += n % 2
    return Grid(
        n=int(n), oversample=q, crop=tuple(int(c) for c in crop),
        use_defocus=needs_defocus(camera, scene), raw_only=raw_only, scaling=scaling,
    )
