"""Run a call in a new interpreter: for libraries whose state outlives their shutdown (Ray's driver)."""

from __future__ import annotations

import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from typing import Any, Callable


def in_fresh_process(fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
    """``fn(*args, **kwargs)`` in a new, spawned interpreter, which exits afterwards; its result or its error.

    A Ray driver lives as long as its process: its C++ core worker keeps threads after ``ray.shutdown()``
    and can end the process with no Python traceback. Run inside a pytest-xdist worker, a Ray test was
    followed, four tests later, by that worker's death ("node down: Not properly terminated", CI of
    2026-12-03), so the tests drive the Ray backends from a process of their own.
    """
    with ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn")) as pool:
        return pool.submit(fn, *args, **kwargs).result()
