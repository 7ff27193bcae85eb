"""``python -m sb3_collapse.zoo {train,enjoy} ...``: :mod:`sb3_collapse.commands.zoo`."""

from sb3_collapse.commands.zoo import main

if __name__ == "__main__":
    raise SystemExit(main())
