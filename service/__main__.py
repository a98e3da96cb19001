"""`python -m service`: the server (service.app builds and runs it)."""

import sys

from service.app import main

if __name__ == "__main__":
    sys.exit(main())
