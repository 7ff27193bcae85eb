"""``python -m sb3_collapse.report``: :mod:`sb3_collapse.commands.report` (docs/sweeps.md)."""

from sb3_collapse.commands.report import main

if __name__ == "__main__":
    raise SystemExit(main())
