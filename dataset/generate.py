"""Generate a sharded, labelled dataset with a local process pool or a Ray cluster; resumable.

    python -m dataset.generate --out data/train --scenes 25000 --split train --workers 2 --seed 0
    python -m dataset.generate --out data/train --scenes 25000 --backend ray --ray-address auto

Scene ``i`` is always annotated from ``config.scene_seed(i)``, and shard ``k`` always holds the same
scene indices, so the output is identical for any backend and worker count, and re-running the same
command after a crash only makes the shards that are missing.
"""

from __future__ import annotations

import argparse
import json
import logging
import multiprocessing as mp
import os
import shutil
import sys
import tempfile
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from tqdm import tqdm

from dataset.config import (
    COMPRESSIONS,
    LAYOUTS,
    OBJECT_SETS,
    RANDOM,
    SPLITS,
    GenerationConfig,
)
from dataset.storage import (
    MANIFEST,
    CorruptShardError,
    Record,
    read_manifest,
    shard_name,
    verify_shard,
    write_manifest,
    write_shard,
)
from parcelpick_env.cli import check_output_path, run_cli
from parcelpick_env.suction.label_sets import LABEL_SETS

log = logging.getLogger(__name__)

# (scene_seed, config) -> (record, {stage: seconds}). Must be a module-level function: workers import it.
# None means dataset.annotate.annotate_scene_timed, imported only where scenes are annotated.
AnnotateFn = Callable[[int, GenerationConfig], "tuple[Record, dict[str, float]]"]
BACKENDS = ("local", "ray")


@dataclass
class GenerationReport:
    scenes_generated: int = 0
    shards_written: list[int] = field(default_factory=list)
    shards_skipped: list[int] = field(default_factory=list)
    shards_replaced: list[int] = field(default_factory=list)
    wall_seconds: float = 0.0
    stage_seconds: dict[str, float] = field(default_factory=dict)


# ----------------------------------------------------------------------------------------------- workers

_WORKER: dict[str, Any] = {}


def _init_worker(config: GenerationConfig, annotate_fn: AnnotateFn | None) -> None:
    if annotate_fn is None:
        from dataset.annotate import annotate_scene_timed as annotate_fn
    _WORKER["config"], _WORKER["annotate_fn"] = config, annotate_fn


def _annotate_index(index: int) -> tuple[int, Record, dict[str, float]]:
    config: GenerationConfig = _WORKER["config"]
    record, timings = _WORKER["annotate_fn"](config.scene_seed(index), config)
    return index, record, timings


def _ray_annotate(index: int, config: GenerationConfig,
                  annotate_fn: AnnotateFn | None) -> tuple[int, Record, dict[str, float]]:
    _init_worker(config, annotate_fn)
    return _annotate_index(index)


def _run_serial(indices: list[int], config: GenerationConfig,
                annotate_fn: AnnotateFn | None) -> Iterator[tuple]:
    _init_worker(config, annotate_fn)
    for index in indices:
        yield _annotate_index(index)


def _run_pool(indices: list[int], config: GenerationConfig, annotate_fn: AnnotateFn | None,
              workers: int) -> Iterator[tuple]:
    # spawn, not fork: pybullet, Open3D and OpenMP state must not be inherited; each worker builds its own.
    context = mp.get_context("spawn")
    pool = context.Pool(workers, initializer=_init_worker, initargs=(config, annotate_fn))
    finished = False
    try:
        yield from pool.imap_unordered(_annotate_index, indices, chunksize=1)
        finished = True
    finally:
        # A finished pool is closed, not terminated: its workers then exit normally and run their exit handlers,
        # which remove each worker's simulator temp directory. An interrupted one is stopped at once.
        if finished:
            pool.close()
        else:
            pool.terminate()
        pool.join()


def _run_ray(indices: list[int], config: GenerationConfig, annotate_fn: AnnotateFn | None, workers: int,
             address: str | None) -> Iterator[tuple]:
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    try:
        import ray
    except ImportError as exc:  # pragma: no cover - ray is a dev/optional dependency
        raise RuntimeError("the ray backend needs `pip install 'ray[default]'` (extra 'ray')") from exc
    started = False
    scratch = None
    if not ray.is_initialized():
        if address is None:
            # A local cluster's workers must import this checkout even when it is not pip-installed. Their
            # temporary files (each worker's simulator OBJ directory) go to one scratch directory removed
            # below: Ray kills its workers at shutdown, so their own exit handlers never run.
            root = str(Path(__file__).resolve().parents[1])
            path = os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH")) if p)
            scratch = tempfile.mkdtemp(prefix="parcelpick_ray_workers_")
            ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False,
                     runtime_env={"env_vars": {"PYTHONPATH": path, "RAY_USAGE_STATS_ENABLED": "0",
                                               "TMPDIR": scratch}})
        else:
            ray.init(address=address, log_to_driver=False)
        started = True
    try:
        task = ray.remote(num_cpus=1)(_ray_annotate)
        config_ref = ray.put(config)
        # Keep a bounded number of tasks in flight so results do not pile up in the object store.
        in_flight_limit = max(2, 2 * int(ray.cluster_resources().get("CPU", workers)))
        pending, queue = [], list(indices)
        while queue or pending:
            while queue and len(pending) < in_flight_limit:
                pending.append(task.remote(queue.pop(0), config_ref, annotate_fn))
            done, pending = ray.wait(pending, num_returns=1)
            yield ray.get(done[0])
    finally:
        if started:
            ray.shutdown()
        if scratch is not None:
            shutil.rmtree(scratch, ignore_errors=True)


# ----------------------------------------------------------------------------------------------- driver

def _normalised(config: GenerationConfig) -> dict[str, Any]:
    return json.loads(json.dumps(config.to_dict()))


def _existing_shards(out: Path, config: GenerationConfig, report: GenerationReport) -> dict[int, dict[str, Any]]:
    """Verified shards already on disk; corrupt ones are removed so they are made again.

    Every shard is re-read and its checksum recomputed: minutes for a paper-size dataset, against
    hours of generation, and it also catches a shard damaged after it was written.
    """
    done: dict[int, dict[str, Any]] = {}
    for shard in range(config.num_shards):
        path = out / shard_name(shard)
        if not path.exists():
            continue
        try:
            info = verify_shard(path, checksum=True, expected=config.shard_range(shard))
        except CorruptShardError as exc:
            log.warning("regenerating %s: %s", path.name, exc)
            path.unlink()
            report.shards_replaced.append(shard)
            continue
        done[shard] = {"file": path.name, "shard": shard, "scene_start": info.scene_start,
                       "scene_stop": info.scene_stop, "sha256": info.sha256, "bytes": path.stat().st_size}
        report.shards_skipped.append(shard)
    return done


def generate(
    out_dir: str | os.PathLike,
    config: GenerationConfig,
    *,
    workers: int = 1,
    backend: str = "local",
    ray_address: str | None = None,
    annotate_fn: AnnotateFn | None = None,
    progress: bool = True,
) -> GenerationReport:
    """Make (or finish) the dataset ``config`` describes in ``out_dir``.

    ``workers=1`` with the local backend annotates in this process; more use a spawn pool. An
    ``out_dir`` made with a different config is refused rather than silently mixed. ``annotate_fn``
    replaces the annotator (default ``dataset.annotate.annotate_scene_timed``).
    """
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers must be a positive integer, got {workers!r}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    report = GenerationReport()

    if (out / MANIFEST).exists():
        previous, wanted = read_manifest(out)["config"], _normalised(config)
        if previous != wanted:
            changed = sorted(k for k in set(previous) | set(wanted) if previous.get(k) != wanted.get(k))
            raise ValueError(f"{out} holds a dataset made with a different config (differs in {changed}); "
                             f"use another --out")
    for stale in list(out.glob("shard-*.h5.tmp")) + list(out.glob(MANIFEST + ".tmp")):
        log.info("removing interrupted write %s", stale.name)
        stale.unlink()

    done = _existing_shards(out, config, report)
    write_manifest(out, config.to_dict(), done.values(), complete=len(done) == config.num_shards)
    todo = [i for shard in range(config.num_shards) if shard not in done for i in config.shard_range(shard)]
    if not todo:
        report.wall_seconds = time.perf_counter() - started
        return report

    if backend == "ray":
        results = _run_ray(todo, config, annotate_fn, workers, ray_address)
    elif workers == 1:
        results = _run_serial(todo, config, annotate_fn)
    else:
        results = _run_pool(todo, config, annotate_fn, workers)

    pending: dict[int, dict[int, Record]] = defaultdict(dict)
    bar = tqdm(total=config.scenes, initial=config.scenes - len(todo), unit="scene", disable=not progress,
               desc=f"{config.split} -> {out}")
    try:
        for index, record, timings in results:
            for stage, seconds in timings.items():
                report.stage_seconds[stage] = report.stage_seconds.get(stage, 0.0) + seconds
            shard = index // config.scenes_per_shard
            pending[shard][index] = record
            report.scenes_generated += 1
            bar.update(1)
            if len(pending[shard]) == len(config.shard_range(shard)):
                t0, c0 = time.perf_counter(), time.process_time()
                done[shard] = write_shard(out / shard_name(shard), shard, pending.pop(shard),
                                          config.shard_range(shard), compression=config.compression,
                                          compression_level=config.compression_level)
                for key, spent in (("write", time.perf_counter() - t0), ("write_cpu", time.process_time() - c0)):
                    report.stage_seconds[key] = report.stage_seconds.get(key, 0.0) + spent
                report.shards_written.append(shard)
                write_manifest(out, config.to_dict(), done.values(), complete=len(done) == config.num_shards)
    finally:
        bar.close()
        close = getattr(results, "close", None)
        if close is not None:
            close()  # stops the pool / ray promptly when interrupted
    report.wall_seconds = time.perf_counter() - started
    return report


# ----------------------------------------------------------------------------------------------- CLI

def build_parser() -> argparse.ArgumentParser:
    d = GenerationConfig()
    p = argparse.ArgumentParser(prog="python -m dataset.generate", description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True, type=Path, help="dataset directory (created; resumed if it exists)")
    p.add_argument("--scenes", type=int, default=d.scenes)
    p.add_argument("--split", choices=SPLITS, default=d.split)
    p.add_argument("--seed", type=int, default=d.seed)
    p.add_argument("--workers", type=int, default=1, help="local processes, or CPUs for a local Ray")
    p.add_argument("--backend", choices=BACKENDS, default="local")
    p.add_argument("--ray-address", default=None, help="'auto' or ray://host:port; default starts a local Ray")
    p.add_argument("--parcels", nargs=2, type=int, metavar=("MIN", "MAX"), default=(d.min_parcels, d.max_parcels))
    p.add_argument("--layout", choices=LAYOUTS + (RANDOM,), default=d.layout)
    p.add_argument("--objects", choices=OBJECT_SETS + (RANDOM,), default=d.object_set)
    p.add_argument("--points", type=int, default=d.annotation_points, help="annotation points per scene")
    p.add_argument("--width", type=int, default=d.width)
    p.add_argument("--height", type=int, default=d.height)
    p.add_argument("--depth-noise", type=float, default=d.depth_noise_std, help="metres (default: camera's)")
    p.add_argument("--dropout", type=float, default=d.dropout_prob, help="pixel dropout probability")
    p.add_argument("--renderer", choices=("auto", "egl", "tiny"), default=d.renderer,
                   help="pybullet renderer (default: the camera's)")
    p.add_argument("--rgb-noise", nargs=2, type=float, metavar=("MIN", "MAX"), default=d.rgb_noise_std)
    p.add_argument("--fps-presample", type=float, default=d.fps_presample)
    p.add_argument("--scenes-per-shard", type=int, default=d.scenes_per_shard)
    p.add_argument("--library-seed", type=int, default=d.library_seed)
    p.add_argument("--compression", choices=COMPRESSIONS, default=d.compression)
    p.add_argument("--labels", choices=LABEL_SETS, default=d.labels,
                   help="channel set (docs/labels.md): the paper's, whether the env's own cup would hold the pick, "
                        "or SuctionNet's evaluator's")
    p.add_argument("--extra-labels", nargs="*", choices=LABEL_SETS, default=list(d.extra_labels),
                   help="more label sets stored beside the main one (labels_<set>, score_<set>)")
    p.add_argument("--no-images", action="store_true", help="store only the annotated points, not RGB-D")
    p.add_argument("--no-progress", action="store_true")
    return p


def config_from_args(args: argparse.Namespace) -> GenerationConfig:
    return GenerationConfig(
        scenes=args.scenes, split=args.split, seed=args.seed, min_parcels=args.parcels[0],
        max_parcels=args.parcels[1], layout=args.layout, object_set=args.objects,
        annotation_points=args.points, width=args.width, height=args.height, depth_noise_std=args.depth_noise,
        dropout_prob=args.dropout, renderer=args.renderer, rgb_noise_std=tuple(args.rgb_noise),
        fps_presample=args.fps_presample,
        scenes_per_shard=args.scenes_per_shard, library_seed=args.library_seed, compression=args.compression,
        store_images=not args.no_images, labels=args.labels,
        extra_labels=tuple(args.extra_labels),
    )


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    check_output_path(args.out, "--out", directory=True)
    try:
        config = config_from_args(args)
        report = generate(args.out, config, workers=args.workers, backend=args.backend,
                          ray_address=args.ray_address, progress=not args.no_progress)
    except ValueError as exc:
        parser.error(str(exc))
    n = max(report.scenes_generated, 1)
    stages = ", ".join(f"{k} {v / n:.2f}s" for k, v in report.stage_seconds.items()
                       if v > 0 and not k.endswith("_cpu"))
    print(f"{report.scenes_generated} scenes in {report.wall_seconds:.1f}s; "
          f"shards written {len(report.shards_written)}, "
          f"skipped {len(report.shards_skipped)}, replaced {len(report.shards_replaced)}; per scene: {stages}")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
