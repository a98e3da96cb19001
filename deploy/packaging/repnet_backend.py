"""The project's build backend: setuptools' own (setuptools.build_meta), with a wheel built from
what pyproject.toml declares and nothing left over in the checkout.

setuptools copies its build folder (build/lib) into the wheel whole and never empties it
(pypa/setuptools#1871), so a checkout that once built another layout ships that layout again: a
`pip install .` after the old flat `service` and `training` packages gave `import service` beside
`import repnet`. build_wheel starts from an empty build/lib.

setuptools' `compat` editable mode (`pip install -e . --config-settings editable_mode=compat`, for
tools that cannot follow an import hook) puts the checkout's root on sys.path: there service/ and
training/ are found under their own names, and repnet is not found at all. build_editable builds
such an install in `strict` mode instead (a tree of links to the folders, itself a plain folder on
sys.path, which those tools read as well). Every other hook is setuptools'.
"""

from __future__ import annotations

import shutil
import sys
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


def build_editable(
    wheel_directory: str,
    config_settings: dict[str, str | list[str]] | None = None,
    metadata_directory: str | None = None,
) -> str:
    """setuptools' build_editable (PEP 660), in strict mode where compat is asked for."""
    settings = dict(config_settings or {})
    for key in ("editable-mode", "editable_mode"):  # setuptools reads either spelling
        if str(settings.get(key, "")).lower() == "compat":
            settings[key] = "strict"
            print(
                "repnet: editable_mode=compat would put the checkout's root on sys.path (service and "
                "training under their own names, no repnet): building in strict mode instead",
                file=sys.stderr,
            )
    return build_meta.build_editable(wheel_directory, settings, metadata_directory)
