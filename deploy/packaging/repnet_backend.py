"""The project's build backend: setuptools' own (setuptools.build_meta), with a wheel built from
what pyproject.toml declares and nothing left over in the checkout.

setuptools copies its build folder (build/lib) into the wheel whole and never empties it
(pypa/setuptools#1871), so a checkout that once built another layout ships that layout again: a
`pip install .` after the old flat `service` and `training` packages gave `import service` beside
`import repnet`. build_wheel starts from an empty build/lib; every other hook is setuptools'.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from setuptools import build_meta
from setuptools.build_meta import *  # noqa: F403 (every PEP 517 and PEP 660 hook, as setuptools has them)


def build_wheel(
    wheel_directory: str,
    config_settings: dict[str, str | list[str]] | None = None,
    metadata_directory: str | None = None,
) -> str:
    """setuptools' build_wheel, after emptying the build folders it copies from (the hooks run in
    the source tree)."""
    build = Path("build")
    for stale in [build / "lib", *build.glob("bdist.*")]:
        shutil.rmtree(stale, ignore_errors=True)
    return build_meta.build_wheel(wheel_directory, config_settings, metadata_directory)
