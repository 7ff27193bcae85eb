"""``python -m sb3_collapse.reproduce``: the paper's whole protocol in one command (docs/reproduce.md); the command
line is :mod:`sb3_collapse.commands.reproduce`."""

from sb3_collapse.commands.reproduce import main

if __name__ == "__main__":
    raise SystemExit(main())
