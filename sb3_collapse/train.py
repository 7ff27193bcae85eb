"""``python -m sb3_collapse.train``: :mod:`sb3_collapse.commands.train` (docs/training.md)."""

from sb3_collapse.commands.train import main

if __name__ == "__main__":
    raise SystemExit(main())
