"""Errors raised by the service core; each adapter translates them in one place."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

# How many violations one error message lists; the rest are counted, not spelled out.
MAX_LISTED_VIOLATIONS = 10
# How many violations one reply lists as items (HTTP `detail`, a stream frame's `violations`); the
# rest are counted: a request whose every value is wrong must not get a reply larger than itself.
MAX_ERROR_ITEMS = 20
# A value from the request quoted in an error (a format name, an unknown key) is cut to this many
# characters, so that no reply echoes a client's input in full.
MAX_ECHO_CHARS = 100
# The longest field name and reason a Violation keeps: the bound behind every echo, whatever built it.
MAX_FIELD_CHARS = 200
MAX_REASON_CHARS = 400
# The way out named by every refusal of a request for its size (HTTP 413, too many poses, gRPC's
# message limit, the page's file limit: static/page.js says the same): the clients that cut a clip.
SPLIT_HINT = (
    "`repnet lift FILE` and the Python client's LiftClient.lift_batch split a long clip into requests"
)


def echo(value: str) -> str:
    """`value` quoted for an error message, cut to MAX_ECHO_CHARS characters with its length."""
    if len(value) <= MAX_ECHO_CHARS:
        return repr(value)
    return f"{value[:MAX_ECHO_CHARS]!r}… ({len(value)} characters)"


def encodable(text: str) -> str:
    """`text` with each character UTF-8 cannot encode escaped (a lone surrogate, which JSON's
    \\ud800 escape can put in a key, becomes the six characters `\\ud800`): an error that quotes
    a request's text must still be writable as JSON, a gRPC status or pydantic's message."""
    return text.encode("utf-8", "backslashreplace").decode("utf-8")


def clip(text: str, limit: int) -> str:
    """`text` cut to at most `limit` characters, marked where it was cut, and `encodable`."""
    text = encodable(text)
    return text if len(text) <= limit else text[: limit - 1] + "…"


@dataclass(frozen=True)
class Violation:
    """One rejected input field: where it is, why, and a short reason code for metrics."""

    field: str  # e.g. "poses[2].keypoints[5]"
    reason: str  # e.g. "coordinates must be finite numbers, got [nan, 3.0]"
    code: str  # e.g. "non_finite"; the `reason` label of repnet_rejected_inputs_total
    pose: int | None = None  # index of the pose in the request, when the field is in one
    joint: int | None = None  # index of the joint in the pose's format, when the field is one
    joint_name: str | None = None  # the joint's name in the pose's format

    def __post_init__(self) -> None:
        object.__setattr__(self, "field", clip(self.field, MAX_FIELD_CHARS))
        object.__setattr__(self, "reason", clip(self.reason, MAX_REASON_CHARS))

    def within(self, parent: str) -> Violation:
        """This violation as a field of `parent`: keypoints[4] within poses[2] is poses[2].keypoints[4]."""
        return replace(self, field=f"{parent}.{self.field}")

    @property
    def message(self) -> str:
        """Field, joint name and reason in one line (the gRPC status message)."""
        where = f"{self.field} ({self.joint_name})" if self.joint_name else self.field
        return f"{where}: {self.reason}"


class LiftError(Exception):
    """Base class of every error the service core raises on purpose."""

    def as_answer(self) -> LiftError:
        """This error kept as an answer (a pose's, a job's, a stream group's) after the `except` that
        caught it: without its traceback, whose frames hold what holds the answer, a cycle that only
        the collector's full collections would free (tests/service/test_pipeline.py)."""
        return self.with_traceback(None)


class InvalidKeypoints(LiftError):
    """The request's keypoints break a documented input rule (HTTP 422, INVALID_ARGUMENT)."""

    def __init__(self, violations: Sequence[Violation]) -> None:
        if not violations:
            raise ValueError("InvalidKeypoints needs at least one violation")
        self.violations = tuple(violations)
        listed = [v.message for v in self.violations[:MAX_LISTED_VIOLATIONS]]
        extra = len(self.violations) - len(listed)
        if extra:
            listed.append(f"and {extra} more")
        super().__init__("; ".join(listed))


class ModelNotReady(LiftError):
    """The model is not loaded or the server is shutting down (HTTP 503, UNAVAILABLE)."""


class Overloaded(LiftError):
    """The batch queue is full; retry later (HTTP 503, RESOURCE_EXHAUSTED)."""


# The stable message of every ModelOutputError, on both transports.
MODEL_OUTPUT_MESSAGE = "the model produced non-finite output for this input; this is a server fault"


class ModelOutputError(LiftError):
    """The model produced non-finite output for some poses: a server fault (HTTP 500, INTERNAL).

    `rows` are the failed poses of the request (replies.Replies.failed); the other poses of the same
    run are answered as usual."""

    def __init__(self, rows: Sequence[int]) -> None:
        self.rows = tuple(rows)
        super().__init__(MODEL_OUTPUT_MESSAGE)


class ModelLoadError(LiftError):
    """The model file is missing, unreadable or breaks the ONNX contract (fatal at start)."""
