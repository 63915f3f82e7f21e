"""The lockstep ceiling of benchmarks/bench_vector_env.py, on known answers."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks.bench_vector_env import lockstep_ceiling


def test_equal_attempt_times_allow_the_full_speed_up():
    assert lockstep_ceiling(np.full(7, 0.8), 2) == pytest.approx(2.0)
    assert lockstep_ceiling(np.full(7, 0.8), 3) == pytest.approx(3.0)


def test_spread_attempt_times_cap_the_speed_up_at_the_expected_maximum():
    """T is 1 s or 3 s with equal odds: E[T] = 2, and two envs wait for E[max] = 1/4 * 1 + 3/4 * 3 = 2.5 s a step,
    so they reach 2 * 2 / 2.5 = 1.6x at best; three wait for 1/8 * 1 + 7/8 * 3 = 2.75 s (3 * 2 / 2.75)."""
    times = np.array([3.0, 1.0, 1.0, 3.0])
    assert lockstep_ceiling(times, 2) == pytest.approx(1.6)
    assert lockstep_ceiling(times, 3) == pytest.approx(6.0 / 2.75)
    assert lockstep_ceiling(times, 1) == pytest.approx(1.0)
