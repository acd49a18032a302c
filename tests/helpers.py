"""Independent truths and helpers for the tests (NumPy/SciPy, not difstar's code).

The implementations live in :mod:`references`; this module keeps the names other tests
import from it."""

from __future__ import annotations

from references import (  # noqa: F401
    airy_psf,
    fd_grad,
    polygon_ft,
    polygon_psf_exact,
)
