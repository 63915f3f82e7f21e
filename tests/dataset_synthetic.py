"""A stand-in annotator for the dataset tests: the real record's per-point keys, no simulation.

Kept in its own numpy-only module so that spawned pool workers can import it by name quickly.
"""

from __future__ import annotations

import numpy as np

_CRASH_AT = {"index": None, "seen": 0}


def synthetic_annotate(scene_seed: int, config) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """Deterministic in ``scene_seed``; sizes follow ``config`` like the real annotator."""
    rng = np.random.default_rng(scene_seed)
    n, m = config.annotation_points, int(rng.integers(config.min_parcels, config.max_parcels + 1))
    normals = rng.normal(size=(n, 3))
    record = {
        "points": rng.uniform(-0.3, 0.3, size=(n, 3)).astype(np.float32),
        "normals": (normals / np.linalg.norm(normals, axis=1, keepdims=True)).astype(np.float32),
        "labels": rng.uniform(size=(n, 4)).astype(np.float32),
        "object_ids": rng.integers(-1, m, size=n).astype(np.int32),
        "object_categories": np.array(["rectangular", "planar", "cylindrical"] * m)[:m],
        "num_parcels": np.array(m), "layout": np.array("stacked"), "object_set": np.array("mixed"),
        "scene_seed": np.array(scene_seed, dtype=np.int64),
    }
    record["score"] = record["labels"].prod(axis=1)
    return record, {"pile": 0.0}


def crash_after(count: int) -> None:
    """Make ``crashing_annotate`` die on its ``count``-th call in this process (0-based)."""
    _CRASH_AT.update(index=count, seen=0)


def crashing_annotate(scene_seed: int, config) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """Like ``synthetic_annotate`` until the call set by ``crash_after``, which raises as a kill would."""
    if _CRASH_AT["seen"] == _CRASH_AT["index"]:
        raise KeyboardInterrupt("simulated kill")
    _CRASH_AT["seen"] += 1
    return synthetic_annotate(scene_seed, config)
