"""Image-fit manifests: a JSON document parsed and checked once, at the boundary, into
an :class:`ImageModel`, its :class:`FitData` and the stages (data paths, captures, σ
maps, sources, parameters)."""

from __future__ import annotations

import dataclasses
import math
import re
import warnings
from collections.abc import Mapping
from typing import Any

import numpy as np

from ..io._images import read_image
from ..io._json import SceneError, check_float32_doc, load_schema, read_json_extends, validate
from ._auto import auto_stages
from ._data import FitData, Noise
from ._detector import halos_of
from ._model import ImageModel, parameter_defaults
from ._params import FitInputError, Param, _as_param
from ._parts import BUILDERS, Light, PupilBuilder
from ._stages import _check_fit_inputs, _InputAt


def resolve_data_path(path: str, manifest_dir, *, field: str | None = None,
                      source: str = "manifest") -> str:
    """A data path from a manifest: absolute, or relative to the manifest's folder, the
    current folder or the repository root (the folder above ``fit/``), whichever exists.
    ``field``: the manifest's field that gave it (named in the error)."""
    import os
    from pathlib import Path

    p = Path(path)
    if p.is_absolute():
        cands = [p]
    else:
        md = Path(manifest_dir).resolve()
        cands = [md / p, Path.cwd() / p] + [a / p for a in md.parents if (a / "fit").is_dir()]
    for c in cands:
        try:
            found = c.exists()
        except (OSError, ValueError):  # a name the system cannot hold
            found = False
        if found:
            return os.path.abspath(c)  # ".." folded: the path the output policy compares
    where = f"{source}: field {field}" if field else source
    raise FitInputError(f"{where}: data file {path!r} not found (looked in "
                        f"{', '.join(str(c.parent) for c in cands[:3])}); give a path "
                        "relative to the manifest's folder, or an absolute one.")

def _read_at(file: str, field: str, source: str):
    """:func:`difstar.io.read_image` of ``file``, its errors naming the manifest's field."""
    try:
        return read_image(file)
    except (ValueError, OSError) as e:
        raise FitInputError(f"{source}: field {field}: {e}") from None

def _load_capture(d: Mapping, where, manifest_dir, *, source: str = "manifest",
                  inputs: list | None = None, transform=None) -> FitData:
    """One capture of a manifest's ``data``: its file, window, σ (a number, a σ map file or
    the noise model), exposure and saturation level, checked against the image (the ROI
    inside it, a σ map of its shape, some signal) with errors naming ``where`` (the
    capture's JSON path). The files read are appended to ``inputs``. Pixels that are NaN
    or infinite (a FITS border) are left out of the fit, with a warning. ``transform``:
    see :func:`load_manifest`."""
    if not isinstance(d, Mapping) or "path" not in d:
        raise FitInputError(f"{source}: field {where}: needs a 'path' (the image file).")
    inputs = [] if inputs is None else inputs
    file = resolve_data_path(d["path"], manifest_dir, field=f"{where}/path", source=source)
    inputs.append(file)
    im = _read_at(file, f"{where}/path", source)
    if transform is not None:  # a changed copy of the image, read as if from a file
        new = np.asarray(transform(np.where(im.valid, im.data, np.nan)), float)
        if new.shape != im.shape:
            raise FitInputError(f"{source}: field {where}/path: the transform returned shape "
                                f"{new.shape} for an image of shape {im.shape}.")
        valid = im.valid & np.isfinite(new)
        im = dataclasses.replace(im, data=np.where(valid, new, 0.0), valid=valid)
    h, w = im.shape
    roi = d.get("roi")
    win = np.s_[:, :]
    if roi is not None:
        r0, r1, c0, c1 = (int(v) for v in roi)
        if not (0 <= r0 < r1 <= h and 0 <= c0 < c1 <= w and r1 - r0 >= 4 and c1 - c0 >= 4):
            raise FitInputError(
                f"{source}: field {where}/roi: {list(roi)} is not a window of the image "
                f"({h} × {w} pixels): give [row0, row1, col0, col1] with 0 <= row0 < row1 <= "
                f"{h}, 0 <= col0 < col1 <= {w}, at least 4 × 4 pixels.")
        win = np.s_[r0:r1, c0:c1]
    mask = np.array(im.valid)
    sigma = d.get("sigma")
    if isinstance(sigma, str):  # a σ map: an image of the data's shape
        sfile = resolve_data_path(sigma, manifest_dir, field=f"{where}/sigma", source=source)
        inputs.append(sfile)
        sm = _read_at(sfile, f"{where}/sigma", source)
        if sm.shape != im.shape:
            raise FitInputError(
                f"{source}: field {where}/sigma: the σ map is {sm.shape[0]} × {sm.shape[1]} "
                f"pixels, the image {h} × {w}: give a σ map of the image's shape (before "
                "roi).")
        mask &= sm.valid
        sigma = np.where(sm.valid, sm.data, 1.0)
        bad = int(np.count_nonzero(mask[win] & (sigma[win] <= 0)))
        if bad:
            raise FitInputError(f"{source}: field {where}/sigma: the σ map holds {bad} values "
                                "<= 0 on pixels of the window; σ must be > 0 (NaN where a "
                                "pixel is not to be used).")
    n_bad = int(np.count_nonzero(~mask[win]))
    used = im.data[win][mask[win]]
    if used.size == 0:
        raise FitInputError(f"{source}: field {where}: no pixel of the window holds a finite "
                            "value; check the file and the roi.")
    if not np.ptp(used) > 0:
        raise FitInputError(f"{source}: field {where}: the data has no signal above the "
                            f"background (every used pixel is {used[0]:g}); check the file "
                            "and the roi.")
    noise = d.get("noise") or {}
    try:
        fd = FitData.from_array(
            im.data, sigma=sigma, mask=mask, roi=roi, pixel_scale=im.pixel_scale, path=file,
            noise=Noise(None if noise.get("read") is None else float(noise["read"]),
                        float(noise.get("gain", 1.0)), float(noise.get("floor", 0.0))),
            exposure=float(d.get("exposure", 1.0)), saturation=d.get("saturation"))
    except FitInputError as e:
        raise FitInputError(f"{source}: field {where}: "
                            f"{str(e).removeprefix('FitData: ')}") from None
    bg = _border_background(fd)
    amp = float(np.max(fd.image[fd.mask])) - bg
    spread = _border_spread(fd, bg)
    if not (amp > 5.0 * spread and amp > 1e-6 * abs(bg)):
        raise FitInputError(f"{source}: field {where}: the data has no signal above the "
                            f"background ({bg:g}, the border's median; the brightest pixel "
                            f"is {amp:.3g} above it, the border's scatter {spread:.3g}); check "
                            "the file, its sign, the roi and the saturation level.")
    if n_bad:
        warnings.warn(f"{source}: field {where}/path: {n_bad} of {used.size + n_bad} pixels "
                      "of the window are NaN or infinite (e.g. a border of the image); they "
                      "are left out of the fit.", stacklevel=3)
    return fd

def _load_source(src, manifest_dir, *, source: str = "manifest",
                 inputs: list | None = None):
    """The manifest's ``source``: "point", "disc" or {"image": path} (FITS, TIFF, PNG or
    .npy: the source as the data's pixels see it; finite, non-negative, a positive sum).
    The file read is appended to ``inputs``."""
    if isinstance(src, Mapping):
        if set(src) != {"image"} or not isinstance(src["image"], str):
            raise FitInputError(f"{source}: field source: must be 'point', 'disc' or "
                                f"{{'image': path}}; got {dict(src)}.")
        file = resolve_data_path(src["image"], manifest_dir, field="source/image",
                                 source=source)
        if inputs is not None:
            inputs.append(file)
        im = _read_at(file, "source/image", source)
        a = np.where(im.valid, im.data, 0.0)
        if not (np.all(a >= 0) and a.sum() > 0):
            raise FitInputError(f"{source}: field source/image: a source image must be "
                                "non-negative with a positive sum (the source's light as "
                                "the data's pixels see it).")
        return a
    return src

def _border_background(data: FitData) -> float:
    """The median of the used pixels in the border of the window (a tenth of its size, at
    least 2 pixels): the ``"auto"`` background. Where that border holds no used pixel (a
    border of NaN in the file), the border of the box of the used pixels instead."""
    m = data.mask
    box = np.s_[:, :]
    if not _edge(m.shape)[m].any():
        rows, cols = np.flatnonzero(m.any(axis=1)), np.flatnonzero(m.any(axis=0))
        box = np.s_[rows[0]:rows[-1] + 1, cols[0]:cols[-1] + 1]
    img, m = data.image[box], m[box]
    return float(np.median(img[_edge(m.shape) & m]))

def _border_spread(data: FitData, background: float) -> float:
    """The scatter of the border's used pixels about ``background`` (1.4826 × their
    median absolute deviation: σ for Gaussian noise)."""
    m = data.mask & _edge(data.mask.shape)
    if not m.any():
        return 0.0
    return 1.4826 * float(np.median(np.abs(data.image[m] - background)))

def _edge(shape) -> np.ndarray:
    b = max(2, min(shape) // 10)
    edge = np.ones(shape, bool)
    edge[b:-b, b:-b] = False
    return edge

def _brightest_offset(data: FitData, background: float) -> tuple[float, float]:
    """(x, y) of the star from the window's centre pixel (columns right, rows down): the
    centroid of (data − ``background``) over the 3 × 3 pixels about the brightest used
    pixel. The ``"auto"`` start of ``x0`` and ``y0`` for a star anywhere in its window."""
    img = np.where(data.mask, data.image - background, -np.inf)
    r, c = np.unravel_index(int(np.argmax(img)), img.shape)
    h, w = img.shape
    r0, r1, c0, c1 = max(r - 1, 0), min(r + 2, h), max(c - 1, 0), min(c + 2, w)
    sub = np.maximum(np.where(np.isfinite(img[r0:r1, c0:c1]), img[r0:r1, c0:c1], 0.0), 0.0)
    yy, xx = np.mgrid[r0:r1, c0:c1]
    tot = sub.sum()
    if not tot > 0:
        return float(c - w // 2), float(r - h // 2)
    return (float((sub * xx).sum() / tot - w // 2), float((sub * yy).sum() / tot - h // 2))

def _manifest_shape(man: Any, src: str) -> None:
    """The mistakes the schema would name less plainly, named first: not an object, an
    empty list of captures, a capture without its file, a pupil without its builder,
    light with neither or both of wavelength and band, unknown keys (with the known
    ones)."""
    if not isinstance(man, Mapping):
        raise FitInputError(f"{src}: field (top level): a manifest is a JSON object with "
                            f"data, pupil, light and params; got {type(man).__name__}.")
    data = man.get("data")
    if isinstance(data, list) and not data:
        raise FitInputError(f"{src}: field data: an empty list; give one capture or more "
                            "({'path': 'star.fits'}).")
    for i, d in enumerate(data if isinstance(data, list) else [data]):
        if isinstance(d, Mapping) and "path" not in d:
            where = f"data/{i}: capture data[{i}]" if isinstance(data, list) else "data: it"
            raise FitInputError(f"{src}: field {where} needs a 'path' (the image file).")
    pu = man.get("pupil")
    if isinstance(pu, Mapping) and "builder" not in pu:
        raise FitInputError(f"{src}: field pupil: needs a 'builder', one of "
                            f"{sorted(BUILDERS)}.")
    li = man.get("light")
    if isinstance(li, Mapping) and ("wavelength" in li) == ("band" in li):
        raise FitInputError(f"{src}: field light: give exactly one of wavelength (metres, "
                            "e.g. 9e-07) or band ([lo, hi] in metres); got "
                            f"{'both' if 'band' in li else 'neither'}.")
    if isinstance(li, Mapping) and "wavelength" in li:
        for q in ("n", "source"):
            if q in li:
                raise FitInputError(f"{src}: field light/{q}: goes with band (the "
                                    "wavelengths over it and their spectrum); with one "
                                    "wavelength leave it out.")
    _known_keys(man, src)

def _known_keys(man: Mapping, src: str) -> None:
    """A key the manifest's schema does not know, in an object with a fixed set of keys
    (a typo would otherwise be refused by the schema without the keys it knows, or passed
    over): refused naming its field and the known keys."""
    schema = load_schema("image_fit_manifest")
    props, defs = schema["properties"], schema["$defs"]

    def check(obj, allowed, where, what=""):
        if isinstance(obj, Mapping):
            bad = sorted(str(q) for q in set(obj) - set(allowed))
            if bad:
                raise FitInputError(f"{src}: field {where}: unknown key{'s' * (len(bad) > 1)} "
                                    f"{', '.join(map(repr, bad))}{what}; known: "
                                    f"{', '.join(sorted(allowed))}.")

    check(man, props, "(top level)")
    data = man.get("data")
    for i, d in enumerate(data if isinstance(data, list) else [data]):
        where = f"data/{i}" if isinstance(data, list) else "data"
        check(d, defs["capture"]["properties"], where)
        if isinstance(d, Mapping):
            check(d.get("noise"), defs["capture"]["properties"]["noise"]["properties"],
                  f"{where}/noise")
    for k in ("detector", "light", "spikes"):
        check(man.get(k), props[k]["properties"], k)
    pu = man.get("pupil")
    if isinstance(pu, Mapping):
        for branch in props["pupil"]["oneOf"]:
            if branch["properties"]["builder"]["const"] == pu.get("builder"):
                check(pu, branch["properties"], "pupil", f" for builder {pu['builder']!r}")
    params = man.get("params")
    if isinstance(params, Mapping):
        for k, spec in params.items():
            check(spec, defs["param_spec"]["properties"], f"params/{k}")
    if isinstance(man.get("source"), Mapping):
        check(man["source"], {"image"}, "source")
    stage = props["stages"]["items"]["properties"]
    stages = man.get("stages")
    for si, st in enumerate(stages if isinstance(stages, list) else ()):
        check(st, stage, f"stages/{si}", " (a stage that is only 'hop' or only 'repeat' "
              "takes no other key)")
        if isinstance(st, Mapping):
            for k in ("scan", "hop", "noise_from_residuals", "reject", "spikes", "repeat"):
                check(st.get(k), stage[k]["properties"], f"stages/{si}/{k}")

def _range_of(p: Param) -> tuple[float, float]:
    """The lowest and highest values a parameter takes in a fit: its value, and its
    bounds when free."""
    vals = [p.value, *(p.bounds if p.free and p.bounds else ())]
    return min(vals), max(vals)

def _check_geometry(kind: str, model: ImageModel, src: str) -> None:
    """An obstruction that covers the whole pupil, or struts as wide as its diameter (all
    its light blocked: the model is not finite, or a fit of nothing), are refused, naming
    the field, before any model is computed."""
    p = model.params
    if kind == "circle":
        outer, what = _range_of(p["radius"])[0], "the pupil's radius"
    elif kind == "jwst":
        f2f, gap = _range_of(p["flat_to_flat"])[0], _range_of(p["gap"])[0]
        outer = 2 * (f2f + gap) + f2f / math.sqrt(3)
        what = "the outermost segment's corner"
    else:
        return
    obs = _range_of(p["obstruction"])[1]
    if not obs < outer:
        raise FitInputError(f"{src}: field params/obstruction: an obstruction of radius "
                            f"{obs:g} m (its value or bound) covers the whole pupil ({what} "
                            f"at {outer:g} m): give an obstruction (and bounds) below "
                            f"{outer:g} m.")
    strut = _range_of(p["strut_width"])[1] if "strut_width" in p else 0.0
    if not strut < 2 * outer:  # a strut from the centre that wide covers every point
        raise FitInputError(f"{src}: field params/strut_width: struts {strut:g} m wide (the "
                            f"value or bound) block the whole pupil ({what} at {outer:g} m): "
                            f"give a width (and bounds) below {2 * outer:g} m, in metres.")

def _halos(det: Mapping, src: str):
    """The manifest's ``detector.halos`` as :class:`Halo` layers (default: one, ``halo``)."""
    try:
        return halos_of(det.get("halos"))
    except FitInputError as e:
        raise FitInputError(f"{src}: field detector/{e}") from None


def _params_of(man: Mapping, kind: str, builder: PupilBuilder, auto: Mapping,
               src: str, halos) -> dict:
    """The manifest's ``params``, each checked and turned into a :class:`Param` (the
    ``"auto"`` and ``"header"`` values and their relative bounds filled in), with errors
    naming the parameter's field."""
    det = man.get("detector", {})
    try:
        known = set(parameter_defaults(builder, zernike=man.get("zernike", ()),
                                       # an image source ({"image": file}) adds none
                                       source=("disc" if man.get("source") == "disc"
                                               else None),
                                       response=bool(det.get("response", False)),
                                       halos=halos))
    except FitInputError as e:  # a halo named as another parameter
        raise FitInputError(f"{src}: field detector/{e}") from None
    out = {}
    for k, spec in man["params"].items():
        at = f"{src}: field params/{k}"
        if k not in known:
            halo = k.removesuffix("_width")
            more = (f" (a halo of its own: name it in the field detector/halos, e.g. "
                    f"[\"halo\", \"{halo}\"])" if k.endswith("_width")
                    or k.startswith("halo") or f"{k}_width" in man["params"] else "")
            raise FitInputError(f"{at}: not a parameter of this model (pupil {kind!r}, its "
                                f"zernike terms, source and detector){more}; known: "
                                f"{sorted(known)}.")
        spec = dict(spec) if isinstance(spec, Mapping) else spec
        if isinstance(spec, dict):
            rel = [q for q in ("bounds", "bounds_relative", "bounds_about") if q in spec]
            if len(rel) > 1:
                raise FitInputError(f"{at}: give one of {rel}, not several.")
            if spec["value"] in ("header", "auto"):
                if auto.get(k) is None:
                    raise FitInputError(f"{at}/value: {spec['value']!r} but it cannot be found "
                                        "from the data (give a number).")
                spec["value"] = auto[k]
                if "bounds_relative" in spec:
                    lo, hi = spec.pop("bounds_relative")
                    spec["bounds"] = sorted([auto[k] * lo, auto[k] * hi])
                if "bounds_about" in spec:
                    lo, hi = spec.pop("bounds_about")
                    spec["bounds"] = [auto[k] + lo, auto[k] + hi]
            elif rel and rel[0] != "bounds":
                raise FitInputError(f"{at}/{rel[0]}: applies only with value 'auto' or "
                                    "'header' (bounds about the value found from the data); "
                                    "give bounds [lo, hi] instead.")
        try:
            out[k] = _as_param(spec)
        except FitInputError as e:
            raise FitInputError(f"{at}: {str(e).removeprefix('Param ')}") from None
        vals = [out[k].value, *(out[k].bounds or ())]
        if k == "pixel_scale" and not all(1e-4 < v < 100 for v in vals):
            raise FitInputError(f"{at}: {vals} is not in arcsec per data pixel (expected "
                                "1e-4 … 100).")
        if re.fullmatch(r"z\d+", k) and max(map(abs, vals)) > 1e4:
            raise FitInputError(f"{at}: {vals} is not in nm RMS (over 10 µm).")
    return out

def _stage_field(e: FitInputError, src: str) -> FitInputError:
    """A fit's refusal as the manifest's field (``stages/1/half``, ``starts/x0``)."""
    if isinstance(e, _InputAt):
        return FitInputError(f"{src}: field {e.field}: {e.detail}")
    return FitInputError(f"{src}: field stages: {e}")

#: the manifest's fields that name files (a base's, under ``extends``, are read from the
#: base's folder)
PATH_KEYS = frozenset({"path", "sigma", "image"})


def manifest_document(path):
    """(the image-fit manifest's JSON as :func:`load_manifest` reads it: strict, its
    ``extends`` merged; the files read, this one first), before any check."""
    return read_json_extends(path, what="manifest", path_keys=PATH_KEYS)


def load_manifest(path, *, transform=None):
    """(model, data, options) from an image-fit manifest (JSON; see
    data_schemas/image_fit_manifest.schema.json). ``data`` is a FitData, or a list of
    them when the manifest's ``data`` is a list of captures (exposures, dithers, an
    exposure bracket); then ``options["per_capture"]`` names the parameters each capture
    has its own of. ``options``: stages, starts, max_steps, per_capture, builder, the raw
    manifest, and ``inputs``: every file the manifest made difstar read (each capture's
    image and σ map, the source image).

    ``"extends": "BASE.json"`` makes the manifest a variant: its keys are laid over the
    base's (objects merged key by key, anything else replaced; the base's files named
    from its own folder; chains of up to 8). The manifest is read strictly (no NaN or
    Infinity, no key given twice), checked
    against its schema, then against its data and model (an ROI inside the image, some
    signal, the obstruction inside the pupil, the parameters the model has, every stage
    with a window that holds pixels and something free): every mistake raises
    :class:`FitInputError` or :class:`difstar.io._scene.SceneError` (both ValueError)
    naming the manifest and the field, before anything is computed.

    ``transform``: a function applied to each capture's image as read (the file's whole
    frame, rows down as the fit sees them, NaN where the file holds no valid value)
    before anything else, returning an image of the same shape: the manifest then fits
    that changed copy as if the file held it (its window, σ from the noise model,
    ``"auto"`` starts, checks; a σ map is not changed). Pixels it makes NaN are left out.
    :func:`difstar.fitting.fit_changed_copy` fits such a copy."""
    from pathlib import Path

    path = Path(path)
    src = str(path)
    try:  # one kind of error for a manifest's every mistake (the command line's prefix)
        man, chain = manifest_document(path)
        _manifest_shape(man, src)
        validate(man, "image_fit_manifest", source=src)
        check_float32_doc(man, source=src)
    except SceneError as e:
        raise FitInputError(str(e)) from None
    several = isinstance(man["data"], list)
    caps = man["data"] if several else [man["data"]]
    inputs: list[str] = [str(c) for c in chain[1:]]  # the manifests it extends
    fds = [_load_capture(d, f"data/{i}" if several else "data", path.parent, source=src,
                         inputs=inputs, transform=transform)
           for i, d in enumerate(caps)]
    fd = fds[0]
    pu = dict(man["pupil"])
    kind = pu.pop("builder")
    pu = {k: int(v) if k == "blades" else float(v) for k, v in pu.items()}
    try:
        builder = BUILDERS[kind](**pu)
    except FitInputError as e:
        raise FitInputError(f"{src}: field pupil: {e}") from None
    li = man["light"]
    at = "light/band" if "band" in li else "light/wavelength"
    try:
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
            if "band" in li:
                light = Light.band(*li["band"], n=int(li.get("n", 4)),
                                   source=li.get("source", "flat"))
            else:
                light = Light.monochromatic(li["wavelength"])
    except FitInputError as e:
        if str(e).startswith("Light.band: source"):
            at = "light/source"
        raise FitInputError(f"{src}: field {at}: {e}") from None
    det = man.get("detector", {})
    bg = _border_background(fd)
    x0, y0 = _brightest_offset(fd, bg)
    auto = {"pixel_scale": fd.pixel_scale, "background": bg,
            "flux": float(np.sum(fd.image[fd.mask] - bg)) / fd.exposure, "x0": x0, "y0": y0}
    halos = _halos(det, src)
    params = _params_of(man, kind, builder, auto, src, halos)
    try:
        model = ImageModel(builder, params, light=light, zernike=man.get("zernike", ()),
                           oversample=float(det.get("oversample", 1.0)),
                           pad=int(det.get("pad", 8)),
                           accuracy=float(man.get("accuracy", 1e-2)),
                           source=_load_source(man.get("source", "point"), path.parent,
                                               source=src, inputs=inputs),
                           response=bool(det.get("response", False)),
                           resampling=det.get("resampling"), halos=halos)
    except FitInputError as e:  # the parameter it names, where it names one
        msg = str(e).removeprefix("ImageModel: ")
        m = re.match(r"(\w+) = ", msg)
        field = f"params/{m.group(1)}" if m and m.group(1) in params else "(top level)"
        raise FitInputError(f"{src}: field {field}: {msg}") from None
    _check_geometry(kind, model, src)
    stages = man.get("stages", "auto")
    if stages == "auto":  # chosen here, so that they are checked like written ones
        stages = auto_stages(model, fds)
    opts = {"stages": stages, "starts": man.get("starts"),
            "max_steps": int(man.get("max_steps", 100)), "manifest": man,
            "builder": kind, "per_capture": man.get("per_capture"), "inputs": inputs}
    # the stages, starts and per-capture names, as fit() will check them: refused here,
    # naming the manifest's field, before anything is computed
    checked = model
    if several or opts["per_capture"]:
        per = (("x0", "y0", "flux", "background") if opts["per_capture"] is None
               else tuple(opts["per_capture"]))
        try:
            checked = model.for_captures(per, len(fds))
        except FitInputError as e:
            raise FitInputError(f"{src}: field per_capture: "
                                f"{str(e).removeprefix('per_capture: ')}") from None
    try:
        _check_fit_inputs(checked, fds, list(opts["stages"] or [{"free": "all"}]),
                          starts=opts["starts"], max_steps=opts["max_steps"])
    except FitInputError as e:
        raise _stage_field(e, src) from None
    return model, (fds if several else fd), opts
