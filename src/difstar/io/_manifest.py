"""Fit manifests: JSON checked against ``data_schemas/fit_manifest.schema.json``.

Outer layer of ``difstar fit`` / ``difstar synth``: validates the document, checks what
the schema cannot (names that refer to each other, array lengths, starts inside bounds),
and builds the pieces :mod:`difstar._fit` takes. Errors are :class:`SceneError` naming
the manifest file and the field.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from .._detector import halos_of
from .._fit import param_shape, zernike_index
from .._geometry import check_geometry, exit_pupil_distance
from .._param import FitInputError
from .._validate import defocus_past_exit_pupil
from ._json import check_float32_doc, read_json_extends
from ._scene import SceneError, check_sensor_spectrum, validate

DEFAULT_WAVELENGTHS = (600e-9, 530e-9, 450e-9)


@dataclasses.dataclass(frozen=True)
class CaptureEntry:
    name: str
    path: Path
    configuration: str
    exposure_time: float | None
    source_position: tuple[float, float]
    roi_size: tuple[int, int]


@dataclasses.dataclass(frozen=True)
class Manifest:
    path: Path
    doc: dict
    camera: dict
    noise: dict
    configurations: dict[str, dict]
    captures: tuple[CaptureEntry, ...]
    parameters: dict[str, dict]
    grid: dict
    solver: dict
    synthetic: dict | None
    #: the true values known for some parameters (all of them for ``synthetic``
    #: manifests; some, from the ``truth`` block, for captures made outside difstar)
    truth: dict | None = None
    #: the manifests this one extends (``"extends"``), nearest first: inputs too
    bases: tuple[Path, ...] = ()

    @property
    def folder(self) -> Path:
        return self.path.parent

    @property
    def name(self) -> str:
        return self.doc.get("name", self.path.parent.name)


def manifest_document(path: str | Path) -> tuple[dict, list[Path]]:
    """(the RAW-fit manifest's JSON as :func:`load_manifest` reads it: strict, its
    ``"extends"`` merged, the base's capture files named from the base's folder; the
    files read, this one first), before any check."""
    return read_json_extends(path, what="fit manifest", path_keys=frozenset({"file"}),
                             anchored=True)


#: the top-level fields that say which fitter a manifest is for (both schemas require them)
KIND_FIELDS = {"raw": ("camera", "configurations", "captures"), "image": ("data", "pupil")}


def manifest_kind(path: str | Path) -> str:
    """Which fitter the manifest at ``path`` is for: ``"raw"`` (RAW captures of a camera,
    data_schemas/fit_manifest.schema.json) or ``"image"`` (intensity images of a star,
    image_fit_manifest.schema.json), from its fields once ``extends`` is merged; a
    manifest with both sets, or neither, is refused naming the fields."""
    doc, _ = read_json_extends(path, what="fit manifest")
    if not isinstance(doc, dict):
        raise SceneError(f"{path}: a fit manifest is a JSON object; got "
                         f"{type(doc).__name__}.")
    kinds = [k for k, fields in KIND_FIELDS.items() if any(f in doc for f in fields)]
    if len(kinds) == 1:
        return kinds[0]
    names = "; ".join(f"{k}: {', '.join(f)}" for k, f in KIND_FIELDS.items())
    which = "both" if kinds else "neither"
    raise SceneError(f"{path}: fields {sorted(doc)}: the manifest has {which} of the field "
                     f"sets that say what it fits ({names}); give one set "
                     "(data_schemas/fit_manifest.schema.json or "
                     "image_fit_manifest.schema.json).")


def load_manifest(path: str | Path) -> Manifest:
    """The RAW-fit manifest at ``path`` (:func:`manifest_document`), checked against its
    schema and resolved."""
    path = Path(path)
    doc, chain = manifest_document(path)
    return dataclasses.replace(manifest_from_dict(doc, path=path), bases=tuple(chain[1:]))


def manifest_from_dict(doc: dict, *, path: str | Path = "<manifest>") -> Manifest:
    """Validate ``doc`` and resolve it (``path`` names it in errors and anchors the
    capture files)."""
    path = Path(path)
    src = str(path)
    check_sensor_spectrum(doc, doc.get("camera") if isinstance(doc, dict) else None,
                          at="camera", source=src)
    validate(doc, "fit_manifest", source=src)
    check_float32_doc(doc, source=src)
    cam = dict(doc["camera"])
    cam.setdefault("principal_separation", 0.0)
    cam.setdefault("pupil_magnification", 1.0)
    cam.setdefault("wavelengths", list(DEFAULT_WAVELENGTHS))
    cam.setdefault("white_balance", [2.0, 1.0, 2.0])
    noise = {"gain_e_per_dn": 1.0, "read_noise_dn": 2.0, **doc.get("noise", {})}

    configs: dict[str, dict] = {}
    for i, c in enumerate(doc["configurations"]):
        if c["name"] in configs:
            raise SceneError(f"{src}: field configurations/{i}/name: duplicate name {c['name']!r}")
        _check_geometry(cam, c, f"{src}: field configurations/{i}")
        configs[c["name"]] = dict(c)

    default_roi = tuple(doc.get("roi_size", (128, 128)))
    caps = []
    names = set()
    for i, c in enumerate(doc["captures"]):
        where = f"{src}: field captures/{i}"
        name = c.get("name", Path(c["file"]).stem)
        if not all(ch.isalnum() or ch in "_.-" for ch in name):
            raise SceneError(f"{where}/name: {name!r} may hold only letters, digits, _ . -")
        if name in names:
            raise SceneError(f"{where}/name: duplicate capture name {name!r}")
        names.add(name)
        if c["configuration"] not in configs:
            raise SceneError(
                f"{where}/configuration: {c['configuration']!r} is not one of the "
                f"configurations {sorted(configs)}"
            )
        roi = tuple(c.get("roi_size", default_roi))
        caps.append(CaptureEntry(
            name=name, path=(path.parent / c["file"]), configuration=c["configuration"],
            exposure_time=(None if c.get("exposure_time") is None
                           else float(c["exposure_time"])),
            source_position=(float(c["source_position"][0]), float(c["source_position"][1])),
            roi_size=(int(roi[0]), int(roi[1])),
        ))
    for cfg in configs:
        sizes = {cp.roi_size for cp in caps if cp.configuration == cfg}
        if len(sizes) > 1:
            raise SceneError(
                f"{src}: field captures: the captures of configuration {cfg!r} have different "
                f"roi_size {sorted(sizes)}; one configuration needs one region size"
            )
        if not sizes:
            raise SceneError(f"{src}: field configurations: {cfg!r} has no captures")

    params: dict[str, dict] = {}
    n = int(cam["blades"])
    pupil = camera_pupil(cam, src)
    try:
        halos = halos_of(doc.get("detector", {}).get("halos"))
    except FitInputError as e:
        raise SceneError(f"{src}: field detector/{e}") from None
    cam["halos"] = halos
    for name, p in doc["parameters"].items():
        where = f"{src}: field parameters/{name}"
        kind, _, ref = name.partition("/")
        if kind in ("defocus", "source_offset") and ref not in configs:
            raise SceneError(f"{where}: {ref!r} is not one of the configurations {sorted(configs)}")
        if kind == "exposure_scale" and ref not in names:
            raise SceneError(f"{where}: {ref!r} is not one of the capture names {sorted(names)}")
        try:
            shape = param_shape(name, n, pupil, halos)
        except ValueError as e:
            raise SceneError(f"{where}: {e}") from None
        start = _shaped(p["start"], shape, where + "/start")
        _check_sign(_blur_kind(name, halos) or kind, start, where + "/start")
        free = bool(p.get("free", False))
        lo = hi = None
        if "bounds" in p:
            lo = _shaped(p["bounds"][0], shape, where + "/bounds/0")
            hi = _shaped(p["bounds"][1], shape, where + "/bounds/1")
            if not np.all(lo < hi):
                raise SceneError(f"{where}/bounds: need lo < hi element-wise; got {p['bounds']}")
            if free and not np.all((start > lo) & (start < hi)):
                raise SceneError(
                    f"{where}/start: {p['start']} must lie strictly inside bounds {p['bounds']}"
                )
        scale = _shaped(p.get("perturb_scale", 0.0), shape, where + "/perturb_scale")
        params[name] = {"shape": shape, "free": free, "start": start, "lo": lo, "hi": hi,
                        "perturb_scale": scale}

    _check_defocus_bounds(cam, configs, params, src)
    if pupil is None and "circumradius" not in params:
        raise SceneError(f"{src}: field parameters: the blades iris needs circumradius (its "
                         "exit-pupil circumradius, m); give it, or a camera.pupil builder.")
    zern = sorted(k for k in params if zernike_index(k) is not None)
    if zern and "zernike_radius" not in cam:
        raise SceneError(
            f"{src}: field camera/zernike_radius: the Zernike parameters {zern} need the "
            "radius (metres, in the exit pupil) of the circle they are normalised over; "
            "give camera.zernike_radius, e.g. the iris's circumradius.")
    if not any(p["free"] for p in params.values()):
        raise SceneError(
            f"{src}: field parameters: no parameter is free, so there is nothing to fit; "
            'set "free": true (with "bounds": [lo, hi]) on at least one parameter.'
        )
    syn = doc.get("synthetic")
    if syn is not None:
        truth = _truth_values(syn["truth"], params, f"{src}: field synthetic/truth")
        for name, v in truth.items():
            _check_sign(_blur_kind(name, halos) or name.partition("/")[0], v,
                        f"{src}: field synthetic/truth/{name}")
        missing = [k for k in params if k not in truth]
        if missing:
            raise SceneError(f"{src}: field synthetic/truth: missing values for {missing}")
        syn = {"black_level": 600.0, "white_level": 16383, "seed": 0, "padding": 2.0,
               **syn, "truth": truth}
        fh, fw = syn["frame_size"]
        for cp in caps:
            if cp.roi_size[0] > fh or cp.roi_size[1] > fw:
                raise SceneError(
                    f"{src}: field captures/{cp.name}/roi_size: {list(cp.roi_size)} does not "
                    f"fit the synthetic frame {fh} × {fw}; give a roi_size <= frame_size."
                )
        for cp, c in zip(caps, doc["captures"]):
            r, col = cp.source_position
            if not (0 <= r < fh and 0 <= col < fw):
                raise SceneError(
                    f"{src}: field captures/{cp.name}/source_position: {[r, col]} is outside "
                    f"the synthetic frame {fh} × {fw}"
                )
    truth = None if syn is None else syn["truth"]
    if doc.get("truth") is not None:
        if syn is not None:
            raise SceneError(f"{src}: field truth: a synthetic manifest's truth is "
                             "synthetic/truth; give one of the two")
        truth = _truth_values(doc["truth"]["values"], params, f"{src}: field truth/values")
    return Manifest(
        path=path, doc=doc, camera=cam, noise=noise, configurations=configs,
        captures=tuple(caps), parameters=params, grid=dict(doc.get("grid", {})),
        solver={"method": "lm", "max_steps": 100, "rtol": 1e-6, "atol": 1e-6,
                "reweight": 1, **doc.get("solver", {})},
        synthetic=syn, truth=truth,
    )


def camera_pupil(cam: dict, src="<manifest>"):
    """The camera's pupil builder from ``camera.pupil`` (``{"builder": "circle",
    "radius": …}``, the image fit's builders and their keyword arguments, exit-pupil
    metres), or None (the ``blades`` iris)."""
    spec = cam.get("pupil")
    if spec is None:
        return None
    from ..fitting._params import FitInputError
    from ..fitting._parts import BUILDERS

    kw = {k: v for k, v in spec.items() if k != "builder"}
    try:
        return BUILDERS[spec["builder"]](**kw)
    except (FitInputError, TypeError, ValueError) as e:
        raise SceneError(f"{src}: field camera/pupil: {e}") from None


def _truth_values(values: dict, params: dict, where: str) -> dict:
    """True values by parameter name, each shaped like its parameter (``where`` names
    the block in errors)."""
    out = {}
    for name, v in values.items():
        if name not in params:
            raise SceneError(f"{where}/{name}: not a parameter of this manifest")
        out[name] = _shaped(v, params[name]["shape"], f"{where}/{name}")
    return out


#: parameters that must be > 0 (or >= 0) to mean anything
_POSITIVE = ("circumradius", "source_radius", "phi0", "knee", "exposure_scale",
             "halo width")
_NONNEGATIVE = ("toe", "background", "jitter")


def _blur_kind(name: str, halos) -> str | None:
    """What a detector-blur parameter is (for its sign checks), or None."""
    for h in halos:
        if name == h.name:
            return "halo fraction"
        if name == f"{h.name}_width":
            return "halo width"
    return "jitter" if name == "jitter" else None


def _check_sign(kind: str, a: np.ndarray, where: str) -> None:
    if kind in _POSITIVE and not np.all(a > 0):
        raise SceneError(f"{where}: {a.tolist()} must be > 0 ({kind} is positive).")
    if kind in _NONNEGATIVE and not np.all(a >= 0):
        raise SceneError(f"{where}: {a.tolist()} must be >= 0.")
    if kind == "halo fraction" and not np.all((a >= 0) & (a <= 1)):
        raise SceneError(f"{where}: {a.tolist()} must lie in [0, 1] (a halo's fraction of "
                         "the light).")


def _check_geometry(cam: dict, c: dict, where: str) -> None:
    """The same geometry ``difstar predict`` accepts: object and focus beyond what the
    lens can focus."""
    for key in ("object_distance", "focus_distance"):
        try:
            check_geometry(focal_length=float(cam["focal_length"]),
                           object_distance=float(c[key]) if key == "object_distance" else None,
                           focus_distance=float(c[key]) if key == "focus_distance" else None,
                           principal_separation=float(cam["principal_separation"]))
        except ValueError:
            f = float(cam["focal_length"])
            near = 4 * f + float(cam["principal_separation"])
            raise SceneError(
                f"{where}/{key}: {c[key]} m is too close: a lens of focal length {f} m "
                f"can only focus beyond {near:.4g} m from the sensor; give {key} > "
                f"{near:.4g}."
            ) from None


def _check_defocus_bounds(cam: dict, configs: dict, params: dict, src: str) -> None:
    """Each configuration's Δz (its start, and its upper bound where it is free) below
    the exit pupil's distance from the sensor, as ``difstar predict`` asks of a lens's
    Δz (:func:`difstar._validate.defocus_past_exit_pupil`): past it the fit would search
    cameras that cannot be."""
    for name, cfg in configs.items():
        p = params.get(f"defocus/{name}")
        if p is None:
            continue
        z_r = exit_pupil_distance(float(cam["focal_length"]), float(cfg["focus_distance"]),
                                  float(cam["principal_separation"]),
                                  float(cam["pupil_magnification"]))
        where = f"{src}: field parameters/defocus/{name}"
        for what, v in (("start", p["start"]), ("bounds/1", p["hi"] if p["free"] else None)):
            why = None if v is None else defocus_past_exit_pupil(float(np.max(v)), z_r)
            if why:
                raise SceneError(f"{where}/{what}: {why}.")


def _shaped(v, shape: tuple[int, ...], where: str) -> np.ndarray:
    a = np.asarray(v, float)
    if a.ndim == 0:
        return np.broadcast_to(a, shape).copy()
    if a.shape != shape:
        raise SceneError(f"{where}: expected a number or an array of shape {list(shape)}; "
                         f"got shape {list(a.shape)}")
    return a.copy()


def roi_origin(position, size, frame) -> tuple[int, int]:
    """Top-left (row, col) of a ``size`` region centred on ``position``, both even (so
    the region keeps the frame's Bayer layout) and inside the frame."""
    out = []
    for p, s, f in zip(position, size, frame):
        if s > f:
            raise ValueError(f"region of {size} px does not fit the {frame} px frame")
        o = int(np.floor(p)) - s // 2
        o -= o % 2
        out.append(int(min(max(o, 0), (f - s) - (f - s) % 2)))
    return out[0], out[1]


__all__ = ["CaptureEntry", "Manifest", "load_manifest", "manifest_from_dict", "roi_origin"]
