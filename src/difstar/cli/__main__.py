"""``python -m difstar.cli ...``: the same command line as the ``difstar`` script."""

import sys

from ._main import main

sys.exit(main())
