"""The model folder read safely (issue 30): only regular files of bounded size, hashed in chunks
(a FIFO, a device or a huge file is refused by name, at once), `.onnx` in any case, and model ids
held to a documented pattern."""

from __future__ import annotations

import os
import threading
from pathlib import Path

import pytest

from repnet.core.errors import ModelLoadError
from repnet.core.inputs import MODEL_ID
from repnet.runtime import session
from repnet.runtime.lifter import Lifter
from repnet.runtime.loading import BUNDLED_MODEL, file_sha256
from repnet.server.config import Settings
from repnet.server.startup import load_dir_lifters, model_files
from tests.service.test_catalog import copy_model


def refused_within(seconds: float, folder: Path, lifter: Lifter) -> str:
    """The ModelLoadError message of loading `folder`, which must come within `seconds`."""
    outcome: list[BaseException | None] = []

    def load() -> None:
        try:
            load_dir_lifters(Settings(model_dir=folder), lifter)
            outcome.append(None)
        except BaseException as err:  # noqa: BLE001 - handed to the test thread
            outcome.append(err)

    thread = threading.Thread(target=load, daemon=True)
    thread.start()
    thread.join(seconds)
    assert not thread.is_alive(), f"loading {folder} still runs after {seconds} s"
    (err,) = outcome
    assert isinstance(err, ModelLoadError), err
    return str(err)


def test_a_fifo_in_the_model_folder_is_refused_at_once(tmp_path: Path, lifter: Lifter) -> None:
    os.mkfifo(tmp_path / "pipe.onnx")  # no writer: opening it for reading would block forever
    message = refused_within(10, tmp_path, lifter)
    assert "pipe.onnx" in message and "not a regular file" in message


def test_a_link_to_a_device_is_refused_without_reading_it(tmp_path: Path, lifter: Lifter) -> None:
    (tmp_path / "zero.onnx").symlink_to("/dev/zero")  # endless: reading it whole exhausts memory
    message = refused_within(10, tmp_path, lifter)
    assert "zero.onnx" in message and "not a regular file" in message


def test_a_file_over_the_size_limit_is_refused_before_it_is_read(
    tmp_path: Path, lifter: Lifter, monkeypatch: pytest.MonkeyPatch
) -> None:
    limit = BUNDLED_MODEL.stat().st_size + 1024  # the default model fits
    monkeypatch.setattr(session, "MAX_MODEL_BYTES", limit)
    with (tmp_path / "big.onnx").open("wb") as f:
        f.truncate(limit + 1)  # sparse: the size is what counts
    message = refused_within(10, tmp_path, lifter)
    assert "big.onnx" in message and f"{limit + 1} bytes" in message


def test_the_sha256_is_read_in_chunks_and_matches_the_whole_file(tmp_path: Path) -> None:
    import hashlib

    data = os.urandom(3 * (1 << 20) + 17)  # more than two chunks and a remainder
    (tmp_path / "m.onnx").write_bytes(data)
    assert file_sha256(tmp_path / "m.onnx") == hashlib.sha256(data).hexdigest()
    assert file_sha256(BUNDLED_MODEL) == hashlib.sha256(BUNDLED_MODEL.read_bytes()).hexdigest()


def test_onnx_in_any_case_is_a_model_file_and_hidden_files_are_not(tmp_path: Path, lifter: Lifter) -> None:
    copy_model(BUNDLED_MODEL, tmp_path / "UPPER.ONNX", model_id="upper-case")
    (tmp_path / ".hidden.onnx").write_bytes(b"an editor's lock file")
    (tmp_path / "notes.txt").write_text("not a model")
    assert [p.name for p in model_files(tmp_path)] == ["UPPER.ONNX"]
    (served,) = load_dir_lifters(Settings(model_dir=tmp_path), lifter)
    assert served.info.model_id == "upper-case"


@pytest.mark.parametrize("bad", ["new\nline", "<script>x", ".", "a b", "x" * 65, "../up", "ünï"])
def test_a_model_id_off_the_pattern_stops_the_start_naming_the_file(
    tmp_path: Path, lifter: Lifter, bad: str
) -> None:
    copy_model(BUNDLED_MODEL, tmp_path / "named.onnx", model_id=bad)
    with pytest.raises(ModelLoadError, match=r"named\.onnx: the model id .* from its metadata model_id"):
        load_dir_lifters(Settings(model_dir=tmp_path), lifter)


def test_a_file_name_off_the_pattern_without_metadata_id_is_named(tmp_path: Path, lifter: Lifter) -> None:
    copy_model(BUNDLED_MODEL, tmp_path / "my model.onnx", model_id="")
    with pytest.raises(ModelLoadError, match="from its file name"):
        load_dir_lifters(Settings(model_dir=tmp_path), lifter)


@pytest.mark.parametrize("good", ["repnet-h36m-v7", "a", "v1.2_x-3", "A" * 64])
def test_the_ids_of_the_pattern_pass(good: str) -> None:
    assert MODEL_ID.fullmatch(good)
