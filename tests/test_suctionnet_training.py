"""Training on a GraspNet/SuctionNet root: ``--data ROOT`` serves the records the reader makes of its train views,
the three trainers run on it unchanged, and a tree without SuctionNet's labels fails in one line.

Three tiny generated scenes (160x120, 2-4 parcels) are written once as train scenes 0-2 of a miniature tree, with
the ParcelPick sidecars removed, so the tree reads as real SuctionNet data would (sampled points, estimated
normals, labels only from the seal / wrench / collision files).
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from generated_records import generate_records
import torch

from dataset.suctionnet.layout import Layout, SuctionNetLayoutError, is_suctionnet_root
from dataset.suctionnet.reader import read_view
from dataset.suctionnet.views import open_store, store_config, suctionnet_views
from dataset.suctionnet.writer import WriterConfig, write_records

CAMERA = "realsense"
SCENES = (0, 1, 2)
TINY = dict(width=160, height=120, min_parcels=2, max_parcels=4, annotation_points=512, object_set="mixed",
            scenes=len(SCENES), split="train")


@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    native = tmp_path_factory.mktemp("native")
    records = generate_records(native, **TINY)
    root = tmp_path_factory.mktemp("sn") / "graspnet"
    write_records(records, root, scenes=list(SCENES), config=WriterConfig(camera=CAMERA))
    for scene in SCENES:
        Layout(root).view_file(scene, CAMERA, "parcelpick", 0).unlink()
    return root, native


def test_a_root_is_served_as_the_reader_reads_its_train_views(tree):
    from dataset.torch_dataset import ParcelSuctionDataset

    root, native = tree
    assert is_suctionnet_root(root) and not is_suctionnet_root(native)
    store = open_store(root)
    assert len(store) == len(SCENES) and store.config["split"] == "train" and store.config["cameras"] == [CAMERA]
    assert store.config["views"] == [[CAMERA, s, 0] for s in SCENES]
    data = ParcelSuctionDataset(root, split="train")
    assert data.label_set == "suctionnet"  # SuctionNet's own labels, not a ParcelPick label set
    with pytest.raises(ValueError, match="holds the label sets"):
        ParcelSuctionDataset(root, label_set="physical")
    for i, scene in enumerate(SCENES):
        record = read_view(root, scene, CAMERA, 0)
        item = data[i]
        np.testing.assert_array_equal(item["points"].numpy(), record["points"])
        np.testing.assert_array_equal(item["normals"].numpy(), record["normals"])
        np.testing.assert_array_equal(item["labels"].numpy(), record["labels"])
        # the channels Diffusion_Suction trains on: seal, wrench, collision-free, visibility (1: SuctionNet has none)
        on = item["object_ids"].numpy() >= 0
        labels = item["labels"].numpy()
        assert np.all(labels[on, 3] == 1.0) and np.all(labels[~on] == 0.0) and np.any(labels[on, 0] > 0)
        cam = record["extrinsics"][:3, 3]
        assert np.all(np.sum((cam - item["points"].numpy()) * item["normals"].numpy(), axis=1) >= -1e-6)
    assert store_config(native)["split"] == "train" and "views" not in store_config(native)
    with pytest.raises(KeyError, match="has no"):
        store.scene(0, ["points", "no_such_key"])


def test_the_diffusion_trainer_runs_on_a_root(tree, tmp_path):
    from policies.diffusion.checkpoint import load_checkpoint
    from policies.diffusion.train import main

    out = tmp_path / "diffusion"
    main(["--data", str(tree[0]), "--out", str(out), "--preset", "tiny", "--num-points", "256", "--steps", "2",
          "--inference-steps", "2", "--batch-size", "2", "--val-every", "2", "--val-scenes", "1", "--threads", "1",
          "--no-progress"])
    payload = load_checkpoint(out / "last.pt", map_location="cpu")
    assert payload["step"] == 2 and np.isfinite(payload["extra"]["metrics"]["loss"])
    assert str(tree[0]) in str(payload["extra"]["provenance"])


def test_the_cao_trainer_runs_on_a_root(tree, tmp_path, capsys):
    from policies.cao.train import main

    out = tmp_path / "cao.pt"
    assert main(["--data", str(tree[0]), "--out", str(out), "--epochs", "1", "--input-height", "48",
                 "--input-width", "64", "--widths", "4", "8", "--threads", "1", "--quiet"]) == 0
    meta = torch.load(out, weights_only=True)["meta"]
    assert meta["scenes"] == len(SCENES) and meta["dataset_config"]["source"] == "suctionnet"
    assert "trained on" in capsys.readouterr().out


def test_the_dexnet_trainer_runs_on_a_root(tree, tmp_path):
    from policies.dexnet.train import main

    out = tmp_path / "dexnet.pt"
    history = main(["--data", str(tree[0]), "--out", str(out), "--epochs", "1", "--batch-size", "32",
                    "--samples-per-epoch", "64", "--max-points-per-scene", "200", "--no-progress"])
    assert history["train_samples"] > 0 and np.isfinite(history["final_loss"])
    from policies.dexnet.network import load_checkpoint

    _, meta = load_checkpoint(out)
    assert meta["num_scenes"] == len(SCENES) and meta["dataset_config"]["source"] == "suctionnet"


def test_a_root_without_suctionnet_labels_fails_in_one_line(tree, tmp_path, capsys):
    from dataset.torch_dataset import ParcelSuctionDataset
    from policies.cao.train import main as cao_main
    from policies.diffusion.train import main as diffusion_main

    root = shutil.copytree(tree[0], tmp_path / "graspnet_only")
    shutil.rmtree(root / "seal_label")
    message = "without SuctionNet-1Billion's labels (no seal_label/)"
    with pytest.raises(SuctionNetLayoutError, match=r"without SuctionNet-1Billion's labels \(no seal_label/\)"):
        ParcelSuctionDataset(root)
    with pytest.raises(SystemExit) as exc:
        diffusion_main(["--data", str(root), "--out", str(tmp_path / "d"), "--preset", "tiny", "--steps", "1"])
    assert message in str(exc.value) and "\n" not in str(exc.value)
    assert cao_main(["--data", str(root), "--out", str(tmp_path / "c.pt"), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert message in err and len(err.splitlines()) == 1


def test_a_root_without_train_views_is_a_clear_error(tree, tmp_path):
    root = tmp_path / "test_only"
    shutil.copytree(tree[0], root)
    shutil.move(root / "scenes" / "scene_0000", root / "scenes" / "scene_0100")
    for scene in SCENES[1:]:
        shutil.rmtree(root / "scenes" / f"scene_{scene:04d}")
    with pytest.raises(SuctionNetLayoutError, match="no views of split train"):
        open_store(root)
    assert len(suctionnet_views(root, split="test_seen")) == 1
    with pytest.raises(SuctionNetLayoutError, match="no kinect views of split test_seen"):
        suctionnet_views(root, split="test_seen", cameras=["kinect"])
