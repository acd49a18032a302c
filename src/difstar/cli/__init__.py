"""The ``difstar`` command line: the outer layer that parses arguments, calls one library
function, writes files and reports progress and exit codes. The only part of difstar that
imports :mod:`argparse`; the library never imports this package.

- :mod:`._main`: the top-level parser, its dispatch, ``difstar predict`` and ``difstar example``
- :mod:`._fit`: ``difstar synth`` and ``difstar fit`` (RAW captures)
- :mod:`._fit_image`: ``difstar fit-image`` (star images)
- :mod:`._design`: ``difstar design`` (the aperture-design study and sweeps)
- :mod:`._args`: the argparse number types they share

Run it as ``difstar ...`` (the installed script) or ``python -m difstar.cli ...``.
"""

from ._main import main as main

__all__ = ["main"]
