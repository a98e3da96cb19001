"""The package's version, as installed (pyproject.toml's): `repnet.__version__` and the OpenAPI version."""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

try:
    VERSION = version("repnet")
except PackageNotFoundError:  # a source tree that was never installed
    VERSION = "0.0.0"
