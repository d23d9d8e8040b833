"""``python -m steerlab``: the same as the ``steerlab`` command."""

import sys

from steerlab.app.cli import main

if __name__ == "__main__":
    sys.exit(main())
