"""One validation layer for user input: files, the command line and the Python API.

Every check here raises :class:`InputError` (a ``ValueError``) whose message names the
field and says what would work, e.g. ``camera/sensor/phi0/1: NaN is not a finite
number; give a finite number > 0``. The command line turns these into exit code 2 with
that one line and no traceback.

- JSON documents are checked in :mod:`difstar.io._json` (``loads_strict``,
  ``check_finite_doc``).
- numbers: :func:`check_number` (finite, in range, the field and the fix).
- physics: :func:`check_camera_scene` (finite, positive where it must be, the object
  beyond what the lens can focus, an obstruction inside the pupil);
  :func:`check_polygon_vertices` (simple, counter-clockwise, a figure-8 is called
  "self-intersecting").
- the PSF's scalars: :func:`check_psf_inputs` for concrete values (tracers pass through
  untouched) and :func:`refuse_nonfinite_traced` (``eqx.error_if``) inside jit.
- sizes: :func:`check_crop` and :func:`memory_budget` (a grid that cannot fit in memory
  is refused before anything is allocated); :func:`check_shape` (a window's (H, W)),
  :func:`check_memory` (bytes estimated from the shapes against the budget),
  :func:`check_wavelength_count` and :func:`check_pupil_cost` (wavelengths, polygon
  vertices, blades and vanes counted from static shapes, so also inside jit).
- the memory limit: :func:`parse_memory_limit` reads ``DIFSTAR_MEMORY_LIMIT`` strictly
  (the one parser; ``difstar._batch`` uses it too).
"""

from __future__ import annotations

import math
import os
import re

import numpy as np

from ._geometry import check_geometry, exit_pupil_distance

# the sizes accepted and the error type live below the pupils (which count their edges
# when built); they are re-exported here (__all__)
from ._limits import (
    ENV_MEMORY_LIMIT,
    MAX_BLADES,
    MAX_BUILD_EDGES,
    MAX_EDGES,
    MAX_EXACT_EDGES,
    MAX_JSON_DEPTH,
    MAX_SOURCES,
    MAX_SPECTRUM_SAMPLES,
    MAX_SPIDERS,
    MAX_VERTICES,
    MAX_WAVELENGTHS,
    MIN_CROP,
    InputError,
    check_edge_count,
)
from ._pupil import Circle, Obstructed, Polygon, RegularPolygon, Spiders, Struts, Transformed, Union
from ._pupil_curved import CurvedIris

# -------------------------------------------------------------------------- numbers


def _fmt(x) -> str:
    try:
        return f"{float(x):.6g}"
    except (TypeError, ValueError, OverflowError):
        return repr(x)


def check_number(value, field: str, *, gt=None, ge=None, lt=None, le=None,
                 integer: bool = False, unit: str = "", fix: str | None = None):
    """A finite number within the given limits, or :class:`InputError` naming ``field``
    and what would work. Returns it as a float (an int when ``integer``)."""
    limits = []
    if gt is not None:
        limits.append(f"> {_fmt(gt)}")
    if ge is not None:
        limits.append(f">= {_fmt(ge)}")
    if lt is not None:
        limits.append(f"< {_fmt(lt)}")
    if le is not None:
        limits.append(f"<= {_fmt(le)}")
    want = ("an integer" if integer else "a finite number") + (
        " " + " and ".join(limits) if limits else "") + (f" {unit}" if unit else "")
    tail = f"; give {want}" + (f" ({fix})" if fix else "") + "."
    if isinstance(value, bool) or value is None:
        raise InputError(f"{field}: {value!r} is not a number" + tail)
    try:
        x = float(value)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"{field}: {value!r} is not a number" + tail) from None
    if not math.isfinite(x):
        raise InputError(f"{field}: {_fmt(value)} is not a finite number" + tail)
    if integer and x != int(x):
        raise InputError(f"{field}: {_fmt(value)} is not an integer" + tail)
    ok = ((gt is None or x > gt) and (ge is None or x >= ge)
          and (lt is None or x < lt) and (le is None or x <= le))
    if not ok:
        raise InputError(f"{field}: {_fmt(value)} is out of range" + tail)
    return int(x) if integer else x


def _concrete_array(x):
    """``x`` as a NumPy float array, or None when it is a JAX tracer."""
    try:
        return np.asarray(x, dtype=float)
    except Exception:  # tracers (inside jit / grad / vmap) have no concrete value
        return None


def check_array(value, field: str, *, gt=None, ge=None, fix: str | None = None) -> None:
    """Every element finite (and > gt / >= ge); tracers pass through."""
    a = _concrete_array(value)
    if a is None:
        return
    flat = a.ravel()
    for i, x in enumerate(flat):
        name = field if a.ndim == 0 else f"{field}[{i}]" if a.ndim == 1 else (
            f"{field}[{', '.join(map(str, np.unravel_index(i, a.shape)))}]")
        check_number(x, name, gt=gt, ge=ge, fix=fix)


# -------------------------------------------------------------------------- the PSF


def check_psf_inputs(*, wavelength=None, z_image=None, pixel_pitch=None, defocus=None,
                     rotation=None, where: str = "difstar.psf") -> None:
    """Refuse non-finite, zero or negative PSF scalars with the field and the fix.

    Concrete values only: a JAX tracer (inside jit/grad) passes through untouched (use
    :func:`refuse_nonfinite_traced` there). ``None`` skips a field.
    """
    spec = (
        ("wavelength", wavelength, dict(gt=0.0, le=1e-3), "metres, e.g. 530e-9 for 530 nm"),
        ("z_image", z_image, dict(gt=0.0), "exit pupil to sensor in metres, e.g. 51.5e-3"),
        ("pixel_pitch", pixel_pitch, dict(gt=0.0, le=1e-2), "metres, e.g. 3.9e-6"),
        ("defocus", defocus, {}, "metres; 0 for in focus"),
        ("rotation", rotation, {}, "radians"),
    )
    for name, v, lim, fix in spec:
        if v is None:
            continue
        a = _concrete_array(v)
        if a is None:
            continue
        if a.size == 0:
            raise InputError(f"{where}: {name} is empty; give a number ({fix}).")
        for x in a.ravel():
            check_number(x, f"{where}: {name}", fix=fix, **lim)
    z, dz = _concrete_array(z_image), _concrete_array(defocus)
    if z is not None and dz is not None and z_image is not None and defocus is not None:
        why = defocus_past_exit_pupil(float(np.max(dz)), float(np.min(z)))
        if why:
            raise InputError(f"{where}: defocus = {why}.")


def refuse_nonfinite_traced(x, name: str):
    """``x``, with a runtime error (``eqx.error_if``) if any element is NaN or infinite.

    For values traced inside jit; concrete values are checked at once."""
    import equinox as eqx
    import jax.numpy as jnp

    return eqx.error_if(
        x, ~jnp.all(jnp.isfinite(x)),
        f"{name} is NaN or infinite; give a finite value (check the inputs upstream).",
    )


def check_pupil(pupil, field: str = "pupil") -> None:
    """Every concrete array inside a pupil finite (e.g. a RegularPolygon's rotation)."""
    import equinox as eqx
    import jax

    leaves = jax.tree_util.tree_leaves_with_path(eqx.filter(pupil, eqx.is_array))
    for path, leaf in leaves:
        a = _concrete_array(leaf)
        if a is not None and not np.all(np.isfinite(a)):
            name = field + "".join(str(k) for k in path)
            raise InputError(f"{name} contains NaN or infinity; give finite values.")


# ------------------------------------------------------------------------- polygons


def _segments_cross_matrix(v: np.ndarray) -> tuple[int, int] | None:
    """First pair (i, j) of non-adjacent edges that cross or touch, or None."""
    w = np.roll(v, -1, axis=0)
    n = len(v)

    def orient(a, b, c):  # broadcast: a, b (n,1,2)-like; c (1,n,2)
        return np.sign((b[..., 0] - a[..., 0]) * (c[..., 1] - a[..., 1])
                       - (b[..., 1] - a[..., 1]) * (c[..., 0] - a[..., 0]))

    p1, p2 = v[:, None, :], w[:, None, :]
    p3, p4 = v[None, :, :], w[None, :, :]
    cross = ((orient(p1, p2, p3) * orient(p1, p2, p4) < 0)
             & (orient(p3, p4, p1) * orient(p3, p4, p2) < 0))
    i, j = np.indices((n, n))
    adjacent = (np.abs(i - j) <= 1) | (np.abs(i - j) == n - 1)
    hits = np.argwhere(cross & ~adjacent & (j > i))
    if len(hits):
        return int(hits[0][0]), int(hits[0][1])
    return None


def check_polygon_vertices(vertices, field: str = "vertices") -> np.ndarray:
    """An (n, 2) array of a simple, counter-clockwise polygon, or :class:`InputError`
    naming the field: a figure-8 is reported as self-intersecting (before its
    orientation, which is meaningless for it)."""
    try:
        v = np.asarray(vertices, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{field}: must be a list of [x, y] pairs in metres.") from None
    if v.ndim != 2 or v.shape[1] != 2 or not 3 <= v.shape[0] <= MAX_VERTICES:
        raise InputError(
            f"{field}: must be 3 to {MAX_VERTICES} [x, y] pairs in metres; got shape "
            f"{list(v.shape)}."
        )
    if not np.all(np.isfinite(v)):
        i = int(np.argwhere(~np.isfinite(v))[0][0])
        raise InputError(f"{field}/{i}: NaN or infinity; give finite coordinates in metres.")
    hit = _segments_cross_matrix(v)
    if hit is not None:
        raise InputError(
            f"{field}: the polygon is self-intersecting (edges {hit[0]} and {hit[1]} "
            "cross, e.g. a figure-8); give the vertices of a simple polygon in order "
            "around its outline."
        )
    w = np.roll(v, -1, axis=0)
    area = 0.5 * float(np.sum(v[:, 0] * w[:, 1] - w[:, 0] * v[:, 1]))
    if area == 0 or not math.isfinite(area):
        raise InputError(f"{field}: the polygon has zero area; give distinct vertices.")
    if area < 0:
        raise InputError(
            f"{field}: the vertices go clockwise; give them counter-clockwise (reverse "
            "the list)."
        )
    return v


# --------------------------------------------------------------- camera and scene


def _inner_radius(pupil) -> float | None:
    """Largest r with the disc of radius r about the axis inside the pupil (concrete
    values; None when unknown)."""
    try:
        if isinstance(pupil, RegularPolygon):
            return float(pupil.circumradius) * math.cos(math.pi / pupil.n)
        if isinstance(pupil, Circle):
            c = np.asarray(pupil.centre, float)
            return float(pupil.radius) - float(np.hypot(*c))
        if isinstance(pupil, Polygon):
            v = np.asarray(pupil.vertices, float)
            w = np.roll(v, -1, axis=0)
            d = w - v
            t = np.clip(-np.sum(v * d, axis=1) / np.maximum(np.sum(d * d, axis=1), 1e-300),
                        0.0, 1.0)
            return float(np.min(np.hypot(*(v + t[:, None] * d).T)))
        return float(pupil.max_radius())
    except Exception:  # traced
        return None


def check_obstruction(pupil, field: str = "camera.lens.pupil") -> None:
    """An Obstructed pupil's central obstruction must leave light through the pupil."""
    if not isinstance(pupil, Obstructed) or pupil.obstruction is None:
        return
    r_in = _inner_radius(pupil.outer)
    ob = _concrete_array(pupil.obstruction.radius)
    if r_in is None or ob is None:
        return
    if not float(ob) < r_in:
        raise InputError(
            f"{field}.obstruction radius {_fmt(ob)} m covers the whole pupil (its inner "
            f"radius is {_fmt(r_in)} m); give an obstruction radius < {_fmt(r_in)} m."
        )


#: the largest condition number of a colour matrix (camera RGB → linear sRGB): the DNG
#: writer stores its inverse (XYZ → camera RGB), which a reader then inverts again
MAX_COLOUR_MATRIX_CONDITION = 1e8


def check_colour_matrix(matrix, field: str) -> None:
    """A concrete colour matrix that can be inverted: its rows independent (condition
    number at most :data:`MAX_COLOUR_MATRIX_CONDITION`). Traced values pass through."""
    m = _concrete_array(matrix)
    if m is None or m.shape != (3, 3):
        return
    cond = float(np.linalg.cond(np.asarray(m, float)))
    if not cond <= MAX_COLOUR_MATRIX_CONDITION:
        raise InputError(
            f"{field}: the matrix is singular or nearly so (condition number "
            f"{_fmt(cond)}): a RAW file (DNG) stores its inverse, and its rows must be "
            "independent; give an invertible 3 x 3 matrix (camera RGB to linear sRGB), "
            "e.g. the identity [[1, 0, 0], [0, 1, 0], [0, 0, 1]].")


def check_camera_scene(camera, scene, *, where: str = "") -> None:
    """Physical consistency of concrete camera and scene values, naming the field:
    finite values, positive where they must be, the object beyond what the lens can
    focus, an obstruction inside the pupil. Traced values pass through."""
    p = f"{where}: " if where else ""
    lens, sen = camera.lens, camera.sensor
    # counts first (static shapes: cheap, and before any per-element work)
    check_pupil_cost(lens.pupil, f"{p}camera.lens.pupil")
    check_wavelength_count(int(np.shape(sen.wavelengths)[-1]) if np.ndim(sen.wavelengths) == 2
                           else 1, f"{p}camera.sensor.wavelengths (per channel)")
    check_pupil(lens.pupil, f"{p}camera.lens.pupil")
    check_obstruction(lens.pupil, f"{p}camera.lens.pupil")
    check_array(lens.focal_length, f"{p}camera.lens.focal_length", gt=0, fix="metres")
    fd = _concrete_array(lens.focus_distance)
    if fd is not None and not (fd.ndim == 0 and float(fd) == math.inf):
        check_array(fd, f"{p}camera.lens.focus_distance", gt=0, fix="metres, or inf")
    check_array(lens.principal_separation, f"{p}camera.lens.principal_separation",
                fix="metres")
    check_array(lens.pupil_magnification, f"{p}camera.lens.pupil_magnification", gt=0)
    if lens.defocus is not None:
        check_array(lens.defocus, f"{p}camera.lens.defocus", fix="metres, or None")
    check_number(sen.pixel_pitch, f"{p}camera.sensor.pixel_pitch", gt=0, le=1e-2,
                 fix="metres, e.g. 3.9e-6")
    check_array(sen.wavelengths, f"{p}camera.sensor.wavelengths", gt=0,
                fix="metres, e.g. 530e-9")
    check_array(sen.phi0, f"{p}camera.sensor.phi0", gt=0)
    check_array(sen.response.toe, f"{p}camera.sensor.response.toe", ge=0)
    check_array(sen.response.knee, f"{p}camera.sensor.response.knee", gt=0)
    check_array(sen.white_balance, f"{p}camera.sensor.white_balance", gt=0)
    check_array(sen.colour_matrix, f"{p}camera.sensor.colour_matrix")
    check_colour_matrix(sen.colour_matrix, f"{p}camera.sensor.colour_matrix")
    check_array(scene.object_distance, f"{p}scene.object_distance", gt=0, fix="metres")
    check_array(scene.exposure_time, f"{p}scene.exposure_time", gt=0, fix="seconds")
    check_array(scene.background, f"{p}scene.background", ge=0)
    if len(scene.sources) > MAX_SOURCES:
        raise InputError(f"{p}scene.sources: {len(scene.sources)} sources; at most "
                         f"{MAX_SOURCES} (each is a coverage map of the whole window): merge "
                         "faint ones, or pass a pixel array of the scene instead.")
    for i, s in enumerate(scene.sources):
        if hasattr(s, "intensity"):  # a PointSource
            check_array(s.position, f"{p}scene.sources[{i}].position", fix="metres")
            check_array(s.intensity, f"{p}scene.sources[{i}].intensity", ge=0)
            a = _concrete_array(s.intensity)
            if a is not None and not np.any(a > 0):
                raise InputError(f"{p}scene.sources[{i}].intensity: {a.tolist()} sends no "
                                 "light; give an intensity > 0 in at least one channel.")
            continue
        check_array(s.radius, f"{p}scene.sources[{i}].radius", gt=0, fix="metres")
        check_array(s.position, f"{p}scene.sources[{i}].position", fix="metres")
        check_array(s.radiance, f"{p}scene.sources[{i}].radiance", ge=0)
    f, ro, rf, zp = (_concrete_array(x) for x in (lens.focal_length, scene.object_distance,
                                                  lens.focus_distance,
                                                  lens.principal_separation))
    if any(x is None or x.ndim for x in (f, ro, rf, zp)):
        return
    try:
        check_geometry(focal_length=float(f), object_distance=float(ro),
                       focus_distance=float(rf), principal_separation=float(zp))
    except ValueError as exc:
        raise InputError(f"{p}{exc}") from None
    check_defocus_override(lens, float(f), float(rf), float(zp), where=p)


def defocus_past_exit_pupil(dz: float, z_r: float) -> str | None:
    """Why a Δz of ``dz`` (metres, positive: the sensor behind the in-focus plane) cannot
    be, for an exit pupil ``z_r`` from the sensor, or None where it can: at z_R or beyond
    the in-focus image would lie at or behind the exit pupil, where no converging beam
    forms the defocused image (the defocus phase's sign and the magnification turn
    over). The one rule of ``difstar.psf``, a lens's override and a RAW fit's bounds."""
    if dz < z_r:
        return None
    return (f"{_fmt(dz)} m puts the object's in-focus image at or behind the exit pupil, "
            f"which lies {_fmt(z_r)} m from the sensor; give defocus < {_fmt(z_r)} m (the "
            "sensor's distance from the in-focus plane, positive behind it)")


def check_defocus_override(lens, f: float, rf: float, zp: float, *, where: str = "") -> None:
    """The lens's Δz override (``lens.defocus``, concrete) below the exit pupil's
    distance to the sensor (:func:`defocus_past_exit_pupil`; past it, the grid planner
    saw a small phase and computed an in-focus image). ``f``, ``rf``, ``zp``: the focal
    length, focus distance and principal-plane separation (metres), as
    :func:`difstar._geometry.camera_geometry` takes them."""
    dz = None if lens.defocus is None else _concrete_array(lens.defocus)
    mp = _concrete_array(lens.pupil_magnification)
    if dz is None or mp is None or dz.ndim or mp.ndim:
        return
    why = defocus_past_exit_pupil(float(dz), exit_pupil_distance(f, rf, zp, float(mp)))
    if why:
        raise InputError(f"{where}camera.lens.defocus = {why}, or null to derive it from "
                         "the focus.")


# ------------------------------------------------------------------ sizes, memory


def check_crop(crop, field: str = "--crop") -> tuple[int, int]:
    """(H, W) even integers >= :data:`MIN_CROP`."""
    try:
        h, w = (v for v in crop)
    except (TypeError, ValueError):
        raise InputError(f"{field}: give two sizes H W in pixels.") from None
    out = []
    for v in (h, w):
        n = check_number(v, field, ge=MIN_CROP, integer=True, unit="pixels",
                         fix=f"even; the smallest crop is {MIN_CROP} {MIN_CROP}")
        if n % 2:
            raise InputError(
                f"{field}: {n} is odd; give even sizes (whole Bayer quads), e.g. {n + 1}."
            )
        out.append(n)
    return out[0], out[1]


_MEMORY_UNITS = {"": 1, "k": 2**10, "m": 2**20, "g": 2**30, "t": 2**40,
                 "kib": 2**10, "mib": 2**20, "gib": 2**30, "tib": 2**40,
                 "kb": 10**3, "mb": 10**6, "gb": 10**9, "tb": 10**12, "b": 1}
MEMORY_LIMIT_FORM = ("a whole number of bytes, or a number with a unit K, M, G, T "
                     "(powers of 1024, also KiB ... TiB) or KB, MB, GB, TB (powers of 1000), "
                     "e.g. 8000000000, 512M or 8G")


def parse_memory_limit(text, field: str = ENV_MEMORY_LIMIT) -> int:
    """Bytes from ``text``: ``8000000000``, ``512M``, ``8G``, ``1.5GiB``, ``8GB`` (K, M,
    G, T and KiB … TiB are powers of 1024, KB … TB of 1000). Anything else (``abc``, a
    negative or zero size, a fraction of a byte) is an :class:`InputError` naming
    ``field`` and the accepted form. The one parser of ``DIFSTAR_MEMORY_LIMIT``."""
    raw = str(text).strip()
    m = re.fullmatch(r"([0-9]{1,30}(?:\.[0-9]{1,30})?)\s*([A-Za-z]{0,3})", raw)
    unit = m.group(2).lower() if m else ""
    if not m or unit not in _MEMORY_UNITS:
        raise InputError(f"{field}: {str(text)!r} is not a memory size; give "
                         f"{MEMORY_LIMIT_FORM}.")
    number = m.group(1)
    if "." in number and unit in ("", "b"):
        raise InputError(f"{field}: {str(text)!r} is not a whole number of bytes; give "
                         f"{MEMORY_LIMIT_FORM}.")
    value = int(float(number) * _MEMORY_UNITS[unit]) if "." in number else (
        int(number) * _MEMORY_UNITS[unit])
    if value < 1:
        raise InputError(f"{field}: {str(text)!r} is no memory at all; give {MEMORY_LIMIT_FORM}.")
    return value


def memory_limit_from_env() -> int | None:
    """``DIFSTAR_MEMORY_LIMIT`` in bytes (:func:`parse_memory_limit`), or None when it is
    unset or empty; a bad value is an :class:`InputError`."""
    env = os.environ.get(ENV_MEMORY_LIMIT)
    if env is None or not env.strip():
        return None
    return parse_memory_limit(env)


def memory_budget() -> int:
    """Bytes a computation may use: ``DIFSTAR_MEMORY_LIMIT`` (:func:`parse_memory_limit`)
    if set, else the accelerator's memory limit where JAX reports one, else the
    machine's memory."""
    env = memory_limit_from_env()
    if env is not None:
        return env
    try:
        import jax

        stats = jax.devices()[0].memory_stats() or {}
        if stats.get("bytes_limit"):
            return int(stats["bytes_limit"])
    except Exception:
        pass
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return 16 * 2**30


def check_memory(need: int | float, *, what: str, fix: str, where: str) -> None:
    """Refuse (:class:`InputError`) a computation estimated to need ``need`` bytes when
    that is more than :func:`memory_budget`: ``what`` says what needs it, ``fix`` what
    would fit. Estimates come from static shapes, so this runs before any allocation
    and also while tracing."""
    budget = memory_budget()
    if not need <= budget:
        raise InputError(
            f"{where}: {what} needs at least {fmt_bytes(need)} of memory, more than the "
            f"{fmt_bytes(budget)} available ({ENV_MEMORY_LIMIT} overrides, e.g. 8G); {fix}"
        )


def check_shape(shape, field: str, *, least: int = 1) -> tuple[int, int]:
    """(H, W): two whole numbers >= ``least`` (not bools, strings or fractions: 8.5 is
    refused, not truncated), or :class:`InputError` naming ``field``."""
    fix = f"give (H, W), two whole numbers of pixels >= {least}"
    if isinstance(shape, (str, bytes)) or not hasattr(shape, "__len__") or len(shape) != 2:
        raise InputError(f"{field}: {shape!r} is not (H, W); {fix}.")
    out = []
    for i, v in enumerate(shape):
        if isinstance(v, (bool, np.bool_, str, bytes)) or v is None:
            raise InputError(f"{field}[{i}]: {v!r} is not a whole number; {fix}.")
        try:
            x = float(v)
        except (TypeError, ValueError, OverflowError):
            raise InputError(f"{field}[{i}]: {v!r} is not a whole number; {fix}.") from None
        if not math.isfinite(x) or x != math.floor(x):
            raise InputError(f"{field}[{i}]: {_fmt(v)} is not a whole number; {fix}.")
        if x < least:
            raise InputError(f"{field}[{i}]: {_fmt(v)} is too small; {fix}.")
        out.append(int(v) if isinstance(v, (int, np.integer)) else int(x))
    return out[0], out[1]


def check_wavelength_count(count: int, field: str) -> None:
    """At most :data:`MAX_WAVELENGTHS` wavelengths (each is a PSF evaluation)."""
    if count > MAX_WAVELENGTHS:
        raise InputError(
            f"{field}: {count} wavelengths; give at most {MAX_WAVELENGTHS} (each is a PSF "
            f"evaluation: a few per channel meet a 1e-3 target, see "
            f"difstar.choose_wavelengths)."
        )


def _outline_counts(pupil, field: str):
    """(field, count, what) for every outline or vane set in ``pupil`` (static shapes
    only: works on traced pupils)."""
    stack = [(pupil, field)]
    while stack:
        p, f = stack.pop()
        if isinstance(p, RegularPolygon):
            yield f"{f}.n", int(p.n), "blades (edges)"
        elif isinstance(p, Polygon):
            yield f"{f}.vertices", int(np.shape(p.vertices)[0]), "vertices"
        elif isinstance(p, CurvedIris):
            yield f"{f}.n", int(p.n), "blades"
            yield f"{f}.n x segments", int(p.n) * int(p.segments), "edges (blades x segments)"
        elif isinstance(p, Spiders):
            yield f"{f}.n", int(p.n), "vanes"
        elif isinstance(p, Struts):
            yield f"{f}.angles", int(np.shape(p.angles)[0]), "struts"
        elif isinstance(p, Union):
            stack.extend((m, f"{f}.members[{i}]") for i, m in enumerate(p.members))
        elif isinstance(p, Obstructed):
            stack.extend((q, f"{f}.{name}") for name, q in (
                ("outer", p.outer), ("obstruction", p.obstruction), ("spiders", p.spiders))
                if q is not None)
        elif isinstance(p, Transformed):
            stack.append((p.pupil, f"{f}.pupil"))


def check_pupil_cost(pupil, field: str = "pupil") -> int:
    """Every outline in ``pupil`` has at most :data:`MAX_EDGES` edges (vertices, blades,
    vanes), else :class:`InputError` naming the field. Returns the largest count."""
    largest = 0
    for f, count, what in _outline_counts(pupil, field):
        check_edge_count(count, f, what)
        largest = max(largest, count)
    return largest


def fmt_count(n, digits: int = 15) -> str:
    """A whole number ``n`` for a reader: as it is up to ``digits`` digits, else
    "1.60e601"; any size, an int beyond a float's range too (a cost estimate for absurd
    inputs)."""
    d = str(int(n))  # exact for ints of any size
    return d if len(d) <= digits else f"{d[0]}.{d[1:3]}e{len(d) - 1}"


def fmt_bytes(b) -> str:
    """``b`` bytes for a reader: "3.2 GB"; any size (:func:`fmt_count` beyond 1e15)."""
    if b >= 1e15:
        return f"{fmt_count(b, digits=0)} bytes"
    for unit, s in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6)):
        if b >= s:
            return f"{b / s:.3g} {unit}"
    return f"{b:.0f} bytes"


__all__ = [
    "ENV_MEMORY_LIMIT", "InputError", "MAX_BLADES", "MAX_BUILD_EDGES", "MAX_EDGES",
    "MAX_EXACT_EDGES",
    "MAX_JSON_DEPTH", "MAX_SPECTRUM_SAMPLES", "MAX_SPIDERS", "MAX_VERTICES",
    "MAX_WAVELENGTHS", "MEMORY_LIMIT_FORM", "MIN_CROP", "check_array",
    "check_camera_scene", "check_crop", "check_edge_count",
    "check_memory", "check_number", "check_obstruction", "check_polygon_vertices",
    "check_psf_inputs", "check_pupil", "check_pupil_cost", "check_shape",
    "check_wavelength_count", "fmt_bytes", "fmt_count",
    "memory_budget", "memory_limit_from_env", "parse_memory_limit", "refuse_nonfinite_traced",
]
