"""``python -m sb3_collapse.probe``: :mod:`sb3_collapse.commands.probe` (docs/probe.md)."""

from sb3_collapse.commands.probe import main

if __name__ == "__main__":
    raise SystemExit(main())
