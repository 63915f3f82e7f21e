"""The local process pool (parcelpick_env/parallel.py): ordered results, and workers that use one core each."""

from __future__ import annotations

import os

import pytest

from parcelpick_env.parallel import limit_worker_threads, parallel_map


def _worker_threads(item: int) -> tuple[int, int, str | None, str | None]:
    import open3d as o3d

    return item, int(o3d.utility.get_max_threads()), os.environ.get("OMP_NUM_THREADS"), os.environ.get("LP_NUM_THREADS")


def test_pool_workers_bound_open3d_openmp_and_llvmpipe_to_one_thread():
    results = list(parallel_map(_worker_threads, [3, 1, 2], workers=2, progress=False))
    assert [r[0] for r in results] == [3, 1, 2]  # submission order
    # oneTBB (Open3D's ray casting) spins idle workers: unbounded, one env process took 1.3 cores
    assert all(r[1:] == (1, "1", "0") for r in results)


def test_limit_worker_threads_rejects_zero():
    with pytest.raises(ValueError, match="threads must be >= 1"):
        limit_worker_threads(0)
