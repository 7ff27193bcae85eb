"""``python -m sb3_collapse.sweep``: :mod:`sb3_collapse.commands.sweep` (docs/sweeps.md)."""

import sys

from sb3_collapse.commands.sweep import main

if __name__ == "__main__":
    sys.exit(main())
