"""The wheel and an editable install: `repnet` alone at its top level; the plain install is the light
one (the clients, the core, the file tools: no onnxruntime, no web framework), and each command whose
extra is missing says which `pip install` brings it. (CI also installs the wheel into a fresh venv:
.ci/run, step wheel.)"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
import tarfile
import zipfile
from email.parser import Parser
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
HEAVY = ("onnxruntime", "fastapi", "uvicorn", "starlette", "pydantic", "prometheus_client", "torch")
# Imports of the heavy packages fail in the child, as in a light install.
BLOCKER = f"""
import importlib.abc, sys
class Light(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in {HEAVY!r}:
            raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
        return None
sys.meta_path.insert(0, Light())
"""
# The project's build backend as a build front end loads it (pyproject.toml: build-backend, backend-path),
# run in the checkout's root: `b` is the module whose PEP 517 and PEP 660 hooks pip calls.
BACKEND = "import sys; sys.path.insert(0, 'deploy/packaging'); import repnet_backend as b"


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return wheel_of(ROOT, tmp_path_factory.mktemp("wheel"))


def wheel_of(source: Path, out: Path) -> Path:
    """The wheel `pip wheel` builds from the source tree `source` into `out` (the project's backend,
    pyproject.toml's build-system)."""
    build = [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q", "-w", str(out)]
    subprocess.run([*build, str(source)], check=True, capture_output=True, timeout=300)
    (found,) = out.glob("repnet-*.whl")
    return found


@pytest.fixture(scope="module")
def sdist(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The sdist, built by the project's backend as `python -m build --sdist` builds it, unpacked:
    its source tree."""
    out = tmp_path_factory.mktemp("sdist")
    hook = f"{BACKEND}; print(b.build_sdist({str(out)!r}))"
    made = subprocess.run(
        [sys.executable, "-c", hook], check=True, capture_output=True, text=True, cwd=ROOT, timeout=300
    )
    with tarfile.open(out / made.stdout.split()[-1]) as archive:
        archive.extractall(out / "src", filter="data")
    (source,) = (out / "src").iterdir()
    return source


def test_the_wheel_holds_repnet_alone(wheel: Path) -> None:
    names = zipfile.ZipFile(wheel).namelist()
    assert {n.split("/")[0] for n in names} == {"repnet", wheel.name.split("-py3")[0] + ".dist-info"}
    for part in (
        "repnet/core/",
        "repnet/client/",
        "repnet/server/static/page.js",
        "repnet/train/",
        "repnet/models/",
        "repnet/models/detector/pose_detection.onnx",  # `repnet video`'s BlazePose, with its licence
        "repnet/models/detector/pose_landmark_full.onnx",
        "repnet/models/detector/LICENSE",
    ):
        assert any(n.startswith(part) for n in names), part


def test_a_wheel_built_from_the_sdist_is_the_checkouts_wheel(
    wheel: Path, sdist: Path, tmp_path: Path
) -> None:
    """`pip install repnet` from an index that has only the sdist builds a wheel from it: the same
    files as the checkout's wheel (repnet alone at the top level, every model and page file), while
    the sdist carries the source folders under their own names and no tests (MANIFEST.in)."""
    tops = {p.name for p in sdist.iterdir()}
    assert {"service", "training", "pyproject.toml"} <= tops and not {"repnet", "tests"} & tops
    rebuilt = wheel_of(sdist, tmp_path)
    assert sorted(zipfile.ZipFile(rebuilt).namelist()) == sorted(zipfile.ZipFile(wheel).namelist())


def test_a_tree_that_built_the_old_flat_layout_still_builds_repnet_alone(
    wheel: Path, sdist: Path, tmp_path: Path
) -> None:
    """setuptools copies its build folder into the wheel whole and never empties it, so a checkout
    that once built the old top-level `service` and `training` packages shipped them again beside
    repnet (`import service` after `pip install .`). The project's backend builds every wheel from
    an empty build/lib."""
    for stale in ("service", "training"):
        (sdist / "build" / "lib" / stale).mkdir(parents=True, exist_ok=True)
        (sdist / "build" / "lib" / stale / "__init__.py").write_text("OLD = True\n")
    rebuilt = wheel_of(sdist, tmp_path)
    assert sorted(zipfile.ZipFile(rebuilt).namelist()) == sorted(zipfile.ZipFile(wheel).namelist())


def test_the_installed_wheel_imports_repnet_and_nothing_else(wheel: Path, tmp_path: Path) -> None:
    """Installed (away from the checkout, whose folders a cwd import would find; no site-packages:
    the wheel's files alone), the wheel gives `import repnet` (with repnet.train) alone: no `service`
    or `training` package."""
    target = tmp_path / "site"
    install = [sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target", str(target), str(wheel)]
    subprocess.run(install, check=True, capture_output=True, timeout=300)
    assert sorted(p.name for p in target.iterdir() if not p.name.endswith(".dist-info")) == ["bin", "repnet"]
    code = (
        "import importlib.util as u; print([n for n in ('repnet', 'service', 'training') "
        "if u.find_spec(n) is not None])"
    )
    found = subprocess.run(
        [sys.executable, "-I", "-S", "-c", f"import sys; sys.path.insert(0, {str(target)!r}); {code}"],
        capture_output=True, text=True, cwd=tmp_path, timeout=60,
    )  # fmt: skip
    assert found.stdout.strip() == "['repnet']", found.stderr
    assert (target / "repnet" / "train" / "__init__.py").is_file()  # training/ is repnet.train


def editable_venv(source: Path, tmp_path: Path, settings: dict[str, str] | None = None) -> tuple[Path, str]:
    """An editable wheel built from the source tree `source` by the project's backend's PEP 660 hook
    (as `pip install -e` calls it, with `settings` as --config-settings), installed into a fresh venv
    without its dependencies: the venv's python, and what the hook printed on stderr."""
    built = tmp_path / "editable"
    built.mkdir()
    hook = f"{BACKEND}; print(b.build_editable({str(built)!r}, {settings!r}))"
    made = subprocess.run(
        [sys.executable, "-c", hook], check=True, capture_output=True, text=True, cwd=source, timeout=300
    )
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=120)
    python = venv / "bin" / "python"
    install = [sys.executable, "-m", "pip", "--python", str(python), "install", "-q", "--no-deps"]
    subprocess.run(
        [*install, str(built / made.stdout.split()[-1])], check=True, capture_output=True, timeout=300
    )
    return python, made.stderr


def test_an_editable_install_imports_repnet_and_nothing_else(tmp_path: Path) -> None:
    """`pip install -e .` (setuptools' default editable mode, what a user running it from a checkout
    gets) maps service/ to repnet and exposes neither service/ nor training/ under its own name:
    looked for outside the checkout, in a fresh venv."""
    python, _ = editable_venv(ROOT, tmp_path)
    code = (
        "import importlib.util as u; print([(n, u.find_spec(n).origin) for n in ('repnet', 'service', "
        "'training') if u.find_spec(n) is not None])"
    )  # top-level names only: importing repnet would need its dependencies (--no-deps)
    found = subprocess.run(
        [str(python), "-c", code], capture_output=True, text=True, cwd=tmp_path, timeout=60
    )
    assert found.stdout.strip() == str([("repnet", str(ROOT / "service" / "__init__.py"))]), found.stderr


# What the image copies to build the package (Dockerfile): the source tree without the checkout's build/.
SOURCE_TREE = (
    "pyproject.toml", "README.md", "LICENSE", "MANIFEST.in", "deploy/packaging", "service", "training",
)  # fmt: skip


@pytest.mark.parametrize("mode", ["strict", "compat"])
def test_an_editable_install_in_another_mode_imports_repnet_alone(mode: str, tmp_path: Path) -> None:
    """`pip install -e . --config-settings editable_mode=strict|compat`. setuptools' compat mode puts
    the checkout's root on sys.path, where service/ and training/ are found under their own names and
    repnet is not: the project's backend builds it in strict mode (a tree of links) instead. Built
    from a copy of the source tree (strict mode writes its links into the tree's build/)."""
    source = tmp_path / "src"
    for name in SOURCE_TREE:
        copy = shutil.copytree if (ROOT / name).is_dir() else shutil.copy2
        (source / name).parent.mkdir(parents=True, exist_ok=True)
        copy(ROOT / name, source / name)
    python, said = editable_venv(source, tmp_path, {"editable_mode": mode})
    assert ("building in strict mode instead" in said) == (mode == "compat")
    code = (
        "import importlib.util as u, pathlib, sys; print([n for n in ('repnet', 'service', 'training') "
        f"if u.find_spec(n) is not None], {str(source)!r} in sys.path, "
        "pathlib.Path(u.find_spec('repnet').origin).resolve())"
    )
    found = subprocess.run(
        [str(python), "-c", code], capture_output=True, text=True, cwd=tmp_path, timeout=60
    )
    expected = ["['repnet']", "False", str(source / "service" / "__init__.py")]  # the root not on sys.path
    assert found.stdout.split() == expected, found.stderr


@pytest.mark.parametrize(("folder", "package"), [("service", "repnet"), ("training", "repnet.train")])
def test_from_the_checkouts_root_a_source_folder_is_not_a_second_package(folder: str, package: str) -> None:
    """Python run in the checkout's root finds service/ and training/ under their own names (the
    current directory is on sys.path); importing them so is refused with the name to use, while
    repnet (the install; strict editable: links to the folders) imports from the same files."""
    refused = subprocess.run(
        [sys.executable, "-c", f"import {folder}"], capture_output=True, text=True, cwd=ROOT, timeout=60
    )
    assert refused.returncode == 1
    assert (
        f"ImportError: '{folder}' is the source folder of the package {package}: import {package}"
        in refused.stderr
    )
    used = subprocess.run(
        [
            sys.executable,
            "-c",
            f"import pathlib, {package}; print(pathlib.Path({package}.__file__).resolve())",
        ],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
    )
    assert used.stdout.strip() == str(ROOT / folder / "__init__.py"), used.stderr


def requirements(wheel: Path) -> dict[str, set[str]]:
    """The wheel's requirements by extra ("" the plain install), as package names."""
    with zipfile.ZipFile(wheel) as z:
        meta = z.read(next(n for n in z.namelist() if n.endswith(".dist-info/METADATA"))).decode()
    found: dict[str, set[str]] = {}
    for line in Parser().parsestr(meta).get_all("Requires-Dist") or []:
        name = re.match(r"[A-Za-z0-9_.\-]+", line)
        extra = re.search(r"extra == ['\"](\w+)['\"]", line)
        assert name is not None
        found.setdefault(extra[1] if extra else "", set()).add(name[0].lower().replace("_", "-"))
    return found


def test_the_plain_install_pulls_no_runtime_and_no_server(wheel: Path) -> None:
    needs = requirements(wheel)
    assert needs[""] == {"numpy", "httpx", "grpcio", "protobuf"}
    assert {"onnxruntime"} <= needs["local"] and {"fastapi", "uvicorn", "repnet"} <= needs["server"]
    assert {"torch", "repnet"} <= needs["train"] and {"matplotlib", "tqdm"} <= needs["cli"]


def light(code: str) -> subprocess.CompletedProcess[str]:
    """`code` in a child whose imports of the heavy packages fail, as in a plain install."""
    return subprocess.run(
        [sys.executable, "-c", BLOCKER + code], capture_output=True, text=True, cwd=ROOT, timeout=120
    )


def test_the_clients_and_the_file_tools_import_without_the_heavy_packages(tmp_path: Path) -> None:
    pose = tmp_path / "pose.json"
    pose.write_text(json.dumps({"keypoints": [[500.0 + 10 * j, 400.0 + 20 * j] for j in range(17)]}))
    run = light(
        "import repnet, sys\n"
        "print(repnet.LiftClient.__name__, repnet.StreamClient.__name__, repnet.LiftResult.__name__)\n"
        "from repnet.io import pose_file, output, bvh\n"
        "from repnet.cli.main import main\n"
        f"sys.exit(main(['lift', {str(pose)!r}, '--url', 'http://127.0.0.1:9', '--timeout', '1']))\n"
    )
    assert run.stdout.split() == ["LiftClient", "StreamClient", "LiftResult"], run.stderr
    assert run.returncode == 3 and "cannot reach" in run.stderr  # it read the file, then found no server
    assert not any(name in run.stderr for name in HEAVY)


@pytest.mark.parametrize(
    ("argv", "extra"),
    [
        (["serve", "--help"], "server"),
        (["lift", "POSE", "--local"], "local"),
        (["video", "CLIP", "--local"], "video"),
    ],
)
def test_a_command_whose_extra_is_missing_says_which_install_brings_it(
    tmp_path: Path, argv: list[str], extra: str
) -> None:
    pose = tmp_path / "pose.json"
    pose.write_text(json.dumps({"keypoints": [[500.0 + 10 * j, 400.0 + 20 * j] for j in range(17)]}))
    clip = ROOT / "tests" / "fixtures" / "video" / "street640.mp4"
    args = [str(pose) if a == "POSE" else str(clip) if a == "CLIP" else a for a in argv]
    run = light(f"import sys; from repnet.cli.main import main; sys.exit(main({args!r}))")
    assert run.returncode == 2, run.stderr
    assert f"[{extra}]" in run.stderr and "Traceback" not in run.stderr, run.stderr
