"""``python -m virtualaxis``: the ``virtualaxis`` command (e.g. where the console script is not on PATH)."""

import sys

from virtualaxis.cli.main import main

sys.exit(main())
