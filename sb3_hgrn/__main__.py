"""``python -m sb3_hgrn``: the ``sb3-hgrn`` command line (see :mod:`sb3_hgrn.cli`)."""

import sys

from sb3_hgrn.cli import main

if __name__ == "__main__":
    sys.exit(main())
