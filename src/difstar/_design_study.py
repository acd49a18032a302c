"""The worked aperture-design study behind ``difstar design`` (:mod:`difstar.design_study`):
for an n-blade iris at f/8 and a fixed open area (an f/8 disc's), how far can blade
curvature and vertex placement cut the spikes, and what does that cost in the smoothness
of a defocused highlight (bokeh)?

Setup (stated in the output): a 50 mm lens focused at infinity, exit pupil at 50 mm,
550 nm, the paper's 3.917 µm pixels. At f/8 the intensity's bandwidth needs a grid pitch
≤ λN/2 = 2.2 µm, so the PSF is computed at 2× oversampling (1.96 µm) and integrated over
each pixel: focused on 96² pixels (64² with ``--quick``), defocused (sensor behind focus,
geometric blur 80 px (40) across, about 9 waves) on 128² (64²).

Designs: straight blades; curved blades (curvature in [0, --max-curvature]); curved
blades with moved vertices (|radial|, |angular| ≤ --vertex-bound, kept convex); the disc
of equal area. Objective: the halo anisotropy (spike energy in any direction) +
--bokeh-weight × the bokeh's coefficient of variation; --optimiser adam (default, on
sigmoid-unconstrained values) or lbfgsb (bound-constrained, in the values themselves).
"""

from __future__ import annotations

import math
import sys
import time

from difstar._batch import map_batch
from difstar._design import OPTIMISERS, IrisFamily, IrisParams, PSFSetup, convexity_bound
from difstar._design_measures import (
    bokeh_nonuniformity,
    core_energy,
    halo_anisotropy,
    spike_energy,
    spike_length,
)
from difstar._validate import MAX_BLADES, InputError, check_number
from difstar.io._scene import SceneError, validate

STUDY_DEFAULTS = {
    "focal_length": 50e-3,
    "wavelength": 550e-9,
    "pixel_pitch": 3.917e-6,
    "oversample": 2,
}


def _log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


#: f-numbers the study takes: faster irises need pupil grids growing as 1/N² (thousands of
#: samples a side at f/1, over any memory below f/0.3) and leave the paraxial model of a
#: 50 mm lens; slower ones put the Airy disc (radius 1.22 λN) beyond --quick's 64-pixel
#: frame, where the spike and core measures mean nothing
MIN_F_NUMBER, MAX_F_NUMBER = 1.0, 128.0
#: optimiser steps per design at most (each step is a PSF and its gradient: seconds)
MAX_STEPS = 10_000
#: the bokeh weight at most: beyond, the halo anisotropy (~1e-3) no longer counts in the
#: objective and float32 gradients can overflow
MAX_BOKEH_WEIGHT = 1e6
#: the study's flags by their Python names (``iris_study``'s keywords)
STUDY_FLAGS = {"blades": "--blades", "f_number": "--f-number", "steps": "--steps",
               "max_curvature": "--max-curvature", "vertex_bound": "--vertex-bound",
               "bokeh_weight": "--bokeh-weight", "optimiser": "--optimiser"}


def check_f_number(f_number, field: str = "f_number") -> float:
    return check_number(f_number, field, ge=MIN_F_NUMBER, le=MAX_F_NUMBER,
                        fix="the study's iris at f/8 by default; faster needs pupil grids "
                        "growing as 1/N², slower puts the Airy disc beyond the frame")


def check_study_args(*, blades=9, f_number=8.0, steps=None, max_curvature=0.6,
                     vertex_bound=0.015, bokeh_weight=0.0, learning_rate=0.1,
                     optimiser="adam", names: dict | None = None) -> dict:
    """The study's arguments checked (each alone, then the curvature and vertex bounds
    together: every iris they allow must be convex), before anything is computed;
    :class:`InputError` names the argument (``names``: Python name → what to call it,
    e.g. :data:`STUDY_FLAGS`) and the fix. Returns them as numbers."""
    n = {k: k for k in (*STUDY_FLAGS, "learning_rate")} | dict(names or {})
    out = {
        "blades": check_number(blades, n["blades"], integer=True, ge=3, le=MAX_BLADES),
        "f_number": check_f_number(f_number, n["f_number"]),
        "steps": None if steps is None else check_number(
            steps, n["steps"], integer=True, ge=1, le=MAX_STEPS,
            fix="each step computes the PSFs and their gradient"),
        "max_curvature": check_number(max_curvature, n["max_curvature"], gt=0, le=1,
                                      fix="relative to the circumradius; 1 is a circle"),
        "vertex_bound": check_number(vertex_bound, n["vertex_bound"], ge=0, lt=0.5,
                                     fix="each vertex's relative radial and angular "
                                     "deviation"),
        "bokeh_weight": check_number(bokeh_weight, n["bokeh_weight"], ge=0,
                                     le=MAX_BOKEH_WEIGHT,
                                     fix="0 optimises the spikes alone"),
        "learning_rate": check_number(learning_rate, n["learning_rate"], gt=0),
        "optimiser": optimiser,
    }
    if not (isinstance(optimiser, str) and optimiser in OPTIMISERS):
        raise InputError(f"{n['optimiser']}: {optimiser!r} is not one of "
                         f"{', '.join(OPTIMISERS)}; give adam (Adam on the unconstrained "
                         "values, the default) or lbfgsb (L-BFGS-B within the bounds).")
    nb, mc, vb = out["blades"], out["max_curvature"], out["vertex_bound"]

    def margin(v):
        return convexity_bound(nb, max_curvature=mc, max_radial=v, max_angular=v)

    if margin(vb) < 0:
        lo, hi = 0.0, vb  # margin(0) >= 0 for any curvature <= 1
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if margin(mid) >= 0 else (lo, mid)
        if lo < 1e-6:  # curvature 1: the blades are arcs of one circle, no room left
            want = f"{n['vertex_bound']} 0"
        else:  # rounded down to two digits
            e = 10.0 ** (math.floor(math.log10(lo)) - 1)
            want = f"{n['vertex_bound']} <= {math.floor(lo / e) * e:.2g}"
        raise InputError(
            f"{n['vertex_bound']}: {vb:g} with {n['max_curvature']} {mc:g} and "
            f"{n['blades']} {nb} allows non-convex irises (a vertex can turn the wrong "
            f"way); give {want} for these blades and curvature, or a smaller "
            f"{n['max_curvature']}.")
    return out


def study_setup(*, blades: int = 9, f_number: float = 8.0, quick: bool = False):
    """(IrisFamily, PSFSetup, measure options) for the worked study."""
    blades = check_number(blades, "blades", integer=True, ge=3, le=MAX_BLADES)
    f_number = check_f_number(f_number)
    f = STUDY_DEFAULTS["focal_length"]
    area = math.pi * (f / (2 * f_number)) ** 2
    size, blur, dsize = (64, 40, 64) if quick else (96, 80, 128)
    p = STUDY_DEFAULTS["pixel_pitch"]
    dz = blur * p * f / (f / f_number)  # blur diameter = D Δz / z  (D = f / N)
    setup = PSFSetup(
        wavelength=STUDY_DEFAULTS["wavelength"], z_focus=f, pixel_pitch=p,
        shape=(size, size), oversample=STUDY_DEFAULTS["oversample"], defocus=dz,
        defocus_shape=(dsize, dsize), max_radius=IrisFamily(blades, area).radius_bound(),
    )
    family = IrisFamily(blades, area)
    opts = {"core_radius": 4.0, "half_width": math.pi / (4 * blades)}
    return family, setup, opts


def measures_fn(family, setup, opts):
    """The pure function ``params → (measures, focused PSF, defocused PSF, outline)`` of
    the study's setup (``measures``: a dict of scalar arrays); :func:`measurer` runs it on
    one design, :func:`sweep_designs` maps it over many."""
    import jax.numpy as jnp

    rb = setup.blur_radius(family.area)
    rc, hw = opts["core_radius"], opts["half_width"]

    def values(params):
        pu = family.pupil(params)
        img = setup.focused(pu)
        bok = setup.defocused(pu)
        d = pu.chord_normal_angles()
        return {
            "curvature": params.curvature,
            "max_abs_radial": jnp.max(jnp.abs(params.radial)),
            "max_abs_angular_rad": jnp.max(jnp.abs(params.angular)),
            "halo_anisotropy": halo_anisotropy(img, core_radius=rc),
            "spike_wedge_energy": spike_energy(img, d, core_radius=rc, half_width=hw),
            "spike_wedge_excess": spike_energy(img, d, core_radius=rc, half_width=hw,
                                               excess=True),
            "spike_length_px": spike_length(img, d, half_width=hw, core_radius=rc),
            "core_energy": core_energy(img, core_radius=rc),
            "bokeh_cv": bokeh_nonuniformity(bok, radius=rb),
            "bokeh_peak": bokeh_nonuniformity(bok, radius=rb, measure="peak"),
            "area_rel_error": pu.area() / family.area - 1,
            "convexity_margin_rad": pu.convexity_margin(),
            "circumradius_m": pu.circumradius,
        }, img, bok, pu.outline()

    return values


def study_objective(family, setup, opts, *, bokeh_weight: float = 0.0):
    """The study's objective ``params → (value, {"halo_anisotropy", ["bokeh_cv"]})``:
    the halo anisotropy of the focused PSF plus ``bokeh_weight`` × the defocused
    highlight's coefficient of variation."""
    rb = setup.blur_radius(family.area)

    def objective(p):
        pu = family.pupil(p)
        value = halo_anisotropy(setup.focused(pu), core_radius=opts["core_radius"])
        aux = {"halo_anisotropy": value}
        if bokeh_weight:
            b = bokeh_nonuniformity(setup.defocused(pu), radius=rb)
            aux["bokeh_cv"] = b
            value = value + bokeh_weight * b
        return value, aux

    return objective


def study_start(family, curvature, vertex_bound: float):
    """The study's start for the vertex design: ``curvature``, the vertices moved by a
    tenth of ``vertex_bound`` off the symmetric point, whose gradient in the vertices
    vanishes by symmetry."""
    import numpy as np

    k = np.arange(family.n)
    return family.params(curvature, radial=0.1 * vertex_bound * np.sin(2.3 * k),
                         angular=0.1 * vertex_bound * np.cos(1.7 * k))


def measurer(family, setup, opts):
    """``params → (measures as concrete floats, focused PSF, defocused PSF, outline)``
    for the study's setup: every reported measure of one design, by one program compiled
    for all the designs it measures."""
    import equinox as eqx

    fn = eqx.filter_jit(measures_fn(family, setup, opts))

    def measure_one(params) -> tuple:
        out, img, bok, outline = fn(params)
        return {k: float(v) for k, v in out.items()}, img, bok, outline

    return measure_one


def iris_study(
    *, blades: int = 9, f_number: float = 8.0, quick: bool = False,
    steps: int | None = None, max_curvature: float = 0.6, vertex_bound: float = 0.015,
    bokeh_weight: float = 0.0, learning_rate: float = 0.1, optimiser: str = "adam",
    log=_log, progress: bool = False,
) -> dict:
    """Run the worked study; returns the rows, histories, PSFs and pupils (no files).

    optimiser: ``"adam"`` (``optax.adam(learning_rate)`` on the sigmoid-unconstrained
    values) or ``"lbfgsb"`` (:class:`difstar._design.LBFGSB` within the bounds;
    ``learning_rate`` unused); ``steps`` iterations either way (L-BFGS-B may stop
    sooner). ``log``: a line a phase (None: none); ``progress``: a bar per optimisation."""
    import numpy as np
    import optax

    from difstar._design import design

    a = check_study_args(blades=blades, f_number=f_number, steps=steps,
                         max_curvature=max_curvature, vertex_bound=vertex_bound,
                         bokeh_weight=bokeh_weight, learning_rate=learning_rate,
                         optimiser=optimiser)
    blades, f_number = a["blades"], a["f_number"]
    family, setup, opts = study_setup(blades=blades, f_number=f_number, quick=quick)
    steps = (12 if quick else 60) if a["steps"] is None else a["steps"]
    max_curvature, vertex_bound = a["max_curvature"], a["vertex_bound"]
    bokeh_weight, learning_rate = a["bokeh_weight"], a["learning_rate"]
    rb = setup.blur_radius(family.area)
    objective = study_objective(family, setup, opts, bokeh_weight=bokeh_weight)

    def optimise(label, start, box):
        return design(objective, start, constraints=box, steps=steps,
                      optimiser=optax.adam(learning_rate) if a["optimiser"] == "adam"
                      else a["optimiser"], progress=label if progress else None)

    log = log or (lambda msg: None)
    designs, histories, evaluations = {"straight": family.params(0.0)}, {}, {}
    t0 = time.perf_counter()
    box = family.bounds(curvature=(0.0, max_curvature))
    log(f"difstar design: optimising the curvature ({steps} {a['optimiser']} steps) ...")
    res = optimise("curvature", family.params(0.5 * max_curvature), box)
    designs["curved"] = res.best_params
    histories["curved"] = res.history["value"]
    evaluations["curved"] = int(res.history["evaluations"][-1])
    box = family.bounds(curvature=(0.0, max_curvature), radial=vertex_bound,
                        angular=vertex_bound)
    log(f"difstar design: optimising curvature and vertices ({steps} {a['optimiser']} "
        "steps) ...")
    start = study_start(family, res.best_params.curvature, vertex_bound)
    res2 = optimise("curvature and vertices", start, box)
    designs["curved+vertices"] = res2.best_params
    histories["curved+vertices"] = res2.history["value"]
    evaluations["curved+vertices"] = int(res2.history["evaluations"][-1])
    designs["disc (reference)"] = family.params(1.0)
    t_opt = time.perf_counter() - t0
    rows = {}
    psfs = {}
    outlines = {}
    measure_one = measurer(family, setup, opts)  # one compile for every design
    for name, p in designs.items():
        rows[name], img, bok, outline = measure_one(p)
        psfs[name] = (np.asarray(img), np.asarray(bok))
        outlines[name] = np.asarray(outline)
    return {
        "config": {
            "blades": blades, "f_number": f_number, "open_area_m2": family.area,
            "focal_length_m": setup.z_focus, "wavelength_m": setup.wavelength,
            "pixel_pitch_m": setup.pixel_pitch, "oversample": setup.oversample,
            "focused_shape": list(setup.shape), "defocused_shape": list(setup.defocus_shape),
            "defocus_m": setup.defocus, "blur_diameter_px": 2 * rb,
            "airy_scale_px": setup.airy_scale(family.area), "steps": steps,
            "max_curvature": max_curvature, "vertex_bound": vertex_bound,
            "bokeh_weight": bokeh_weight, "learning_rate": learning_rate,
            "optimiser": a["optimiser"], **opts, "quick": quick,
        },
        "rows": rows,
        "params": {k: {"curvature": float(v.curvature), "radial": np.asarray(v.radial),
                       "angular": np.asarray(v.angular)} for k, v in designs.items()},
        "histories": histories,
        "evaluations": evaluations,
        "psfs": psfs,
        "outlines": outlines,
        "optimise_s": t_opt,
    }


COLUMNS = (
    ("halo_anisotropy", "halo anisotropy", "{:.3e}"),
    ("spike_wedge_energy", "wedge energy", "{:.4f}"),
    ("spike_wedge_excess", "wedge excess", "{:.2e}"),
    ("core_energy", "core energy", "{:.4f}"),
    ("bokeh_cv", "bokeh CV", "{:.4f}"),
    ("bokeh_peak", "bokeh peak", "{:.4f}"),
    ("curvature", "curvature", "{:.3f}"),
    ("max_abs_radial", "max abs radial", "{:.4f}"),
    ("area_rel_error", "area rel. err.", "{:.1e}"),
    ("convexity_margin_rad", "convexity margin", "{:.3f}"),
)


def table_markdown(rows: dict) -> str:
    head = "| design | " + " | ".join(c[1] for c in COLUMNS) + " |"
    sep = "|---|" + "---|" * len(COLUMNS)
    lines = [head, sep]
    for name, r in rows.items():
        lines.append(f"| {name} | " + " | ".join(f.format(r[k]) for k, _, f in COLUMNS) + " |")
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------------- sweeps

#: the most designs one sweep may hold
MAX_SWEEP_DESIGNS = 100_000
#: the largest sweep file read (100000 designs with 64 deviations each take ~60 MB)
MAX_SWEEP_BYTES = 256 * 2**20
_DESIGN_FIELDS = ("name", "curvature", "radial", "angular")
_SWEEP_FIELDS = ("designs", "grid")


def _number(value, field: str, **limits):
    """:func:`difstar._validate.check_number`, refusing a number written as a string
    (JSON's numbers have no quotes)."""
    if isinstance(value, str):
        fix = f" ({limits['fix']})" if "fix" in limits else ""
        raise InputError(f"{field}: {value!r} is a string, not a number; write the number "
                         f"without quotes{fix}.")
    return check_number(value, field, **limits)


def _vertex_values(value, field: str, blades: int):
    """One number (every vertex alike) or ``blades`` numbers, each in (−0.5, 0.5)."""
    import numpy as np

    if isinstance(value, (list, tuple)):
        if len(value) != blades:
            raise InputError(
                f"{field}: {len(value)} values for a {blades}-blade iris; give one number "
                f"(every vertex alike) or {blades} (one per vertex), or change --blades.")
        vals = [_number(v, f"{field}[{i}]", gt=-0.5, lt=0.5,
                        fix="a relative deviation; 0 is the regular vertex")
                for i, v in enumerate(value)]
        return np.asarray(vals, float)
    v = _number(value, field, gt=-0.5, lt=0.5,
                fix="a relative deviation, or a list of one per vertex")
    return np.full(blades, v)


def parse_sweep(doc, *, blades: int, source: str = "sweep") -> list[dict]:
    """The designs of a sweep document (see ``data_schemas/design_sweep.schema.json``):
    ``{"designs": [{"name", "curvature", "radial", "angular"}, …], "grid": {"curvature":
    [...]}}`` (either or both; the grid's designs follow the listed ones). Returns
    ``[{"name", "curvature", "radial" (blades,), "angular" (blades,)}]``; anything else
    raises :class:`InputError` naming the field and the fix.

    The document must satisfy the schema and the checks here, which also know
    ``blades`` (one deviation per blade) and that names are unique; where both refuse
    it, the message is the one from here (the field and the fix), else the schema's
    (the field as a JSON path). Convexity is :func:`check_convex`'s (it computes the
    outlines)."""
    blades = check_number(blades, "blades", integer=True, ge=3, le=MAX_BLADES)
    if isinstance(doc, dict):  # the count first: the schema would look at every design
        grid = doc.get("grid")
        lists = (doc.get("designs"), grid.get("curvature") if isinstance(grid, dict) else None)
        n = sum(len(v) for v in lists if isinstance(v, list))
        if n > MAX_SWEEP_DESIGNS:
            raise InputError(f"{source}: {n} designs (designs and grid.curvature); a "
                             f"sweep holds at most {MAX_SWEEP_DESIGNS}: split it into "
                             "several sweeps.")
    try:
        validate(doc, "design_sweep", source=source)
    except SceneError as schema_error:
        try:
            _parse_sweep(doc, blades=blades, source=source)
        except InputError as own:  # the field and the fix
            raise own from None
        except Exception:  # noqa: BLE001 - what the schema refused: its message
            pass
        raise SceneError(f"{str(schema_error).rstrip('.')}; see data_schemas/"
                         "design_sweep.schema.json for what a sweep holds.") from None
    return _parse_sweep(doc, blades=blades, source=source)


def _parse_sweep(doc, *, blades: int, source: str) -> list[dict]:
    import numpy as np

    if not isinstance(doc, dict):
        raise InputError(f'{source}: expected a JSON object like {{"designs": [{{"name": '
                         f'"c0.3", "curvature": 0.3}}]}} or {{"grid": {{"curvature": '
                         f'[0, 0.3, 0.6]}}}}.')
    for k in doc:
        if k not in _SWEEP_FIELDS and not str(k).startswith("$"):
            raise InputError(f"{source}: {k}: unknown field; a sweep has "
                             f"{' and/or '.join(_SWEEP_FIELDS)}.")
    if "designs" not in doc and "grid" not in doc:
        raise InputError(f'{source}: no designs; give "designs" (a list of designs) and/or '
                         f'"grid" (e.g. {{"curvature": [0, 0.3, 0.6]}}).')
    out = []
    listed = doc.get("designs", [])
    if not isinstance(listed, list):
        raise InputError(f"{source}: designs: expected a list of designs, got "
                         f"{type(listed).__name__}.")
    for i, d in enumerate(listed):
        where = f"{source}: designs[{i}]"
        if not isinstance(d, dict):
            raise InputError(f'{where}: expected an object like {{"name": "c0.3", '
                             f'"curvature": 0.3, "radial": 0.0, "angular": 0.0}}.')
        for k in d:
            if k not in _DESIGN_FIELDS:
                raise InputError(f"{where}.{k}: unknown field; a design has "
                                 f"{', '.join(_DESIGN_FIELDS)}.")
        if "curvature" not in d:
            raise InputError(f"{where}.curvature: missing; give the blade curvature in "
                             "[0, 1] (0 straight, 1 a circle).")
        name = d.get("name", f"design {i}")
        if not isinstance(name, str) or not name.strip():
            raise InputError(f"{where}.name: {name!r} is not a name; give a non-empty "
                             "string (or leave it out).")
        out.append({
            "name": name,
            "curvature": _number(d["curvature"], f"{where}.curvature", ge=0, le=1,
                                 fix="0 straight blades, 1 a circle"),
            "radial": _vertex_values(d.get("radial", 0.0), f"{where}.radial", blades),
            "angular": _vertex_values(d.get("angular", 0.0), f"{where}.angular", blades),
        })
    if "grid" in doc:
        grid = doc["grid"]
        if not isinstance(grid, dict) or set(grid) != {"curvature"}:
            raise InputError(f'{source}: grid: expected {{"curvature": [values in [0, 1]]}} '
                             f"(the grid varies the curvature; list other designs under "
                             f'"designs").')
        cs = grid["curvature"]
        if not isinstance(cs, list) or not cs:
            raise InputError(f"{source}: grid.curvature: expected a non-empty list of "
                             "curvatures in [0, 1], e.g. [0, 0.3, 0.6].")
        values = [_number(c, f"{source}: grid.curvature[{j}]", ge=0, le=1,
                          fix="0 straight blades, 1 a circle") for j, c in enumerate(cs)]
        first = {}
        for j, c in enumerate(values):
            if c in first:
                raise InputError(f"{source}: grid.curvature[{j}]: {c:g} repeats "
                                 f"grid.curvature[{first[c]}]; give each curvature once.")
            first[c] = j
        digits = 4  # as few as tell the grid's values apart (a fine grid needs more)
        while digits < 17 and len({f"{c:.{digits}g}" for c in values}) < len(values):
            digits += 1
        for c in values:
            out.append({"name": f"curvature={c:.{digits}g}", "curvature": c,
                        "radial": np.zeros(blades), "angular": np.zeros(blades)})
    if not out:
        raise InputError(f"{source}: the sweep holds no design; list at least one.")
    if len(out) > MAX_SWEEP_DESIGNS:
        raise InputError(f"{source}: {len(out)} designs; a sweep holds at most "
                         f"{MAX_SWEEP_DESIGNS}; split it into several sweeps.")
    seen = {}
    for i, d in enumerate(out):
        if d["name"] in seen:
            raise InputError(f"{source}: designs[{i}].name: {d['name']!r} is also design "
                             f"{seen[d['name']]}'s name; give every design its own name.")
        seen[d["name"]] = i
    return out


def curvature_grid(lo, hi, n, *, blades: int, flag: str = "--sweep-curvature") -> list[dict]:
    """``n`` designs with straight-to-curved blades, curvature evenly from ``lo`` to
    ``hi`` (the flag's three values), as :func:`parse_sweep` returns them."""
    import numpy as np

    lo = check_number(lo, f"{flag} LO", ge=0, le=1, fix="0 straight blades, 1 a circle")
    hi = check_number(hi, f"{flag} HI", ge=0, le=1, fix="0 straight blades, 1 a circle")
    n = check_number(n, f"{flag} N", integer=True, ge=1, le=MAX_SWEEP_DESIGNS,
                     fix="the number of designs")
    if hi < lo:
        raise InputError(f"{flag}: HI {hi:g} < LO {lo:g}; give LO HI N with LO <= HI, "
                         "e.g. 0 0.6 7.")
    return parse_sweep({"grid": {"curvature": [float(c) for c in np.linspace(lo, hi, n)]}},
                       blades=blades, source=flag)


def check_convex(designs, *, blades: int = 9, f_number: float = 8.0,
                 source: str = "sweep") -> None:
    """Refuse (:class:`InputError`: the design, its name and the fix) a design of
    :func:`parse_sweep`'s whose iris is not convex: exact margins from the outlines,
    no PSF computed."""
    area = math.pi * (STUDY_DEFAULTS["focal_length"] / (2 * check_f_number(f_number))) ** 2
    _check_convex(IrisFamily(blades, area), designs, source)


def _check_convex(family, designs, source: str) -> None:
    """Refuse a design whose iris is not convex (exact margins, computed before the
    PSFs)."""
    import jax
    import numpy as np

    if not designs:
        return
    margins = np.asarray(jax.jit(jax.vmap(
        lambda b: family.pupil(_params(b)).convexity_margin()))(_stack(designs)))
    for i, m in enumerate(margins):
        if not (m >= -1e-9):  # a disc (curvature 1) has margin 0 to rounding
            d = designs[i]
            raise InputError(
                f"{source}: design {i} ({d['name']!r}): the iris is not convex (turning "
                f"{m:.3g} rad at a vertex); reduce its curvature or its radial/angular "
                "vertex deviations.")


def _stack(designs) -> dict:
    """The designs as arrays with a leading axis: curvature (B,), radial and angular (B,
    blades) (:func:`_params` makes one item's :class:`difstar._design.IrisParams`)."""
    import jax.numpy as jnp
    import numpy as np

    dt = jnp.result_type(float)
    return {"curvature": jnp.asarray(np.array([d["curvature"] for d in designs]), dt),
            "radial": jnp.asarray(np.stack([d["radial"] for d in designs]), dt),
            "angular": jnp.asarray(np.stack([d["angular"] for d in designs]), dt)}


def _params(item):
    return IrisParams(item["curvature"], item["radial"], item["angular"])


def sweep_designs(designs, *, blades: int = 9, f_number: float = 8.0, quick: bool = False,
                  devices=None, chunk=None, progress=None, plan_out=None,
                  source: str = "sweep", convexity_checked: bool = False) -> dict:
    """Every measure of many designs at once, the designs sharded over ``devices``
    (:func:`difstar.map_batch` over the stacked :class:`IrisParams`; ``chunk`` designs
    at a time at most, default memory-sized; ``progress(done, total, seconds)`` after
    each chunk). ``designs``: as :func:`parse_sweep` returns them (radial/angular
    (blades,) arrays). Returns ``{"config", "rows"}``: one row per design, in order, with
    its parameters and the same measures as :func:`measurer` (equal to them to rounding).
    ``convexity_checked``: :func:`check_convex` has passed these designs already."""
    import numpy as np

    family, setup, opts = study_setup(blades=blades, f_number=f_number, quick=quick)
    for i, d in enumerate(designs):
        for k in ("radial", "angular"):
            if np.shape(d[k]) != (family.n,):
                raise ValueError(f"{source}: design {i} ({d['name']!r}).{k}: shape "
                                 f"{np.shape(d[k])}, expected ({family.n},) for "
                                 f"{family.n} blades.")
    if not convexity_checked:
        _check_convex(family, designs, source)
    values = measures_fn(family, setup, opts)
    out = map_batch(lambda b: values(_params(b))[0], _stack(designs), devices=devices,
                    chunk=chunk, progress=progress, plan_out=plan_out)
    rows = []
    for i, d in enumerate(designs):
        row = {"name": d["name"], "radial": [float(v) for v in d["radial"]],
               "angular": [float(v) for v in d["angular"]]}
        row.update({k: float(v[i]) for k, v in out.items()})
        rows.append(row)
    rb = setup.blur_radius(family.area)
    return {
        "config": {
            "blades": family.n, "f_number": f_number, "open_area_m2": family.area,
            "focal_length_m": setup.z_focus, "wavelength_m": setup.wavelength,
            "pixel_pitch_m": setup.pixel_pitch, "focused_shape": list(setup.shape),
            "defocused_shape": list(setup.defocus_shape), "defocus_m": setup.defocus,
            "blur_diameter_px": 2 * rb, **opts, "quick": quick,
        },
        "rows": rows,
    }
