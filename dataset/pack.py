"""A compact training copy of a dataset: only the arrays a model reads, in half precision, to travel light.

A generated scene holds RGB-D, pixel coordinates, colours, both label sets, scores and the objects' poses; the trainer
reads four arrays of it (``dataset.torch_dataset.ITEM_KEYS``: points, normals, one label set, object ids). At 16,384
points those four are ~390 KB of a scene's ~1 MB (float32, gzip); in float16 with gzip 9 they are ~175 KB, so ~280
scenes fit beside the repository in the 64 MiB that travels to a lent GPU (docs/training.md). Half precision is
within what training adds anyway: a coordinate under 1 m moves by at most 0.24 mm (0.24 mm measured on a 16,384-point
training set), against the 1 mm jitter of augmentation; a normal or a label by at most 2.4e-4. The largest error of
each array is measured and kept.

The copy is a dataset directory of the same format (manifest, shards, a digest on every array), read by the same
code; its manifest's ``config.pack`` names the source, its manifest's SHA-256 and the errors, and its ``labels`` is
the one label set kept.
"""

from __future__ import annotations

import argparse
import hashlib
import sys
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from dataset.storage import MANIFEST, open_dataset, shard_name, write_manifest, write_shard
from dataset.torch_dataset import label_key
from parcelpick_env.cli import UsageError, check_input_dir, check_output_path, run_cli
from parcelpick_env.suction.label_sets import LABEL_SETS

HALF_KEYS = ("points", "normals", "labels")  # stored as float16; object_ids as the narrowest int that holds them
UNIT_KEYS = ("normals", "labels")  # values in [-1, 1]: what ``unit_step`` rounds
COMPRESSION_LEVEL = 9  # the copy is written once and read many times: the slowest gzip costs nothing later


def _narrow_ids(ids: np.ndarray) -> np.ndarray:
    return ids.astype(np.int16) if ids.size == 0 or (ids.min() >= -2**15 and ids.max() < 2**15) else ids


def pack_scene(arrays: dict[str, np.ndarray], stored_labels: str, unit_step: float = 0.0
               ) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """(record, largest absolute rounding error per half-precision array) of one scene's model arrays; ``unit_step``
    > 0 first rounds the normals and labels to its multiples (gzip then stores them in fewer bytes)."""
    source = {"points": arrays["points"], "normals": arrays["normals"], "labels": arrays[stored_labels]}
    record: dict[str, np.ndarray] = {}
    errors: dict[str, float] = {}
    for key, value in source.items():
        value = np.asarray(value, dtype=np.float64)
        rounded = np.round(value / unit_step) * unit_step if unit_step > 0 and key in UNIT_KEYS else value
        half = rounded.astype(np.float16)
        if not np.isfinite(half).all():
            raise ValueError(f"{key} exceeds float16's range (|x| <= 65504)")
        record[key] = half
        errors[key] = float(np.abs(half.astype(np.float64) - value).max(initial=0.0))
    record["object_ids"] = _narrow_ids(np.asarray(arrays["object_ids"]))
    return record, errors


def pack(source: Path, out: Path, label_set: str | None = None, scenes: int | None = None,
         progress: bool = True, unit_step: float = 0.0) -> dict[str, Any]:
    """Write the compact copy of ``source`` (its first ``scenes`` scenes, default all) to ``out``; return the
    manifest. Shard ``k`` of the copy holds the scenes of the source's shard ``k``. ``unit_step``: see
    :func:`pack_scene` (0, the default, rounds only to float16)."""
    if not (np.isfinite(unit_step) and 0.0 <= unit_step <= 0.1):
        raise UsageError(f"--unit-step must be in [0, 0.1], got {unit_step}")
    store = open_dataset(source)  # every array read is checked against its digest
    config = dict(store.config)
    kept, stored = label_key(config, label_set, source)
    total = len(store) if scenes is None else scenes
    if not 1 <= total <= len(store):
        raise UsageError(f"--scenes must be in [1, {len(store)}] for {source}, got {scenes}")
    out.mkdir(parents=True, exist_ok=True)
    entries, worst = [], dict.fromkeys(HALF_KEYS, 0.0)
    keys = ("points", "normals", stored, "object_ids")
    with tqdm(total=total, desc="pack", unit="scene", disable=not progress, file=sys.stderr) as bar:
        for shard in store.manifest["shards"]:
            start, stop = shard["scene_start"], min(shard["scene_stop"], total)
            if start >= total:
                break
            records = {}
            for index in range(start, stop):
                records[index], errors = pack_scene(store.scene(index, keys), stored, unit_step)
                worst = {key: max(worst[key], errors[key]) for key in HALF_KEYS}
                bar.update(1)
            entries.append(write_shard(out / shard_name(shard["shard"]), shard["shard"], records, range(start, stop),
                                       compression="gzip", compression_level=COMPRESSION_LEVEL))
    store.close()
    config.update(labels=kept, extra_labels=[], store_images=False, scenes=total, pack={
        "source": str(source), "source_manifest_sha256": hashlib.sha256((source / MANIFEST).read_bytes()).hexdigest(),
        "dtype": "float16", "unit_step": unit_step, "max_abs_error": worst})
    return write_manifest(out, config, entries, complete=True)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m dataset.pack", description=__doc__.split("\n\n")[0])
    p.add_argument("source", type=Path, help="dataset directory made by python -m dataset.generate")
    p.add_argument("out", type=Path, help="directory for the compact copy (created)")
    p.add_argument("--label-set", choices=list(LABEL_SETS), default=None,
                   help="the label set to keep (default: the source's main one)")
    p.add_argument("--scenes", type=int, default=None, help="keep the first N scenes (default: all)")
    p.add_argument("--unit-step", type=float, default=0.0,
                   help="round normals and labels to multiples of this first (0.00390625 = 1/256 stores a 16,384-point "
                        "scene in ~133 KB instead of ~175 KB, to within 0.002)")
    p.add_argument("--no-progress", action="store_true")
    args = p.parse_args(argv)
    check_input_dir(args.source, "source")
    check_output_path(args.out, "out", directory=True)
    if args.out.resolve() == args.source.resolve():
        raise UsageError("out must differ from source")
    try:
        manifest = pack(args.source, args.out, args.label_set, args.scenes, progress=not args.no_progress,
                        unit_step=args.unit_step)
    except ValueError as e:  # a label set the source does not hold, or a value past float16
        raise UsageError(str(e)) from e
    size = sum(entry["bytes"] for entry in manifest["shards"])
    errors = ", ".join(f"{k} {v:.2g}" for k, v in manifest["config"]["pack"]["max_abs_error"].items())
    print(f"packed {manifest['num_scenes']} scenes of {args.source} into {args.out}: {size / 2**20:.1f} MiB, "
          f"labels {manifest['config']['labels']!r}; largest rounding error: {errors}")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
