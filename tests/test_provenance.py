"""Checkpoint provenance: what trainers record, and what the shipped checkpoints say (never invented)."""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path

from policies.provenance import (
    FIELDS,
    NO_DATASET,
    NOT_RECORDED,
    SIDECAR_SUFFIX,
    chain_parts,
    checkpoint_provenance,
    command_line,
    manifest_sha256,
    repo_path,
    shipped_provenance,
    training_provenance,
)


def test_training_provenance_records_commit_command_seed_manifest_hash_and_wall_time(tmp_path: Path):
    (tmp_path / "manifest.json").write_text('{"shards": []}')
    started = time.perf_counter() - 2.0
    record = training_provenance(command_line("policies.cao.train", ["--seed", "3"]), 3, tmp_path, started)
    assert set(FIELDS) <= set(record)
    assert record["command"] == "python -m policies.cao.train --seed 3" and record["seed"] == 3
    assert record["dataset_manifest_sha256"] == hashlib.sha256(b'{"shards": []}').hexdigest()
    assert record["wall_time_s"] >= 2.0
    assert len(record["git_commit"].split("+")[0]) == 40 or record["git_commit"] == NOT_RECORDED
    assert manifest_sha256(None) == NO_DATASET and manifest_sha256(tmp_path / "absent") == NOT_RECORDED


def test_a_diffusion_checkpoint_carries_its_provenance(tmp_path: Path):
    from policies.diffusion.checkpoint import save_checkpoint
    from policies.diffusion.config import DiffusionConfig
    from policies.diffusion.model import build_model

    prov = training_provenance("python -m policies.diffusion.train --synthetic 4", 0, None, time.perf_counter())
    path = save_checkpoint(tmp_path / "best.pt", build_model(DiffusionConfig.tiny()), extra={"provenance": prov})
    read = checkpoint_provenance(path)
    assert read["source"] == "checkpoint" and read["command"] == prov["command"] and read["seed"] == 0


def test_an_old_checkpoint_reads_its_sidecar_and_says_not_recorded_for_the_rest(tmp_path: Path):
    ckpt = tmp_path / "old.pt"
    ckpt.write_bytes(b"not a torch file")
    assert all(checkpoint_provenance(ckpt)[k] == NOT_RECORDED for k in FIELDS)
    (tmp_path / ("old.pt" + SIDECAR_SUFFIX)).write_text(json.dumps({"command": "python -m x", "seed": 1}))
    read = checkpoint_provenance(ckpt)
    assert read["command"] == "python -m x" and read["git_commit"] == NOT_RECORDED and read["source"].endswith(".json")


def test_every_shipped_checkpoint_has_a_record_and_none_claims_a_commit_it_does_not_know():
    shipped = shipped_provenance()
    assert {"diffusion", "cao", "dexnet", "sb3"} <= set(shipped)
    for name, record in shipped.items():
        assert record["source"] != NOT_RECORDED, name
        assert record["command"].startswith("python -m policies."), name
        assert record["seed"] == 0, name
        commit = str(record["git_commit"])
        assert commit == NOT_RECORDED or len(commit.split("+")[0]) == 40, name  # a hash, or honestly unknown


def test_a_trained_cao_checkpoint_records_how_it_was_made(tmp_path: Path):
    from test_cao import H, W, synthetic_record  # four of test_cao's synthetic scenes, at its tiny size

    from dataset.config import GenerationConfig
    from dataset.storage import shard_name, write_manifest, write_shard
    from policies.cao.train import main as train_main

    data = tmp_path / "data"
    data.mkdir()

    entry = write_shard(data / shard_name(0), 0, {i: synthetic_record(i) for i in range(4)}, range(4),
                        compression="lzf")
    write_manifest(data, GenerationConfig(scenes=4, width=W, height=H, annotation_points=256,
                                          scenes_per_shard=4).to_dict(), [entry], complete=True)
    argv = ["--data", str(data), "--out", str(tmp_path / "cao.pt"), "--epochs", "1", "--seed", "2",
            "--input-height", str(H), "--input-width", str(W), "--widths", "4", "8", "--threads", "1", "--quiet"]
    assert train_main(argv) == 0
    record = checkpoint_provenance(tmp_path / "cao.pt")
    assert record["source"] == "checkpoint" and record["command"] == "python -m policies.cao.train " + " ".join(argv)
    assert record["seed"] == 2 and record["wall_time_s"] > 0
    assert record["dataset_manifest_sha256"] == hashlib.sha256((data / "manifest.json").read_bytes()).hexdigest()


def test_a_diffusion_training_run_stores_its_provenance_in_every_checkpoint(tmp_path: Path):
    from policies.diffusion.train import main

    argv = ["--synthetic", "4", "--preset", "tiny", "--num-points", "256", "--inference-steps", "3", "--batch-size",
            "2", "--val-every", "2", "--val-scenes", "1", "--threads", "1", "--no-progress", "--seed", "5",
            "--out", str(tmp_path), "--steps", "2"]
    main(argv)
    for name in ("last.pt", "best.pt"):
        record = checkpoint_provenance(tmp_path / name)
        assert record["command"] == "python -m policies.diffusion.train " + " ".join(argv) and record["seed"] == 5
        assert record["dataset_manifest_sha256"] == NO_DATASET and record["wall_time_s"] > 0  # synthetic scenes


def test_an_sb3_model_reads_the_provenance_from_the_log_beside_it(tmp_path: Path):
    (tmp_path / "ppo.safetensors").write_bytes(b"")
    prov = training_provenance("python -m policies.sb3.train --seed 4", 4, None, time.perf_counter())
    (tmp_path / "ppo.json").write_text(json.dumps({"seconds": 1.0, "provenance": prov}))
    record = checkpoint_provenance(tmp_path / "ppo.safetensors")
    assert record["source"] == "checkpoint" and record["seed"] == 4 and record["dataset_manifest_sha256"] == NO_DATASET


def test_the_commit_the_sender_names_wins_over_what_git_finds(tmp_path: Path, monkeypatch):
    from policies.provenance import COMMIT_ENV, git_commit

    monkeypatch.delenv(COMMIT_ENV, raising=False)
    assert git_commit(tmp_path) == NOT_RECORDED  # a copy of the tree without .git
    assert git_commit() != "0acb31c"  # this checkout's HEAD (or NOT_RECORDED where the tree has no .git)
    monkeypatch.setenv(COMMIT_ENV, "0acb31c")  # a copy sent elsewhere, whose .git may hold an older HEAD
    assert git_commit(tmp_path) == git_commit() == "0acb31c"


def test_a_resumed_runs_record_sums_its_parts_and_a_fresh_one_is_unchanged():
    first = {"git_commit": "a" * 40, "command": "python -m x --max-minutes 30", "seed": 0, "wall_time_s": 1800.0,
             "recorded_at": "t0"}
    second = dict(first, command="python -m x --resume", wall_time_s=600.0, recorded_at="t1")
    assert chain_parts(second, None) is second
    chained = chain_parts(second, first)
    assert chained["wall_time_s"] == 2400.0 and [p["command"] for p in chained["parts"]] == [first["command"],
                                                                                          second["command"]]
    third = chain_parts(dict(second, wall_time_s=5.0), chained)  # a second resume extends the chain
    assert third["wall_time_s"] == 2405.0 and len(third["parts"]) == 3
    assert chain_parts(second, dict(first, wall_time_s=NOT_RECORDED))["wall_time_s"] == NOT_RECORDED


def test_a_path_inside_the_repository_is_named_from_its_root_and_one_outside_as_given(tmp_path: Path):
    from policies.provenance import REPO

    assert repo_path(REPO / "policies" / "sb3" / "ppo_pixel.safetensors") == "policies/sb3/ppo_pixel.safetensors"
    assert repo_path(tmp_path / "model.pt") == str(tmp_path / "model.pt")
    assert repo_path(tmp_path / "a" / "b.pt", root=tmp_path) == "a/b.pt"
