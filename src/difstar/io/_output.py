"""Writing results whole or not at all.

``output_dir`` yields a fresh temporary directory beside the destination; when the block
finishes without error it is renamed into place (an atomic rename on one filesystem),
otherwise it is removed and nothing appears at the destination. An existing non-empty
destination is never overwritten unless asked.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np


class OutputExistsError(FileExistsError):
    pass


def check_output_free(dest: str | Path, *, overwrite: bool = False) -> None:
    """Raise OutputExistsError before any work when ``dest`` would be overwritten."""
    dest = Path(dest)
    if dest.exists() and (not dest.is_dir() or any(dest.iterdir())) and not overwrite:
        raise OutputExistsError(
            f"output {dest} already exists and is not empty; choose another --out or "
            "pass --overwrite to replace it."
        )


@contextlib.contextmanager
def output_dir(dest: str | Path, *, overwrite: bool = False):
    dest = Path(dest)
    check_output_free(dest, overwrite=overwrite)
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{dest.name}.", dir=dest.parent))
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o777 & ~umask)  # mkdtemp makes it private; results are for sharing
    try:
        yield tmp
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    if dest.exists():
        old = dest.with_name(f".{dest.name}.old.{os.getpid()}")
        os.replace(dest, old)
        os.replace(tmp, dest)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.replace(tmp, dest)


def write_json(path: str | Path, doc) -> None:
    Path(path).write_text(json.dumps(doc, indent=2, default=_json_default) + "\n")


def _json_default(x):
    if isinstance(x, (np.generic,)):
        return x.item()
    if hasattr(x, "tolist"):
        return np.asarray(x).tolist()
    raise TypeError(f"not JSON serialisable: {type(x).__name__}")


def write_png_srgb(path: str | Path, srgb) -> None:
    """(3, h, w) sRGB in [0, 1] → 8-bit PNG."""
    from PIL import Image

    a = np.clip(np.asarray(srgb, float), 0.0, 1.0)
    a = np.round(np.moveaxis(a, 0, -1) * 255.0).astype(np.uint8)
    Image.fromarray(a, mode="RGB").save(path)


def write_tiff_raw(path: str | Path, cfa, *, pattern: str) -> None:
    """(h, w) ζ in [0, 1] → 16-bit TIFF (0 ↔ black, 65535 ↔ white), the Bayer layout in
    the description tag."""
    import tifffile

    a = np.round(np.clip(np.asarray(cfa, float), 0.0, 1.0) * 65535.0).astype(np.uint16)
    tifffile.imwrite(path, a, description=json.dumps({"cfa_pattern": pattern, "scale": 65535}))
