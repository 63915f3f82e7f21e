"""The evaluation report's tables, plots and failure handling, on hand-made results (no simulation)."""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest

from eval.clearance import EpisodeResult, attempt_record, summarise
from eval.metrics import aggregate_ap, scene_ap
from eval.paper_results import TABLE_II_TOP50, TABLE_V
from eval.stats import format_interval
from eval.report import (TRAINED_VARIANTS, ReportConfig, ablation_table, compare, differences, evaluate_ablations,
                         evaluate_policy, failure_table, main, table_ii, write_report)
from eval.stats import TIE
from policies import registry
from policies.base import Policy

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _ap(qualities_per_scene: list[list[float]]) -> dict:
    """A real aggregate_ap result from hand-made ranked qualities (scores descend with the list order)."""
    scenes = [scene_ap(np.linspace(1, 0, len(q)), np.asarray(q), categories=["rectangular"] * len(q))
              for q in qualities_per_scene]
    return aggregate_ap(scenes)


def _clearance(successes: int, attempts: int, cleared: int, placed: int) -> dict:
    log = [attempt_record({"outcome": "success"})] * successes + [
        attempt_record({"outcome": "collision", "failure_cause": "free-space: tool_rod"})] * (attempts - successes)
    episode = EpisodeResult(objects="rectangular", layout="scattered", episode=0, seed=1, attempts=attempts,
                            successes=successes, parcels_placed=placed, parcels_cleared=cleared,
                            reason="consecutive_failures",
                            outcomes={"success": successes, "collision": attempts - successes},
                            replay=None, wall_time_s=0.0, attempt_log=log)
    summary = summarise([episode])
    summary["episodes"] = [asdict(episode)]
    return summary


def _entry(name: str, label: str, ap=None, clearance=None, status="ok", reason=None, clearance_error=None) -> dict:
    return {"name": name, "label": label, "status": status, "reason": reason, "ap": ap, "ap_error": None,
            "clearance": clearance, "clearance_error": clearance_error}


@pytest.fixture()
def report(tmp_path: Path) -> dict:
    config = ReportConfig(test_data=str(tmp_path), objects=("rectangular",), layouts=("scattered",),
                          out=str(tmp_path / "RESULTS.md"))
    missing = [{"name": v.name, "kind": "trained", "description": v.description, "paper": list(v.paper) if v.paper else None,
                "checkpoint": f"runs/ablations/{v.name}/best.pt", "command": f"train {' '.join(v.train_flags)}",
                "ap": None, "reason": None, "status": "not trained"} for v in TRAINED_VARIANTS]
    steps = {"name": "infer5", "kind": "inference_steps", "description": "main checkpoint, sampled with 5 DDIM steps",
             "paper": [28.10, 22.99, 29.86, 181], "checkpoint": "x", "command": None, "status": "ok", "reason": None,
             "ap": _ap([[0.1, 0.5]])}
    return {"generated": "now", "config": asdict(config),
            "policies": {
                "diffusion": _entry("diffusion", "Diffusion-Suction", _ap([[0.9, 0.9, 0.3], [0.85, 0.1]]),
                                    _clearance(3, 4, 3, 4)),
                "cao": _entry("cao", "Cao et al.", _ap([[0.5, 0.2]]), clearance_error="RuntimeError: boom"),
                "dexnet": _entry("dexnet", "Dex-Net 3.0", status="not available",
                                 reason="FileNotFoundError: no model at x.pt"),
            },
            "ablations": [steps, *missing]}


def test_report_has_our_and_paper_numbers_and_writes_pngs(report, tmp_path: Path):
    paths = write_report(report, tmp_path / "out" / "RESULTS.md", tmp_path / "out" / "figs")
    md = paths["markdown"].read_text()
    ours = report["policies"]["diffusion"]["ap"]
    # Table II: ours beside the paper's, Top-50 and Top-1.
    # Every figure of ours carries its bootstrap interval over scenes: 'ours [low, high] / paper'.
    assert f"{format_interval(ours['intervals']['AP'])} / 94.42" in md
    assert f"{format_interval(ours['intervals']['top1_AP'])} / 98.00" in md
    assert f"{format_interval(report['policies']['cao']['ap']['intervals']['AP0.8'])} / 28.29" in md
    assert "Dex-Net 3.0 (not available: FileNotFoundError: no model at x.pt)" in md
    assert "– / 9.56" in md  # the paper's Dex-Net number stays beside the missing run
    # Table V: our pooled rates beside the paper's robot; outcome counts.
    assert "| rectangular | 75.00 [no interval, n=1] / 75.00 [no interval, n=1] | 96.43 / 100.00 |" in md  # one episode
    assert "| Diffusion-Suction | 4 | 3 |" in md and "failed: RuntimeError: boom" in md
    # Ablations: the measured row with the paper's, every untrained variant with its command.
    assert "28.10" in md and "not trained" in md and "train --no-normals" in md and "train --encoder pointnet" in md
    # The gaps are stated, with sign and direction.
    assert f"Diffusion-Suction Top-50 AP: ours {format_interval(ours['intervals']['AP'])}, paper 94.42" in md
    assert "below the paper" in md
    # Plots exist, are PNGs, and the markdown links them relative to itself.
    for key, link in (("precision_at_k", "figs/precision_at_k.png"), ("clearance", "figs/clearance.png")):
        assert paths[key].read_bytes()[:8] == PNG_MAGIC and f"]({link})" in md
    dump = json.loads(paths["json"].read_text())
    assert dump["policies"]["diffusion"]["ap"]["AP"] == pytest.approx(ours["AP"])
    assert dump["policies"]["dexnet"]["status"] == "not available"


def test_differences_are_signed_and_rank_is_checked(report):
    lines = differences(report)
    cao = report["policies"]["cao"]["ap"]["AP"]
    cao_iv = format_interval(report["policies"]["cao"]["ap"]["intervals"]["AP"])
    assert f"- Cao et al. Top-50 AP: ours {cao_iv}, paper 62.81 ({cao - 62.81:+.2f} points" in "\n".join(lines)
    ranking = next(line for line in lines if "ranking" in line)
    ours_first = report["policies"]["diffusion"]["ap"]["AP"] > cao
    assert ("NOT the same" in ranking) != ours_first  # the paper ranks Diffusion-Suction above Cao et al.
    paper_grasp = TABLE_V[("rectangular", "scattered")][0]
    assert any(f"R_grasp (simulation vs real robot): ours 75.00 [no interval, n=1], paper {paper_grasp:.2f}" in line
               for line in lines)
    assert any("Dex-Net 3.0: no AP of ours" in line for line in lines)


def test_precision_at_k_curve_averages_to_ap():
    result = _ap([[0.9, 0.5, 0.1], [0.3]])
    curve = np.asarray(result["precision_at_k"])
    assert curve.shape == (result["max_k"], len(result["thresholds"]))
    assert curve.mean() == pytest.approx(result["AP"])
    assert curve[0].mean() == pytest.approx(result["top1_AP"])


class _NeedsModel(Policy):
    name = "needs_model"

    def __init__(self, **_):
        raise FileNotFoundError("no weights at runs/needs_model/best.pt")

    def predict(self, obs, info=None, top_k=50):  # pragma: no cover - never built
        raise AssertionError


def test_policy_that_fails_to_load_is_listed_not_available(tmp_path: Path, monkeypatch):
    monkeypatch.setitem(registry._CLASSES, "needs_model", _NeedsModel)
    monkeypatch.setitem(registry._LAZY, "unbuilt", "policies.no_such_module:Nope")
    config = ReportConfig(test_data=str(tmp_path), policies=("needs_model", "unbuilt", "nope"))
    entries = {name: evaluate_policy(name, config) for name in config.policies}
    for entry in entries.values():
        assert entry["status"] == "not available" and entry["ap"] is None and entry["clearance"] is None
    assert "FileNotFoundError: no weights" in entries["needs_model"]["reason"]
    assert "not implemented" in entries["unbuilt"]["reason"]
    assert "unknown policy 'nope'" in entries["nope"]["reason"]
    table = table_ii(entries)
    assert table.count("not available:") == 3


def test_missing_ablation_checkpoints_are_listed_with_training_commands(tmp_path: Path):
    config = ReportConfig(test_data=str(tmp_path), diffusion_checkpoint=str(tmp_path / "missing.pt"),
                          ablation_dir=str(tmp_path / "ablations"), ablation_steps=(5,), train_data="data/train")
    rows = evaluate_ablations(config)
    assert rows[0]["name"] == "infer5" and rows[0]["status"] == "not available" and rows[0]["ap"] is None
    trained = {row["name"]: row for row in rows[1:]}
    assert set(trained) == {"reference", "no_segment_levers", "no_normals", "no_visibility", "pointnet", "steps5",
                            "steps10", "steps15"}
    assert all(row["status"] == "not trained" for row in trained.values())
    assert trained["no_normals"]["command"] == (
        f".venv/bin/python -m policies.diffusion.train --data data/train --out {tmp_path}/ablations/no_normals "
        "--preset cpu --steps 1000 --batch-size 4 --lr 1e-3 --seed 0 --threads 1 --workers 0 --no-normals")
    assert trained["reference"]["command"].endswith("--workers 0")
    assert trained["steps10"]["command"].endswith("--inference-steps 10")
    assert trained["pointnet"]["paper"][0] == 38.39
    assert trained["no_segment_levers"]["command"].endswith("--no-segment-levers")
    assert trained["no_segment_levers"]["paper"] is None  # not in the paper


@pytest.mark.parametrize("bad", [dict(policies=()), dict(episodes=0), dict(parcels=0), dict(ap_scenes=0),
                                 dict(backend="spark"), dict(objects=("spheres",)), dict(ablation_steps=(0,))])
def test_config_rejects_bad_values(bad, tmp_path):
    with pytest.raises(ValueError):
        ReportConfig(test_data=str(tmp_path), **bad)


def test_cli_rejects_missing_test_data(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--test-data", str(tmp_path / "absent")])
    assert exc.value.code == 2 and "does not exist" in capsys.readouterr().err


def test_paper_table_ii_is_beside_every_method_it_has(report):
    table = table_ii(report["policies"])
    for name in ("diffusion", "cao", "dexnet"):
        assert f"/ {TABLE_II_TOP50[name][0]:.2f}" in table


@pytest.fixture(scope="module")
def one_scene(tmp_path_factory) -> Path:
    """One hand-built stored test scene (test_ap's), so the real evaluators run without simulation."""
    from dataset.storage import shard_name, write_manifest, write_shard
    from test_ap import _record

    data = tmp_path_factory.mktemp("report_data")
    write_manifest(data, {"split": "test"}, [write_shard(data / shard_name(0), 0, {0: _record()}, range(0, 1))],
                   complete=True)
    return data


def test_cli_end_to_end_on_one_stored_scene(one_scene: Path, tmp_path: Path, capsys):
    data = one_scene
    out = tmp_path / "report" / "RESULTS.md"
    assert main(["--test-data", str(data), "--policies", "random", "nope", "--ap-scenes", "1", "--skip-clearance",
                 "--skip-ablations", "--quiet", "--out", str(out)]) == 0
    md = out.read_text()
    dump = json.loads(out.with_suffix(".json").read_text())
    random_ap = dump["policies"]["random"]["ap"]
    assert random_ap["num_scenes"] == 1 and len(random_ap["precision_at_k"]) == random_ap["max_k"]
    assert f"| Random | {format_interval(random_ap['intervals']['AP'])} / – |" in md
    assert "nope (not available: ValueError: unknown policy 'nope'" in md
    assert (out.parent / "figures" / "precision_at_k.png").read_bytes()[:8] == PNG_MAGIC
    assert "Skipped (--skip-clearance)." in md and "Skipped (--skip-ablations)." in md
    assert "# ParcelPick evaluation report" in capsys.readouterr().out


def test_ablations_evaluate_found_checkpoints_and_reuse_the_main_run(one_scene: Path, tmp_path: Path):
    from policies.diffusion.checkpoint import save_checkpoint
    from policies.diffusion.config import DiffusionConfig
    from policies.diffusion.model import build_model

    main_ckpt = save_checkpoint(tmp_path / "main.pt", build_model(DiffusionConfig.tiny(inference_steps=4)))
    save_checkpoint(tmp_path / "abl" / "no_visibility" / "best.pt",
                    build_model(DiffusionConfig.tiny(inference_steps=4, use_visibility=False)))
    config = ReportConfig(test_data=str(one_scene), diffusion_checkpoint=str(main_ckpt),
                          ablation_dir=str(tmp_path / "abl"), ablation_steps=(2, 4), progress=False)
    main_ap = {"AP": 12.5}
    rows = {row["name"]: row for row in evaluate_ablations(config, main_ap=main_ap)}
    assert rows["infer4"]["ap"] is main_ap and "trained with 4" in rows["infer4"]["description"]
    assert rows["infer2"]["status"] == "ok" and rows["infer2"]["ap"]["num_scenes"] == 1
    assert 0.0 <= rows["infer2"]["ap"]["AP"] <= 100.0
    assert rows["no_visibility"]["status"] == "ok" and rows["no_visibility"]["ap"]["num_scenes"] == 1
    assert rows["no_normals"]["status"] == "not trained" and rows["no_normals"]["ap"] is None


def test_step_count_variants_are_the_inference_rows_when_training_never_samples(tmp_path: Path):
    """With map_loss_weight = 0 a model 'trained with k steps' is the main model: no run to ask for."""
    from policies.diffusion.checkpoint import save_checkpoint
    from policies.diffusion.config import DiffusionConfig
    from policies.diffusion.model import build_model

    main = save_checkpoint(tmp_path / "main.pt", build_model(DiffusionConfig.tiny(inference_steps=5,
                                                                                  map_loss_weight=0.0)))
    config = ReportConfig(test_data=str(tmp_path), diffusion_checkpoint=str(main), ablation_dir=str(tmp_path / "a"),
                          ablation_steps=(5,), progress=False)
    main_ap = {"AP": 40.0, "AP0.8": 10.0, "AP0.4": 50.0, "top1_AP": 45.0}
    rows = {row["name"]: row for row in evaluate_ablations(config, main_ap=main_ap)}
    assert rows["steps5"]["ap"] is main_ap and rows["steps5"]["kind"] == "same_as_inference"
    assert rows["steps5"]["command"] is None and "map_loss_weight = 0" in rows["steps5"]["reason"]
    assert rows["steps10"]["status"] == "not trained"  # no inference row at 10 steps to stand in for it
    assert "map_loss_weight = 0" in ablation_table(list(rows.values()))


def _scored(per_scene_ap: np.ndarray) -> dict:
    """An AP result whose scene k has (close to) the given AP, with the scene indices evaluate_ap records."""
    result = _ap([[1.0] * int(round(a * 50 / 100)) + [0.0] * (50 - int(round(a * 50 / 100))) for a in per_scene_ap])
    result["scenes"] = [{"index": i} for i in range(len(per_scene_ap))]
    return result


def test_paired_comparison_calls_a_method_ahead_only_when_its_interval_excludes_zero():
    rng = np.random.default_rng(0)
    base = rng.uniform(10, 60, 40)
    strong = _entry("diffusion", "Diffusion-Suction", _scored(np.clip(base + 8, 0, 100)), _clearance(6, 10, 6, 8))
    weak = _entry("cao", "Cao et al.", _scored(base), _clearance(3, 10, 3, 8))
    ahead = compare(strong, weak)
    assert ahead["AP"]["low"] > 0 and ahead["AP"]["verdict"] == "Diffusion-Suction ahead"
    assert compare(weak, strong)["AP"]["verdict"] == "Diffusion-Suction ahead"
    itself = compare(strong, strong)
    assert all(itself[k]["verdict"] == TIE for k in ("AP", "R_grasp", "R_object"))
    assert ahead["R_grasp"]["estimate"] == pytest.approx(30.0)  # 6/10 - 3/10 on the one shared episode
    lines = differences({"policies": {"diffusion": strong, "cao": weak}, "ablations": []})
    assert any("Diffusion-Suction over Cao et al. resolved (paired difference" in line for line in lines)
    tie = differences({"policies": {"diffusion": strong, "cao": {**strong, "name": "cao", "label": "Cao et al."}},
                       "ablations": []})
    assert any("over" in line and "NOT resolved" in line for line in tie)


def test_failure_anatomy_table_figure_and_provenance_are_in_the_report(report, tmp_path: Path):
    from policies.provenance import shipped_provenance

    table = failure_table(report["policies"], ("rectangular",), ("scattered",))
    assert "| Diffusion-Suction | collision: free-space | 1 | 1 |" in table
    report = {**report, "provenance": shipped_provenance()}
    paths = write_report(report, tmp_path / "RESULTS.md", tmp_path / "figs")
    md = paths["markdown"].read_text()
    assert paths["failures"].read_bytes()[:8] == PNG_MAGIC and "](figs/failures.png)" in md
    assert "### Failure anatomy" in md and "collision: free-space (tool_rod) × 1" in md
    assert "## Checkpoint provenance" in md and "not recorded" in md
    assert "`python -m policies.cao.train --data data/baselines_train" in md
    assert "## Paired comparisons with Diffusion-Suction" in md and "Diffusion-Suction − Cao et al." in md
