"""The command line's persistent compilation cache (:mod:`difstar._compilation_cache`):
where it lives, that it can be turned off, and that a run that loads its programs from it
writes the same results as one that compiled them."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import rawpy
from test_cli import _small_doc

from difstar._compilation_cache import ENV, cache_folder, enable_compilation_cache


def test_the_cache_folder_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv(ENV, "off")
    assert cache_folder() is None
    assert enable_compilation_cache() is None
    monkeypatch.setenv(ENV, str(tmp_path / "c"))
    assert cache_folder() == tmp_path / "c"
    monkeypatch.delenv(ENV)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert cache_folder() == tmp_path / "xdg" / "difstar" / "jax"


def test_a_folder_that_cannot_be_made_leaves_the_cache_off(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    assert enable_compilation_cache(blocker / "jax") is None


@pytest.mark.xdist_group("subprocess")
def test_a_run_from_the_cache_writes_what_a_compiling_run_writes(tmp_path):
    """``difstar predict`` three times in fresh processes: with the cache off, into an
    empty cache (which it fills), and from that cache: the RAW mosaics are identical."""
    scene = tmp_path / "scene.json"
    scene.write_text(json.dumps(_small_doc()))
    cache = tmp_path / "cache"
    raws = []
    for name, where in (("off", "off"), ("fill", str(cache)), ("load", str(cache))):
        env = dict(os.environ, **{ENV: where})
        out = tmp_path / name
        done = subprocess.run([sys.executable, "-m", "difstar.cli", "predict", str(scene),
                               "--out", str(out)], env=env, capture_output=True, text=True,
                              timeout=600)
        assert done.returncode == 0, done.stderr
        with rawpy.imread(str(out / "raw.dng")) as r:
            raws.append(r.raw_image_visible.copy())
        if name == "fill":
            assert any(Path(cache).iterdir()), "the run stored no compiled program"
    np.testing.assert_array_equal(raws[0], raws[1])
    np.testing.assert_array_equal(raws[1], raws[2])
