"""``python -m irdrc RECIPE [overrides…]``: the ``irdrc`` command."""

import sys

from irdrc.runs.cli import main

sys.exit(main())
