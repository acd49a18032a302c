"""Bad input to ``difstar fit-image`` never passes silently, never ends in a traceback and
never loses data (issue 31).

Every case runs the command line in-process (``difstar.cli.main``) on a tiny synthetic
star (a 32 × 32 Gaussian, nothing compiled: every refusal comes before any model is
computed) and asserts: exit status 2 with one line ``difstar: error: ...`` naming the
manifest's field, no traceback, the input folder unchanged and ``--out`` not created. The
Python API's own refusals (:func:`difstar.fitting.fit`) come before any solving. A
property-based test throws non-finite, out-of-range and junk values into every numeric
field of the manifest: a clean refusal naming a field, never another exception.
"""

from __future__ import annotations

import copy
import json
import math
import os
import re
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_bad_input import numeric_leaves, run, snapshot

from difstar.fitting import FitInputError
from difstar.io._scene import SceneError

REPO = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------------------ helpers


def star(shape=(32, 32), x=16.3, y=15.6, s=1.6, flux=1000.0, bg=10.0, seed=0):
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]]
    img = bg + flux / (2 * math.pi * s**2) * np.exp(-0.5 * ((xx - x) ** 2 + (yy - y) ** 2)
                                                    / s**2)
    return img + np.random.default_rng(seed).normal(0, 0.5, shape)


BASE = {
    "name": "tiny",
    "data": {"path": "star.npy", "sigma": 0.5, "noise": {"gain": 1.0}},
    "pupil": {"builder": "circle", "radius": 0.425},
    "light": {"wavelength": 3.6e-6},
    "detector": {"pad": 4, "oversample": 1},
    "accuracy": 0.01,
    "params": {
        "pixel_scale": 1.2, "obstruction": 0.16, "strut_width": 0.03,
        "rotation": {"value": 0.0, "free": True, "bounds": [-30, 30]},
        "x0": {"value": "auto", "free": True, "bounds_about": [-2, 2]},
        "y0": {"value": "auto", "free": True, "bounds_about": [-2, 2]},
        "flux": {"value": "auto", "free": True, "scale": 100.0},
        "background": {"value": "auto", "free": True, "scale": 1.0},
        "jitter": {"value": 0.5, "free": True, "bounds": [0.0, 3.0]},
    },
    "stages": [
        {"free": ["x0", "y0", "flux", "background"], "half": 8},
        {"free": "all", "scan": {"name": "rotation", "half_range": 5, "step": 0.5},
         "max_steps": 10},
        {"hop": {"name": "rotation", "offsets": [-1, 1], "stages": 1}},
    ],
    "starts": {"jitter": [0.3, 0.6]},
    "max_steps": 20,
    "spikes": {"r_min": 4, "r_max": 12, "n_spikes": 3},
}


def write_case(folder: Path, man=None, text: str | None = None, image=None) -> Path:
    """The star (or ``image``) as star.npy and the manifest (or its raw ``text``) as
    m.json in ``folder``."""
    np.save(folder / "star.npy", star() if image is None else image)
    p = folder / "m.json"
    p.write_text(json.dumps(BASE if man is None else man) if text is None else text)
    return p


def refused_fit_image(work: Path, capsys, *fields: str, man=None, text=None,
                      image=None) -> str:
    """``difstar fit-image m.json --out out`` refused: exit 2, one line starting
    ``difstar: error:`` holding every ``fields`` string, no traceback, the folder
    unchanged and ``out`` not created."""
    p = write_case(work, man, text, image)
    before = snapshot(work)
    code, err = run(["fit-image", p, "--out", work / "out", "--quiet"], capsys)
    assert code == 2, (code, err)
    assert "Traceback" not in err, err
    assert err.startswith("difstar: error:") and err.count("\n") == 1, err
    for f in fields:
        assert f in err, (f, err)
    assert snapshot(work) == before, "files changed or left behind"
    assert not (work / "out").exists()
    return err


def edited(path: tuple, value, doc=None) -> dict:
    d = copy.deepcopy(BASE if doc is None else doc)
    node = d
    for k in path[:-1]:
        node = node[k]
    if value is DELETE:
        if isinstance(node, dict):
            node.pop(path[-1], None)
        else:
            del node[path[-1]]
    else:
        node[path[-1]] = value
    return d


DELETE = object()


def png_header(path: Path, width: int, height: int) -> Path:
    """A PNG that declares ``width`` × ``height`` grey pixels (its data left out: the
    reader must refuse it from its header, before Pillow decompresses anything)."""
    def chunk(kind, data):
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF))

    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr)
                     + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(b"IEND", b""))
    return path


@pytest.fixture
def work(tmp_path, monkeypatch):
    """A scratch folder that is also the current folder (relative outputs land here)."""
    w = tmp_path / "work"
    w.mkdir()
    monkeypatch.chdir(w)
    return w


def test_the_base_manifest_loads(work):
    """The cases below differ from a manifest that loads: its auto values found, every
    file it reads listed in ``inputs``."""
    from difstar.fitting import load_manifest

    model, data, opts = load_manifest(write_case(work))
    assert data.image.shape == (32, 32) and data.mask.all()
    assert abs(model.params["x0"].value - 0.3) < 0.35  # the 3 × 3 centroid about the peak
    assert abs(model.params["background"].value - 10.0) < 1.0
    assert list(map(os.path.realpath, opts["inputs"])) == [os.path.realpath(work / "star.npy")]


# ----------------------------------------------------------- refused manifests

BAD = [
    # tracebacks before
    ("pupil without builder", ("pupil",), {"radius": 0.425}, ["field pupil", "builder"]),
    ("unknown pupil key", ("pupil", "flat_to_flat"), 1.32, ["field pupil", "flat_to_flat"]),
    ("empty light", ("light",), {}, ["field light", "exactly one of wavelength"]),
    ("both wavelength and band", ("light", "band"), [3e-6, 4e-6], ["field light"]),
    ("noise a number", ("data", "noise"), 5, ["field data/noise", "object"]),
    ("params a list", ("params",), [1, 2], ["field params", "object"]),
    # raw Python messages before
    ("roi of two", ("data", "roi"), [0, 10], ["field data/roi", "4"]),
    ("roi of strings", ("data", "roi"), ["a", "b", "c", "d"], ["field data/roi/0"]),
    ("saturation text", ("data", "saturation"), "high", ["field data/saturation"]),
    ("light n 0", ("light",), {"band": [3e-6, 4e-6], "n": 0}, ["field light/n", ">= 1"]),
    ("obstruction over the pupil", ("params", "obstruction"), 0.5,
     ["field params/obstruction", "covers the whole pupil"]),
    ("obstruction bound over the pupil", ("params", "obstruction"),
     {"value": 0.2, "free": True, "bounds": [0.1, 0.6]}, ["field params/obstruction"]),
    # accepted in silence before
    ("negative roi", ("data", "roi"), [-5, 20, 0, 20], ["field data/roi/0", ">= 0"]),
    ("roi outside the image", ("data", "roi"), [0, 100, 0, 20],
     ["field data/roi", "32 × 32"]),
    ("roi of 2 rows", ("data", "roi"), [4, 6, 0, 20], ["field data/roi", "4 × 4"]),
    ("pad -1", ("detector", "pad"), -1, ["field detector/pad", ">= 0"]),
    ("oversample 0", ("detector", "oversample"), 0, ["field detector/oversample", ">= 1"]),
    ("jitter -1", ("params", "jitter"), -1, ["field params/jitter", ">= 0"]),
    ("jitter value -1", ("params", "jitter"), {"value": -1, "free": False},
     ["field params/jitter/value", ">= 0"]),
    ("jitter bounds reversed", ("params", "jitter"), {"value": 1, "free": True,
                                                      "bounds": [3, 0]},
     ["field params/jitter", "lo < hi"]),
    ("halo 2", ("params", "halo"), 2.0, ["field params/halo", "<= 1"]),
    ("struts wider than the pupil", ("params", "strut_width"), 1e300,
     ["field params/strut_width", "block the whole pupil"]),
    ("a second halo not declared", ("params", "halo2"), 0.1,
     ["field params/halo2", "detector/halos"]),
    ("a declared halo's fraction 2", ("params", "scatter"), 2.0,
     ["field params/scatter", "[0, 1]"]),
    ("halos a name", ("detector", "halos"), "halo", ["field detector/halos", "array"]),
    ("halos twice", ("detector", "halos"), ["halo", "halo"], ["field detector/halos",
                                                              "twice"]),
    ("a halo named as another parameter", ("detector", "halos"), ["halo", "x0"],
     ["field detector/halos", "x0"]),
    ("a halo's width 0", ("detector", "halos"), [{"name": "halo", "width": 0}],
     ["field detector/halos/0/width"]),
    ("max_steps 0", ("max_steps",), 0, ["field max_steps", ">= 1"]),
    ("max_steps 2.7", ("max_steps",), 2.7, ["field max_steps", "integer"]),
    ("stage max_steps 0", ("stages", 1, "max_steps"), 0, ["field stages/1/max_steps"]),
    ("blackbody -5000 K", ("light",), {"band": [3e-6, 4e-6], "source": -5000},
     ["field light/source"]),
    ("blackbody 0.001 K", ("light",), {"band": [3e-6, 4e-6], "source": 1e-3},
     ["field light/source", "kelvin"]),
    ("band reversed", ("light",), {"band": [4e-6, 3e-6]}, ["field light/band", "lo < hi"]),
    ("wavelength in nm", ("light", "wavelength"), 550, ["field light/wavelength"]),
    ("n with a wavelength", ("light", "n"), 3, ["field light", "band"]),
    ("sigma 0", ("data", "sigma"), 0, ["field data/sigma"]),
    ("exposure 0", ("data", "exposure"), 0, ["field data/exposure", "> 0"]),
    ("gain 0", ("data", "noise", "gain"), 0, ["field data/noise/gain", "> 0"]),
    ("unknown parameter", ("params", "focus"), 1.0, ["field params/focus", "known"]),
    ("zernike not in nm", ("params", "z4"), 3e5, ["field params/z4", "nm RMS"]),
    ("pixel_scale in degrees", ("params", "pixel_scale"), 1e-5,
     ["field params/pixel_scale", "arcsec"]),
    ("pixel_scale from no header", ("params", "pixel_scale"),
     {"value": "header", "free": False}, ["field params/pixel_scale/value", "header"]),
    ("bounds_relative with a number", ("params", "jitter"),
     {"value": 0.5, "free": True, "bounds_relative": [0.5, 2]},
     ["field params/jitter/bounds_relative", "auto"]),
    ("a typo at the top", ("stage",), [{"free": "all"}], ["field (top level)", "stage"]),
    ("missing data file", ("data", "path"), "nope.npy", ["field data/path", "not found"]),
    ("per_capture unknown", ("per_capture",), ["x0", "focus"], ["field per_capture"]),
    ("starts unknown", ("starts",), {"focus": [1.0]}, ["field starts/focus"]),
    ("starts empty", ("starts", "jitter"), [], ["field starts/jitter"]),
    ("too many starts", ("starts",), {"jitter": [0.1] * 40, "x0": [0.0] * 40},
     ["field starts", "at most 1000"]),
    ("unknown stage key", ("stages", 0, "halfwidth"), 3, ["field stages/0", "halfwidth"]),
    ("spikes option", ("spikes", "rmin"), 3, ["field spikes", "rmin"]),
    ("spike stage radii", ("stages", 1, "spikes"), {"r_min": 12, "r_max": 5},
     ["field stages/1/spikes/r_max", "exceed"]),
    ("hop over too many stages", ("stages", 2, "hop", "stages"), 5,
     ["field stages/2/hop", "stages <= 2"]),
    ("hop of an unknown name", ("stages", 2, "hop", "name"), "focus",
     ["field stages/2/hop", "focus"]),
    ("repeat of an unknown name", ("stages", 2), {"repeat": {"until": {"focus": 0.1}}},
     ["field stages/2/repeat", "until.focus"]),
    ("set of an unknown name", ("stages", 1, "set"), {"focus": 1.0},
     ["field stages/1/set", "focus"]),
    # success reported for nothing done
    ("negative half-width", ("stages", 0, "half"), -1, ["field stages/0/half", ">= 0"]),
    ("annulus inside out", ("stages", 0, "annulus"), [10, 5],
     ["field stages/0/annulus", "r_min < r_max"]),
    ("annulus beyond the window", ("stages", 0, "annulus"), [40, 50],
     ["field stages/0/annulus", "no used pixel"]),
    ("nothing free", ("stages", 0, "fix"), ["x0", "y0", "flux", "background"],
     ["field stages/0/free", "nothing is free"]),
    ("free a fixed parameter", ("stages", 0, "free"), ["strut_width"],
     ["field stages/0/free", "not free parameters"]),
    ("free an empty list", ("stages", 0, "free"), [], ["field stages/0/free"]),
    ("scan of 1e8 points", ("stages", 1, "scan", "step"), 1e-7,
     ["field stages/1/scan", "at most 1000"]),
    ("scan step wider than the range", ("stages", 1, "scan", "step"), 20,
     ["field stages/1/scan", "half_range"]),
    ("scan of an unknown name", ("stages", 1, "scan", "name"), "focus",
     ["field stages/1/scan", "focus"]),
    ("nothing free in the model", ("params",),
     {"pixel_scale": 1.2, "flux": 900.0, "background": 10.0},
     ["field params", "no parameter is free"]),
]


@pytest.mark.parametrize("name,path,value,fields", BAD, ids=[c[0] for c in BAD])
def test_bad_manifest_is_refused_naming_the_field(work, capsys, name, path, value, fields):
    man = edited(path, value)
    if name == "nothing free in the model":
        man.pop("stages")
        man.pop("starts")
    if name == "zernike not in nm":
        man["zernike"] = [4]
    if name == "a declared halo's fraction 2":
        man["detector"]["halos"] = ["halo", "scatter"]
    refused_fit_image(work, capsys, *fields, man=man)


def test_more_than_64_captures_are_refused(work, capsys):
    np.save(work / "star.npy", star())
    caps = [{"path": "star.npy", "sigma": 1.0}] * 65
    refused_fit_image(work, capsys, "field data", man=edited(("data",), caps))


def test_bad_json_is_refused(work, capsys):
    text = json.dumps(BASE)
    dup = text.replace('"max_steps": 20', '"max_steps": 20, "max_steps": 30')
    assert dup != text
    refused_fit_image(work, capsys, "field max_steps", "more than once", text=dup)
    nan = text.replace('"sigma": 0.5', '"sigma": NaN')
    refused_fit_image(work, capsys, "field data/sigma", "finite", text=nan)
    refused_fit_image(work, capsys, "not valid JSON", text=text[:-3])
    code, err = run(["fit-image", work / "missing.json", "--out", work / "out"], capsys)
    assert code == 2 and "missing.json" in err and "Traceback" not in err


def test_bad_images_are_refused(work, capsys):
    # an image with no signal: the fit ran, then matplotlib failed
    refused_fit_image(work, capsys, "field data", "no signal", image=np.zeros((32, 32)))
    refused_fit_image(work, capsys, "field data", "no signal", image=np.full((32, 32), 7.0))
    # a star of the wrong sign (was: the whole fit, then "Invalid vmin or vmax")
    refused_fit_image(work, capsys, "field data", "no signal", "its sign", image=-star())
    # values whose squares overflow or underflow (was: a fit of garbage, exit 0, or
    # matplotlib's "Invalid vmin or vmax")
    refused_fit_image(work, capsys, "field data", "rescale", image=star() * 1e300)
    refused_fit_image(work, capsys, "field data", "rescale", image=star() * 1e-300)
    # a σ map of the wrong shape (was a NumPy broadcast error)
    np.save(work / "sigma.npy", np.ones((10, 10)))
    refused_fit_image(work, capsys, "field data/sigma", "10 × 10", "32 × 32",
                      man=edited(("data", "sigma"), "sigma.npy"))
    np.save(work / "sigma.npy", np.zeros((32, 32)))
    refused_fit_image(work, capsys, "field data/sigma", "<= 0",
                      man=edited(("data", "sigma"), "sigma.npy"))
    (work / "sigma.npy").unlink()
    # a decompression bomb (was Pillow's DecompressionBombError traceback), a huge .npy
    big = work.parent / "big"
    big.mkdir()
    png_header(big / "huge.png", 20000, 20000)
    refused_fit_image(work, capsys, "field data/path", "huge.png", "20000 × 20000",
                      "at most", man=edited(("data", "path"), str(big / "huge.png")))
    with open(big / "huge.npy", "wb") as fh:
        np.lib.format.write_array_header_1_0(fh, {"descr": "<f8", "fortran_order": False,
                                                  "shape": (20000, 20000)})
    refused_fit_image(work, capsys, "field data/path", "20000 × 20000",
                      man=edited(("data", "path"), str(big / "huge.npy")))
    # a source image that does not fit the stages' padded windows
    np.save(work / "src.npy", np.ones((40, 40)))
    refused_fit_image(work, capsys, "field source/image", "padded window",
                      man=edited(("source",), {"image": "src.npy"}))
    np.save(work / "src.npy", -np.ones((3, 3)))
    refused_fit_image(work, capsys, "field source/image", "non-negative",
                      man=edited(("source",), {"image": "src.npy"}))


def test_fit_that_cannot_fit_in_memory_is_refused_before_compiling(work, capsys,
                                                                    monkeypatch):
    """The Jacobian's memory (a lower estimate) against DIFSTAR_MEMORY_LIMIT, before any
    compile (was: a 81² fit peaked at 9.4 GB with no check)."""
    monkeypatch.setenv("DIFSTAR_MEMORY_LIMIT", "5M")
    refused_fit_image(work, capsys, "field data", "memory", "DIFSTAR_MEMORY_LIMIT", "roi")


def test_image_readers_refuse_huge_images_from_their_headers(tmp_path):
    """Every reader checks the size its header declares before reading any data (FITS
    and TIFF as sparse files: nothing is allocated)."""
    import tifffile
    from astropy.io import fits

    from difstar.io import read_image
    from difstar.io._images import MAX_VALUES, ImageReadError

    png_header(tmp_path / "a.png", 20000, 20000)
    hdr = fits.Header()
    hdr.update(SIMPLE=True, BITPIX=8, NAXIS=2, NAXIS1=20000, NAXIS2=20000)
    hdr.tofile(tmp_path / "a.fits")
    with open(tmp_path / "a.fits", "r+b") as fh:
        fh.truncate(2880 * (1 + math.ceil(20000 * 20000 / 2880)))
    tifffile.imwrite(tmp_path / "a.tif", shape=(20000, 20000), dtype=np.uint8)
    with open(tmp_path / "a.npy", "wb") as fh:
        np.lib.format.write_array_header_1_0(fh, {"descr": "<f8", "fortran_order": False,
                                                  "shape": (20000, 20000)})
    for name in ("a.png", "a.fits", "a.tif", "a.npy"):
        with pytest.raises(ImageReadError, match=rf"{name}: an image of shape 20000 × 20000"
                                                 rf" .*at most {MAX_VALUES}"):
            read_image(tmp_path / name)


def test_nan_border_is_masked_and_the_auto_values_found(tmp_path):
    """A border of NaN (common in FITS) is left out of the fit with a warning; the
    automatic background, flux and position come from the finite pixels (was: "Param
    value must be finite" about ``background: auto``)."""
    from difstar.fitting import load_manifest

    img = star()
    img[:3], img[-3:], img[:, :4], img[:, -4:] = np.nan, np.nan, np.nan, np.inf
    p = write_case(tmp_path, image=img)
    with pytest.warns(UserWarning, match=r"field data/path: \d+ of 1024 pixels .* NaN"):
        model, data, opts = load_manifest(p)
    assert not data.mask[:3].any() and data.mask[3:-3, 4:-4].all()
    v = {k: p.value for k, p in model.params.items()}
    assert all(math.isfinite(x) for x in v.values())
    assert abs(v["background"] - 10.0) < 1.0 and abs(v["flux"] / 1000 - 1) < 0.1
    assert abs(v["x0"] - 0.3) < 0.35 and abs(v["y0"] + 0.4) < 0.35


def test_data_near_the_float_range_are_refused_with_the_reason(tmp_path):
    """An image in absurd units (values near 1e300) is refused naming the data and the
    fix, before the noise model would overflow (no NumPy overflow warning on the way)."""
    import warnings

    from difstar.fitting import FitData, Noise, load_manifest

    man = edited(("data",), {"path": "star.npy", "noise": {"read": None, "gain": 1e9,
                                                           "floor": 0.02}})
    p = write_case(tmp_path, man, image=star() * 1e298)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        with pytest.raises(FitInputError, match=r"field data: values up to .*e\+(29|30)\d.*"
                                                r"rescale the data"):
            load_manifest(p)
        # the library's own door refuses them as well, with the same reason and fix
        with pytest.raises(FitInputError, match=r"FitData: values up to .*e\+(29|30)\d.*"
                                                r"rescale the data"):
            FitData.from_array(star() * 1e298, noise=Noise(None, 1e9, 0.02))


def test_inputs_lists_every_file_read(tmp_path):
    from difstar.fitting import load_manifest

    np.save(tmp_path / "star2.npy", star(seed=1))
    np.save(tmp_path / "sig.npy", np.full((32, 32), 0.5))
    np.save(tmp_path / "src.npy", np.ones((3, 3)))
    man = edited(("data",), [{"path": "star.npy", "sigma": "sig.npy"},
                             {"path": str(tmp_path / "star2.npy"), "sigma": 0.5}])
    man["source"] = {"image": "src.npy"}
    model, data, opts = load_manifest(write_case(tmp_path, man))
    assert list(map(os.path.realpath, opts["inputs"])) == [
        os.path.realpath(tmp_path / f) for f in ("star.npy", "sig.npy", "star2.npy", "src.npy")]
    assert len(data) == 2 and np.all(data[0].sigma == 0.5)


def test_every_image_fit_manifest_in_the_repository_is_valid():
    """Every fit-image manifest in the repository (fit/**, tests, notebooks: a JSON file
    with a pupil builder) validates against the tightened schema and loads."""
    from difstar.fitting import load_manifest
    from difstar.fitting._manifest import manifest_document
    from difstar.io._scene import validate

    found = [p for p in REPO.rglob("*.json")
             if ".venv" not in p.parts and "data_schemas" not in p.parts
             and not any(q.startswith(".") for q in p.relative_to(REPO).parts)
             and ('"builder"' in p.read_text(errors="replace")
                  or '"extends"' in p.read_text(errors="replace"))]
    assert len(found) >= 17 and REPO / "fit" / "spitzer-irac" / "manifest.json" in found
    for p in found:
        validate(manifest_document(p)[0], "image_fit_manifest", source=str(p))
        load_manifest(p)


# -------------------------------------------------------------- the Python API


def _api_case():
    from difstar.fitting import FitData, ImageModel, Light, Param, obstructed_circle_pupil

    model = ImageModel(obstructed_circle_pupil(0.425),
                       {"pixel_scale": Param(1.2), "x0": Param(0.3, True, (-2, 2)),
                        "y0": Param(-0.4, True, (-2, 2)), "flux": Param(1000.0, True),
                        "background": Param(10.0, True, scale=1.0),
                        "rotation": Param(0.0, True, (-30, 30))},
                       light=Light.monochromatic(3.6e-6), pad=4)
    return model, FitData.from_array(star(), sigma=0.5)


API_BAD = [
    ([{"free": "all", "half": -1}], "stage 1: half"),
    ([{"free": "all", "annulus": [10, 5]}], "stage 1: annulus"),
    ([{"free": "all", "annulus": [30, 40]}], "stage 1: annulus: the window"),
    ([{"free": "all", "half": 0}], "stage 1: half: the window (half 0"),  # 1 px, 5 free
    ([{"free": ["x0"], "fix": ["x0"]}], "stage 1: free: nothing is free"),
    ([{"free": ["x0"], "fix": ["focus"]}], "stage 1: fix"),
    ([{"free": "all", "scan": {"name": "rotation", "half_range": 5, "step": 1e-7}}],
     "stage 1: scan"),
    ([{"free": "all", "max_steps": 0}], "stage 1: max_steps"),
    ([{"free": "all", "rtol": -1.0}], "stage 1: rtol"),
    ([{"free": "all", "spikes": {"n_spikes": 0}}], "stage 1: spikes/n_spikes"),
    ([{"free": "all", "reject": {"above": -1}}], "stage 1: reject/above"),
    ([{"free": "all", "noise_from_residuals": {"bins": 1}}],
     "stage 1: noise_from_residuals/bins"),
    ([{"hop": {"name": "rotation", "offsets": [1.0], "stages": 3}}], "stage 1: hop: needs"),
]


@pytest.mark.parametrize("later,match", API_BAD, ids=[m for _, m in API_BAD])
def test_fit_refuses_a_bad_stage_before_solving(monkeypatch, later, match):
    """fit() finds a later stage's mistake before the first stage solves (the solver is
    replaced by one that fails the test)."""
    import difstar.fitting._analysis as analysis
    import difstar.fitting._procedure as procedure

    def never(*a, **k):
        raise AssertionError("the fit started before refusing its input")

    monkeypatch.setattr(procedure, "_one_fit", never)
    monkeypatch.setattr(analysis, "chi2_slice", never)
    model, data = _api_case()
    with pytest.raises(FitInputError, match=re.escape(match)):
        procedure.fit(model, data, stages=[{"free": ["x0", "y0"], "half": 6}] + later)


def test_fit_refuses_bad_arguments_before_solving(monkeypatch):
    import difstar.fitting._procedure as fitting

    monkeypatch.setattr(fitting, "_one_fit", lambda *a, **k: pytest.fail("solved"))
    model, data = _api_case()
    for kw, match in ((dict(max_steps=0), "max_steps"),
                      (dict(rtol=float("nan")), "rtol"),
                      (dict(starts={"focus": [1.0]}), "starts/focus"),
                      (dict(starts={"x0": []}), "starts/x0"),
                      (dict(starts={"x0": [0.1] * 50, "y0": [0.1] * 50}), "at most 1000")):
        with pytest.raises(FitInputError, match=re.escape(match)):
            fitting.fit(model, data, **kw)
    from difstar.fitting._analysis import _scan

    with pytest.raises(FitInputError, match="scan: half_range 1 / step 1e-09"):
        _scan(model, [data], None, model.values(), name="rotation", half_range=1.0,
              step=1e-9)


# ------------------------------------------------------------- property-based tests


PROP_DOC = edited(("light",), {"band": [3e-6, 4e-6], "n": 3, "source": 5000})
PROP_DOC["data"].update(roi=[0, 32, 0, 32], exposure=1.0, saturation=1e6)
PROP_DOC["params"]["halo"] = {"value": 0.1, "free": True, "bounds": [0.0, 0.5]}
PROP_DOC["stages"][0]["annulus"] = [0, 20]
PROP_DOC["stages"][1].update(rtol=1e-5, spikes={"r_min": 3, "r_max": 12, "half_width": 8},
                             reject={"above": 20, "r_min": 4, "grow": 1},
                             noise_from_residuals={"floor": 0.03, "bins": 8})
PROP_DOC["stages"].append({"repeat": {"until": {"rotation": 0.01}, "stages": 1,
                                      "max_rounds": 3}})
LEAVES = list(numeric_leaves(PROP_DOC))
NONFINITE = st.sampled_from([math.nan, math.inf, -math.inf])
OUT_OF_RANGE = st.one_of(st.sampled_from([0, -1, -1e-300, 1e-300, 1e300, -5000, 2.7, 1e9]),
                         st.floats(-1e6, 1e6, allow_nan=False))
JUNK = st.one_of(st.none(), st.booleans(), st.integers(-10**20, 10**20), st.text(max_size=4),
                 st.lists(st.floats(-1e3, 1e3), max_size=4),
                 st.dictionaries(st.text(max_size=3), st.integers(), max_size=2))
PROP = settings(max_examples=40, deadline=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture])


@pytest.fixture(scope="module")
def prop_folder(tmp_path_factory):
    d = tmp_path_factory.mktemp("prop")
    np.save(d / "star.npy", star())
    from difstar.fitting import load_manifest

    (d / "ok.json").write_text(json.dumps(PROP_DOC))
    load_manifest(d / "ok.json")  # the document the values go into loads
    return d


def _load_or_refuse(folder: Path, doc) -> str | None:
    """load_manifest on ``doc`` written as JSON (NaN and Infinity as Python writes them):
    None when it loads, else the refusal's message, which must name the manifest and a
    field; any other exception fails the test."""
    from difstar.fitting import load_manifest

    p = folder / "m.json"
    p.write_text(json.dumps(doc))
    try:
        load_manifest(p)
    except (FitInputError, SceneError) as e:
        msg = str(e)
        assert str(p) in msg and "field " in msg, msg
        assert "\n" not in msg.strip()
        return msg
    return None


@PROP
@given(path=st.sampled_from(LEAVES), value=NONFINITE)
def test_nonfinite_anywhere_is_refused_naming_the_field(prop_folder, path, value):
    msg = _load_or_refuse(prop_folder, edited(path, value, PROP_DOC))
    assert msg is not None and "field " + "/".join(map(str, path)) + ":" in msg, msg
    assert "finite" in msg


@PROP
@given(path=st.sampled_from(LEAVES), value=OUT_OF_RANGE)
def test_out_of_range_numbers_load_or_are_refused_cleanly(prop_folder, path, value):
    _load_or_refuse(prop_folder, edited(path, value, PROP_DOC))


def test_a_pupil_wider_than_a_kilometre_is_refused_not_overflowed(prop_folder):
    """Found by the property test above: a pupil radius of 1e300 m overflowed a float in
    the PSF planner (OverflowError) instead of being refused at the manifest."""
    msg = _load_or_refuse(prop_folder, edited(("pupil", "radius"), 1e300, PROP_DOC))
    assert msg is not None and "pupil/radius" in msg and "1000" in msg, msg


@PROP
@given(path=st.sampled_from(LEAVES), value=JUNK)
def test_junk_never_escapes_as_another_error(prop_folder, path, value):
    _load_or_refuse(prop_folder, edited(path, value, PROP_DOC))


KEYS = [p for p in LEAVES] + [("data", "path"), ("pupil", "builder"), ("light",),
                              ("params", "x0", "value"), ("stages", 0, "free"),
                              ("stages", 1, "scan"), ("source",), ("per_capture",),
                              ("detector",), ("data",), ("params", "x0")]


@PROP
@given(path=st.sampled_from(KEYS), value=st.one_of(JUNK, st.just(DELETE)))
def test_junk_or_missing_anywhere_is_a_clean_refusal(prop_folder, path, value):
    _load_or_refuse(prop_folder, edited(path, value, PROP_DOC))


@pytest.mark.parametrize("kw,match", [
    (dict(n=10000), "n must be a whole number from 1 to 1024"),  # was: minutes, memory growing
    (dict(n=2.5), "n must be a whole number"),
    (dict(n="4"), "n must be a whole number"),
    (dict(n=3, source=-5000), "temperature in kelvin > 0"),  # was: accepted
    (dict(n=3, source=math.nan), "temperature in kelvin > 0"),
])
def test_light_band_is_bounded_in_the_python_api(kw, match):
    from difstar.fitting import FitInputError, Light

    with pytest.raises(FitInputError, match=match):
        Light.band(3e-6, 4e-6, **kw)
    with pytest.raises(FitInputError, match="at most 1024"):
        Light((1e-6,) * 2000, (1.0,) * 2000)


def test_a_model_not_finite_at_the_start_is_named(monkeypatch):
    """A model image that is not finite at the start (units off by 10⁶, say) is refused
    with a message naming the units to check, from the solver's first step (which only
    evaluates the start), not a solver's traceback."""
    import jax.numpy as jnp

    from difstar.fitting import ImageModel, fit
    from difstar.fitting._programs import release_programs

    model, data = _api_case()
    # the last step of every path to the model's image (the PSF engine's, and one PSF
    # at the star's centre moved in its spectrum)
    read_out = ImageModel.read_out
    monkeypatch.setattr(ImageModel, "read_out",
                        lambda self, *a, **k: read_out(self, *a, **k) * jnp.nan)
    with pytest.raises(FitInputError, match="not finite at the start; check the units"):
        fit(model, data, stages=[{"free": ["x0", "flux"], "max_steps": 5}])
    # a model that turns non-finite only where the solver did not look (its stage held
    # the optics and solved on one PSF; the standard errors need the whole model): named,
    # not a linear-algebra traceback
    monkeypatch.setattr(ImageModel, "read_out", read_out)
    release_programs()  # the kept programs hold the code they were traced from
    image = ImageModel.image
    monkeypatch.setattr(ImageModel, "image",
                        lambda self, *a, **k: image(self, *a, **k) * jnp.nan)
    with pytest.raises(FitInputError, match="not finite at the answer; check the units"):
        fit(model, data, stages=[{"free": ["x0", "flux"], "max_steps": 5}])


def test_joint_fit_too_large_for_memory_is_refused_saying_how_many_fit(monkeypatch):
    """Captures fitted together (the stars of a field): the solver holds each capture's
    linearisation and every pixel by the Jacobian's columns, and nothing bounded it (a
    joint fit's check counted one window). With equal windows (the block structure: the
    compressed directions only) each further capture costs the same; with unequal ones
    (every free parameter a column) the cost grows faster than their number. Against
    DIFSTAR_MEMORY_LIMIT between the estimates for 8 and 9 captures, 40 captures are
    refused before any compile, naming the captures, the fix (per_capture, roi) and how
    many fit together; 8 pass the check."""
    from difstar.fitting import FitData, ImageModel, Light, Param, fit, obstructed_circle_pupil
    from difstar.fitting._stages import fit_memory

    per = ("x0", "y0", "flux", "background")
    model = ImageModel(obstructed_circle_pupil(), {
        "pixel_scale": Param(0.6), "x0": Param(0.0, True, (-2.0, 2.0)),
        "y0": Param(0.0, True, (-2.0, 2.0)), "rotation": Param(3.0, True, (-30.0, 30.0)),
        "flux": Param(50.0, True, scale=10.0), "background": Param(0.5, True, scale=1.0)},
        light=Light.monochromatic(3.6e-6), pad=4)
    rng = np.random.default_rng(0)
    datas = [FitData.from_array(rng.random((41, 41)), sigma=0.05) for _ in range(40)]
    counts = (1, 8, 9, 20, 40)
    need = [fit_memory(model.for_captures(per, n), datas[:n]) for n in counts]
    assert need[0] > 0 and need[1] < need[2] < need[3] < need[4]
    # equal windows: each further capture costs the same (20 more after 20 cost 20 times
    # the one after 8)
    assert need[4] - need[3] == pytest.approx(20 * (need[2] - need[1]), rel=1e-9)
    # unequal windows: faster than their number (20 more captures after 20 cost more
    # than 20/19 of the 19 more after 1)
    uneven = [FitData.from_array(rng.random((41, 41) if i % 2 else (41, 40)), sigma=0.05)
              for i in range(40)]
    dense = [fit_memory(model.for_captures(per, n), uneven[:n]) for n in counts]
    assert dense[4] - dense[3] > 1.1 * 20 / 19 * (dense[3] - dense[0])
    assert all(d > b for d, b in zip(dense[1:], need[1:]))
    monkeypatch.setenv("DIFSTAR_MEMORY_LIMIT", str(int((need[1] + need[2]) / 2)))
    with pytest.raises(FitInputError) as e:
        fit(model, datas)
    msg = str(e.value)
    for part in ("40 captures together", "memory", "DIFSTAR_MEMORY_LIMIT",
                 "at most 8 of them together", "per_capture", "roi"):
        assert part in msg, (part, msg)
    from difstar.fitting._stages import _check_fit_memory
    _check_fit_memory(model.for_captures(per, 8), datas[:8])  # 8 pass
