"""difstar's twin of a camera of the independent generator (``raw_generator``): the
same lens, iris, wavefront, sensor and source built from difstar's public classes, so
that its image can be held against the generator's. Shared by
``tests/test_independent_camera.py`` and ``benchmarks/independent_camera.py``."""

from __future__ import annotations

import time

import equinox as eqx
import numpy as np

import difstar


def twin_image(camp, cfg, *, straight: bool = False, source_scale: float = 1.0,
               **grid_kw):
    """difstar's linear image (3, h, w) of the generator's ``camp`` at configuration
    ``cfg`` through ``simulate`` on ``choose_grid(..., **grid_kw)``'s grid; the grid and
    the seconds ``simulate`` took (compile included).

    ``straight``: the iris as a RegularPolygon without wavefront (the camera the exact
    and fft paths serve; the generator's curvature and aberration must then be 0)."""
    iris, sen = camp.iris, camp.sensor
    if straight:
        if iris.curvature or iris.spherical:
            raise ValueError("straight=True needs the generator's iris at curvature 0 and "
                             "spherical 0")
        pupil, wave = difstar.RegularPolygon(iris.n, iris.circumradius,
                                             rotation=iris.rotation), None
    else:
        pupil = difstar.CurvedIris(iris.n, iris.circumradius, iris.curvature,
                                   rotation=iris.rotation)
        wave = (difstar.Zernike({11: iris.spherical}, radius=iris.zernike_radius)
                if iris.spherical else None)
    lens = difstar.Lens(pupil, focal_length=camp.lens.focal_length,
                        focus_distance=cfg.focus_distance,
                        principal_separation=camp.lens.principal_separation,
                        pupil_magnification=camp.lens.pupil_magnification, wavefront=wave)
    camera = difstar.Camera(lens, difstar.Sensor(pixel_pitch=sen.pixel_pitch,
                                                 pattern=sen.pattern,
                                                 wavelengths=sen.wavelengths))
    scene = difstar.Scene(object_distance=cfg.object_distance,
                          sources=(difstar.DiscSource(camp.source_radius * source_scale),),
                          exposure_time=0.01)
    grid = difstar.choose_grid(camera, scene, crop=camp.frame, **grid_kw)
    t0 = time.perf_counter()
    img = np.asarray(eqx.filter_jit(difstar.simulate)(camera, scene, grid).image)  # compiled
    return img, grid, time.perf_counter() - t0


def shape_error(gen: np.ndarray, img: np.ndarray) -> float:
    """Worst channel's RMS difference over the window relative to its peak, after one
    radiometric constant per channel (the ratio of the totals)."""
    return max(float(np.sqrt(np.mean((gen[c] * img[c].sum() / gen[c].sum() - img[c]) ** 2))
                     / img[c].max()) for c in range(3))
