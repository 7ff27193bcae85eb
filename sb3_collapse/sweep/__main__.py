"""``python -m sb3_collapse.sweep``: :mod:`sb3_collapse.commands.sweep` (docs/sweeps.md)."""

from sb3_collapse.commands.sweep import main

if __name__ == "__main__":
    raise SystemExit(main())
