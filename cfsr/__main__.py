"""``python -m cfsr``: the ``cfsr`` command line."""

import sys

from cfsr.cli import main

sys.exit(main())
