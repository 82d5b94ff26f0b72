"""`python -m mcsplat.cli`: the `mcsplat` command."""

import sys

from . import main

sys.exit(main())
