"""``python -m sb3_hgrn``: the ``sb3-hgrn`` command line (see :mod:`sb3_hgrn.cli`)."""

import sys

from sb3_hgrn.cli import main
from sb3_hgrn.experiments.backends import die_with_parent

if __name__ == "__main__":
    die_with_parent()  # a run a sweep started ends with the sweep (or the Ray worker) that started it
    sys.exit(main())
