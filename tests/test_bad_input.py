"""Bad input never loses data, never passes silently, never hangs (issue 16).

Every case runs the command line in-process (``difstar.cli.main``) unless it needs a
real process (signals) and asserts: exit status 2 (user error) with one line naming the
field, no traceback, the input files unchanged (checksums), nothing written and no
temporary folders left behind. Property-based tests (hypothesis) throw non-finite and
out-of-range numbers into every numeric field of a scene and of a fit manifest.
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from difstar.cli import main
from difstar.cli._main import example_document
from difstar.io._output import MARKER
from difstar.io._scene import SceneError

REPO = Path(__file__).resolve().parents[1]
CAMPAIGN = REPO / "fit" / "synthetic-paper-camera"


# ------------------------------------------------------------------------ helpers


def snapshot(folder: Path) -> dict:
    """{relative path: sha256} of every file (hidden ones too) and every folder."""
    out = {}
    for root, dirs, files in os.walk(folder):
        for d in dirs:
            out[str(Path(root, d).relative_to(folder)) + "/"] = "dir"
        for f in files:
            p = Path(root, f)
            out[str(p.relative_to(folder))] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def run(argv, capsys) -> tuple[int, str]:
    """main(argv) in-process → (exit status, stderr)."""
    try:
        code = main([str(a) for a in argv])
    except SystemExit as exc:  # argparse
        code = exc.code
    err = capsys.readouterr().err
    return code, err


def refused(argv, capsys, folder: Path, *fields: str) -> str:
    """Run; assert exit 2, every ``fields`` string in the message, no traceback, and
    ``folder`` unchanged (inputs intact, nothing written, no temporaries)."""
    before = snapshot(folder)
    code, err = run(argv, capsys)
    assert code == 2, (code, err)
    assert "Traceback" not in err, err
    for f in fields:
        assert f in err, (f, err)
    assert snapshot(folder) == before, "files changed or left behind"
    return err


def small_doc(config: str = "focused", crop=(16, 16)) -> dict:
    doc = example_document(f"paper-{config}", crop=crop)
    doc["scene"]["sources"][0]["radius"] = 0.2e-3
    return doc


def write_text(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def doc_with(path: tuple, value, doc=None) -> dict:
    d = copy.deepcopy(small_doc() if doc is None else doc)
    node = d
    for k in path[:-1]:
        node = node[k]
    node[path[-1]] = value
    return d


@pytest.fixture
def work(tmp_path, monkeypatch):
    """A scratch folder that is also the current folder (relative outputs land here)."""
    monkeypatch.chdir(tmp_path)
    return tmp_path


# ------------------------------------------------------------ silent NaN / garbage

# (JSON path, the text that replaces its value, what the message must name)
NONFINITE_SCENE = [
    (("camera", "sensor", "phi0", 1), "NaN", "camera/sensor/phi0/1"),
    (("scene", "exposure_time"), "NaN", "scene/exposure_time"),
    (("scene", "sources", 0, "radiance", 0), "Infinity", "scene/sources/0/radiance/0"),
    (("scene", "background", 2), "-Infinity", "scene/background/2"),
    (("camera", "sensor", "colour_matrix", 1, 1), "NaN", "camera/sensor/colour_matrix/1/1"),
    (("camera", "sensor", "white_balance", 0), "NaN", "camera/sensor/white_balance/0"),
    (("camera", "sensor", "response", "knee", 2), "NaN", "camera/sensor/response/knee/2"),
    (("camera", "sensor", "wavelengths", 0), "Infinity", "camera/sensor/wavelengths/0"),
    (("camera", "sensor", "pixel_pitch"), "Infinity", "camera/sensor/pixel_pitch"),
    (("camera", "lens", "focal_length"), "1e999", "camera/lens/focal_length"),
    (("camera", "lens", "pupil", "rotation"), "NaN", "camera/lens/pupil/rotation"),
    (("camera", "lens", "defocus"), "NaN", "camera/lens/defocus"),
    (("scene", "object_distance"), "-Infinity", "scene/object_distance"),
    (("grid", "accuracy"), "NaN", "grid/accuracy"),
]


@pytest.mark.parametrize("path,text,field", NONFINITE_SCENE)
def test_nonfinite_scene_numbers_are_refused(work, capsys, path, text, field):
    marker = "__BAD__"
    doc = doc_with(path, marker)
    scene = write_text(work / "s.json", json.dumps(doc).replace(f'"{marker}"', text))
    err = refused(["predict", scene, "--out", work / "out"], capsys, work, field,
                  "finite")
    assert err.count("\n") == 1  # one line


BAD_SCENE = [
    # 100,000 sources (was: no answer after minutes; each is a coverage map of the window)
    ("too many sources", lambda d: d["scene"].update(sources=d["scene"]["sources"] * 1025),
     ["scene/sources", "at most 1024"]),
    # an obstruction larger than the pupil (was: an all-NaN PSF, psf_peak NaN)
    ("obstruction", lambda d: d["camera"]["lens"].update(pupil={
        "type": "obstructed", "outer": d["camera"]["lens"]["pupil"],
        "obstruction_radius": 0.01}), ["camera/lens/pupil/obstruction_radius", "covers"]),
    # the object inside what the lens can focus (4 f)
    ("object inside focus", lambda d: d["scene"].update(object_distance=0.03),
     ["object_distance", "too close"]),
    ("focus inside focal length", lambda d: d["camera"]["lens"].update(focus_distance=0.02),
     ["focus_distance", "too close"]),
    # a figure-8 polygon: "self-intersecting", not "clockwise"
    ("figure-8", lambda d: d["camera"]["lens"].update(pupil={
        "type": "polygon", "vertices": [[0, 0], [1e-3, 1e-3], [1e-3, 0], [0, 1e-3]]}),
     ["camera/lens/pupil/vertices", "self-intersecting"]),
    ("clockwise", lambda d: d["camera"]["lens"].update(pupil={
        "type": "polygon", "vertices": [[-1e-3, -1e-3], [-1e-3, 1e-3], [1e-3, 1e-3],
                                        [1e-3, -1e-3]]}),
     ["camera/lens/pupil/vertices", "counter-clockwise"]),
    # a bad f-number: the field, not a dump of the whole pupil
    ("f-number -1", lambda d: d["camera"]["lens"].update(pupil={
        "type": "regular_polygon", "n": 7, "f_number": -1}),
     ["camera/lens/pupil/f_number", "must be > 0"]),
    ("f-number 0", lambda d: d["camera"]["lens"].update(pupil={
        "type": "circle", "f_number": 0}), ["camera/lens/pupil/f_number"]),
    ("focus -1", lambda d: d["camera"]["lens"].update(focus_distance=-1),
     ["camera/lens/focus_distance", "must be > 0"]),
    # 100000 blades compiled for minutes
    ("100000 blades", lambda d: d["camera"]["lens"]["pupil"].update(n=100000),
     ["camera/lens/pupil/n", "<= 64"]),
    ("1000 vertices", lambda d: d["camera"]["lens"].update(pupil={
        "type": "polygon", "vertices": [[1e-3 * math.cos(k * math.pi / 500),
                                         1e-3 * math.sin(k * math.pi / 500)]
                                        for k in range(1000)]}),
     ["camera/lens/pupil/vertices", "at most 256"]),
    ("crop 2 2", lambda d: d.update(grid={"crop": [2, 2]}), ["grid/crop/", ">= 8"]),
    ("grid n 4", lambda d: d.update(grid={"n": 4}), ["grid/n"]),
    ("wavelength in nm", lambda d: d["camera"]["sensor"].update(wavelengths=[600, 530, 450]),
     ["camera/sensor/wavelengths/", "<= 0.001"]),
    ("huge integer", lambda d: d["scene"].update(exposure_time=10**30),
     ["scene/exposure_time", "too large"]),
    ("negative phi0", lambda d: d["camera"]["sensor"].update(phi0=[0.1, -0.1, 0.1]),
     ["camera/sensor/phi0/1"]),
    # a Δz beyond the exit pupil's distance: the planner saw a small (negative) defocus
    # phase and rendered the in-focus image without a word
    ("defocus 1 m", lambda d: d["camera"]["lens"].update(defocus=1.0),
     ["camera.lens.defocus", "exit pupil", "defocus <"]),
    # the DNG stores the colour matrix's inverse: NumPy's bare "Singular matrix" before
    ("singular colour matrix", lambda d: d["camera"]["sensor"].update(
        colour_matrix=[[1, 0, 0], [2, 0, 0], [0, 0, 1]]),
     ["camera.sensor.colour_matrix", "singular", "invertible"]),
]


@pytest.mark.parametrize("name,edit,fields", BAD_SCENE, ids=[c[0] for c in BAD_SCENE])
def test_inconsistent_scene_is_refused(work, capsys, name, edit, fields):
    doc = small_doc()
    edit(doc)
    scene = write_text(work / "s.json", json.dumps(doc))
    err = refused(["predict", scene, "--out", work / "out"], capsys, work, *fields)
    assert len(err) < 400 and "{'" not in err  # no dump of a whole object


# ------------------------------------------------------------------ hangs, memory


def test_huge_accuracy_target_is_refused_at_once(work, capsys):
    doc = small_doc("defocused", (64, 64))
    doc["grid"] = {"crop": [64, 64], "accuracy": 1e-12}
    scene = write_text(work / "s.json", json.dumps(doc))
    t0 = time.perf_counter()
    # the PSF engine's range of targets (on the paper's grid: the padding's memory)
    refused(["predict", scene, "--out", work / "out"], capsys, work, "accuracy", "[1e-7, 1)")
    assert time.perf_counter() - t0 < 30  # it hung in fast_length
    doc["grid"]["method"] = "fft"
    scene = write_text(work / "s2.json", json.dumps(doc))
    refused(["predict", scene, "--out", work / "out"], capsys, work, "accuracy", "memory")


def test_too_many_sources_are_refused_in_the_python_api():
    import difstar
    from difstar._validate import InputError, check_camera_scene

    camera, scene = difstar.paper_camera("focused")
    many = type(scene)(**{**{f: getattr(scene, f) for f in scene.__dataclass_fields__},
                          "sources": scene.sources * 1025})
    with pytest.raises(InputError, match="scene.sources: 1025 sources; at most 1024"):
        check_camera_scene(camera, many)


def test_huge_crop_is_refused_before_allocation(work, capsys):
    scene = write_text(work / "s.json", json.dumps(small_doc()))
    err = refused(["predict", scene, "--out", work / "out", "--crop", 100000, 100000],
                  capsys, work, "memory", "crop of at most")
    # the crop it names fits
    fit = int(err.split("crop of at most ")[1].split(" ")[0])
    assert 8 <= fit < 100000


def test_numbers_float32_cannot_hold_are_refused_naming_the_field(work, capsys):
    """Found by mutating every field of a scene: in float32, 1e300 m became infinity
    (the message named "inf", a value the user never gave, after a NumPy overflow
    warning) and 1e-300 m became 0; in float64, a crop of 1e300 px or a pitch of
    1e-300 m made a cost estimate too large for a float (an internal error)."""
    import jax

    for path, value, field in ((("camera", "lens", "focal_length"), 1e300,
                                "camera/lens/focal_length"),
                               (("camera", "sensor", "pixel_pitch"), 1e-300,
                                "camera/sensor/pixel_pitch")):
        scene = write_text(work / "s.json", json.dumps(doc_with(path, value)))
        with jax.enable_x64(False):  # as the command runs without --x64
            err = refused(["predict", scene, "--out", work / "out"], capsys, work, field,
                          "float32", "--x64")
        assert "RuntimeWarning" not in err
    for path, value in ((("camera", "sensor", "pixel_pitch"), 1e-300),
                        (("grid", "crop", 0), 1e300)):
        doc = doc_with(path, value)
        scene = write_text(work / "s.json", json.dumps(doc))
        err = refused(["--x64", "predict", scene, "--out", work / "out"], capsys, work,
                      "memory")
        assert len(err) < 400  # no number of 600 digits


def test_fmt_bytes_takes_any_size():
    from difstar._validate import fmt_bytes

    assert fmt_bytes(3.2e9) == "3.2 GB"
    assert fmt_bytes(10**600 * 16) == "1.60e601 bytes"


def test_source_far_outside_the_frame_is_refused(work, capsys):
    doc = small_doc()
    doc["scene"]["sources"][0]["position"] = [1e4, 0.0]
    scene = write_text(work / "s.json", json.dumps(doc))
    refused(["predict", scene, "--out", work / "out"], capsys, work, "memory")


def test_crop_too_small_names_the_minimum(work, capsys):
    scene = write_text(work / "s.json", json.dumps(small_doc()))
    refused(["predict", scene, "--out", work / "out", "--crop", 2, 2], capsys, work,
            "--crop", "smallest crop is 8 8")
    refused(["predict", scene, "--out", work / "out", "--crop", 9, 16], capsys, work,
            "--crop", "odd")
    refused(["example", "paper-focused", "--crop", 0, 0], capsys, work, "--crop")


def test_deeply_nested_json(work, capsys):
    scene = write_text(work / "deep.json", "[" * 100000 + "]" * 100000)
    refused(["predict", scene, "--out", work / "out"], capsys, work, "nested")
    scene = write_text(work / "deep2.json", '{"a":' * 200 + "1" + "}" * 200)
    refused(["predict", scene, "--out", work / "out"], capsys, work, "nested")
    refused(["fit", scene], capsys, work, "nested")


def test_unreadable_inputs(work, capsys):
    (work / "adir").mkdir()
    refused(["predict", work / "adir", "--out", work / "out"], capsys, work, "is a folder")
    refused(["fit", work / "adir"], capsys, work, "is a folder")
    refused(["predict", work / "none.json", "--out", work / "out"], capsys, work,
            "does not exist")
    write_text(work / "bin.json", "")
    (work / "bin.json").write_bytes(b"\xff\xfe\x00garbage")
    refused(["predict", work / "bin.json", "--out", work / "out"], capsys, work, "bin.json")
    refused(["predict", "--out", work / "out"], capsys, work, "scene file or --example")


# --------------------------------------------------------------------- data loss


def test_overwrite_never_replaces_a_folder_with_other_files(work, capsys):
    scene = write_text(work / "s.json", json.dumps(small_doc()))
    own = work / "mine"
    own.mkdir()
    write_text(own / "notes.txt", "my notes")
    write_text(own / "scene.json", "{}")
    refused(["predict", scene, "--out", own, "--overwrite"], capsys, work, "not made by difstar")
    # even a difstar folder (marker) into which the user put a file of their own
    write_text(own / ".difstar-output", json.dumps({"difstar": "output",
                                                    "files": ["scene.json"]}))
    refused(["predict", scene, "--out", own, "--overwrite"], capsys, work, "notes.txt")
    # without --overwrite, never
    refused(["predict", scene, "--out", own], capsys, work, "--overwrite")


def test_an_input_is_never_replaced(work, capsys):
    scene = write_text(work / "s.json", json.dumps(small_doc()))
    refused(["predict", scene, "--out", scene, "--overwrite"], capsys, work, "input")
    # the input inside a folder difstar made
    out = work / "out"
    out.mkdir()
    write_text(out / "scene.json", json.dumps(small_doc()))
    write_text(out / ".difstar-output", json.dumps({"difstar": "output",
                                                    "files": ["scene.json"]}))
    refused(["predict", out / "scene.json", "--out", out, "--overwrite"], capsys, work, "input")
    # a file is never replaced by a folder
    other = write_text(work / "other.txt", "x")
    refused(["predict", scene, "--out", other, "--overwrite"], capsys, work, "is a file")


def test_out_of_reach_destinations(work, capsys):
    scene = write_text(work / "s.json", json.dumps(small_doc()))
    f = write_text(work / "afile", "x")
    refused(["predict", scene, "--out", f / "sub"], capsys, work, "is a file")
    refused(["predict", scene, "--out", "."], capsys, work, "current folder")
    if Path("/proc/self").exists():
        refused(["predict", scene, "--out", "/proc/difstar-test"], capsys, work,
                "cannot write")
    refused(["example", "paper-focused", "--out", "nodir/x.json"], capsys, work,
            "does not exist")
    (work / "d").mkdir()
    refused(["example", "paper-focused", "--out", work / "d"], capsys, work, "is a folder")
    ex = write_text(work / "ex.json", "{}")
    refused(["example", "paper-focused", "--out", ex], capsys, work, "--overwrite")
    refused(["design", "--out", f / "x", "--quick"], capsys, work, "is a file")


def test_overwrite_replaces_only_what_difstar_made(work, capsys):
    """A real run: writes the marker; --overwrite replaces that folder; stale temporary
    folders of a dead run beside it are removed; the input is unchanged."""
    scene = write_text(work / "s.json", json.dumps(small_doc()))
    digest = hashlib.sha256(scene.read_bytes()).hexdigest()
    out = work / "out"
    from difstar.io._output import _write_marker

    stale = work / ".out.difstar-tmp-0a0b0c0d0e0f1a1b"  # a killed run's, its lock gone
    stale.mkdir()
    _write_marker(stale, [], "predict", "0a0b0c0d0e0f1a1b")
    write_text(stale / "raw.dng", "half written")
    foreign = work / ".out.someone-elses-tmp"
    foreign.mkdir()
    code, err = run(["predict", scene, "--out", out], capsys)
    assert code == 0, err
    marker = json.loads((out / ".difstar-output").read_text())
    assert set(marker["files"]) == {p.name for p in out.iterdir()} - {".difstar-output"}
    assert not stale.exists() and foreign.exists()  # only difstar's own stale folder
    code, err = run(["predict", scene, "--out", out, "--overwrite"], capsys)
    assert code == 0, err
    assert hashlib.sha256(scene.read_bytes()).hexdigest() == digest
    assert sorted(p.name for p in work.iterdir()) == [".out.someone-elses-tmp", "out", "s.json"]


def test_failure_while_writing_leaves_nothing(work, capsys, monkeypatch):
    """An internal failure half-way through writing: exit status 1, the folders it made
    for --out removed, no temporary folder, the input unchanged."""
    import difstar.io._image_files as output

    scene = write_text(work / "s.json", json.dumps(small_doc()))

    def broken(*args, **kwargs):
        raise RuntimeError("disk on fire")

    monkeypatch.setattr(output, "write_raw_dng", broken)
    before = snapshot(work)
    code, err = run(["predict", scene, "--out", work / "new" / "deeper" / "out"], capsys)
    assert code == 1 and "internal error" in err and "disk on fire" in err
    assert snapshot(work) == before


# ------------------------------------------------- data loss, second round (issue 31)


def _star_manifest(folder: Path, data_path: str = "star.npy") -> Path:
    """A small valid fit-image manifest and its 24 × 24 Gaussian star (NumPy): every case
    below is refused before anything is computed."""
    yy, xx = np.mgrid[:24, :24]
    np.save(folder / data_path, 100.0 * np.exp(-((xx - 12) ** 2 + (yy - 12) ** 2) / 4.0) + 1.0)
    doc = {"data": {"path": data_path, "sigma": 1.0},
           "pupil": {"builder": "circle", "radius": 0.425},
           "light": {"wavelength": 3.6e-6}, "detector": {"pad": 4},
           "params": {"pixel_scale": 0.3,
                      "flux": {"value": "auto", "free": True},
                      "background": {"value": "auto", "free": True}},
           "stages": [{"free": "all", "max_steps": 2}]}
    return write_text(folder / "manifest.json", json.dumps(doc))


def test_fit_image_overwrite_never_replaces_a_folder_of_look_alike_names(work, capsys):
    """No marker, only files named like fit-image's outputs: a user's folder (was:
    deleted, exit 0)."""
    man = _star_manifest(work)
    mine = work / "results"
    mine.mkdir()
    for name in ("result.json", "model.npy", "fit.png"):
        write_text(mine / name, "my own " + name)
    refused(["fit-image", man, "--out", mine, "--overwrite"], capsys, work,
            "not made by difstar")


def test_fit_image_never_replaces_the_folder_of_its_data(work, capsys):
    """The data file the manifest names is an input too (was: only the manifest), even
    inside a folder that carries difstar's marker."""
    d = work / "d"
    d.mkdir()
    man = _star_manifest(work, data_path="d/star.npy")
    write_text(d / MARKER, json.dumps({"difstar": "output", "files": ["star.npy"]}))
    refused(["fit-image", man, "--out", d, "--overwrite"], capsys, work, "input", "star.npy")


# entries a user may have made whose names look like difstar's temporaries
LOOK_ALIKES = [
    (".ex.json.difstar-old-999999999-abcd", "dir"),
    (".ex.json.difstar-tmp-999999999-abcd", "file"),
    (".out.difstar-tmp-999999999-abcd", "dir+marker"),  # an old-style name, no token
    (".out.difstar-tmp-0123456789abcdef", "dir+marker"),  # a token the marker lacks
    (".out.difstar-tmp-fedcba9876543210", "dir+marker+token+otherhost"),
]


def _make_look_alike(work: Path, name: str, kind: str) -> None:
    p = work / name
    if kind == "file":
        write_text(p, "a user's file")
        return
    p.mkdir()
    write_text(p / "notes.txt", "a user's notes")
    if "marker" in kind:
        doc = {"difstar": "output", "files": []}
        if "token" in kind:
            doc.update(token=name[-16:], host="another-host-" + os.urandom(4).hex())
        write_text(p / MARKER, json.dumps(doc))


def test_clean_up_never_touches_a_look_alike_entry(work, capsys):
    """The clean-up beside every destination (was: deleted or moved a user's entry named
    like a temporary whose 'PID' was not running)."""
    for name, kind in LOOK_ALIKES:
        _make_look_alike(work, name, kind)
    before = snapshot(work)
    code, err = run(["example", "paper-focused", "--out", work / "ex.json"], capsys)
    assert code == 0, err
    after = snapshot(work)
    assert after.pop("ex.json")
    assert after == before


def test_clean_up_leaves_a_live_run_alone(work):
    """A temporary folder whose run holds its lock (a run in another container sharing
    the folder, or a PID reused) is live: never removed."""
    from difstar.io import _output

    tmp = work / ".out.difstar-tmp-00112233445566aa"
    tmp.mkdir()
    _output._write_marker(tmp, [], "test", "00112233445566aa")
    lock = _output._lock(tmp)
    assert lock is not None
    try:
        assert _output.remove_stale(work) == [] and tmp.exists()
    finally:
        lock.close()
    assert _output.remove_stale(work) == [tmp] and not tmp.exists()


def test_clean_up_skips_a_folder_committed_while_it_looked(work, monkeypatch):
    """A live run's temporary folder renamed into place between the clean-up reading
    its marker and taking its lock (was: FileNotFoundError in a run beside it, seen
    with eight concurrent writers on a loaded machine): left alone, no error."""
    import shutil as sh

    from difstar.io import _output

    tmp = work / ".out.difstar-tmp-00112233445566bb"
    tmp.mkdir()
    _output._write_marker(tmp, [], "test", "00112233445566bb")
    real_read = _output.read_marker

    def read_then_commit(folder):
        doc = real_read(folder)
        if Path(folder) == tmp:
            sh.move(tmp, work / "out")  # the run commits at this moment
        return doc

    monkeypatch.setattr(_output, "read_marker", read_then_commit)
    assert _output.remove_stale(work) == []
    assert (work / "out" / _output.MARKER).exists()


def test_run_killed_between_the_renames_puts_the_old_result_back(work):
    """--overwrite moves the old result into the new temporary folder; a run killed
    there leaves it, and the next run beside it puts it back in place."""
    from difstar.io import _output

    old = work / "out"
    with _output.output_dir(old, command="test") as tmp:
        write_text(tmp / "a.txt", "old result")
    token = "a1b2c3d4e5f60718"
    tmp = work / f".out.difstar-tmp-{token}"
    tmp.mkdir()
    _output._write_marker(tmp, [], "test", token)
    write_text(tmp / "a.txt", "new result, half written")
    os.replace(old, tmp / _output.DISPLACED)  # the kill came here
    assert not old.exists()
    assert _output.remove_stale(work) == [tmp]
    assert (old / "a.txt").read_text() == "old result" and not tmp.exists()


def test_synth_overwrite_never_replaces_a_camera_raw(work, capsys):
    """A real camera's DNG under a capture's name, in a folder with no marker (was:
    replaced). Only DNGs difstar wrote (TIFF Software tag) may be."""
    import shutil as sh

    from difstar._fit_run import synth_replaceable
    from difstar.io._manifest import load_manifest

    man = base_manifest(work)
    p = write_text(work / "m.json", json.dumps(man))
    caps = work / "caps"
    caps.mkdir()
    real = REPO.parent / "shared" / "data" / "raw" / "camera_raw" / "Blackmagic.dng"
    sh.copyfile(real, caps / Path(man["captures"][0]["file"]).name)
    refused(["synth", p, "--out", caps, "--overwrite"], capsys, work, "did not write",
            Path(man["captures"][0]["file"]).name)
    # the committed synthetic captures are difstar's own DNGs: replaceable
    ok = synth_replaceable(load_manifest(CAMPAIGN / "manifest.json"))
    assert all(ok(f) for f in (CAMPAIGN / "captures").iterdir())
    assert not ok(caps / Path(man["captures"][0]["file"]).name)


def test_full_disk_is_refused_up_front_and_named_while_writing(work, capsys, monkeypatch):
    import errno as err_no
    import shutil as sh

    import difstar.io._image_files as image_files
    import difstar.io._output as output

    scene = write_text(work / "s.json", json.dumps(small_doc()))
    usage = sh.disk_usage(work)
    monkeypatch.setattr(output.shutil, "disk_usage",
                        lambda p: type(usage)(usage.total, usage.total - 1000, 1000))
    refused(["predict", scene, "--out", work / "out"], capsys, work, "--out", "free")
    monkeypatch.undo()
    monkeypatch.chdir(work)

    def full(*args, **kwargs):
        raise OSError(err_no.ENOSPC, "No space left on device")

    monkeypatch.setattr(image_files, "write_raw_dng", full)
    err = refused(["predict", scene, "--out", work / "out"], capsys, work,
                  "No space left on device", str(work / "out"), "nothing was written")
    assert len([ln for ln in err.splitlines() if "error" in ln]) == 1  # one line, no trace


# ------------------------------------------------------------------- fit / synth


def base_manifest(folder: Path, **synthetic) -> dict:
    doc = json.loads((CAMPAIGN / "manifest.json").read_text())
    for c in doc["captures"]:
        c["file"] = str(CAMPAIGN / c["file"])
    doc["solver"] = {"max_steps": 1}
    doc["synthetic"].update(synthetic)
    return doc


def test_fit_refuses_what_predict_refuses(work, capsys):
    man = base_manifest(work)
    m = copy.deepcopy(man)
    m["configurations"][0]["object_distance"] = 0.03
    p = write_text(work / "m.json", json.dumps(m))
    refused(["fit", p], capsys, work, "configurations/0/object_distance", "too close")
    m = copy.deepcopy(man)
    for v in m["parameters"].values():
        v.pop("free", None)
        v.pop("bounds", None)
    p = write_text(work / "m.json", json.dumps(m))
    refused(["fit", p], capsys, work, "field parameters", "no parameter is free")
    # a Δz bound past the exit pupil (0.059 m from the sensor here): predict refuses
    # such a lens.defocus, and the fit would have searched cameras that cannot be
    m = copy.deepcopy(man)
    m["parameters"]["defocus/defocused"]["bounds"] = [0.003, 0.2]
    p = write_text(work / "m.json", json.dumps(m))
    refused(["fit", p], capsys, work, "parameters/defocus/defocused/bounds/1", "exit pupil")
    m = copy.deepcopy(man)
    m["captures"][2]["exposure_time"] = "__NaN__"
    p = write_text(work / "m.json", json.dumps(m).replace('"__NaN__"', "NaN"))
    refused(["fit", p], capsys, work, "captures/2/exposure_time", "finite")
    p = write_text(work / "m.json", json.dumps(man))
    refused(["fit", p, "--max-steps", -5], capsys, work, "--max-steps")
    refused(["fit", p, "--max-steps", 0], capsys, work, "--max-steps")
    refused(["fit", p, "--recovery-study", -1], capsys, work, "--recovery-study")
    refused(["fit", p, "--out", p], capsys, work, "input")
    f = write_text(work / "afile", "x")
    refused(["fit", p, "--out", f], capsys, work, "is a file")
    refused(["fit", p, "--out", work, "--overwrite"], capsys, work, "current folder")


def test_fit_refuses_unbounded_capture_lists(work, capsys):
    """2000 captures (was: no answer after minutes), 17 configurations: refused by the
    schema before any capture is read."""
    man = base_manifest(work)
    man["captures"] = [dict(man["captures"][i % 10], name=f"c{i}") for i in range(2000)]
    p = write_text(work / "m.json", json.dumps(man))
    refused(["fit", p], capsys, work, "field captures", "at most 64")


def test_fit_checks_the_captures(work, capsys):
    # a capture of the wrong size (the DNGs are 192 × 192)
    p = write_text(work / "m.json", json.dumps(base_manifest(work, frame_size=[256, 256])))
    refused(["fit", p], capsys, work, "frame_size", "192 × 192")
    # a source far outside the frame (was an int32 overflow)
    man = base_manifest(work)
    del man["synthetic"]
    man["captures"][0]["source_position"] = [900000.0, -900000.0]
    p = write_text(work / "m.json", json.dumps(man))
    refused(["fit", p], capsys, work, "source_position", "outside")
    # a capture that is a folder, one that is missing
    man = base_manifest(work)
    (work / "cap.dng").mkdir()
    man["captures"][0]["file"] = "cap.dng"
    p = write_text(work / "m.json", json.dumps(man))
    refused(["fit", p], capsys, work, "captures/focused_t0p03906s/file", "folder")


def test_synth_never_deletes_the_manifest(work, capsys):
    """The manifest inside its captures folder (was: deleted with --overwrite)."""
    man = base_manifest(work)
    for c in man["captures"]:
        c["file"] = Path(c["file"]).name  # captures beside the manifest
    (work / "camp").mkdir()
    p = write_text(work / "camp" / "manifest.json", json.dumps(man))
    refused(["synth", p, "--overwrite"], capsys, work, "input")
    (work / "caps").mkdir()
    write_text(work / "caps" / "notes.txt", "mine")
    refused(["synth", p, "--out", work / "caps", "--overwrite"], capsys, work, "notes.txt")
    # a folder holding the captures synth writes, and another file
    for c in man["captures"]:
        write_text(work / "caps" / c["file"], "old capture")
    refused(["synth", p, "--out", work / "caps", "--overwrite"], capsys, work,
            "holds files difstar did not write")


def test_design_arguments(work, capsys):
    for args, field in ((["--f-number", -1], "--f-number"), (["--f-number", 0], "--f-number"),
                        (["--f-number", "nan"], "--f-number"), (["--steps", 0], "--steps"),
                        (["--blades", 100000], "--blades"), (["--blades", 2], "--blades"),
                        (["--max-curvature", "inf"], "--max-curvature")):
        refused(["design", "--out", work / "o", *args], capsys, work, field)
    # the same checks in the Python API
    from difstar._design_study import iris_study
    from difstar._validate import InputError

    for kw, field in ((dict(f_number=-1.0), "f_number"), (dict(steps=0), "steps"),
                      (dict(blades=1000), "blades"), (dict(max_curvature=math.nan),
                                                      "max_curvature")):
        with pytest.raises(InputError, match=field):
            iris_study(quick=True, **kw)


def test_help_gives_defaults(capsys):
    for cmd in ("predict", "design", "fit"):
        with pytest.raises(SystemExit) as e:
            main([cmd, "--help"])
        assert e.value.code == 0
    out = capsys.readouterr().out
    assert "(default: 8.0)" in out and "(default: 9)" in out and "default: 0" in out
    assert "default: 60, or 12" in out and "(default: None)" not in out


# ------------------------------------------------------------------- the Python API


def test_python_api_validation():
    import difstar
    from difstar._sampling import choose_grid, fast_length
    from difstar._validate import InputError

    camera, scene = difstar.paper_camera("focused")
    bad = difstar.Camera(camera.lens, difstar.Sensor(pixel_pitch=3.917e-6,
                                                     phi0=(0.1, float("nan"), 0.1)))
    with pytest.raises(InputError, match=r"camera\.sensor\.phi0\[1\]"):
        choose_grid(bad, scene, crop=(16, 16))
    obs = difstar.Obstructed(camera.lens.pupil, difstar.Circle(0.01), None)
    lens = difstar.Lens(obs, focal_length=51.5e-3, focus_distance=1.0)
    with pytest.raises(InputError, match="obstruction"):
        choose_grid(difstar.Camera(lens, camera.sensor), scene, crop=(16, 16))
    with pytest.raises(InputError, match="smallest crop is 8 8"):
        choose_grid(camera, scene, crop=(2, 2))
    with pytest.raises(ValueError, match="crop of at most"):
        choose_grid(camera, scene, crop=(100000, 100000))
    t0 = time.perf_counter()
    with pytest.raises(ValueError, match="accuracy"):
        choose_grid(camera, scene, crop=(64, 64), accuracy=1e-12)
    assert time.perf_counter() - t0 < 10
    t0 = time.perf_counter()
    assert fast_length(10**15 + 1) >= 10**15 + 1
    assert time.perf_counter() - t0 < 1
    far = difstar.Scene(object_distance=1.0, exposure_time=1.0,
                        sources=(difstar.DiscSource(1e-3, (1e5, 0.0)),))
    with pytest.raises(ValueError, match="memory"):
        choose_grid(camera, far, crop=(16, 16))
    # an empty wavelength list: was min()'s "arg is an empty sequence"
    with pytest.raises(InputError, match="wavelength is empty"):
        difstar.psf(camera.lens.pupil, wavelength=[], z_image=0.05, pixel_pitch=3.9e-6,
                    shape=(16, 16))
    # Δz past the exit pupil through the Python API's camera, as the CLI's scene
    lens = difstar.Lens(camera.lens.pupil, focal_length=51.5e-3, focus_distance=1.0,
                        defocus=0.2)
    with pytest.raises(InputError, match=r"camera\.lens\.defocus = 0\.2 m"):
        choose_grid(difstar.Camera(lens, camera.sensor), scene, crop=(16, 16))


def test_psf_bad_inputs():
    """difstar.psf refuses NaN / 0 / negative / infinite scalars naming the field (was: an
    all-NaN array, ZeroDivisionError, or "Use oversample >= 0"). Needs difstar.psf to
    call difstar._validate.check_psf_inputs (the PSF owner wires it)."""
    import difstar

    pupil = difstar.RegularPolygon(7, 51.5e-3 / 44, 0.0)
    good = dict(wavelength=530e-9, z_image=51.5e-3, pixel_pitch=3.917e-6, shape=(32, 32))
    for field in ("wavelength", "z_image", "pixel_pitch"):
        for v in (float("nan"), 0.0, -1e-6, float("inf")):
            with pytest.raises(ValueError, match=field) as e:
                difstar.psf(pupil, **{**good, field: v})
            assert "oversample >= 0" not in str(e.value)
    with pytest.raises(ValueError, match="defocus"):
        difstar.psf(pupil, **good, defocus=float("nan"))
    with pytest.raises(ValueError, match="rotation|finite|NaN"):
        difstar.psf(difstar.RegularPolygon(7, 51.5e-3 / 44, float("nan")), **good)


def test_validators_pass_tracers_and_refuse_traced_nan():
    import jax
    import jax.numpy as jnp

    from difstar._validate import check_psf_inputs, refuse_nonfinite_traced

    @jax.jit
    def f(w):
        check_psf_inputs(wavelength=w, z_image=0.05, pixel_pitch=4e-6)  # traced: passes
        return refuse_nonfinite_traced(w, "wavelength") * 2

    assert float(f(1.0)) == 2.0
    with pytest.raises(Exception, match="wavelength is NaN or infinite"):
        jax.block_until_ready(f(jnp.nan))
    with pytest.raises(Exception, match="wavelength is NaN or infinite"):
        refuse_nonfinite_traced(jnp.asarray([1.0, jnp.inf]), "wavelength")


# --------------------------------------------------------------- signals, killed runs


def _start_predict(work: Path, out: Path) -> subprocess.Popen:
    scene = write_text(work / "s.json", json.dumps(small_doc("defocused", (64, 64))))
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    return subprocess.Popen([sys.executable, "-m", "difstar.cli", "predict", str(scene),
                             "--out", str(out)], cwd=work, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def _wait_for_tmp(work: Path, proc, timeout=120.0) -> Path:
    t0 = time.time()
    while time.time() - t0 < timeout:
        # the folder with its marker: a folder killed before its marker is written is
        # (rightly) not difstar's to remove, so the kill must come after it
        tmps = [p for p in work.iterdir()
                if ".difstar-tmp-" in p.name and (p / MARKER).is_file()]
        if tmps:
            return tmps[0]
        if proc.poll() is not None:
            raise AssertionError(proc.communicate()[1].decode())
        time.sleep(0.05)
    proc.kill()
    proc.communicate()
    raise AssertionError("no temporary folder appeared")


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_interrupted_run_leaves_nothing(work, sig):
    out = work / "out"
    proc = _start_predict(work, out)
    _wait_for_tmp(work, proc)
    proc.send_signal(sig)
    try:
        _, err = proc.communicate(timeout=120)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise
    assert proc.returncode in (128 + sig, 130, -sig), err.decode()
    assert b"Traceback" not in err
    assert sorted(p.name for p in work.iterdir()) == ["s.json"]


def test_killed_run_is_cleaned_next_time(work, capsys):
    out = work / "out"
    proc = _start_predict(work, out)
    tmp = _wait_for_tmp(work, proc)
    proc.kill()
    proc.communicate()
    assert tmp.exists()  # SIGKILL cannot be caught...
    code, err = run(["example", "paper-focused", "--out", work / "ex.json"], capsys)
    assert code == 0, err
    assert not tmp.exists()  # ...but the next run beside it removes what it left
    assert sorted(p.name for p in work.iterdir()) == ["ex.json", "s.json"]


# ------------------------------------------------------------- property-based tests


def numeric_leaves(doc, path=()):
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield from numeric_leaves(v, (*path, k))
    elif isinstance(doc, list):
        for i, v in enumerate(doc):
            yield from numeric_leaves(v, (*path, i))
    elif isinstance(doc, (int, float)) and not isinstance(doc, bool):
        yield path


SCENE_DOC = small_doc()
SCENE_DOC["scene"]["sources"][0]["position"] = [1e-4, -1e-4]
SCENE_DOC["grid"]["padding"] = 1.0
SCENE_LEAVES = list(numeric_leaves(SCENE_DOC))
SCENE_POSITIVE = [p for p in SCENE_LEAVES if p[:3] != ("camera", "sensor", "colour_matrix")
                  and p[-1] not in ("rotation", "principal_separation")
                  and "position" not in p and p[0] != "grid"
                  and not any(k in p for k in ("toe", "background", "radiance"))]
SCENE_NONNEG = [p for p in SCENE_LEAVES if any(k in p for k in ("toe", "background",
                                                                    "radiance"))]
NONFINITE = st.sampled_from([math.nan, math.inf, -math.inf])
PROP = settings(max_examples=40, deadline=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture])


def _path(p) -> str:
    return "/".join(map(str, p))


def _scene_error(doc) -> str:
    from difstar.io._scene import scene_from_dict

    with pytest.raises(SceneError) as e:
        scene_from_dict(doc, source="s.json")
    return str(e.value)


@PROP
@given(path=st.sampled_from(SCENE_LEAVES), value=NONFINITE, via_json=st.booleans())
def test_scene_nonfinite_anywhere_is_refused(tmp_path, path, value, via_json):
    doc = doc_with(path, value, SCENE_DOC)
    if via_json:  # Python's json writes and reads NaN/Infinity: the loader must not
        from difstar.io._scene import load_scene

        p = write_text(tmp_path / "s.json", json.dumps(doc))
        with pytest.raises(SceneError) as e:
            load_scene(p)
        msg = str(e.value)
    else:
        msg = _scene_error(doc)
    assert f"field {_path(path)}:" in msg and "finite" in msg


@PROP
@given(path=st.sampled_from(SCENE_POSITIVE),
       value=st.floats(max_value=0.0, allow_nan=False, allow_infinity=False))
def test_scene_nonpositive_is_refused(path, value):
    msg = _scene_error(doc_with(path, value, SCENE_DOC))
    assert _path(path) in msg


@PROP
@given(path=st.sampled_from(SCENE_NONNEG),
       value=st.floats(max_value=-1e-300, allow_nan=False, allow_infinity=False))
def test_scene_negative_is_refused(path, value):
    msg = _scene_error(doc_with(path, value, SCENE_DOC))
    assert _path(path) in msg


JUNK = st.one_of(st.none(), st.booleans(), st.integers(), st.text(max_size=4),
                 st.floats(allow_nan=True, allow_infinity=True),
                 st.lists(st.floats(-1e3, 1e3), max_size=4),
                 st.dictionaries(st.text(max_size=3), st.integers(), max_size=2))


@PROP
@given(path=st.sampled_from(SCENE_LEAVES), value=JUNK)
def test_scene_junk_never_escapes_as_another_error(path, value):
    from difstar.io._scene import scene_from_dict

    try:
        scene_from_dict(doc_with(path, value, SCENE_DOC), source="s.json")
    except SceneError as exc:
        assert "s.json" in str(exc)


MANIFEST = json.loads((CAMPAIGN / "manifest.json").read_text())
MANIFEST_LEAVES = list(numeric_leaves(MANIFEST))
MANIFEST_POSITIVE = [
    ("camera", "focal_length"), ("camera", "pixel_pitch"), ("camera", "wavelengths", 1),
    ("camera", "white_balance", 0), ("camera", "pupil_magnification"),
    ("noise", "gain_e_per_dn"), ("configurations", 0, "focus_distance"),
    ("configurations", 1, "object_distance"), ("captures", 3, "exposure_time"),
    ("parameters", "circumradius", "start"), ("parameters", "source_radius", "start"),
    ("synthetic", "truth", "circumradius"),
]


def _manifest_error(doc) -> str:
    from difstar.io._manifest import manifest_from_dict

    with pytest.raises(SceneError) as e:
        manifest_from_dict(doc, path=CAMPAIGN / "manifest.json")
    return str(e.value)


@PROP
@given(path=st.sampled_from(MANIFEST_LEAVES), value=NONFINITE)
def test_manifest_nonfinite_anywhere_is_refused(path, value):
    msg = _manifest_error(doc_with(path, value, MANIFEST))
    assert f"field {_path(path)}:" in msg and "finite" in msg


@PROP
@given(path=st.sampled_from(MANIFEST_POSITIVE),
       value=st.floats(max_value=0.0, allow_nan=False, allow_infinity=False))
def test_manifest_nonpositive_is_refused(path, value):
    msg = _manifest_error(doc_with(path, value, MANIFEST))
    assert _path(path).rsplit("/", 1)[0] in msg


@PROP
@given(path=st.sampled_from(MANIFEST_LEAVES), value=JUNK)
def test_manifest_junk_never_escapes_as_another_error(path, value):
    from difstar.io._manifest import manifest_from_dict

    try:
        manifest_from_dict(doc_with(path, value, MANIFEST), path=CAMPAIGN / "manifest.json")
    except SceneError as exc:
        assert "manifest.json" in str(exc)


def test_validate_module_units():
    from difstar._validate import InputError, check_number, check_polygon_vertices
    from difstar.io._json import json_depth, loads_strict

    with pytest.raises(InputError, match=r"field a/1: Infinity"):
        loads_strict('{"a": [1, Infinity]}', source="x")
    with pytest.raises(InputError, match="nested"):
        loads_strict("[" * 10000 + "]" * 10000, source="x")
    assert json_depth({"a": [[1]]}) == 3
    with pytest.raises(InputError, match=r"f: nan is not a finite number; give a finite "
                                         r"number > 0"):
        check_number(float("nan"), "f", gt=0)
    with pytest.raises(InputError, match="self-intersecting"):
        check_polygon_vertices([[0, 0], [1, 1], [1, 0], [0, 1]])
    assert check_polygon_vertices(np.array([[0, 0], [1, 0], [0, 1]])).shape == (3, 2)


@pytest.mark.parametrize("overwrite", [False, True])
def test_concurrent_writers_leave_one_whole_folder(tmp_path, overwrite):
    """Eight writers on one destination at once: one whole result (every file from the
    same writer), the others refused (or, with overwrite, replaced whole), nothing else
    left beside it."""
    import threading

    from difstar.io._output import OutputExistsError, output_dir

    dest = tmp_path / "out"
    errors, done = [], []
    start = threading.Barrier(8)

    def writer(i):
        try:
            start.wait()
            with output_dir(dest, overwrite=overwrite, command="test") as tmp:
                for k in range(5):
                    (tmp / f"f{k}.txt").write_text(str(i))
                    time.sleep(0.002)
            done.append(i)
        except OutputExistsError as e:
            errors.append(e)

    threads = [threading.Thread(target=writer, args=(i,)) for i in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(done) + len(errors) == 8 and done
    if not overwrite:
        assert len(done) == 1
    ids = {(dest / f"f{k}.txt").read_text() for k in range(5)}
    assert len(ids) == 1 and int(ids.pop()) in done
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    assert sorted(p.name for p in dest.iterdir()) == [MARKER] + [f"f{k}.txt" for k in range(5)]
