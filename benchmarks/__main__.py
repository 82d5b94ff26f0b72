"""`python -m benchmarks NAME [OPTIONS]`: run an experiment of framework.py (`python -m benchmarks --help` lists
them). Also each arm's worker process: `python benchmarks/__main__.py --worker PAYLOAD`."""

import sys
from pathlib import Path

# The benchmark modules import each other and `_common` as top-level modules (they also run as scripts).
sys.path.insert(0, str(Path(__file__).resolve().parent))

import framework  # noqa: E402

if __name__ == "__main__":
    sys.exit(framework.main())
