"""Memory bounded by what a client sends (issue 30), measured on a real `repnet serve` (one worker):
the peak resident memory (VmHWM) an attack leaves above what the server held before it, against the
issue's bounds. The attacks are bench.memory_attacks' (`python -m bench.memory_attacks` prints all
of them, longer)."""

from __future__ import annotations

import pytest

from bench.memory_attacks import measure

# (attack, seconds it runs, most MB of peak growth): the targets. The offline gap bomb (an
# 85 KB body) took +1.4 GB; 4 streams of 1,024-person frames that never read a reply took +925 MB.
BOUNDS = [("gap-bomb", 0.0, 200.0), ("silent-streams", 6.0, 300.0)]


@pytest.mark.parametrize(("attack", "seconds", "bound_mb"), BOUNDS, ids=[b[0] for b in BOUNDS])
def test_an_attack_leaves_the_server_alive_within_its_memory_bound(
    attack: str, seconds: float, bound_mb: float
) -> None:
    result = measure(attack, seconds, ["--workers", "1"])
    assert "the server died" not in result["seen"], result
    assert not result["seen"].startswith("5"), result  # answered, never a server error
    assert result["growth_mb"] <= bound_mb, result


def test_a_frame_number_past_the_exact_range_is_a_field_error() -> None:
    result = measure("frame-overflow", 0.0, ["--workers", "1"])
    assert result["seen"].startswith("422") and "frame" in result["seen"], result
