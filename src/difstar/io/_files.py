"""Input files: the checks every reader makes before it parses anything."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path


def readable_file(path: str | os.PathLike, err: Callable[[Path, str], Exception]) -> Path:
    """``path`` as a Path, or the reader's error (``err(path, problem)``) when it is
    missing, not a regular file, or cannot be opened for reading."""
    path = Path(path)
    if not path.exists():
        raise err(path, "file not found")
    if not path.is_file():
        raise err(path, "not a regular file")
    try:
        with path.open("rb"):
            pass
    except OSError as e:
        raise err(path, f"cannot be opened for reading ({e.strerror or e})") from e
    return path
