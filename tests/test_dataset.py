"""Dataset pipeline: generation, storage integrity, resume, backends, torch Dataset and stats.

Real-pipeline tests share one tiny dataset (160x120 images, 2-4 parcels, 512 points) made once
per module; storage-only tests use a synthetic stand-in annotator (tests/dataset_synthetic.py).
"""

from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch

from dataset.annotate import annotate_scene
from dataset.config import GenerationConfig
from dataset.generate import generate, main as generate_main
from dataset.stats import compute_stats, format_table, plot_stats
from dataset.storage import (
    CorruptShardError,
    open_dataset,
    read_manifest,
    shard_name,
    verify_shard,
)
from dataset.torch_dataset import ParcelSuctionDataset

sys.path.insert(0, str(Path(__file__).resolve().parent))  # spawned workers import the stand-in by name
from dataset_synthetic import crash_after, crashing_annotate, synthetic_annotate  # noqa: E402
from fresh_process import in_fresh_process  # noqa: E402

os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")

TINY = dict(width=160, height=120, min_parcels=2, max_parcels=4, annotation_points=512, object_set="rectangular",
            fps_presample=0.0)


def _tiny(**overrides) -> GenerationConfig:
    return GenerationConfig(**{**TINY, "scenes": 2, "scenes_per_shard": 1, **overrides})


def _all_arrays(root: Path) -> dict[int, dict[str, np.ndarray]]:
    store = open_dataset(root, checksum=True)
    return {idx: store.scene(i) for i, idx in enumerate(store.scene_indices)}


def _assert_identical(a: dict, b: dict) -> None:
    assert sorted(a) == sorted(b)
    for idx in a:
        assert sorted(a[idx]) == sorted(b[idx])
        for key in a[idx]:
            x, y = a[idx][key], b[idx][key]
            assert x.dtype == y.dtype and x.shape == y.shape, (idx, key)
            if x.dtype.kind == "U":
                assert np.array_equal(x, y), (idx, key)
            else:
                assert x.tobytes() == y.tobytes(), (idx, key)


# --------------------------------------------------------------------------- config

@pytest.mark.parametrize("bad", [
    dict(scenes=0), dict(split="val"), dict(min_parcels=0), dict(min_parcels=5, max_parcels=3),
    dict(max_parcels=51), dict(layout="heap"), dict(object_set="spheres"), dict(annotation_points=0),
    dict(width=16, height=16, annotation_points=1000), dict(rgb_noise_std=(5.0, 1.0)),
    dict(rgb_noise_std=(-1.0, 1.0)), dict(rgb_noise_std=3.0), dict(renderer="opengl"), dict(scenes_per_shard=0), dict(compression="zstd"), dict(seed=-1),
    dict(dropout_prob=1.5), dict(depth_noise_std=float("nan")), dict(fps_presample=0.5), dict(scenes=2.5),
])
def test_bad_config_raises(bad):
    with pytest.raises(ValueError):
        GenerationConfig(**bad)


def test_scene_seeds_and_shards_are_fixed_by_config():
    config = GenerationConfig(scenes=250, scenes_per_shard=100, seed=3)
    assert config.num_shards == 3 and config.shard_range(2) == range(200, 250)
    seeds = [config.scene_seed(i) for i in range(250)]
    assert len(set(seeds)) == 250
    assert seeds[7] == GenerationConfig(scenes=1000, seed=3).scene_seed(7)  # index, not run size, decides
    assert seeds[7] != GenerationConfig(scenes=250, seed=3, split="test").scene_seed(7)
    assert GenerationConfig.from_dict(config.to_dict()) == config
    with pytest.raises(ValueError):
        generate("unused", config, workers=0)


# --------------------------------------------------------------------------- storage (synthetic records)

def test_kill_and_resume_matches_uninterrupted_run(tmp_path):
    config = GenerationConfig(scenes=7, scenes_per_shard=3, annotation_points=64, width=16, height=16)
    generate(tmp_path / "ref", config, annotate_fn=synthetic_annotate, progress=False)

    out = tmp_path / "resumed"
    crash_after(4)  # shard 0 (scenes 0-2) written, shard 1 half done, then killed
    with pytest.raises(KeyboardInterrupt):
        generate(out, config, annotate_fn=crashing_annotate, progress=False)
    assert (out / shard_name(0)).exists() and not (out / shard_name(1)).exists()
    assert not read_manifest(out)["complete"]
    with pytest.raises(CorruptShardError, match="incomplete"):
        open_dataset(out)
    (out / (shard_name(1) + ".tmp")).write_bytes(b"half a shard")  # a write cut short by the kill

    report = generate(out, config, annotate_fn=synthetic_annotate, progress=False)
    assert report.shards_skipped == [0] and sorted(report.shards_written) == [1, 2]
    assert report.scenes_generated == 4  # no scene is made twice
    assert not list(out.glob("*.tmp"))
    _assert_identical(_all_arrays(tmp_path / "ref"), _all_arrays(out))
    assert open_dataset(out).scene_indices == list(range(7))

    again = generate(out, config, annotate_fn=synthetic_annotate, progress=False)
    assert again.scenes_generated == 0 and again.shards_skipped == [0, 1, 2]
    with pytest.raises(ValueError, match="different config"):
        generate(out, GenerationConfig(**{**config.to_dict(), "seed": 1, "suction": config.suction}),
                 annotate_fn=synthetic_annotate, progress=False)


def test_process_pool_matches_serial_run(tmp_path):
    config = GenerationConfig(scenes=5, scenes_per_shard=2, annotation_points=64, width=16, height=16)
    generate(tmp_path / "serial", config, annotate_fn=synthetic_annotate, progress=False)
    report = generate(tmp_path / "pool", config, workers=2, annotate_fn=synthetic_annotate, progress=False)
    assert sorted(report.shards_written) == [0, 1, 2] and report.scenes_generated == 5
    _assert_identical(_all_arrays(tmp_path / "serial"), _all_arrays(tmp_path / "pool"))


def test_truncated_or_corrupt_shard_is_named(tmp_path):
    config = GenerationConfig(scenes=4, scenes_per_shard=2, annotation_points=256, width=16, height=16)
    generate(tmp_path, config, annotate_fn=synthetic_annotate, progress=False)
    victim = tmp_path / shard_name(1)
    data = victim.read_bytes()
    victim.write_bytes(data[: len(data) // 2])
    with pytest.raises(CorruptShardError, match=shard_name(1)):
        open_dataset(tmp_path)
    with pytest.raises(CorruptShardError, match=shard_name(1)):
        verify_shard(victim)

    victim.write_bytes(data)  # same size, but one flipped label value
    with h5py.File(victim, "r+") as handle:
        handle["scene_00000003/labels"][0, 0] += 0.5
    with pytest.raises(CorruptShardError, match=f"{shard_name(1)}.*checksum"):
        verify_shard(victim)

    report = generate(tmp_path, config, annotate_fn=synthetic_annotate, progress=False)  # resume repairs it
    assert report.shards_replaced == [1] and report.shards_written == [1]
    open_dataset(tmp_path, checksum=True)
    (tmp_path / shard_name(0)).unlink()
    with pytest.raises(CorruptShardError, match=f"{shard_name(0)} is missing"):
        open_dataset(tmp_path)


def test_torch_dataset_subsamples_augments_and_loads_in_workers(tmp_path):
    config = GenerationConfig(scenes=3, scenes_per_shard=2, annotation_points=300, width=32, height=32)
    generate(tmp_path, config, annotate_fn=synthetic_annotate, progress=False)
    plain = ParcelSuctionDataset(tmp_path, split="train")
    item = plain[2]
    stored = open_dataset(tmp_path).scene(2)
    assert torch.equal(item["points"], torch.from_numpy(stored["points"]))
    assert item["object_ids"].dtype == torch.int64 and item["labels"].shape == (300, 4)

    aug = ParcelSuctionDataset(tmp_path, num_points=128, augment=True, jitter_std=0.0, shuffle_points=True, seed=5)
    a = aug[2]
    assert a["points"].shape == (128, 3) and a["normals"].shape == (128, 3)
    # rotation about z: heights and normal z unchanged, labels follow their points
    rows = [int(np.flatnonzero((stored["labels"] == lab.numpy()).all(1))[0]) for lab in a["labels"][:10]]
    assert np.allclose(a["points"][:10, 2].numpy(), stored["points"][rows, 2], atol=1e-6)
    assert np.allclose(a["normals"][:10, 2].numpy(), stored["normals"][rows, 2], atol=1e-6)
    assert not np.allclose(a["points"][:10, :2].numpy(), stored["points"][rows, :2], atol=1e-3)
    assert torch.equal(aug[2]["points"], a["points"])  # same epoch -> same draw
    aug.set_epoch(1)
    assert not torch.equal(aug[2]["points"], a["points"])
    with pytest.raises(ValueError):
        ParcelSuctionDataset(tmp_path, split="test")
    with pytest.raises(ValueError):
        ParcelSuctionDataset(tmp_path, num_points=0)

    loader = torch.utils.data.DataLoader(ParcelSuctionDataset(tmp_path, num_points=64), batch_size=3, num_workers=1)
    batch = next(iter(loader))
    assert batch["points"].shape == (3, 64, 3) and batch["labels"].dtype == torch.float32


def test_stats_table_and_png(tmp_path, capsys):
    config = GenerationConfig(scenes=2, annotation_points=100, width=16, height=16)
    generate(tmp_path, config, annotate_fn=synthetic_annotate, progress=False)
    stats = compute_stats(tmp_path)
    assert stats.num_scenes == 2 and sum(stats.histograms["seal"]) == 200
    labels = np.concatenate([open_dataset(tmp_path).scene(i)["labels"] for i in range(2)])
    ids = np.concatenate([open_dataset(tmp_path).scene(i)["object_ids"] for i in range(2)])
    assert np.allclose(stats.category_means["background"][:4], labels[ids < 0].mean(0), atol=1e-5)
    assert "| background |" in format_table(stats)
    plot_stats(stats, tmp_path / "s.png")
    assert (tmp_path / "s.png").read_bytes()[:4] == b"\x89PNG"


# --------------------------------------------------------------------------- the real pipeline

@pytest.fixture(scope="module")
def real_dataset(tmp_path_factory) -> tuple[Path, GenerationConfig]:
    out = tmp_path_factory.mktemp("real")
    # 8-10 parcels: enough for some to occlude others, so every label channel varies
    config = _tiny(scenes=2, seed=11, min_parcels=8, max_parcels=10)
    assert generate_main(["--out", str(out), "--scenes", "2", "--seed", "11", "--parcels", "8", "10",
                          "--objects", "rectangular", "--points", "512", "--width", "160", "--height", "120",
                          "--scenes-per-shard", "1", "--fps-presample", "0", "--no-progress"]) == 0
    assert read_manifest(out)["config"] == __import__("json").loads(__import__("json").dumps(config.to_dict()))
    return out, config


def test_real_dataset_shapes_dtypes_and_ranges(real_dataset):
    root, config = real_dataset
    store = open_dataset(root, checksum=True)
    assert len(store) == 2
    for i in range(2):
        s = store.scene(i)
        n, m = 512, int(s["num_parcels"])
        assert 8 <= m <= 10 and s["object_poses"].shape == (m, 7) and s["bbox_corners"].shape == (m, 8, 3)
        assert s["points"].shape == (n, 3) and s["points"].dtype == np.float32
        assert s["labels"].shape == (n, 4) and s["labels"].dtype == np.float32
        assert s["object_ids"].dtype == np.int32 and s["object_ids"].max() < m and s["object_ids"].min() >= -1
        assert np.all((s["labels"] >= 0) & (s["labels"] <= 1))
        assert np.allclose(s["score"], s["labels"].prod(axis=1), atol=1e-6)
        assert np.allclose(np.linalg.norm(s["normals"], axis=1), 1.0, atol=1e-3)
        assert s["rgb"].shape == (120, 160, 3) and s["depth"].shape == (120, 160)
        assert set(s["object_categories"]) == {"rectangular"}
        assert int(s["library_seed"]) == 0 and s["split"] == "train"
        # corners really are the oriented box of the pose: centre = mean of corners
        assert np.allclose(s["bbox_corners"].mean(axis=1), s["bbox_center"], atol=1e-9)
    item = ParcelSuctionDataset(root, split="train")[0]
    assert item["points"].dtype == torch.float32 and item["labels"].shape == (512, 4)


def test_real_labels_vary_and_box_tops_beat_edges(real_dataset):
    """Seal is high in the middle of a box's top face and low within a few mm of its rim."""
    from parcelpick_env.assets.library import AssetLibrary

    root, _ = real_dataset
    store = open_dataset(root)
    library = AssetLibrary.default(seed=0)
    interior, edge, on_objects = [], [], []
    for i in range(len(store)):
        s = store.scene(i)
        on_objects.append(s["labels"][s["object_ids"] >= 0])
        assert s["labels"][:, 0].std() > 0.1 and s["labels"][:, 2].std() > 0.1  # not constant
        assert len(np.unique(s["object_ids"])) >= 2
        for k in range(int(s["num_parcels"])):
            on = s["object_ids"] == k
            if not on.any():
                continue
            # the stored pose rebuilds the true mesh: sampled points lie on its surface
            asset = library.get(str(s["object_asset_ids"][k]))
            R, c, e = s["bbox_rotation"][k], s["bbox_center"][k], s["bbox_extent"][k]
            local = (s["points"][on] - c) @ R  # box frame
            up = int(np.argmax(np.abs(R[2])))  # box axis closest to world z
            top = np.abs(np.abs(local[:, up]) - e[up] / 2) < 0.006
            side = [a for a in range(3) if a != up]
            to_rim = np.min(e[side] / 2 - np.abs(local[:, side]), axis=1)
            vertical = np.abs(s["normals"][on][:, 2]) > 0.95
            seal = s["labels"][on][:, 0]
            interior.extend(seal[top & vertical & (to_rim > 0.02)])
            edge.extend(seal[top & (to_rim < 0.004)])
            assert asset.category == "rectangular"
    # wrench is mostly 0 on big boxes (lever > 5 cm), but must be positive near the centre of mass
    assert all(len(np.unique(channel)) > 1 for channel in np.concatenate(on_objects).T)
    assert len(interior) >= 20 and len(edge) >= 3, (len(interior), len(edge))
    assert np.mean(interior) > 0.8 and np.mean(interior) > np.mean(edge) + 0.4, (np.mean(interior), np.mean(edge))


def _assert_same_scenes(a: dict, b: dict) -> None:
    """Byte-identical, RGB included: rendering must not depend on what the process simulated before."""
    _assert_identical(a, b)


def test_annotation_is_deterministic_per_seed(real_dataset):
    """Scene 1 again, now in a process that has simulated other scenes since: same geometry and labels."""
    root, config = real_dataset
    _assert_same_scenes({1: annotate_scene(config.scene_seed(1), config)}, {1: open_dataset(root).scene(1)})


def test_annotation_survives_another_simulator_closing(real_dataset):
    """pybullet's EGL state is process-wide: a simulator closed elsewhere must not blank the cached one's renders."""
    from parcelpick_env.sim.simulator import Simulator

    _, config = real_dataset
    before = annotate_scene(config.scene_seed(0), config)
    with Simulator() as other:
        other.client  # noqa: B018  (connects, so closing it really releases an EGL client)
    _assert_same_scenes({0: before}, {0: annotate_scene(config.scene_seed(0), config)})


def test_ray_backend_matches_local(real_dataset, tmp_path):
    pytest.importorskip("ray")
    root, config = real_dataset
    report = in_fresh_process(generate, tmp_path, config, workers=1, backend="ray", progress=False)
    assert report.scenes_generated == 2
    _assert_same_scenes(_all_arrays(root), _all_arrays(tmp_path))


def test_real_resume_after_kill_rebuilds_only_the_missing_shard(real_dataset, tmp_path):
    root, config = real_dataset
    out = tmp_path / "resumed"
    shutil.copytree(root, out)
    (out / shard_name(1)).rename(out / (shard_name(1) + ".tmp"))  # killed before the rename
    report = generate(out, config, progress=False)
    assert report.shards_skipped == [0] and report.shards_written == [1] and report.scenes_generated == 1
    assert read_manifest(out)["complete"] and not list(out.glob("*.tmp"))
    _assert_same_scenes(_all_arrays(root), _all_arrays(out))
