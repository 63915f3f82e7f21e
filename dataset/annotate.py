"""Self-Parcel-Suction-Labeling for one scene: pile -> capture -> sample points -> shared scorer.

Everything a scene needs is drawn from its one ``scene_seed``, so any process that annotates the
same seed with the same config produces byte-identical arrays. Labels come only from
``parcelpick_env.suction`` (the scorer the environment and the evaluator also use). Each record also
keeps what an evaluator needs to rebuild the true meshes and re-score any prediction: the library
seed, every parcel's asset id and 6-D pose, and the bin.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from typing import Any

import numpy as np

from dataset.config import LAYOUTS, OBJECT_SETS, RANDOM, GenerationConfig
from parcelpick_env.farthest_points import fixed_size_sample

Record = dict[str, np.ndarray]
STAGES = ("pile", "render", "fps", "scoring", "write")  # timing keys; "<stage>_cpu" holds CPU seconds
LABEL_CHANNELS = ("seal", "wrench", "collision", "visibility")
# Unit-cube corner signs, in the order the 8 stored bounding-box corners follow.
_CORNER_SIGNS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)

_RESOURCES: dict[str, Any] = {}


def _resources(config: GenerationConfig) -> tuple[Any, Any, Any]:
    """This process's Simulator, asset library and camera, made once and reused scene after scene."""
    from parcelpick_env.assets.library import AssetLibrary
    from parcelpick_env.camera.camera import Camera
    from parcelpick_env.camera.config import CameraConfig
    from parcelpick_env.sim.simulator import Simulator

    overrides = {"width": config.width, "height": config.height}
    if config.depth_noise_std is not None:
        overrides["depth_noise_std"] = config.depth_noise_std
    if config.dropout_prob is not None:
        overrides["dropout_prob"] = config.dropout_prob
    if config.renderer is not None:
        overrides["renderer"] = config.renderer
    key = json.dumps([os.getpid(), config.library_seed, overrides], sort_keys=True)
    # Other simulators closing cannot blank this one's camera (parcelpick_env/sim/egl.py), so only a new key
    # (or a new process) needs a new simulator.
    if _RESOURCES.get("key") != key:
        if _RESOURCES.get("sim") is not None:
            _RESOURCES["sim"].close()
        _RESOURCES.update(key=key, sim=Simulator(), library=AssetLibrary.default(seed=config.library_seed),
                          camera=Camera(CameraConfig(**overrides)))
    return _RESOURCES["sim"], _RESOURCES["library"], _RESOURCES["camera"]


def _bounding_boxes(scene: Any) -> dict[str, np.ndarray]:
    """Oriented 3-D boxes: each parcel's body-frame mesh bounds carried by its pose."""
    m = len(scene.parcels)
    centers, extents, rotations = np.zeros((m, 3)), np.zeros((m, 3)), np.zeros((m, 3, 3))
    for i, parcel in enumerate(scene.parcels):
        T = parcel.transform
        lo, hi = parcel.asset.mesh.bounds
        rotations[i] = T[:3, :3]
        centers[i] = T[:3, :3] @ ((lo + hi) / 2) + T[:3, 3]
        extents[i] = hi - lo
    half = 0.5 * extents[:, None, :] * _CORNER_SIGNS[None]  # (M, 8, 3) in the box frame
    corners = centers[:, None, :] + np.einsum("mij,mkj->mki", rotations, half)
    return {"bbox_center": centers, "bbox_extent": extents, "bbox_rotation": rotations, "bbox_corners": corners}


def _label_scores(label_set: str, scene: Any, points: np.ndarray, normals: np.ndarray, object_ids: np.ndarray,
                  visibility: np.ndarray, config: GenerationConfig) -> Any:
    """One label set's four channels for the sampled points (docs/labels.md, "Label sets")."""
    from parcelpick_env.suction.quality import definition_scorer, score_definition
    from parcelpick_env.suction.scorer import SuctionScorer

    p, n = points.astype(np.float64), normals.astype(np.float64)
    if label_set == "paper":  # the paper's channels, with the run's own scorer config
        return SuctionScorer.from_scene(scene, config.suction).score(p, n, object_ids, visibility=visibility)
    scorer = definition_scorer(label_set, scene, num_threads=config.suction.num_threads)
    return score_definition(label_set, scorer, p, n, object_ids, visibility=visibility)


def annotate_scene_timed(scene_seed: int, config: GenerationConfig) -> tuple[Record, dict[str, float]]:
    """``annotate_scene`` plus wall and CPU seconds per stage (for benchmarks and progress reports)."""
    from parcelpick_env.scene.config import PileConfig
    from parcelpick_env.scene.pile import build_pile
    from parcelpick_env.suction.visibility import object_visibility

    if not isinstance(config, GenerationConfig):
        raise TypeError(f"config must be a GenerationConfig, got {type(config)}")
    if not 0 <= int(scene_seed) < 2**63:
        raise ValueError(f"scene_seed must be in [0, 2**63), got {scene_seed}")
    choice_ss, pile_ss, camera_ss, noise_ss, sample_ss = np.random.SeedSequence(int(scene_seed)).spawn(5)
    choice = np.random.default_rng(choice_ss)
    num_parcels = int(choice.integers(config.min_parcels, config.max_parcels + 1))
    layout = str(choice.choice(LAYOUTS)) if config.layout == RANDOM else config.layout
    object_set = str(choice.choice(OBJECT_SETS)) if config.object_set == RANDOM else config.object_set
    rgb_noise_std = float(choice.uniform(*config.rgb_noise_std))
    pile_seed = int(pile_ss.generate_state(1, dtype=np.uint64)[0] >> np.uint64(1))

    t0, c0 = time.perf_counter(), time.process_time()
    sim, library, camera = _resources(config)
    pile_config = PileConfig(num_parcels=num_parcels, layout=layout, object_set=object_set, split=config.split)
    scene = build_pile(sim, pile_config, seed=pile_seed, library=library)
    t1, c1 = time.perf_counter(), time.process_time()
    frame = camera.capture(sim, scene, np.random.default_rng(camera_ss), normals=False)  # normals: at samples only
    noise = np.random.default_rng(noise_ss).normal(0.0, rgb_noise_std, size=frame.rgb.shape)
    rgb = np.clip(np.rint(frame.rgb.astype(np.float64) + noise), 0, 255).astype(np.uint8)
    t2, c2 = time.perf_counter(), time.process_time()
    over_bin = (scene.bin.contains(frame.points, margin=scene.bin.wall_thickness, floor_tolerance=scene.bin.wall_thickness)
                if config.crop_to_bin else np.ones(len(frame.points), bool))  # wall tops kept: labelled negatives
    candidates = np.flatnonzero(over_bin)
    if len(candidates) == 0:
        raise RuntimeError(f"scene seed {scene_seed}: the camera saw no points over the bin")
    chosen = candidates[fixed_size_sample(frame.points[candidates], config.annotation_points,
                                          np.random.default_rng(sample_ss), config.fps_presample)]
    points = np.ascontiguousarray(frame.points[chosen], dtype=np.float32)
    tn, cn = time.perf_counter(), time.process_time()
    normals = np.ascontiguousarray(camera.normals_at(frame, chosen), dtype=np.float32)
    normals_s, normals_cpu = time.perf_counter() - tn, time.process_time() - cn  # timed as part of the render
    object_ids = np.ascontiguousarray(frame.point_object_ids[chosen], dtype=np.int32)
    pixels = np.ascontiguousarray(frame.point_pixels[chosen], dtype=np.int32)
    t3, c3 = time.perf_counter(), time.process_time()
    meshes = scene.world_meshes()
    visibility = np.asarray(object_visibility(meshes, frame.intrinsics, frame.extrinsics, frame.width, frame.height,
                                              occluders=scene.bin.meshes()), dtype=np.float64)
    label_sets = {name: _label_scores(name, scene, points, normals, object_ids, visibility, config)
                  for name in (config.labels, *config.extra_labels)}
    scores = label_sets[config.labels]
    labels = np.ascontiguousarray(scores.as_array(), dtype=np.float32)
    t4, c4 = time.perf_counter(), time.process_time()
    # wall seconds per stage, and this process's CPU seconds (all threads), which contention does not inflate
    timings = {"pile": t1 - t0, "render": t2 - t1 + normals_s, "fps": t3 - t2 - normals_s, "scoring": t4 - t3,
               "pile_cpu": c1 - c0, "render_cpu": c2 - c1 + normals_cpu, "fps_cpu": c3 - c2 - normals_cpu,
               "scoring_cpu": c4 - c3}

    parcels = scene.parcels
    record: Record = {
        # per point (what a model trains on)
        "points": points,
        "normals": normals,
        "labels": labels,  # LABEL_CHANNELS, of the label set below
        "label_set": np.array(config.labels),
        **{key: value for name in config.extra_labels for key, value in (
            (f"labels_{name}", np.ascontiguousarray(label_sets[name].as_array(), dtype=np.float32)),
            (f"score_{name}", np.ascontiguousarray(label_sets[name].total, dtype=np.float32)))},
        "score": np.ascontiguousarray(scores.total, dtype=np.float32),
        "object_ids": object_ids,
        "point_pixels": pixels,
        "colors": rgb[pixels[:, 0], pixels[:, 1]],
        # per object (what an evaluator needs to rebuild meshes and re-score)
        "object_asset_ids": np.array([p.asset.asset_id for p in parcels], dtype=str).reshape(-1),
        "object_categories": np.array([p.asset.category for p in parcels], dtype=str).reshape(-1),
        "object_poses": np.array([np.r_[p.position, p.orientation] for p in parcels], dtype=np.float64).reshape(-1, 7),
        "object_mass": scene.masses(),
        "object_com": np.array([p.asset.com for p in parcels], dtype=np.float64).reshape(-1, 3),
        "object_com_world": scene.world_coms(),
        "object_friction": np.array([p.friction for p in parcels], dtype=np.float64),
        "object_visibility": visibility,
        **_bounding_boxes(scene),
        # scene
        "intrinsics": np.asarray(frame.intrinsics, dtype=np.float64),
        "extrinsics": np.asarray(frame.extrinsics, dtype=np.float64),
        "bin_spec": np.array(json.dumps(dataclasses.asdict(scene.bin), sort_keys=True)),
        "library_seed": np.array(config.library_seed, dtype=np.int64),
        "scene_seed": np.array(int(scene_seed), dtype=np.int64),
        "pile_seed": np.array(pile_seed, dtype=np.int64),
        "split": np.array(config.split),
        "layout": np.array(layout),
        "object_set": np.array(object_set),
        "num_parcels": np.array(len(parcels), dtype=np.int64),
        "rgb_noise_std": np.array(rgb_noise_std, dtype=np.float64),
    }
    if config.store_images:
        record["rgb"] = rgb
        record["depth"] = np.asarray(frame.depth, dtype=np.float32)
        record["segmentation"] = np.asarray(frame.segmentation, dtype=np.int16)
    return record, timings


def annotate_scene(scene_seed: int, config: GenerationConfig) -> Record:
    """Build, capture and label one scene; see the module docstring for what the record holds."""
    return annotate_scene_timed(scene_seed, config)[0]
