"""benchmarks/timing.py: the interleaved timer the benchmark tables share."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from timing import interleaved_times  # noqa: E402


def test_each_call_is_warmed_once_then_the_calls_alternate_round_by_round():
    log: list[str] = []
    ticks = iter(range(100))
    calls = {"a": lambda: log.append("a"), "b": lambda: log.append("b")}
    samples = interleaved_times(calls, 3, clock=lambda: next(ticks) / 1000.0)  # one clock tick, 1 ms, per call
    assert log == ["a", "b"] + ["a", "b"] * 3
    assert set(samples) == {"a", "b"}
    for name in calls:
        assert samples[name] == pytest.approx([1.0, 1.0, 1.0])
