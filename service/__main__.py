"""`python -m repnet`: the `repnet` command (`python -m repnet serve` runs the server)."""

import sys

from repnet.cli.main import main

if __name__ == "__main__":
    sys.exit(main())
