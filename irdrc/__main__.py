"""``python -m irdrc RECIPE [overrides…]``: the ``irdrc`` command."""

import sys

from irdrc.experiments.cli import main

sys.exit(main())
