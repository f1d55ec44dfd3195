"""``python -m sim.plant_checks``: print the "ours vs the paper" table of docs/plant.md."""

import sys

from sim.plant_checks.report import main

if __name__ == "__main__":
    sys.exit(main())
