"""Lineage: where a checkpoint or an exported model comes from, free of the training machine's paths.

A checkpoint's lineage is the list of its stages, oldest first: the stages of the checkpoint it
started from, then its own. A stage's record names its preset and stage (if any), the command
that started it, its parent (the checkpoint or model it started from: how, path, sha256, command),
the resumes since, the git commit and torch version, the sha256 of every data file read, its
first and last step and its own wall time. An exported model's lineage (metadata key "lineage")
holds the export's own record and the stages of its generator and of its critic.

Paths are written relative to a run's root (the folder that holds the run's out-dir: a preset's
out-dir, whose stages are its sub-folders) or, outside it, as their basename (path_free).
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import re
import shlex
import subprocess
from pathlib import Path
from typing import Any

import torch

FORMAT = 1
CACHE_ENV = "REPNET_CACHE_DIR"
Record = dict[str, Any]


def cache_dir() -> Path:
    """Where repnet keeps what it can recompute: $REPNET_CACHE_DIR, else ~/.cache/repnet."""
    return Path(os.environ.get(CACHE_ENV) or Path.home() / ".cache" / "repnet")


def file_sha256(path: Path) -> str:
    """The sha256 of a file, read once: cached in cache_dir()/sha256.json by the file's resolved
    path, size and modification time, so a resumed run or the next stage pays nothing for it."""
    path = path.resolve()
    stat = path.stat()
    key = f"{path}|{stat.st_size}|{stat.st_mtime_ns}"
    cache_file = cache_dir() / "sha256.json"
    try:
        cache: dict[str, str] = json.loads(cache_file.read_text())
    except (OSError, ValueError):
        cache = {}
    if key in cache:
        return cache[key]
    digest = hashlib.sha256()
    with path.open("rb") as file:
        for block in iter(lambda: file.read(1 << 20), b""):
            digest.update(block)
    # Drop this file's older versions and the files that are gone.
    cache = {
        k: v for k, v in cache.items() if not k.startswith(f"{path}|") and Path(k.split("|")[0]).exists()
    }
    cache[key] = digest.hexdigest()
    cache_file.parent.mkdir(parents=True, exist_ok=True)
    tmp = cache_file.with_name(f"sha256.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(cache, indent=0))
    tmp.replace(cache_file)
    return cache[key]


def data_hashes(data_dir: Path, names: tuple[str, ...]) -> dict[str, str]:
    """{file name: sha256} of the named files of the data folder (file_sha256)."""
    return {name: file_sha256(data_dir / name) for name in names}


@functools.cache
def git_state() -> dict[str, Any]:
    """The commit of the code that runs and whether tracked files differ from it; None for both
    outside a git checkout."""
    repo = Path(__file__).resolve().parent.parent

    def git(*args: str) -> str:
        return subprocess.run(
            ["git", "-C", str(repo), *args], capture_output=True, text=True, check=True, timeout=30
        ).stdout.strip()

    try:
        commit = git("rev-parse", "HEAD")
        dirty = bool(git("status", "--porcelain", "--untracked-files=no"))
    except (OSError, subprocess.SubprocessError):
        return {"commit": None, "dirty": None}
    return {"commit": commit, "dirty": dirty}


def environment() -> Record:
    """The code and library a stage or an export ran with: git commit (and dirty flag), torch."""
    return {"git": git_state(), "torch": str(torch.__version__)}  # a str: checkpoints load with weights_only


def path_free_path(value: str, root: Path | None) -> str:
    """An absolute (or ~) path written relative to root when inside it, else as its basename;
    anything else unchanged."""
    if not value.startswith(("/", "~")):
        return value
    path = Path(value).expanduser().resolve()
    if root is not None:
        try:
            return str(path.relative_to(root.expanduser().resolve()))
        except ValueError:
            pass
    return path.name or value


# A path in a command line: a word (or the value of --flag=) that starts with / or ~, bare or
# quoted as a shell quotes it (shlex.join quotes a path with a space: '/tmp/my models/a.onnx').
_PATH_WORD = re.compile(r"(?:(?<=\s)|(?<==)|^)[~/][^\s;'\"]*")
_QUOTED_PATH_WORD = re.compile(r"""(?:(?<=\s)|(?<==)|^)(['"])([~/][^'"]*)\1""")


def path_free(command: str, root: Path | None) -> str:
    """A command line with every absolute path made path_free_path (quoted ones too, quoted again
    if they need it), the rest kept as written: what a lineage records, so no model tells where it
    was trained."""
    unquoted = _QUOTED_PATH_WORD.sub(lambda match: shlex.quote(path_free_path(match[2], root)), command)
    return _PATH_WORD.sub(lambda match: path_free_path(match[0], root), unquoted)


def command_line(argv: list[str], root: Path | None, module: str = "repnet.train.train") -> str:
    """`python -m module argv...`, path free."""
    return path_free(shlex.join(["python", "-m", module, *argv]), root)


def describe_parent(path: Path, state: dict[str, Any], how: str, root: Path | None) -> Record:
    """What a stage started from: how ("init_from", "extend" or "resume"), the file (path_free),
    its sha256 and the command that made it."""
    stages = stages_of(state, "generator")
    command = stages[-1].get("command", "") if stages else state.get("command", "")
    return {
        "how": how,
        "path": path_free_path(str(path.resolve()), root),
        "sha256": file_sha256(path),
        "command": path_free(command, root),
    }


def stages_of(state: dict[str, Any], role: str) -> list[Record]:
    """The stages recorded in a checkpoint's state, or in an exported model's state for its
    "generator" or "critic" (checkpoint.from_onnx); a state written before lineage was recorded
    gives one stage with its command alone, none without one."""
    found = state.get("lineage")
    if isinstance(found, list):
        return [dict(record) for record in found]
    if isinstance(found, dict) and isinstance(found.get(role), list):
        return [dict(record) for record in found[role]]
    command = state.get("critic_command" if role == "critic" else "command") or state.get("command")
    return [{"command": path_free(command, None)}] if command else []


def new_stage(
    preset: str | None,
    stage: str | None,
    command: str,
    parent_record: Record | None,
    data: dict[str, str],
    first_step: int,
) -> Record:
    """The record of a stage that starts now (its steps and wall time are filled in as it saves)."""
    return {
        "preset": preset,
        "stage": stage,
        "command": command,
        "parent": parent_record,
        "resumed": [],
        **environment(),
        "data": data,
        "first_step": first_step,
        "steps": first_step,
        "wall_time_s": 0.0,
    }


def export_lineage(
    command: str,
    generator: tuple[Path, dict[str, Any]],
    critic: tuple[Path, dict[str, Any]] | None,
    data: dict[str, str],
    root: Path | None,
) -> Record:
    """An exported model's lineage: the export's record (its command, the generator's and the
    critic's files with their sha256), then every stage of the generator and of the critic.
    critic None: no plausibility output; the generator's own file: its critic, "critic" None."""

    def source(path: Path) -> Record:
        return {"path": path_free_path(str(path.resolve()), root), "sha256": file_sha256(path)}

    same = critic is not None and critic[0].resolve() == generator[0].resolve()
    return {
        "format": FORMAT,
        "export": {
            "command": command,
            **environment(),
            "data": data,
            "generator": source(generator[0]),
            "critic": None if critic is None else source(critic[0]),
        },
        "generator": stages_of(generator[1], "generator"),
        "critic": None if critic is None or same else stages_of(critic[1], "critic"),
    }


def run_stages(
    out: Path,
    command: str,
    hashes: dict[str, str],
    origin: tuple[str | None, str | None],
    resumed: tuple[Path | None, dict[str, Any] | None, bool],
    init: tuple[Path, dict[str, Any]] | None,
) -> list[Record]:
    """The run's lineage: a fresh run appends a new stage to its init_from's stages; a run resumed
    from its own out_dir/last.pt continues its stage (one more entry in "resumed": the step, the
    checkpoint's sha256 and the command); a run resumed from another run's checkpoint, or
    extended, appends a new stage to that checkpoint's."""
    root = out.resolve().parent
    resume_path, state, extend = resumed
    if state is None or resume_path is None:
        if init is None:
            return [new_stage(*origin, command, None, hashes, 0)]
        origin_parent = describe_parent(init[0], init[1], "init_from", root)
        return stages_of(init[1], "generator") + [new_stage(*origin, command, origin_parent, hashes, 0)]
    if resume_path.resolve().parent == out.resolve() and not extend:
        stages = stages_of(state, "generator") or [new_stage(*origin, "", None, hashes, 0)]
        entry: dict[str, Any] = {
            "step": state["step"],
            "sha256": file_sha256(resume_path),
            "command": command,
        }
        if stages[-1].get("data") != hashes:
            entry["data"] = hashes  # the data changed under a running stage: say so
        stages[-1].setdefault("resumed", []).append(entry)
        return stages
    source = describe_parent(resume_path, state, "extend" if extend else "resume", root)
    return stages_of(state, "generator") + [new_stage(*origin, command, source, hashes, state["step"])]
