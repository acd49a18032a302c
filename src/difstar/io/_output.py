"""Writing results whole or not at all, and never over anything that is not difstar's.

The output policy (README, "The command line"):

- difstar writes a result folder only where it creates it. :func:`output_dir` makes a
  temporary folder beside the destination (``.NAME.difstar-tmp-PID-XXXX``, holding the
  marker file :data:`MARKER`), the command writes into it, and only when everything is
  written is it renamed into place; on any error, Ctrl-C or SIGTERM it is removed and
  nothing appears. Temporary folders left by a killed run (its process gone) are removed
  the next time difstar writes beside them.
- An existing folder is replaced only with ``--overwrite``, and only when difstar made
  it: it holds the marker, and every file in it is one the marker lists (``difstar
  synth`` may also replace a folder holding exactly the captures it writes). A folder
  with any other file, a file, the current folder, or a folder holding one of the
  command's inputs is never replaced.
- :func:`check_output_free` checks all of this, and that the destination is writable,
  before any computation.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import secrets
import shutil
import signal
import sys
import tempfile
import threading
import time
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from .._validate import InputError

#: the file that marks a folder as difstar's own output (JSON: the files it wrote)
MARKER = ".difstar-output"
_STALE = re.compile(r"^\.(?P<name>.+)\.difstar-(?P<kind>tmp|old)-(?P<pid>\d+)-[A-Za-z0-9_-]+$")


class OutputError(InputError):
    """The destination cannot be written, or must not be (names the path and the fix)."""


class OutputExistsError(OutputError, FileExistsError):
    """The destination exists and may not be replaced."""


class Terminated(SystemExit):
    """Raised in the main thread on SIGTERM / SIGHUP while difstar writes, so that the
    temporary folder is removed (exit status 128 + signal number)."""


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    except OSError:
        return False
    return True


def read_marker(folder: Path) -> dict | None:
    """The marker of a folder difstar made, or None."""
    p = Path(folder) / MARKER
    try:
        doc = json.loads(p.read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(doc, dict) or doc.get("difstar") != "output":
        return None
    return doc


def _write_marker(folder: Path, files: list[str], command: str) -> None:
    doc = {"difstar": "output", "version": 1, "command": command, "pid": os.getpid(),
           "written": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "files": sorted(files)}
    (Path(folder) / MARKER).write_text(json.dumps(doc, indent=1) + "\n")


def remove_stale(parent: str | Path) -> list[Path]:
    """Remove the temporary folders that killed difstar runs left in ``parent`` (only
    those named by difstar whose process is gone; a temporary folder must also hold the
    marker). A displaced old result whose replacement never arrived is put back.
    Returns what was removed or restored."""
    parent = Path(parent)
    done = []
    try:
        entries = list(parent.iterdir())
    except OSError:
        return done
    for e in entries:
        m = _STALE.match(e.name)
        if not m or e.is_symlink() or _pid_alive(int(m["pid"])):
            continue
        if m["kind"] == "tmp" and e.is_file():  # write_file_atomic's temporary file
            with contextlib.suppress(OSError):
                e.unlink()
            done.append(e)
            continue
        if not e.is_dir():
            continue
        if m["kind"] == "tmp":
            if read_marker(e) is None:
                continue
            shutil.rmtree(e, ignore_errors=True)
        else:
            dest = parent / m["name"]
            if not dest.exists() and not dest.is_symlink():
                os.replace(e, dest)
            else:
                shutil.rmtree(e, ignore_errors=True)
        done.append(e)
    return done


def _first_existing(p: Path) -> Path:
    while not p.exists() and not p.is_symlink() and p != p.parent:
        p = p.parent
    return p


def _probe_writable(folder: Path, dest: Path, what: str) -> None:
    try:
        probe = tempfile.mkdtemp(prefix=".difstar-probe-", dir=folder)
    except OSError as exc:
        raise OutputError(
            f"{what} {dest}: cannot write in {folder} ({exc.strerror or exc}); choose an "
            "--out in a folder you can write to."
        ) from None
    os.rmdir(probe)


def check_output_free(dest: str | Path, *, overwrite: bool = False, inputs: Iterable = (),
                      will_write: Iterable[str] | None = None, what: str = "--out") -> None:
    """Raise :class:`OutputError` (before any work) unless ``dest`` may be written by
    the policy above. ``inputs``: the command's input files (never replaced, never
    inside the destination). ``will_write``: names the command writes, which an
    existing folder may hold in place of a marker."""
    dest = Path(os.path.abspath(dest))
    real = dest.resolve()
    cwd = Path.cwd().resolve()
    if real == cwd or real in cwd.parents:
        raise OutputError(
            f"{what} {dest} is the current folder (or holds it); give a new folder name, "
            "e.g. --out out/result."
        )
    for inp in inputs:
        if inp is None:
            continue
        ri = Path(inp).resolve()
        if ri == real or real in ri.parents:
            raise OutputError(
                f"{what} {dest} is an input of this command or holds one ({inp}); difstar "
                "never replaces its inputs: choose another --out."
            )
    anc = _first_existing(dest.parent)
    if not anc.is_dir():
        raise OutputError(
            f"{what} {dest}: {anc} is a file, not a folder; choose an --out whose parent "
            "is a folder."
        )
    if dest.is_symlink():
        raise OutputError(f"{what} {dest} is a symbolic link; give a new folder name.")
    if dest.exists():
        if not dest.is_dir():
            raise OutputExistsError(
                f"{what} {dest} is a file; difstar writes a folder and never replaces a "
                "file: choose another --out."
            )
        try:
            entries = {e.name for e in dest.iterdir()}
        except OSError as exc:
            raise OutputError(f"{what} {dest}: cannot read it ({exc.strerror}).") from None
        if entries:
            if not overwrite:
                raise OutputExistsError(
                    f"output {dest} already exists and is not empty; choose another --out, "
                    "or pass --overwrite to replace a folder difstar made."
                )
            marker = read_marker(dest)
            allowed = set(marker.get("files", [])) if marker else set()
            ww = set(will_write or ())
            if marker is None and not ww:
                raise OutputExistsError(
                    f"{what} {dest} was not made by difstar (it has no {MARKER} marker); "
                    "--overwrite replaces only a folder difstar made: choose another --out "
                    "or empty it yourself."
                )
            extra = sorted(entries - allowed - ww - {MARKER})
            if extra:
                shown = ", ".join(extra[:3]) + (f" and {len(extra) - 3} more" if len(extra) > 3
                                                else "")
                raise OutputExistsError(
                    f"{what} {dest} holds files difstar did not write ({shown}); "
                    "--overwrite never replaces a folder holding other files: move them "
                    "away or choose another --out."
                )
    _probe_writable(anc, dest, what)


def _make_parents(folder: Path) -> list[Path]:
    """mkdir -p, returning the folders it created (outermost first)."""
    made = []
    p = folder
    while not p.exists():
        made.append(p)
        p = p.parent
    made.reverse()
    for d in made:
        d.mkdir()
    return made


#: The last termination signal received while writing (its exit code), or 0. A handler's
#: exception can be swallowed (raised inside a garbage-collection callback, Python only
#: prints it), so the commit step checks this too.
_TERMINATED = [0]


def _check_terminated() -> None:
    if _TERMINATED[0]:
        raise Terminated(_TERMINATED[0])


@contextlib.contextmanager
def _signals_raise():
    """While writing: SIGTERM and SIGHUP raise :class:`Terminated` in the main thread
    (Ctrl-C already raises KeyboardInterrupt), so clean-up code runs."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        _TERMINATED[0] = 128 + signum
        if signum == signal.SIGINT:
            raise KeyboardInterrupt
        raise Terminated(128 + signum)

    _TERMINATED[0] = 0
    # a signal's exception raised inside a callback Python cannot propagate from (a
    # garbage-collection callback) is recorded above and acted on at the commit step:
    # not printed as an "Exception ignored" traceback
    old_hook = sys.unraisablehook

    def hook(unraisable):
        if not isinstance(unraisable.exc_value, (Terminated, KeyboardInterrupt)):
            old_hook(unraisable)

    sys.unraisablehook = hook
    old = {}
    for s in (signal.SIGTERM, signal.SIGINT, getattr(signal, "SIGHUP", None)):
        if s is None:
            continue
        try:
            old[s] = signal.signal(s, handler)
        except (ValueError, OSError):
            pass
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)
        sys.unraisablehook = old_hook


@contextlib.contextmanager
def output_dir(dest: str | Path, *, overwrite: bool = False, inputs: Iterable = (),
               will_write: Iterable[str] | None = None, command: str = "difstar",
               what: str = "--out"):
    """Yield a fresh temporary folder beside ``dest``; rename it into place when the block
    ends without error (with the marker listing the files), remove it otherwise.

    Enter it before the computation: the destination is checked (and stale temporary
    folders beside it removed) at once, and a refused or failed run leaves nothing."""
    inputs = list(inputs)
    will_write = None if will_write is None else list(will_write)
    dest = Path(os.path.abspath(dest))
    check_output_free(dest, overwrite=overwrite, inputs=inputs, will_write=will_write,
                      what=what)
    with _signals_raise():
        made = []
        tmp = None
        try:
            made = _make_parents(dest.parent)
            remove_stale(dest.parent)
            try:
                tmp = Path(tempfile.mkdtemp(
                    prefix=f".{dest.name}.difstar-tmp-{os.getpid()}-", dir=dest.parent))
            except OSError as exc:
                raise OutputError(f"{what} {dest}: cannot write there ({exc.strerror}).") \
                    from None
            _write_marker(tmp, [], command)
            umask = os.umask(0)
            os.umask(umask)
            os.chmod(tmp, 0o777 & ~umask)  # mkdtemp makes it private; results are shared
            yield tmp
            _check_terminated()
            files = [e.name for e in tmp.iterdir() if e.name != MARKER]
            _write_marker(tmp, files, command)
            # the destination may have changed while we computed: check again
            check_output_free(dest, overwrite=overwrite, inputs=inputs,
                              will_write=will_write, what=what)
            _check_terminated()
            if dest.exists():
                old = dest.parent / f".{dest.name}.difstar-old-{os.getpid()}-{secrets.token_hex(4)}"
                os.replace(dest, old)
                try:
                    os.replace(tmp, dest)
                except BaseException:
                    os.replace(old, dest)
                    raise
                shutil.rmtree(old, ignore_errors=True)
            else:
                os.replace(tmp, dest)
            tmp = None
        except BaseException:
            if tmp is not None:
                shutil.rmtree(tmp, ignore_errors=True)
            for d in reversed(made):
                with contextlib.suppress(OSError):
                    d.rmdir()
            raise


def write_file_atomic(path: str | Path, data: str | bytes, *, overwrite: bool = False,
                      inputs: Iterable = (), what: str = "--out") -> None:
    """Write one file whole or not at all; its folder must exist; an existing file is
    replaced only with ``overwrite``, a folder or an input never."""
    path = Path(os.path.abspath(path))
    parent = path.parent
    if not parent.exists():
        raise OutputError(
            f"{what} {path}: the folder {parent} does not exist; create it first or "
            "choose another path."
        )
    if not parent.is_dir():
        raise OutputError(f"{what} {path}: {parent} is a file, not a folder.")
    for inp in inputs:
        if inp is not None and Path(inp).resolve() == path.resolve():
            raise OutputError(f"{what} {path} is an input of this command; choose another path.")
    if path.is_dir():
        raise OutputExistsError(f"{what} {path} is a folder; give a file name.")
    if path.exists() and not overwrite:
        raise OutputExistsError(f"{what} {path} exists; pass --overwrite to replace it.")
    remove_stale(parent)
    try:
        fd, name = tempfile.mkstemp(prefix=f".{path.name}.difstar-tmp-{os.getpid()}-",
                                    dir=parent)
    except OSError as exc:
        raise OutputError(f"{what} {path}: cannot write there ({exc.strerror}).") from None
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data.encode() if isinstance(data, str) else data)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(name, 0o666 & ~umask)
        os.replace(name, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(name)
        raise


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
