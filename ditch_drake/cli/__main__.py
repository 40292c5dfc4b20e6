"""`python -m ditch_drake.cli`, the same as `ditch-drake`."""

import sys

from ditch_drake.cli.main import main

if __name__ == "__main__":
    sys.exit(main())
