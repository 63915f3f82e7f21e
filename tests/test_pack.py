"""The compact training copy (dataset/pack.py) and what lets a trainer run on a machine without the simulator."""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from dataset.config import GenerationConfig
from dataset.generate import generate
from dataset.pack import main as pack_main, pack
from dataset.storage import CorruptShardError, open_dataset
from dataset.torch_dataset import ParcelSuctionDataset
from parcelpick_env.cli import UsageError

sys.path.insert(0, str(Path(__file__).resolve().parent))
from dataset_synthetic import synthetic_annotate  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def source(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("source")
    config = GenerationConfig(scenes=5, scenes_per_shard=2, annotation_points=200, width=16, height=16)
    generate(root, config, annotate_fn=synthetic_annotate, progress=False)
    return root


def test_the_copy_holds_the_model_arrays_in_half_precision_within_the_recorded_error(source, tmp_path):
    manifest = pack(source, tmp_path, progress=False)
    store, original = open_dataset(tmp_path, checksum=True), open_dataset(source)
    assert len(store) == 5 and [s["shard"] for s in manifest["shards"]] == [0, 1, 2]
    record = store.scene(3)
    assert sorted(record) == ["labels", "normals", "object_ids", "points"]  # nothing else travels
    assert all(record[key].dtype == np.float16 for key in ("points", "normals", "labels"))
    assert record["object_ids"].dtype == np.int16
    errors = manifest["config"]["pack"]["max_abs_error"]
    for i in range(5):
        packed, full = store.scene(i), original.scene(i)
        assert np.array_equal(packed["object_ids"], full["object_ids"])
        for key in ("points", "normals", "labels"):
            gap = np.abs(packed[key].astype(np.float64) - full[key]).max()
            assert 0 < gap <= errors[key] <= 2.0**-11 * np.abs(full[key]).max() + 1e-12  # float16's half step
    assert manifest["config"]["pack"]["source_manifest_sha256"] == hashlib.sha256(
        (source / "manifest.json").read_bytes()).hexdigest()
    # the trainer's reader serves it as float32, unchanged otherwise
    item = ParcelSuctionDataset(tmp_path)[3]
    assert item["points"].dtype == torch.float32
    assert torch.equal(item["points"], torch.from_numpy(record["points"].astype(np.float32)))


def test_a_label_set_and_a_scene_count_are_kept_as_asked(source, tmp_path):
    phys_root = tmp_path / "phys"  # a source with both label sets: the copy keeps only the one asked for
    config = GenerationConfig(scenes=2, scenes_per_shard=2, annotation_points=64, width=16, height=16)

    def two_sets(seed, cfg):
        record, times = synthetic_annotate(seed, cfg)
        return {**record, "labels_physical": record["labels"][:, ::-1].copy()}, times

    generate(phys_root, GenerationConfig(**{**config.to_dict(), "extra_labels": ("physical",),
                                            "suction": config.suction}), annotate_fn=two_sets, progress=False)
    manifest = pack(phys_root, tmp_path / "p", label_set="physical", progress=False)
    assert manifest["config"]["labels"] == "physical" and manifest["config"]["extra_labels"] == []
    kept = open_dataset(tmp_path / "p").scene(1)["labels"].astype(np.float32)
    assert np.allclose(kept, open_dataset(phys_root).scene(1)["labels_physical"], atol=1e-3)
    assert not np.allclose(kept, open_dataset(phys_root).scene(1)["labels"], atol=1e-3)
    assert ParcelSuctionDataset(tmp_path / "p", label_set="physical").label_set == "physical"
    first = pack(source, tmp_path / "three", scenes=3, progress=False)
    assert first["num_scenes"] == 3 and first["config"]["scenes"] == 3
    assert [(s["scene_start"], s["scene_stop"]) for s in first["shards"]] == [(0, 2), (2, 3)]


def test_a_unit_step_rounds_the_normals_and_labels_only_and_saves_bytes(source, tmp_path):
    plain = pack(source, tmp_path / "plain", progress=False)
    step = 2.0**-8
    rounded = pack(source, tmp_path / "rounded", progress=False, unit_step=step)
    a, b = open_dataset(tmp_path / "plain"), open_dataset(tmp_path / "rounded")
    for i in range(5):
        assert np.array_equal(a.scene(i)["points"], b.scene(i)["points"])  # points are not rounded further
        for key in ("normals", "labels"):
            values = b.scene(i)[key].astype(np.float64)
            assert np.allclose(values / step, np.round(values / step), atol=1e-6), key  # multiples of the step
    errors = rounded["config"]["pack"]["max_abs_error"]
    assert plain["config"]["pack"]["unit_step"] == 0.0 and rounded["config"]["pack"]["unit_step"] == step
    assert errors["normals"] <= step / 2 + 2.0**-11 and errors["normals"] > plain["config"]["pack"]["max_abs_error"][
        "normals"]
    assert sum(e["bytes"] for e in rounded["shards"]) < sum(e["bytes"] for e in plain["shards"])
    with pytest.raises(UsageError, match="--unit-step"):
        pack(source, tmp_path / "bad", progress=False, unit_step=float("nan"))


def test_bad_arguments_and_a_corrupt_source_fail_in_one_line(source, tmp_path, capsys):
    with pytest.raises(UsageError, match="--scenes must be in \\[1, 5\\]"):
        pack_main([str(source), str(tmp_path / "a"), "--scenes", "9", "--no-progress"])
    with pytest.raises(UsageError, match="physical"):  # a label set the source does not hold
        pack_main([str(source), str(tmp_path / "b"), "--label-set", "physical", "--no-progress"])
    with pytest.raises(UsageError, match="source .* does not exist"):
        pack_main([str(tmp_path / "missing"), str(tmp_path / "c")])
    with pytest.raises(UsageError, match="differ"):
        pack_main([str(source), str(source)])
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "manifest.json").write_text(json.dumps({"format_version": 1}) + "{")
    with pytest.raises(CorruptShardError, match="not valid JSON"):
        pack(broken, tmp_path / "d", progress=False)
    pack_main([str(source), str(tmp_path / "ok"), "--scenes", "2", "--no-progress"])
    assert "packed 2 scenes" in capsys.readouterr().out


def test_the_trainer_and_the_copy_import_without_the_simulator_or_open3d():
    """A lent GPU's image has torch but not pybullet, Open3D, trimesh, OMPL or ruckig (0.9 GB that cannot travel):
    training, the dataset reader and the pack must not need them."""
    heavy = ("open3d", "pybullet", "trimesh", "ompl", "ruckig", "rerun", "manifold3d")
    code = (f"import sys, importlib.abc\n"
            f"class Block(importlib.abc.MetaPathFinder):\n"
            f"    def find_spec(self, name, path=None, target=None):\n"
            f"        if name.split('.')[0] in {heavy!r}: raise ImportError('blocked ' + name)\n"
            f"sys.meta_path.insert(0, Block())\n"
            f"import policies.diffusion.train, policies.diffusion.checkpoint, dataset.torch_dataset, dataset.pack\n"
            f"print('ok')\n")
    result = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0 and result.stdout.strip() == "ok", result.stderr[-2000:]
