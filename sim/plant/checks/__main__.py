"""``python -m sim.plant.checks``: print the "ours vs the paper" table of docs/plant.md."""

import sys

from sim.plant.checks.report import main

if __name__ == "__main__":
    sys.exit(main())
