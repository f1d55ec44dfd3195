"""Meta-tests (python-control style): properties of the code base itself, read from the source."""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).parent))  # import_graph
