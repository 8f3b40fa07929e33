"""``python -m ctcvo``: the same as the ``ctcvo`` command."""

import sys

from ctcvo.cli import main

sys.exit(main())
