"""`python -m tests.hardening.nofile_service FLAGS`: the service with at most 1024 open files (soft
and hard), as a workstation's `ulimit -n 1024` shell starts it."""

from __future__ import annotations

import resource

from repnet.server.app import main

if __name__ == "__main__":
    resource.setrlimit(resource.RLIMIT_NOFILE, (1024, 1024))
    raise SystemExit(main())
