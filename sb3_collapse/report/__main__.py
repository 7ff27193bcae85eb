"""``python -m sb3_collapse.report``: :mod:`sb3_collapse.commands.report` (docs/sweeps.md)."""

import sys

from sb3_collapse.commands.report import main

if __name__ == "__main__":
    sys.exit(main())
