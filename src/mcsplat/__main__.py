"""`python -m mcsplat ...` (what `torchrun -m mcsplat train ...` runs): the same as the `mcsplat` command."""

import sys

from .cli import main

if __name__ == "__main__":
    sys.exit(main())
