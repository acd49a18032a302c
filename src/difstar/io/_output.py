"""Writing results whole or not at all, and never over anything that is not difstar's.

The output policy (README, "Where difstar writes"):

- difstar writes a result folder only where it creates it. :func:`output_dir` makes a
  temporary folder beside the destination, ``.NAME.difstar-tmp-TOKEN`` (TOKEN: 16 random
  hex digits), whose marker file :data:`MARKER` records that same token, this host's name
  and the process; the run holds an exclusive lock (``flock``) on that marker while it
  works. The command writes into the folder, and only when everything is written is it
  renamed into place; on any error, Ctrl-C or SIGTERM it is removed and nothing appears.
- A temporary folder left by a killed run is removed the next time difstar writes beside
  it only when *all* of these hold: its name has the pattern above, it holds a marker whose
  token is the one in its name, the marker was written on this host, and no process holds
  its lock. Anything else (a user's entry with a look-alike name, a run on another host or
  in a container sharing the folder, a live run) is left alone. Temporary *files*
  (``example --out``) are never removed by a later run.
- An existing folder is replaced only with ``--overwrite``, and only when difstar made
  it: it holds the marker, and every file in it is one the marker lists. The one
  exception: ``difstar synth`` may replace a folder with no marker whose every entry is a
  capture its manifest names *and* a DNG that difstar wrote (its TIFF ``Software`` tag
  reads ``difstar``); a camera's own RAW file under a capture's name is never replaced.
  A folder with any other file, a file, the current folder, or a folder holding one of
  the command's inputs (every file it reads: manifest, data, σ maps, source images,
  captures) is never replaced.
- The replaced folder is first moved *into* the new temporary folder
  (:data:`DISPLACED`), then the temporary folder is renamed into place, then the old
  result is removed; a run killed between the two renames leaves a temporary folder that
  the next run puts back (the old result returns to its place).
- In a job of several processes (``jax.distributed``; docs/sharding.md) only the writing
  process (:func:`difstar._distributed.writes_output`: process 0) checks and commits the
  destination. The others compute the same results and write them into a temporary
  folder of their own in the system's temporary folder (``tempfile.gettempdir()``,
  named, marked and locked as above), which is removed at the end without being committed:
  they never look at, create or replace the destination, so one result appears.
- :func:`check_output_free` checks all of this, that the destination is writable and
  that the disk has room for what the command expects to write, before any computation.
  A disk that fills up while writing is reported naming the destination; nothing stays.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import re
import secrets
import shutil
import signal
import socket
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from .._distributed import writes_output
from .._validate import InputError

try:  # POSIX; elsewhere no lock can be checked, so no temporary folder is ever removed
    import fcntl
except ImportError:  # pragma: no cover
    fcntl = None

#: the file that marks a folder as difstar's own output (JSON: the files it wrote)
MARKER = ".difstar-output"
#: inside a temporary folder: the result it replaces, until the new one is in place
DISPLACED = ".difstar-displaced"
_TMP = re.compile(r"^\.(?P<name>.+)\.difstar-tmp-(?P<token>[0-9a-f]{16})$")
#: the least free space an output folder needs beyond what the command expects to write
_MIN_FREE = 1 << 20
_DISK_ERRORS = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS}


class OutputError(InputError):
    """The destination cannot be written, or must not be (names the path and the fix)."""


class OutputExistsError(OutputError, FileExistsError):
    """The destination exists and may not be replaced."""


class Terminated(SystemExit):
    """Raised in the main thread on SIGTERM / SIGHUP while difstar writes, so that the
    temporary folder is removed (exit status 128 + signal number)."""


def read_marker(folder: Path) -> dict | None:
    """The marker of a folder difstar made, or None."""
    p = Path(folder) / MARKER
    try:
        if p.is_symlink() or not p.is_file() or p.stat().st_size > 1 << 20:
            return None
        doc = json.loads(p.read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(doc, dict) or doc.get("difstar") != "output":
        return None
    return doc


def _write_marker(folder: Path, files: list[str], command: str, token: str) -> None:
    """Write (or rewrite in place: the same file, so that its lock stays) the marker."""
    doc = {"difstar": "output", "version": 2, "command": command, "token": token,
           "host": socket.gethostname(), "pid": os.getpid(),
           "written": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "files": sorted(files)}
    with open(Path(folder) / MARKER, "r+" if (Path(folder) / MARKER).exists() else "w") as fh:
        fh.seek(0)
        fh.write(json.dumps(doc, indent=1) + "\n")
        fh.truncate()


def _lock(folder: Path):
    """An open file holding an exclusive lock on ``folder``'s marker (None where locks
    are not available); the lock lasts while the file stays open."""
    if fcntl is None:
        return None
    fh = open(Path(folder) / MARKER, "r+")
    try:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        fh.close()
        return None
    return fh


@contextlib.contextmanager
def _folder_lock(folder: Path):
    """An exclusive lock on ``folder`` itself (``flock`` on its descriptor) while a
    destination in it is checked and swapped: concurrent writers (processes on this
    host, or threads) commit one at a time. Where it cannot be taken, nothing is locked."""
    fd = None
    if fcntl is not None:
        try:
            fd = os.open(folder, os.O_RDONLY)
            fcntl.flock(fd, fcntl.LOCK_EX)
        except OSError:
            if fd is not None:
                os.close(fd)
            fd = None
    try:
        yield
    finally:
        if fd is not None:
            os.close(fd)  # closing releases the lock


def _abandoned(entry: Path) -> bool:
    """True only for a temporary folder of a difstar run that is certainly over: named
    like one, holding a marker with the token of its name written on this host, and
    with no process holding the marker's lock."""
    m = _TMP.match(entry.name)
    if not m or entry.is_symlink() or not entry.is_dir():
        return False
    marker = read_marker(entry)
    if marker is None or marker.get("token") != m["token"]:
        return False
    if marker.get("host") != socket.gethostname():
        return False
    try:
        lock = _lock(entry)
    except OSError:  # gone meanwhile (a live run committed or removed it)
        return False
    if lock is None:  # held by a live run, or no locks here: not ours to judge
        return False
    lock.close()
    return True


def remove_stale(parent: str | Path) -> list[Path]:
    """Remove the temporary folders that killed difstar runs left in ``parent`` (only
    those :func:`_abandoned` proves are; see the module's docstring). A replaced result
    whose replacement never arrived is put back in its place. Returns what was removed."""
    parent = Path(parent)
    done = []
    try:
        entries = list(parent.iterdir())
    except OSError:
        return done
    for e in entries:
        if not _abandoned(e):
            continue
        displaced = e / DISPLACED
        dest = parent / _TMP.match(e.name)["name"]
        if displaced.is_dir() and not displaced.is_symlink() and not dest.exists() \
                and not dest.is_symlink():
            with contextlib.suppress(OSError):
                os.replace(displaced, dest)
        if (e / DISPLACED).exists():
            continue  # the old result could not be put back: keep it where it is
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


def _free_bytes(folder: Path) -> int | None:
    try:
        return shutil.disk_usage(folder).free
    except OSError:
        return None


def check_output_free(dest: str | Path, *, overwrite: bool = False, inputs: Iterable = (),
                      replaceable: Callable[[Path], bool] | None = None,
                      expected_bytes: int = 0, what: str = "--out") -> None:
    """Raise :class:`OutputError` (before any work) unless ``dest`` may be written by
    the policy above. ``inputs``: every file the command reads (never replaced, never
    inside the destination). ``replaceable``: for a folder with no marker, a test each
    of its entries must pass for ``--overwrite`` to replace it (``synth``: a DNG difstar
    wrote under a capture's name); without it such a folder is never replaced.
    ``expected_bytes``: about how much the command will write (the disk must have it).
    A process of a multi-process job that does not write (:func:`_writes_output`) checks
    nothing: the destination is the writing process's alone."""
    if not _writes_output():
        return
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
            if marker is not None:
                allowed = {f for f in marker.get("files", []) if isinstance(f, str)}
                extra = sorted(entries - allowed - {MARKER, DISPLACED})
                if extra:
                    raise OutputExistsError(
                        f"{what} {dest} holds files difstar did not write ({_few(extra)}); "
                        "--overwrite never replaces a folder holding other files: move them "
                        "away or choose another --out."
                    )
            elif replaceable is None:
                raise OutputExistsError(
                    f"{what} {dest} was not made by difstar (it has no {MARKER} marker); "
                    "--overwrite replaces only a folder difstar made: choose another --out "
                    "or empty it yourself."
                )
            else:
                foreign = sorted(n for n in entries if not replaceable(dest / n))
                if foreign:
                    raise OutputExistsError(
                        f"{what} {dest} has no {MARKER} marker and holds files difstar did "
                        f"not write ({_few(foreign)}); --overwrite never replaces them: move them "
                        "away or choose another --out."
                    )
    _probe_writable(anc, dest, what)
    free = _free_bytes(anc)
    need = int(expected_bytes) + _MIN_FREE
    if free is not None and free < need:
        raise OutputError(
            f"{what} {dest}: the disk holding {anc} has {_fmt(free)} free and this command "
            f"writes about {_fmt(need)}; free some space or choose an --out on another disk."
        )


def _few(names: list[str]) -> str:
    """The first three names, and how many more."""
    return ", ".join(names[:3]) + (f" and {len(names) - 3} more" if len(names) > 3 else "")


def _fmt(n: int) -> str:
    for unit, size in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= size:
            return f"{n / size:.1f} {unit}"
    return f"{n} bytes"


def _disk_error(exc: OSError, dest: Path, what: str) -> OutputError:
    return OutputError(
        f"{what} {dest}: {exc.strerror or exc} while writing the results; nothing was "
        "written. Free some space (or write access) or choose an --out on another disk."
    )


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


def _writes_output() -> bool:
    """Whether this process writes the outputs: :func:`difstar._distributed.writes_output`
    (process 0 of a multi-process job, or a process alone)."""
    return writes_output()


def _marked_tmp(parent: Path, name: str, command: str):
    """A fresh temporary folder ``parent/.NAME.difstar-tmp-TOKEN`` with its marker and
    the marker's lock (the open file; None where locks are not available)."""
    token = secrets.token_hex(8)
    tmp = parent / f".{name}.difstar-tmp-{token}"
    umask = os.umask(0)
    os.umask(umask)
    os.mkdir(tmp, 0o777 & ~umask)
    lock = None
    try:
        # the lock first, then the marker's content: a run is never seen with a valid
        # marker and a free lock while it lives
        (tmp / MARKER).touch()
        lock = _lock(tmp)
        _write_marker(tmp, [], command, token)
    except BaseException:
        if lock is not None:
            lock.close()
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return tmp, token, lock


@contextlib.contextmanager
def _discarded_dir(dest: Path, command: str, what: str):
    """A non-writing process's folder (see the module's docstring): in the system's
    temporary folder, removed whatever happens; ``dest`` is never touched."""
    parent = Path(tempfile.gettempdir())
    with _signals_raise():
        remove_stale(parent)  # those of this host's killed non-writers
        try:
            tmp, _, lock = _marked_tmp(parent, dest.name, command)
        except OSError as exc:
            raise OutputError(f"{what} {dest}: this process (not the one that writes) "
                              f"cannot make its temporary folder in {parent} "
                              f"({exc.strerror}); set TMPDIR to a writable folder.") from None
        try:
            yield tmp
            _check_terminated()
        except OSError as exc:
            if exc.errno in _DISK_ERRORS:
                raise OutputError(f"{what} {dest}: {exc.strerror} in this process's "
                                  f"temporary folder {parent} (it is not the one that "
                                  "writes); free some space there or set TMPDIR to "
                                  "another folder.") from None
            raise
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
            if lock is not None:
                lock.close()


@contextlib.contextmanager
def output_dir(dest: str | Path, *, overwrite: bool = False, inputs: Iterable = (),
               replaceable: Callable[[Path], bool] | None = None, expected_bytes: int = 0,
               command: str = "difstar", what: str = "--out"):
    """Yield a fresh temporary folder beside ``dest``; rename it into place when the block
    ends without error (with the marker listing the files), remove it otherwise.

    Enter it before the computation: the destination is checked (and abandoned temporary
    folders beside it removed) at once, and a refused or failed run leaves nothing.

    In a process of a multi-process job that does not write (:func:`_writes_output`), the
    folder is one of its own in the system's temporary folder, removed at the end and
    never committed: only the writing process checks and commits ``dest``."""
    if not _writes_output():
        with _discarded_dir(Path(os.path.abspath(dest)), command, what) as tmp:
            yield tmp
        return
    inputs = list(inputs)
    dest = Path(os.path.abspath(dest))
    check = dict(overwrite=overwrite, inputs=inputs, replaceable=replaceable, what=what)
    with _folder_lock(_first_existing(dest.parent)):
        check_output_free(dest, expected_bytes=expected_bytes, **check)
    with _signals_raise():
        made = []
        tmp = None
        lock = None
        try:
            made = _make_parents(dest.parent)
            remove_stale(dest.parent)
            try:
                tmp, token, lock = _marked_tmp(dest.parent, dest.name, command)
            except OSError as exc:
                tmp = None
                raise OutputError(f"{what} {dest}: cannot write there ({exc.strerror}).") \
                    from None
            try:
                yield tmp
            except OSError as exc:
                if exc.errno in _DISK_ERRORS:
                    raise _disk_error(exc, dest, what) from None
                raise
            _check_terminated()
            files = [e.name for e in tmp.iterdir() if e.name != MARKER]
            try:
                _write_marker(tmp, files, command, token)
            except OSError as exc:
                if exc.errno in _DISK_ERRORS:
                    raise _disk_error(exc, dest, what) from None
                raise
            # the destination may have changed while we computed: check again, and swap
            # while no other difstar run commits beside it
            with _folder_lock(dest.parent):
                check_output_free(dest, **check)
                _check_terminated()
                if dest.exists():
                    # the old result moves into our own marked folder first: a run killed
                    # between the two renames leaves it there, and the next run puts it
                    # back
                    os.replace(dest, tmp / DISPLACED)
                    try:
                        os.replace(tmp, dest)
                    except BaseException:
                        os.replace(tmp / DISPLACED, dest)
                        raise
                    tmp = None
                else:
                    os.replace(tmp, dest)
                    tmp = None
            shutil.rmtree(dest / DISPLACED, ignore_errors=True)
        except BaseException:
            if tmp is not None:
                shutil.rmtree(tmp, ignore_errors=True)
            for d in reversed(made):
                with contextlib.suppress(OSError):
                    d.rmdir()
            raise
        finally:
            if lock is not None:
                lock.close()


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
    if path.is_symlink():
        raise OutputError(f"{what} {path} is a symbolic link; give a new file name.")
    if path.is_dir():
        raise OutputExistsError(f"{what} {path} is a folder; give a file name.")
    if path.exists() and not overwrite:
        raise OutputExistsError(f"{what} {path} exists; pass --overwrite to replace it.")
    remove_stale(parent)
    blob = data.encode() if isinstance(data, str) else data
    free = _free_bytes(parent)
    if free is not None and free < len(blob) + _MIN_FREE:
        raise OutputError(f"{what} {path}: the disk has {_fmt(free)} free; free some space "
                          "or choose another path.")
    try:
        fd, name = tempfile.mkstemp(prefix=f".{path.name}.difstar-part-", dir=parent)
    except OSError as exc:
        raise OutputError(f"{what} {path}: cannot write there ({exc.strerror}).") from None
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(blob)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(name, 0o666 & ~umask)
        if path.exists() and not overwrite:  # appeared meanwhile
            raise OutputExistsError(f"{what} {path} exists; pass --overwrite to replace it.")
        os.replace(name, path)
    except OSError as exc:
        with contextlib.suppress(OSError):
            os.unlink(name)
        if exc.errno in _DISK_ERRORS:
            raise OutputError(f"{what} {path}: {exc.strerror}; nothing was written. Free "
                              "some space or choose another path.") from None
        raise
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
