"""Label sets (docs/labels.md): dataset.generate --labels paper|physical, extra sets beside the main one, and the
AP's label oracle reading the set that matches each quality definition."""

from __future__ import annotations

import numpy as np
import pytest

from dataset.config import GenerationConfig
from dataset.generate import generate
from dataset.storage import open_dataset
from dataset.scene_record import scene_from_record
from eval.ap import label_observation, label_score_key
from parcelpick_env.suction.quality import PhysicalCell, definition_scorer, score_definition


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    root = tmp_path_factory.mktemp("label_sets") / "data"
    config = GenerationConfig(scenes=1, split="test", seed=3, min_parcels=4, max_parcels=4, width=160, height=120,
                              annotation_points=1024, scenes_per_shard=1, labels="paper",
                              extra_labels=("physical", "suctionnet"))
    generate(root, config, workers=1, progress=False)
    return root


@pytest.fixture(scope="module")
def record(root):
    store = open_dataset(root)
    assert store.config["extra_labels"] == ["physical", "suctionnet"]
    return store.scene(0)


def _assert_stored_set_is_its_definition(record, name: str) -> None:
    """The stored ``labels_<name>`` are definition ``name`` re-scored on the true scene, ``score_<name>`` their product."""
    on_parcel = record["object_ids"] >= 0
    scorer = definition_scorer(name, scene_from_record(record))
    again = score_definition(name, scorer, record["points"][on_parcel].astype(np.float64),
                             record["normals"][on_parcel].astype(np.float64), record["object_ids"][on_parcel],
                             visibility=record["object_visibility"])
    np.testing.assert_allclose(record[f"labels_{name}"][on_parcel], again.as_array(), atol=1e-6)
    np.testing.assert_allclose(record[f"score_{name}"], np.prod(record[f"labels_{name}"], axis=1), atol=1e-6)


def test_physical_labels_are_the_physical_definition_on_the_true_scene(record):
    _assert_stored_set_is_its_definition(record, "physical")
    seal = record["labels_physical"][:, 0]
    assert np.all((seal == 0) | (seal >= PhysicalCell().seal_threshold))  # below the env's threshold: nothing held
    assert np.any(record["score_physical"] > 0) and np.any(record["score"] > 0)
    # the two sets disagree somewhere: they are different notions of a good suction
    assert not np.allclose(record["score_physical"], record["score"])


def test_suctionnet_labels_are_the_evaluators_definition_on_the_true_scene(record):
    """The set that scores each point as SuctionNet's evaluator re-scores a prediction (surface-centroid wrench, no
    angle factor, the tool blocked by objects and the floor only), so a model can learn the AP's own target."""
    _assert_stored_set_is_its_definition(record, "suctionnet")
    wrench = 1
    assert not np.allclose(record["labels_suctionnet"][:, wrench], record["labels"][:, wrench])  # centroid vs COM


def test_label_oracle_reads_the_set_matching_the_quality(record):
    assert str(record["label_set"]) == "paper"
    assert label_score_key(record, "suctionnet") == "score"
    assert label_score_key(record, "physical") == "score_physical"
    np.testing.assert_array_equal(label_observation(record, "physical")["label_score"], record["score_physical"])
    older = {k: v for k, v in record.items() if k not in ("label_set", "score_physical", "labels_physical")}
    assert label_score_key(older, "physical") == "score"  # records without the set fall back to their own labels


@pytest.mark.parametrize("fields, message", [({"labels": "dexnet"}, "labels"),
                                             ({"extra_labels": ("paper",)}, "extra_labels"),
                                             ({"extra_labels": ("bogus",)}, "extra_labels")])
def test_bad_label_sets_are_one_clear_error(fields, message):
    with pytest.raises(ValueError, match=message):
        GenerationConfig(**fields)


def test_the_torch_dataset_serves_the_asked_label_set(root, record):
    """ParcelSuctionDataset(label_set=...) reads labels_<set> as `labels`; an absent set is one clear error."""
    from dataset.torch_dataset import ParcelSuctionDataset, label_key

    physical = ParcelSuctionDataset(root, label_set="physical")[0]["labels"].numpy()
    np.testing.assert_array_equal(physical, record["labels_physical"])
    np.testing.assert_array_equal(ParcelSuctionDataset(root)[0]["labels"].numpy(), record["labels"])

    config = {"labels": "paper", "extra_labels": ["physical"]}
    assert label_key(config, None) == ("paper", "labels")
    assert label_key(config, "physical") == ("physical", "labels_physical")
    assert label_key({}, None) == ("paper", "labels")  # datasets made before label sets
    with pytest.raises(ValueError, match="holds the label sets \\['paper'\\], not 'physical'"):
        label_key({"labels": "paper"}, "physical")


def test_the_diffusion_trainer_learns_a_stored_label_set(tmp_path):
    """The trainer's --label-set reaches the dataset: a set the data lacks stops it with one line."""
    import subprocess
    import sys

    data = tmp_path / "data"
    generate(data, GenerationConfig(scenes=2, split="train", seed=0, min_parcels=2, max_parcels=2, width=160,
                                    height=120, annotation_points=256, scenes_per_shard=2), workers=1, progress=False)
    run = subprocess.run([sys.executable, "-m", "policies.diffusion.train", "--data", str(data), "--label-set",
                          "physical", "--preset", "tiny", "--steps", "1", "--out", str(tmp_path / "run")],
                         capture_output=True, text=True)
    assert run.returncode != 0 and "not 'physical'" in run.stderr


def test_the_diffusion_trainer_refuses_more_points_than_the_data_stores(root, tmp_path):
    """A model asking for more points than a scene stores would see each one twice: one line, before training."""
    from policies.diffusion.train import main

    common = ["--data", str(root), "--val-data", str(root), "--preset", "tiny", "--steps", "1", "--threads", "1",
              "--no-progress"]
    with pytest.raises(SystemExit, match=r"stores 1024 points per scene, fewer than the model's 2048"):
        main(common + ["--num-points", "2048", "--out", str(tmp_path / "more")])
    main(common + ["--num-points", "1024", "--out", str(tmp_path / "same")])
    assert (tmp_path / "same" / "last.pt").is_file()
