"""Ordered parallel map over independent jobs: a local process pool by default, Ray when asked.

Dataset generation and evaluation sweeps share this so that results never depend on the backend or
the worker count: every job carries its own seed, and results come back in submission order.
"""

from __future__ import annotations

import multiprocessing as mp
import os
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from typing import Any, Literal, TypeVar

from tqdm.auto import tqdm

T = TypeVar("T")
R = TypeVar("R")
Backend = Literal["local", "ray"]
BACKENDS: tuple[str, ...] = ("local", "ray")


def limit_worker_threads(threads: int = 1) -> None:
    """Bound this process's native thread pools, for a worker that shares the machine with others.

    Open3D ray-casts on a oneTBB pool whose idle workers spin (measured: an env worker's TBB thread burnt 0.35 s
    of CPU per second of stepping, making one env use 1.3 cores, so two workers on two cores could not double the
    rate); oneTBB reads no environment variable, so only ``open3d.utility.set_max_threads`` bounds it. OpenMP (Open3D's
    normals) reads ``OMP_NUM_THREADS`` when first loaded, so it is set before Open3D is imported; Mesa's llvmpipe
    reads ``LP_NUM_THREADS`` when a renderer starts (0: rasterise on the calling thread); torch's pool is bounded if
    torch is loaded. Results do not depend on it: every ray and normal is computed alike on any number of
    threads.
    """
    import sys

    if threads < 1:
        raise ValueError(f"threads must be >= 1, got {threads}")
    os.environ["OMP_NUM_THREADS"] = str(threads)
    os.environ["LP_NUM_THREADS"] = "0" if threads == 1 else str(threads)
    import open3d as o3d

    o3d.utility.set_max_threads(threads)
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(threads)


def _validate(backend: str, workers: int) -> None:
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; choose one of {BACKENDS}")
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")


def init_ray(address: str | None, num_cpus: int | None = None) -> None:
    """Connect to a cluster (``address='auto'`` or ``'ray://host:port'``) or start a local one."""
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    import ray

    if ray.is_initialized():
        return
    if address:
        ray.init(address=address, include_dashboard=False, log_to_driver=False)
    else:
        ray.init(num_cpus=num_cpus, include_dashboard=False, log_to_driver=False)


def parallel_map(fn: Callable[[T], R], items: Sequence[T], *, workers: int = 1, backend: Backend = "local",
                 ray_address: str | None = None, desc: str | None = None,
                 progress: bool = True) -> Iterator[R]:
    """Yield ``fn(item)`` for every item, in order. ``fn`` must be a picklable top-level function."""
    _validate(backend, workers)
    items = list(items)
    bar = tqdm(total=len(items), desc=desc, disable=not progress, dynamic_ncols=True)
    try:
        if backend == "ray":
            yield from _ray_map(fn, items, workers, ray_address, bar)
        elif workers == 1 or len(items) <= 1:
            for item in items:
                yield fn(item)
                bar.update()
        else:
            ctx = mp.get_context("spawn")  # pybullet and torch do not survive fork reliably
            with ProcessPoolExecutor(max_workers=min(workers, len(items)), mp_context=ctx,
                                     initializer=limit_worker_threads) as pool:
                for result in pool.map(fn, items):
                    yield result
                    bar.update()
    finally:
        bar.close()


def _in_limited_worker(fn: Callable[[T], R], item: T) -> R:
    """``fn(item)`` in a Ray worker, with its thread pools bounded as the local pool's initializer does."""
    limit_worker_threads()
    return fn(item)


def _ray_map(fn: Callable[[T], R], items: list[T], workers: int, address: str | None,
             bar: tqdm) -> Iterable[R]:
    import ray

    init_ray(address, num_cpus=None if address else workers)
    remote_fn: Any = ray.remote(num_cpus=1)(_in_limited_worker)  # a Ray RemoteFunction
    refs = [remote_fn.remote(fn, item) for item in items]
    for ref in refs:  # in submission order, so output order is backend-independent
        yield ray.get(ref)
        bar.update()
