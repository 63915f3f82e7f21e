"""Wall-clock timing shared by the benchmark scripts (imported as a sibling module when a script runs)."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Hashable, Mapping


def time_calls(fn: Callable[[], object], runs: int) -> float:
    """Median wall time of ``fn()`` over ``runs`` calls, in milliseconds, after one warm-up call."""
    fn()
    samples = []
    for _ in range(runs):
        start = time.perf_counter()
        fn()
        samples.append(time.perf_counter() - start)
    return statistics.median(samples) * 1e3


def interleaved_times(calls: Mapping[Hashable, Callable[[], object]], repeats: int,
                      clock: Callable[[], float] = time.perf_counter) -> dict[Hashable, list[float]]:
    """Times in milliseconds (``clock``: wall by default) of each named call over ``repeats`` rounds, after one
    warm-up call each; every round calls each in turn, so a drift in the machine's load falls on all alike."""
    for fn in calls.values():
        fn()
    samples: dict[Hashable, list[float]] = {name: [] for name in calls}
    for _ in range(repeats):
        for name, fn in calls.items():
            start = clock()
            fn()
            samples[name].append((clock() - start) * 1e3)
    return samples
