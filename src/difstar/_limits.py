"""The sizes difstar accepts and the one error type for bad input: the bottom layer of
the checks, below the pupils (which count their edges when built) and
:mod:`._validate` (which checks everything else and re-exports these)."""

from __future__ import annotations

import math

#: deepest JSON nesting a difstar document needs (scene files: 6; manifests: 5)
MAX_JSON_DEPTH = 32
#: crop sizes (pixels a side) accepted by the command line and ``choose_grid``
MIN_CROP = 8
#: at most this many polygon vertices / iris blades / spider vanes: more are almost
#: certainly a mistake, and compile for minutes (on a 2-core CPU, a 16 px in-focus
#: prediction compiles in 10 s with 64 vertices, 16 s with 128, 66 s with 256 blades,
#: and exhausts memory with 1024 vertices)
MAX_VERTICES = 256
MAX_BLADES = 64
MAX_SPIDERS = 64
#: at most this many wavelengths in one PSF or simulation (each is a PSF evaluation;
#: the same bound as scene files'): difstar.psf's ``wavelength``, a spectral sensor's K,
#: choose_wavelengths' ``max_wavelengths``
MAX_WAVELENGTHS = 1024
#: the most disc sources a scene may hold (each is rasterised over the whole window)
MAX_SOURCES = 1024
#: at most this many straight edges in one outline that difstar.psf / simulate take
#: (Polygon vertices, RegularPolygon.n, CurvedIris.n × segments, vanes): the closed form
#: costs time and memory per edge (1024 edges: 15 s and 1 GB for a 32 × 32 px window on
#: a 2-core CPU; 4096: 53 s, 2.8 GB), and a regular polygon of 1024 edges is a circle to
#: 5e-6 of its radius, which Circle gives at a fraction of the cost
MAX_EDGES = 1024
#: the closed form (method "exact") is unrolled edge by edge, so its compile time and
#: memory grow with the edges (a jitted 16 px in-focus simulate: 9 s and 0.6 GB with 64
#: edges, 65 s and 2.5 GB with 256): above this many edges difstar.psf and choose_grid
#: sample the pupil instead (whose cost does not grow with them), and method="exact" is
#: refused
MAX_EXACT_EDGES = 256
#: at most this many vertices / blades / vanes when a pupil is built (Polygon's check
#: that it is simple costs O(n²): 2 s for 4096 vertices)
MAX_BUILD_EDGES = 4096
#: at most this many samples in a tabulated spectrum or a dense wavelength grid (NumPy
#: tables, not PSFs: cheap, but not unbounded)
MAX_SPECTRUM_SAMPLES = 100_000
#: the environment variable that caps the memory difstar plans for
ENV_MEMORY_LIMIT = "DIFSTAR_MEMORY_LIMIT"


class InputError(ValueError):
    """Invalid user input; the message names the field and the fix."""


def check_edge_count(count: int, field: str, what: str, *, most: int = MAX_EDGES) -> None:
    """At most ``most`` (default :data:`MAX_EDGES`) straight edges / blades / vanes."""
    if count > most:
        why = ("telescopes have a handful" if what in ("vanes", "struts") else
               f"a regular polygon of that many edges is a circle to "
               f"{1 - math.cos(math.pi / most):.1g} of its radius: use Circle")
        raise InputError(f"{field}: {count} {what}; give at most {most} ({why}).")
