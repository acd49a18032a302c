"""Speed against error for the paper's scenes (same as ``difstar bench``).

    python benchmarks/speed_vs_error.py [--quick] [--json out.json] ...

See BENCHMARKS.md for the table this produced and how to read it.
"""

import sys

from difstar.cli import main

if __name__ == "__main__":
    sys.exit(main(["bench", *sys.argv[1:]]))
