"""The RAW camera fit's parameters: their names, shapes and units, and the detector
layers they switch on.

Parameters (name → shape, unit):

- ``circumradius`` (), m — exit-pupil circumradius of the regular n-gon;
- ``curvature`` (), 1 — every blade's relative edge curvature R·κ (present: the iris is a
  :class:`difstar.CurvedIris`, 0 straight, 1 the circumscribed circle; absent: straight);
- ``z<j>`` (), nm RMS — the Noll-``j`` Zernike term of the wavefront (j ≥ 2; e.g. ``z11``
  spherical aberration), normalised over a circle of the camera's ``zernike_radius``
  (nm, as in image-fit manifests);
- ``rotation`` (), rad — angle of the first vertex (a regular n-gon is only defined
  modulo 2π/n; :func:`difstar._fit_truth.wrap_rotation` compares angles accordingly);
- ``vertex_radial`` (n,), fraction of the circumradius, and ``vertex_angular`` (n,),
  rad — per-vertex deviations from the regular polygon, mean removed (the mean is the
  circumradius and the rotation); with both free the vertices are free;
- ``defocus/<config>`` (), m — Δz of each configuration (absent: Δz from geometry);
- ``source_radius`` (), m in the object plane;
- ``source_offset/<config>`` (2,), pixels (row, col) — sub-pixel correction to the
  rough source position given for the captures of that configuration;
- ``phi0`` (3,), s; ``toe`` (3,); ``knee`` (3,) — exposure scale and response curve
  per channel (R, G, B), see ``_sensor.py``;
- ``background`` (3,), relative radiance added to the image;
- ``exposure_scale/<capture>`` () — multiplies the capture's nominal exposure time;
- ``jitter`` (), pixels — the σ of a Gaussian blur of the linear image (the detector's
  :class:`difstar.Jitter`; absent: none);
- ``<halo>`` (), fraction, and ``<halo>_width`` (), pixels — each of the camera's
  ``halos`` (:class:`difstar.Halo`, default one named ``halo``) moves that fraction of
  the light into a Gaussian of that σ (absent: none; the width absent: the halo's own).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from ._detector import Halo, Jitter, reach_of

UNITS = {
    "circumradius": "m", "curvature": "1", "zernike": "nm", "rotation": "rad",
    "vertex_radial": "1", "vertex_angular": "rad",
    "defocus": "m", "source_radius": "m", "source_offset": "px", "phi0": "s", "toe": "1",
    "knee": "1", "background": "1", "exposure_scale": "1",
    # a pupil builder's parameters (CameraConstants.pupil): exit-pupil metres, degrees
    "radius": "m", "obstruction": "m", "strut_width": "m", "flat_to_flat": "m", "gap": "m",
    "strut_spread": "deg", "strut_tilt": "deg",
}


#: the parameters of the blades iris (no CameraConstants.pupil) only
IRIS_ONLY = ("circumradius", "curvature", "vertex_radial", "vertex_angular")


def base_name(name: str) -> str:
    return name.split("/", 1)[0]


def zernike_index(name: str) -> int | None:
    """j for a parameter named ``z<j>`` (a Zernike term), else None."""
    if len(name) > 1 and name[0] == "z" and name[1:].isdigit():
        return int(name[1:])
    return None


def unit_of(name: str, halos=(Halo(),)) -> str:
    """The unit of parameter ``name`` (``halos``: the camera's, for theirs)."""
    blur = {**Jitter().units, **_halo_names(halos)}
    if name in blur:
        return blur[name]
    return UNITS["zernike"] if zernike_index(name) is not None else UNITS[base_name(name)]


def param_shape(name: str, n_blades: int, pupil=None, halos=(Halo(),)) -> tuple[int, ...]:
    """The shape of parameter ``name``; ``pupil`` (a :class:`difstar.PupilBuilder`, as
    :attr:`CameraConstants.pupil`) adds its named parameters, each a number, and
    ``halos`` (:attr:`CameraConstants.halos`) theirs."""
    if name == "jitter" or name in _halo_names(halos):
        return ()
    b = base_name(name)
    if pupil is not None and b in builder_parameters(pupil):
        return ()
    if pupil is not None and b in IRIS_ONLY:
        raise ValueError(f"{name!r} belongs to the blades iris; a camera.pupil builder "
                         f"({pupil.name!r}) has {', '.join(sorted(builder_parameters(pupil)))}")
    if b in ("vertex_radial", "vertex_angular"):
        return (n_blades,)
    if b in ("phi0", "toe", "knee", "background"):
        return (3,)
    if b == "source_offset":
        return (2,)
    if b in ("circumradius", "curvature", "rotation", "defocus", "source_radius",
             "exposure_scale"):
        return ()
    j = zernike_index(b)
    if j is not None and j >= 2:
        return ()
    known = "" if pupil is None else (f"; this pupil ({pupil.name!r}) has "
                                      f"{', '.join(sorted(builder_parameters(pupil)))}")
    halo = "" if not halos else f"; the halos' are {', '.join(_halo_names(halos))}"
    raise ValueError(f"unknown fit parameter {name!r}{known}{halo}")


def builder_parameters(pupil) -> dict[str, float]:
    """A pupil builder's parameters a RAW fit can name, with their defaults (those a
    camera's single pupil has: not the segmented pupils' ``incoherent`` fraction)."""
    return {k: v for k, v in pupil.defaults.items() if k != "incoherent"}


def _halo_names(halos) -> dict[str, str]:
    """{parameter name: its unit} of the declared ``halos``."""
    return {k: u for h in halos for k, u in h.units.items()}


def blur_layers(params: Mapping, halos) -> tuple:
    """The detector's layers a RAW fit's ``params`` switch on: :class:`Jitter` where
    ``jitter`` is a parameter, each of ``halos`` whose fraction is."""
    return ((Jitter(),) if "jitter" in params else ()) + tuple(
        h for h in halos if h.name in params)


def blur_reach(params: Mapping, layers) -> int:
    """The pixels the blur of ``layers`` reaches at most over the fit
    (:func:`difstar._detector.reach_of`), each free parameter at its upper bound (a
    static number for the chain, from the parameters' concrete starts and bounds; a
    layer's parameter the fit does not name at its default)."""
    values = {}
    for layer in layers:
        for k, default in layer.parameters.items():
            p = params.get(k)
            values[k] = default if p is None else float(np.max(np.abs(np.asarray(
                p.hi if p.free else p.value))))
    return reach_of(layers, values)
