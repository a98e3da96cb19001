"""Errors raised by the service core; each adapter translates them in one place."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

# How many violations one error message lists; the rest are counted, not spelled out.
MAX_LISTED_VIOLATIONS = 10


@dataclass(frozen=True)
class Violation:
    """One rejected input field: where it is, why, and a short reason code for metrics."""

    field: str  # e.g. "poses[2].keypoints[5]"
    reason: str  # e.g. "coordinates must be finite numbers, got [nan, 3.0]"
    code: str  # e.g. "non_finite"; the `reason` label of repnet_rejected_inputs_total
    pose: int | None = None  # index of the pose in the request, when the field is in one
    joint: int | None = None  # index of the joint in the pose's format, when the field is one
    joint_name: str | None = None  # the joint's name in the pose's format

    @property
    def message(self) -> str:
        where = f"{self.field} ({self.joint_name})" if self.joint_name else self.field
        return f"{where}: {self.reason}"


class LiftError(Exception):
    """Base class of every error the service core raises on purpose."""


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


class ModelLoadError(LiftError):
    """The model file is missing, unreadable or breaks the ONNX contract (fatal at start)."""
