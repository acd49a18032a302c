"""Scene files: JSON checked against ``data_schemas/scene.schema.json`` ↔ difstar objects.

Outer layer: reads files, validates, builds the PyTrees the core takes. Errors name the
file and the field (a JSON path) and say what is expected.
"""

from __future__ import annotations

import math
import numbers
from pathlib import Path

import numpy as np

from .._validate import InputError, _inner_radius, check_camera_scene, check_polygon_vertices
from ._json import (  # noqa: F401
    SceneError,
    _short,
    check_finite_doc,
    check_float32_doc,
    load_schema,
    read_json,
    schema_path,
    validate,
)

SCHEMA_DIR_ENV = "DIFSTAR_SCHEMAS"


def _pupil_from_dict(d: dict, *, focal_length: float, m_p: float, where: str,
                     source: str = "<scene>"):
    import difstar

    t = d["type"]
    if t == "regular_polygon":
        r = _radius(d, "circumradius", focal_length, m_p, where)
        return difstar.RegularPolygon(int(d["n"]), r, float(d.get("rotation", 0.0)))
    if t == "polygon":
        try:
            v = check_polygon_vertices(d["vertices"], f"{where}/vertices")
            return difstar.Polygon(v)
        except ValueError as exc:
            raise SceneError(f"{source}: field {exc}" if isinstance(exc, InputError)
                             else f"{source}: field {where}/vertices: {exc}") from None
    if t == "circle":
        return difstar.Circle(_radius(d, "radius", focal_length, m_p, where))
    if t == "obstructed":
        outer = _pupil_from_dict(d["outer"], focal_length=focal_length, m_p=m_p,
                                 where=where + "/outer", source=source)
        obs = None
        if "obstruction_radius" in d:
            r_in = _inner_radius(outer)
            if r_in is not None and not d["obstruction_radius"] < r_in:
                raise SceneError(
                    f"{source}: field {where}/obstruction_radius: {d['obstruction_radius']} m "
                    f"covers the whole pupil (its inner radius is {r_in:.6g} m); give an "
                    f"obstruction_radius < {r_in:.6g} m."
                )
            obs = difstar.Circle(d["obstruction_radius"])
        sp = None
        if "spiders" in d:
            s = d["spiders"]
            sp = difstar.Spiders(int(s["n"]), s["width"], s.get("rotation", 0.0),
                                 s.get("length", 2 * float(outer.max_radius())))
        return difstar.Obstructed(outer, obs, sp)
    raise SceneError(f"{source}: field {where}/type: unknown pupil type {t!r}")


def _radius(d, key, focal_length, m_p, where):
    if key in d and "f_number" in d:
        raise SceneError(f"{where}: give either {key} or f_number, not both.")
    if key in d:
        return float(d[key])
    if "f_number" in d:
        return m_p * focal_length / (2 * float(d["f_number"]))
    raise SceneError(f"{where}: give {key} (metres) or f_number.")


#: the most wavelengths per channel a scene file may give (each is one PSF per channel)
MAX_WAVELENGTHS = 1024


def _is_number(x) -> bool:
    return isinstance(x, numbers.Real) and not isinstance(x, (bool, np.bool_))


def _check_spectrum(doc, *, source: str) -> None:
    """The sensor's ``wavelengths`` and ``spectral_weights``, checked before the schema
    (whose messages for a list that may hold numbers or lists name the wrong form) and
    beyond it (equal lengths, weights with a positive sum): 3 numbers (trichromatic), or
    3 lists of K numbers with optional ``spectral_weights`` of the same shape (spectral).
    Raises :class:`SceneError` naming the field and the fix."""
    sd = doc.get("camera") if isinstance(doc, dict) else None
    sd = sd.get("sensor") if isinstance(sd, dict) else None
    check_sensor_spectrum(doc, sd, at="camera/sensor", source=source)


def check_sensor_spectrum(doc, sd, *, at: str, source: str) -> None:
    """The ``wavelengths`` and ``spectral_weights`` of the block ``sd`` of ``doc`` (a
    scene's ``camera/sensor``, a RAW-fit manifest's ``camera``: ``at``) as
    :func:`_check_spectrum` checks them, after ``doc``'s NaN and infinities are refused
    (each named as such)."""
    try:
        check_finite_doc(doc, source=source)
    except InputError as exc:
        raise SceneError(str(exc)) from None
    if not isinstance(sd, dict):
        return  # the schema names what is missing
    forms = ("give 3 numbers (one wavelength per channel R, G, B, in metres, e.g. "
             "[600e-9, 530e-9, 450e-9]) or, for a spectral sensor, 3 lists of K numbers "
             "(the same K for every channel)")

    def bad(field, why):
        raise SceneError(f"{source}: field {at}/{field}: {why}")

    def wavelength(x, field):
        if not _is_number(x):
            bad(field, f"{_short(x)} is not a number; give a wavelength in metres, e.g. 530e-9.")
        if not 0 < x <= 1e-3:
            bad(field, f"{_short(x)} is not a wavelength in metres: it must be > 0 and "
                       "<= 0.001 (1 mm); give metres, e.g. 530e-9 (not nanometres).")

    def rows(v, field, what):
        """3 lists of one length K; returns K."""
        ks = []
        for c, row in enumerate(v):
            if not isinstance(row, list):
                bad(f"{field}/{c}", f"{_short(row)} is not a list; give 3 lists of K {what}.")
            if not 1 <= len(row) <= MAX_WAVELENGTHS:
                bad(f"{field}/{c}", f"has {len(row)} {what}; give 1 to {MAX_WAVELENGTHS}.")
            ks.append(len(row))
        if len(set(ks)) != 1:
            bad(field, f"the channels' lists have {', '.join(map(str, ks))} {what} (ragged); "
                       "give every channel the same number K" + (
                           " (pad a shorter channel with any wavelength of spectral weight 0)."
                           if what == "wavelengths" else ", one weight per wavelength."))
        return ks[0]

    wl = sd.get("wavelengths")
    k = None
    if wl is not None:
        if not isinstance(wl, list) or len(wl) != 3:
            n = f"has {len(wl)} items" if isinstance(wl, list) else f"{_short(wl)} is not a list"
            bad("wavelengths", f"{n}; {forms}.")
        lists = [isinstance(x, list) for x in wl]
        if any(lists) and not all(lists):
            bad("wavelengths", f"mixes numbers and lists; {forms}.")
        if all(lists):
            k = rows(wl, "wavelengths", "wavelengths")
            for c, row in enumerate(wl):
                for j, x in enumerate(row):
                    wavelength(x, f"wavelengths/{c}/{j}")
        else:
            for c, x in enumerate(wl):
                wavelength(x, f"wavelengths/{c}")
    wts = sd.get("spectral_weights")
    if wts is None:
        return
    if k is None:
        bad("spectral_weights", f"given, but {at}/wavelengths "
            + ("is not given" if wl is None else "has one wavelength per channel")
            + " (trichromatic); give wavelengths as 3 lists of K numbers (a spectral "
            "sensor), or drop spectral_weights.")
    if not isinstance(wts, list) or len(wts) != 3:
        n = f"has {len(wts)} items" if isinstance(wts, list) else f"{_short(wts)} is not a list"
        bad("spectral_weights", f"{n}; give 3 lists of {k} numbers >= 0, one weight per "
            f"wavelength of {at}/wavelengths.")
    kw = rows(wts, "spectral_weights", "weights")
    if kw != k:
        bad("spectral_weights", f"{kw} weights per channel for {k} wavelengths; give 3 "
            f"lists of {k}, one weight per wavelength of {at}/wavelengths.")
    for c, row in enumerate(wts):
        for j, x in enumerate(row):
            if not _is_number(x) or x < 0:
                bad(f"spectral_weights/{c}/{j}", f"{_short(x)} is not a number >= 0; give a "
                    "non-negative weight (only the ratios within a channel matter).")
        if not sum(row) > 0:
            bad(f"spectral_weights/{c}", f"channel {'RGB'[c]}'s weights are all 0; give "
                "at least one weight > 0 (they are normalised per channel).")


def _blur_from_dict(bd):
    """A scene's ``camera/sensor/blur`` (``jitter``, ``halos``: name, fraction, width;
    pixels) as a :class:`difstar.Blur`, or None."""
    if not bd:
        return None
    import difstar

    layers = [difstar.Jitter()] if "jitter" in bd else []
    values = {"jitter": float(bd["jitter"])} if "jitter" in bd else {}
    for h in bd.get("halos", ()):
        layers.append(difstar.Halo(h["name"], float(h["width"])))
        values |= {h["name"]: float(h["fraction"]), f"{h['name']}_width": float(h["width"])}
    return difstar.Blur(layers, values) if layers else None


def _blur_to_dict(blur) -> dict:
    """:func:`_blur_from_dict`'s inverse."""
    import difstar

    out, halos = {}, []
    for layer in blur.layers:
        if isinstance(layer, difstar.Jitter):
            out["jitter"] = float(blur.values["jitter"])
        else:
            halos.append({"name": layer.name, "fraction": float(blur.values[layer.name]),
                          "width": float(blur.values[f"{layer.name}_width"])})
    return out | ({"halos": halos} if halos else {})


def scene_from_dict(doc: dict, *, source: str = "<scene>"):
    """(camera, scene, grid options) from a validated scene document."""
    import difstar

    _check_spectrum(doc, source=source)
    validate(doc, "scene", source=source)
    check_float32_doc(doc, source=source)
    cam = doc["camera"]
    ld = cam["lens"]
    f = float(ld["focal_length"])
    m_p = float(ld.get("pupil_magnification", 1.0))
    pupil = _pupil_from_dict(ld["pupil"], focal_length=f, m_p=m_p, where="camera/lens/pupil",
                             source=source)
    fd = ld["focus_distance"]
    try:
        lens = difstar.Lens(
            pupil,
            focal_length=f,
            focus_distance=math.inf if fd == "inf" else float(fd),
            principal_separation=float(ld.get("principal_separation", 0.0)),
            pupil_magnification=m_p,
            defocus=ld.get("defocus"),
        )
        sd = cam["sensor"]
        resp = sd.get("response", {})
        sensor = difstar.Sensor(
            pixel_pitch=float(sd["pixel_pitch"]),
            pattern=sd.get("pattern", "RGGB"),
            wavelengths=sd.get("wavelengths", (600e-9, 530e-9, 450e-9)),
            spectral_weights=sd.get("spectral_weights"),
            phi0=sd.get("phi0", (0.1, 0.1, 0.1)),
            response=difstar.Response(resp.get("toe", (0.0, 0.0, 0.0)),
                                      resp.get("knee", (60.0,) * 3)),
            white_balance=sd.get("white_balance", (2.0, 1.0, 2.0)),
            colour_matrix=sd.get("colour_matrix"),
            blur=_blur_from_dict(sd.get("blur")),
        )
        sc = doc["scene"]
        sources = tuple(_source_from_dict(s) for s in sc["sources"])
        scene = difstar.Scene(
            object_distance=float(sc["object_distance"]),
            sources=sources,
            exposure_time=float(sc["exposure_time"]),
            background=sc.get("background", (0.0, 0.0, 0.0)),
        )
        camera = difstar.Camera(lens, sensor)
        check_camera_scene(camera, scene)  # physics: the object beyond the focus limit...
    except (ValueError, TypeError) as exc:
        if isinstance(exc, SceneError):
            raise
        raise SceneError(f"{source}: {exc}") from None
    grid = dict(doc.get("grid", {}))
    # JSON's integers may be written 1e3 or 64.0 (the schema takes them): ints from here
    for k in ("n", "oversample"):
        if k in grid:
            grid[k] = int(grid[k])
    if "crop" in grid:
        grid["crop"] = [int(c) for c in grid["crop"]]
    return camera, scene, grid


def _source_from_dict(s: dict):
    """A validated ``scene/sources[i]`` entry → a DiscSource or a PointSource."""
    import difstar

    position = s.get("position", (0.0, 0.0))
    if s.get("type", "disc") == "point":
        return difstar.PointSource(position, s["intensity"])
    return difstar.DiscSource(s["radius"], position, s.get("radiance", (1.0, 1.0, 1.0)))


def _source_to_dict(s) -> dict:
    import difstar

    if isinstance(s, difstar.PointSource):
        return {"type": "point", "position": np.asarray(s.position).tolist(),
                "intensity": np.asarray(s.intensity).tolist()}
    return {"type": "disc", "radius": float(s.radius), "position": np.asarray(s.position).tolist(),
            "radiance": np.asarray(s.radiance).tolist()}


def load_scene(path: str | Path):
    """Read a scene JSON file → (camera, scene, grid options dict)."""
    return scene_from_dict(read_json(path, what="scene file"), source=str(path))


def _shortest_float32(doc):
    """Without x64 the values were float32: each written as the shortest decimal that is
    the same float32 (0.0515, not 0.051500000059604645), so that a scene file reads as
    its author wrote it. Values that are no float32 number are left as they are."""
    import jax

    if jax.config.jax_enable_x64:
        return doc
    if isinstance(doc, dict):
        return {k: _shortest_float32(v) for k, v in doc.items()}
    if isinstance(doc, list):
        return [_shortest_float32(v) for v in doc]
    if isinstance(doc, float) and math.isfinite(doc):
        f = np.float32(doc)
        if float(f) == doc:
            return float(str(f))
    return doc


def scene_to_dict(camera, scene, grid_options: dict | None = None, *,
                  name: str | None = None) -> dict:
    """The JSON document (schema ``scene``) for a camera and scene."""
    import difstar

    def tolist(x):
        return np.asarray(x).tolist()

    def pupil_dict(p):
        if isinstance(p, difstar.RegularPolygon):
            return {"type": "regular_polygon", "n": p.n, "circumradius": float(p.circumradius),
                    "rotation": float(p.rotation)}
        if isinstance(p, difstar.Polygon):
            return {"type": "polygon", "vertices": tolist(p.vertices)}
        if isinstance(p, difstar.Circle):
            return {"type": "circle", "radius": float(p.radius)}
        if isinstance(p, difstar.Obstructed):
            d = {"type": "obstructed", "outer": pupil_dict(p.outer)}
            if p.obstruction is not None:
                d["obstruction_radius"] = float(p.obstruction.radius)
            if p.spiders is not None:
                s = p.spiders
                d["spiders"] = {"n": s.n, "width": float(s.width), "rotation": float(s.rotation),
                                "length": float(s.length)}
            return d
        raise SceneError(f"cannot write a {type(p).__name__} pupil to a scene file")

    lens, sen = camera.lens, camera.sensor
    fd = float(lens.focus_distance)
    doc = {
        "camera": {
            "lens": {
                "focal_length": float(lens.focal_length),
                "focus_distance": "inf" if math.isinf(fd) else fd,
                "principal_separation": float(lens.principal_separation),
                "pupil_magnification": float(lens.pupil_magnification),
                "defocus": None if lens.defocus is None else float(lens.defocus),
                "pupil": pupil_dict(lens.pupil),
            },
            "sensor": {
                "pixel_pitch": sen.pixel_pitch,
                "pattern": sen.pattern,
                "wavelengths": tolist(sen.wavelengths),
                **({} if sen.spectral_weights is None
                   else {"spectral_weights": tolist(sen.spectral_weights)}),
                "phi0": tolist(sen.phi0),
                "response": {"toe": tolist(sen.response.toe), "knee": tolist(sen.response.knee)},
                "white_balance": tolist(sen.white_balance),
                "colour_matrix": tolist(sen.colour_matrix),
                **({} if sen.blur is None else {"blur": _blur_to_dict(sen.blur)}),
            },
        },
        "scene": {
            "object_distance": float(scene.object_distance),
            "exposure_time": float(scene.exposure_time),
            "background": tolist(scene.background),
            "sources": [_source_to_dict(s) for s in scene.sources],
        },
    }
    if name:
        doc = {"name": name, **doc}
    doc = _shortest_float32(doc)
    if grid_options:
        doc["grid"] = {k: (list(v) if isinstance(v, tuple) else v) for k, v in grid_options.items()}
    return doc
