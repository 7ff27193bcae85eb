"""``python -m sb3_collapse.zoo {train,enjoy} ...``: see :mod:`sb3_collapse.zoo.launcher`."""

import sys

from sb3_collapse.zoo.launcher import main

if __name__ == "__main__":
    sys.exit(main())
