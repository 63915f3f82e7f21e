"""The evaluation report's tables, plots and failure handling, on hand-made results (no simulation)."""

from __future__ import annotations

import json
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np
import pytest

from eval.clearance import EpisodeResult, attempt_record, summarise
from eval.metrics import aggregate_ap, scene_ap
from eval.paper_results import TABLE_II_TOP50, TABLE_V
from eval.stats import format_interval
from eval.ap import PAPER_COMPAT_NMS_RADIUS, APConfig, ceiling_ap
from eval.report import (TRAINED_VARIANTS, ReportConfig, ablation_table, compare, differences, evaluate_ablations,
                         evaluate_policy, failure_table, main, table_ii, write_report)
from eval.report import orchestration
from eval.report.config import CEILING, LABEL_ORACLE, PAPER_COMPAT_VARIANTS
from eval.report.markdown import render_markdown
from eval.report.tables import (channel_cost_table, glance_table, paper_compat_sentences, paper_compat_table,
                                table_v)
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
                          out=str(tmp_path / "RESULTS.md"), label_physics=str(tmp_path / "absent.json"))
    missing = [{"name": v.name, "kind": "trained", "description": v.description, "paper": list(v.paper) if v.paper else None,
                "ap": None, "reason": None, "status": "not trained",
                "runs": [{"seed": 0, "checkpoint": f"runs/ablations/{v.name}/seed0/best.pt", "status": "not trained",
                          "command": f"train {' '.join(v.train_flags)}", "ap": None, "val_ap_proxy": None}]}
               for v in TRAINED_VARIANTS]
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


def test_each_clearance_table_says_whether_the_method_acted_through_the_tool_check(report, tmp_path: Path):
    report["policies"]["diffusion"]["clearance"]["tool_check"] = True
    md = write_report(report, tmp_path / "on" / "RESULTS.md", tmp_path / "on" / "figs")["markdown"].read_text()
    assert "Acting through the cell's tool check" in md and "--no-tool-check" not in md
    assert "whose cup seals on it" not in md
    report["policies"]["diffusion"]["clearance"]["seal_check"] = True
    md = write_report(report, tmp_path / "seal" / "RESULTS.md", tmp_path / "seal" / "figs")["markdown"].read_text()
    assert "clear of the observed scene and whose cup seals on it" in md and "retry rule" not in md  # not recorded
    report["policies"]["diffusion"]["clearance"]["retry_radius"] = 0.0
    md = write_report(report, tmp_path / "none" / "RESULTS.md", tmp_path / "none" / "figs")["markdown"].read_text()
    assert "on it (`policies/tool_check.py`). No retry rule." in md
    report["policies"]["diffusion"]["clearance"].update(tool_check=False, config={"tool_check": False})
    md = write_report(report, tmp_path / "off" / "RESULTS.md", tmp_path / "off" / "figs")["markdown"].read_text()
    assert "Acting on its top candidate as ranked (`--no-tool-check`)" in md and "through the cell's" not in md


def test_glance_table_puts_each_methods_headline_figures_in_one_row(report):
    """Top-50 AP as a share of the label oracle's, the pooled rates and the lowest cell; '–' where not measured."""
    policies = report["policies"]
    policies["oracle"] = _entry("oracle", "Oracle (privileged ceiling)", _ap([[1.0, 1.0, 0.9], [1.0, 0.8]]),
                                _clearance(4, 4, 4, 4))
    rows = {line.split(" | ")[0].lstrip("| "): line for line in glance_table(policies).splitlines()[2:]}
    ours, oracle = policies["diffusion"]["ap"], policies["oracle"]["ap"]
    assert ours["AP"] < oracle["AP"]
    share = f"{100 * ours['AP'] / oracle['AP']:.1f}%"
    assert rows["Diffusion-Suction"] == (f"| Diffusion-Suction | {format_interval(ours['intervals']['AP'])} | {share} | "
                                         "– | 75.00 [no interval, n=1] | 75.00 [no interval, n=1] | "
                                         "rectangular scattered: 75.00 |")
    assert rows[f"{LABEL_ORACLE} / Oracle (privileged ceiling)"].split(" | ")[2] == "100.0%"
    assert rows["Cao et al."].endswith("| – | – | – |")  # its clearance failed
    assert rows["Dex-Net 3.0"] == "| Dex-Net 3.0 | – | – | – | – | – | – |"  # not available at all
    del policies["oracle"]
    assert "%" not in glance_table(policies)  # no label oracle, no share


def test_table_v_counts_parting_pushes_apart_from_attempts():
    """The oracle parts piles with pushes (no attempts): its Table V says how many, the rates are the picks'."""
    summary = _clearance(3, 4, 3, 3)
    assert "parting pushes" not in table_v({"clearance": summary}, ("rectangular",), ("scattered",))
    episode = EpisodeResult(**{**summary["episodes"][0], "push_log": [attempt_record({"outcome": "pushed"})] * 2})
    pushed = table_v({"clearance": summarise([episode])}, ("rectangular",), ("scattered",))
    assert "(3/4 attempts, 3/3 parcels; 2 parting pushes, which are no attempts)." in pushed


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
    assert set(trained) == {"reference", "no_segment_levers", "segment_size", "levers_in_encoder", "no_normals",
                            "no_visibility", "pointnet", "physical_labels", "points4096_400", "points8192", "steps5",
                            "steps10", "steps15"}
    assert all(row["status"] == "not trained" and [run["seed"] for run in row["runs"]] == [0, 1, 2]
               for row in trained.values())
    assert trained["no_normals"]["runs"][1]["command"] == (
        f".venv/bin/python -m policies.diffusion.train --data data/train --out {tmp_path}/ablations/no_normals/seed1 "
        "--preset cpu --steps 1000 --batch-size 4 --lr 1e-3 --threads 1 --workers 0 --seed 1 --no-normals")
    assert trained["reference"]["runs"][2]["command"].endswith("--workers 0 --seed 2")
    assert trained["steps10"]["runs"][0]["command"].endswith("--inference-steps 10")
    assert trained["physical_labels"]["runs"][0]["command"].endswith("--label-set physical")
    assert trained["pointnet"]["paper"][0] == 38.39
    assert trained["no_segment_levers"]["runs"][0]["command"].endswith("--no-segment-levers")
    assert trained["no_segment_levers"]["paper"] is None  # not in the paper
    # the more-points pair trains on its own splits (the same piles at two densities) and is tested on its own
    assert " --data data/train8k " in trained["points8192"]["runs"][0]["command"]
    assert trained["points8192"]["runs"][0]["command"].endswith("--seed 0 --num-points 8192")
    assert " --data data/train4k400 " in trained["points4096_400"]["runs"][0]["command"]
    assert trained["points8192"]["baseline"] == "points4096_400" and trained["points4096_400"]["baseline"] is None
    assert trained["points8192"]["test_data"] == trained["points4096_400"]["test_data"] == "data/test8k"
    assert trained["no_normals"]["baseline"] == "reference" and trained["no_normals"]["test_data"] == str(tmp_path)
    table = ablation_table(rows)
    assert f"`{trained['pointnet']['runs'][2]['command']}`" in table  # every missing run says how to make it


def test_a_trained_variant_without_its_own_test_split_says_how_to_make_it(tmp_path: Path, monkeypatch):
    from policies.diffusion.checkpoint import save_checkpoint
    from policies.diffusion.config import DiffusionConfig
    from policies.diffusion.model import build_model

    save_checkpoint(tmp_path / "abl" / "points8192" / "seed0" / "best.pt", build_model(DiffusionConfig.tiny()))
    config = ReportConfig(test_data=str(tmp_path), diffusion_checkpoint=str(tmp_path / "missing.pt"),
                          ablation_dir=str(tmp_path / "abl"), ablation_steps=(5,), ablation_seeds=(0,),
                          progress=False)
    test = tmp_path / "absent8k"
    variant = next(v for v in TRAINED_VARIANTS if v.name == "points8192")
    moved = replace(variant, test_split=replace(variant.test_split, path=str(test)))
    monkeypatch.setattr("eval.report.orchestration.TRAINED_VARIANTS",
                        tuple(moved if v is variant else v for v in TRAINED_VARIANTS))
    rows = {row["name"]: row for row in evaluate_ablations(config)}
    run = rows["points8192"]["runs"][0]
    assert run["status"] == "failed" and rows["points8192"]["status"] == "failed"
    assert f"its test split {test} is missing" in run["reason"]
    assert f"python -m dataset.generate --out {test} --scenes 64 --split test --seed 1" in run["reason"]
    assert "--points 8192" in run["reason"]


@pytest.mark.parametrize("bad", [dict(policies=()), dict(episodes=0), dict(parcels=0), dict(ap_scenes=0),
                                 dict(backend="spark"), dict(objects=("spheres",)), dict(ablation_steps=(0,)),
                                 dict(ablation_seeds=()), dict(ablation_seeds=(0, 0)), dict(ablation_seeds=(-1,)),
                                 dict(ap_qualities=("physical",)), dict(ap_qualities=("suctionnet", "bogus")),
                                 dict(ap_qualities=("suctionnet", "suctionnet")), dict(ap_qualities=())])
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
                 "--skip-ablations", "--quiet", "--out", str(out), "--label-physics", str(tmp_path / "none.json")]) == 0
    md = out.read_text()
    dump = json.loads(out.with_suffix(".json").read_text())
    random_ap = dump["policies"]["random"]["ap"]
    assert random_ap["num_scenes"] == 1 and len(random_ap["precision_at_k"]) == random_ap["max_k"]
    by_quality = dump["policies"]["random"]["ap_by_quality"]  # both definitions by default, ap the suctionnet one
    assert {q: r["quality"] for q, r in by_quality.items()} == {"suctionnet": "suctionnet", "physical": "physical"}
    assert random_ap["AP"] == by_quality["suctionnet"]["AP"]
    assert "### `physical`" in md and md.count(f"| {CEILING} |") == 2
    assert f"| Random | {format_interval(random_ap['intervals']['AP'])} / – |" in md
    assert "nope (not available: ValueError: unknown policy 'nope'" in md
    assert (out.parent / "figures" / "precision_at_k.png").read_bytes()[:8] == PNG_MAGIC
    assert "Skipped (--skip-clearance)." in md and "Skipped (--skip-ablations)." in md
    assert "# ParcelPick evaluation report" in capsys.readouterr().out


def test_ablations_evaluate_found_checkpoints_and_reuse_the_main_run(one_scene: Path, tmp_path: Path):
    import torch

    from policies.diffusion.checkpoint import save_checkpoint
    from policies.diffusion.config import DiffusionConfig
    from policies.diffusion.model import build_model

    main_ckpt = save_checkpoint(tmp_path / "main.pt", build_model(DiffusionConfig.tiny(inference_steps=4)))
    for seed in (0, 1):
        torch.manual_seed(0)  # the same network under both seeds' names
        save_checkpoint(tmp_path / "abl" / "no_visibility" / f"seed{seed}" / "best.pt",
                        build_model(DiffusionConfig.tiny(inference_steps=4, use_visibility=False)))
    (tmp_path / "abl" / "no_visibility" / "seed1" / "log.jsonl").write_text(
        '{"step": 0, "val_ap_proxy": 0.1}\n{"step": 200, "loss": 0.5}\n{"step": 200, "val_ap_proxy": 0.25}\n{"step": 40')
    config = ReportConfig(test_data=str(one_scene), diffusion_checkpoint=str(main_ckpt),
                          ablation_dir=str(tmp_path / "abl"), ablation_steps=(2, 4), ablation_seeds=(0, 1, 2),
                          progress=False)
    main_ap = {"AP": 12.5}
    rows = {row["name"]: row for row in evaluate_ablations(config, main_ap=main_ap)}
    assert rows["infer4"]["ap"] is main_ap and "trained with 4" in rows["infer4"]["description"]
    assert rows["infer2"]["status"] == "ok" and rows["infer2"]["ap"]["num_scenes"] == 1
    assert 0.0 <= rows["infer2"]["ap"]["AP"] <= 100.0
    runs = rows["no_visibility"]["runs"]
    assert rows["no_visibility"]["status"] == "2 of 3 seeds measured" and rows["no_visibility"]["ap"]["seeds"] == [0, 1]
    assert [run["status"] for run in runs] == ["ok", "ok", "not trained"]
    assert runs[0]["val_ap_proxy"] is None and runs[1]["val_ap_proxy"] == 0.25  # the best logged; a cut line skipped
    # the same untrained network twice: the seed mean is that network's AP, with no spread over seeds
    assert rows["no_visibility"]["ap"]["AP"] == pytest.approx(runs[0]["ap"]["AP"])
    assert rows["no_visibility"]["ap"]["seed_std"]["AP"] == pytest.approx(0.0)
    assert rows["no_normals"]["status"] == "not trained" and rows["no_normals"]["ap"] is None


def test_a_runs_ap_is_kept_beside_its_checkpoint_and_reused_only_for_the_same_weights_and_scenes(
        one_scene: Path, tmp_path: Path):
    from policies.diffusion.checkpoint import save_checkpoint
    from policies.diffusion.config import DiffusionConfig
    from policies.diffusion.model import build_model

    checkpoint = save_checkpoint(tmp_path / "run" / "best.pt", build_model(DiffusionConfig.tiny(inference_steps=2)))
    config = ReportConfig(test_data=str(one_scene), progress=False)
    ap, error = orchestration.run_ap((str(checkpoint), config))
    cache = json.loads((tmp_path / "run" / "ap.json").read_text())
    assert error is None and cache["ap"] == ap and cache["key"]["ap_scenes"] is None
    cache["ap"] = {"AP": -1.0}  # a stand-in result under the same key is what comes back: nothing re-ran
    (tmp_path / "run" / "ap.json").write_text(json.dumps(cache))
    assert orchestration.run_ap((str(checkpoint), config))[0] == {"AP": -1.0}
    save_checkpoint(checkpoint, build_model(DiffusionConfig.tiny(inference_steps=2), seed=1))  # new weights
    assert orchestration.run_ap((str(checkpoint), config))[0]["num_scenes"] == 1
    (tmp_path / "run" / "ap.json").write_text("{cut short")
    assert orchestration.run_ap((str(checkpoint), config))[0]["num_scenes"] == 1  # a corrupt cache is redone


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
    # The report runs them as two parts: the rows that read the main checkpoint, and the variants trained apart.
    main_rows = evaluate_ablations(config, main_ap=main_ap, part="main")
    trained_rows = evaluate_ablations(config, main_ap=main_ap, part="trained")
    assert {r["name"] for r in main_rows} == {"infer5", "steps5"}
    assert {r["kind"] for r in main_rows} == set(orchestration.MAIN_ABLATION_KINDS)
    assert "steps5" not in {r["name"] for r in trained_rows} and "steps10" in {r["name"] for r in trained_rows}
    assert orchestration.merge_ablations(main_rows, trained_rows) == list(rows.values())
    with pytest.raises(ValueError, match="part must be one of"):
        evaluate_ablations(config, part="steps")


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
    provenance = shipped_provenance()
    report = {**report, "provenance": provenance}
    paths = write_report(report, tmp_path / "RESULTS.md", tmp_path / "figs")
    md = paths["markdown"].read_text()
    assert paths["failures"].read_bytes()[:8] == PNG_MAGIC and "](figs/failures.png)" in md
    assert "### Failure anatomy" in md and "collision: free-space (tool_rod) × 1" in md
    assert "## Checkpoint provenance" in md
    assert all(record["git_commit"] in md for record in provenance.values())  # every shipped file's commit
    assert "`python -m policies.cao.train --data data/train" in md
    assert "## Paired comparisons with Diffusion-Suction" in md and "Diffusion-Suction − Cao et al." in md


def test_the_report_shows_which_parcels_were_picked_where_every_cell_was_audited(report, tmp_path: Path):
    from eval.report.tables import cover_table

    assert cover_table(report["policies"]) is None  # nothing audited: no table, no section
    plain = write_report(report, tmp_path / "a.md", tmp_path / "f")["markdown"].read_text()
    assert "### Which parcels were picked" not in plain
    audited = _clearance(3, 4, 3, 4)
    log = audited["episodes"][0]["attempt_log"]
    for k, attempt in enumerate(log):  # 3 held: 2 on free parcels, 1 on a covered one; the strike on a covered one
        attempt["audit"] = {"parcel": k, "covered": k >= 2, "free_parcels": 1, "off_com_mm": 5.0, "to_surface_mm": 0.2}
    summary = summarise([EpisodeResult(**audited["episodes"][0])])
    summary["episodes"] = audited["episodes"]
    policies = {**report["policies"], "diffusion": {**report["policies"]["diffusion"], "clearance": summary}}
    table = cover_table(policies)
    assert "| Diffusion-Suction | 2/2 (100%) | 1/2 (50%) | 2 | – |" in table
    md = write_report({**report, "policies": policies}, tmp_path / "b.md", tmp_path / "g")["markdown"].read_text()
    assert "### Which parcels were picked" in md and table in md


def _full_ap(qualities: list[list[float]], visibility: float, cost: dict[str, float], quality: str,
             parcels: int = 3, nms_radius: float = 0.02) -> dict:
    """What evaluate_ap returns, from hand-made qualities: AP, AP+vis (each quality times ``visibility``), the
    q = 1 ceiling of ``parcels`` parcels a scene, the channel costs, and the scene indices."""
    result = _ap(qualities)
    with_vis = _ap([[q * visibility for q in scene] for scene in qualities])
    ceiling = aggregate_ap([ceiling_ap(parcels, APConfig())] * len(qualities))
    result["AP+vis"], result["intervals"]["AP+vis"] = with_vis["AP"], with_vis["intervals"]["AP"]
    result["with_visibility"] = with_vis
    result["ceiling"] = {k: v for k, v in ceiling.items() if isinstance(v, float) or k in ("num_scenes", "intervals")}
    result.update(channel_cost=cost, quality=quality, policy="x", data="d",
                  config={"quality": quality, "nms_radius": nms_radius},
                  scenes=[{"index": i, "seconds": 0.5} for i in range(len(qualities))])
    return result


ORACLE_Q = [[1.0, 0.9, 0.8, 0.7], [0.9, 0.9, 0.6], [1.0, 0.5]]


@pytest.fixture()
def two_definitions(report: dict) -> dict:
    """The label oracle and Diffusion-Suction under both definitions, and the paper-compatible rows."""
    oracle = {"suctionnet": _full_ap(ORACLE_Q, 0.8, {"seal": 4.0, "wrench": 9.0, "collision": 1.0}, "suctionnet"),
              "physical": _full_ap([[0.5, 0.4], [0.3, 0.9], [0.2]], 0.8, {"seal": 20.0, "wrench": 2.0,
                                                                           "collision": 0.5}, "physical")}
    diffusion = {"suctionnet": report["policies"]["diffusion"]["ap"],  # an older result: no AP+vis, no ceiling
                 "physical": _full_ap([[0.3, 0.1], [0.2]], 0.9, {}, "physical", parcels=2)}
    policies = {"oracle": {**_entry("oracle", "Oracle (privileged ceiling)", oracle["suctionnet"]),
                           "ap_by_quality": oracle},
                "diffusion": {**report["policies"]["diffusion"], "ap_by_quality": diffusion},
                "cao": report["policies"]["cao"],  # no physical result: 'not measured'
                "dexnet": report["policies"]["dexnet"]}
    nms = _full_ap([[1.0] * 10] * 3, 0.8, {}, "suctionnet", nms_radius=PAPER_COMPAT_NMS_RADIUS)
    wrench = _full_ap([[min(1.0, q + 0.1) for q in s] for s in ORACLE_Q], 0.8, {}, "paper_compat")
    both = _full_ap([[1.0] * 10] * 3, 0.9, {}, "paper_compat", nms_radius=PAPER_COMPAT_NMS_RADIUS)
    compat = [{"name": "oracle", "label": "Oracle (privileged ceiling)", "status": "ok", "reason": None, "errors": {},
               "results": {"suctionnet": oracle["suctionnet"], "nms": nms, "wrench": wrench, "both": both}},
              {"name": "diffusion", "label": "Diffusion-Suction", "status": "not available",
               "reason": "no checkpoint", "results": {}, "errors": {}}]
    config = {**report["config"], "ap_qualities": ["suctionnet", "physical"]}
    return {**report, "config": config, "policies": policies, "paper_compat": compat}


def _section(md: str, title: str) -> str:
    """The markdown from the heading ``title`` to the next heading of any level."""
    start = md.index(title)
    rest = md[start + len(title):]
    ends = [i for i in (rest.find("\n## "), rest.find("\n### ")) if i >= 0]
    return rest[: min(ends)] if ends else rest


def _rows(table: str) -> list[str]:
    return [line for line in table.splitlines() if line.startswith("| ") and not line.startswith("| method")]


def test_every_ap_table_has_the_label_oracle_and_a_last_ceiling_row(two_definitions: dict, tmp_path: Path):
    md = render_markdown(two_definitions, {}, tmp_path / "RESULTS.md")
    oracle = two_definitions["policies"]["oracle"]["ap_by_quality"]
    ceiling = oracle["suctionnet"]["ceiling"]
    assert ceiling["AP"] < 100.0  # three parcels a scene: 30 slots cannot fill the top 50
    for quality, with_paper in (("suctionnet", True), ("physical", False)):
        rows = _rows(_section(md, f"### `{quality}`"))
        assert rows[0].startswith(f"| {LABEL_ORACLE} | {format_interval(oracle[quality]['intervals']['AP'])}")
        assert rows[0].endswith(f" | {format_interval(oracle[quality]['intervals']['AP+vis'])} |")
        assert rows[-1].startswith(f"| {CEILING} | {format_interval(ceiling['intervals']['AP'])}")
        assert format_interval(ceiling["intervals"]["top1_AP"]) in rows[-1]
        assert len(rows) == 5  # oracle, Diffusion-Suction, Cao et al., Dex-Net 3.0, ceiling
        assert ("/ 94.42" in _section(md, f"### `{quality}`")) == with_paper  # the paper's numbers: suctionnet only
    physical = _section(md, "### `physical`")
    assert "this project's own definition" in md and "Cao et al. (not measured)" in physical
    assert "Dex-Net 3.0 (not available: FileNotFoundError" in physical
    diffusion = two_definitions["policies"]["diffusion"]["ap_by_quality"]["physical"]
    assert f"| Diffusion-Suction | {format_interval(diffusion['intervals']['AP'])} |" in physical


def test_table_ii_without_any_ceiling_still_prints_the_ceiling_row(report: dict):
    table = table_ii(report["policies"], "physical")
    assert _rows(table)[-1].startswith(f"| {CEILING} | – |")
    assert all("/" not in row.split("|", 2)[2] for row in _rows(table))  # no paper column off suctionnet


def test_channel_costs_of_the_label_oracle_are_the_negated_channel_cost(two_definitions: dict):
    policies = two_definitions["policies"]
    table = channel_cost_table(policies, ("suctionnet", "physical"))
    ap = policies["oracle"]["ap_by_quality"]["suctionnet"]
    vis = ap["AP+vis"] - ap["AP"]
    assert vis < 0  # visibility 0.8 on every parcel lowers it
    assert f"| `suctionnet` | {format_interval(ap['intervals']['AP'])} | -4.00 | -9.00 | -1.00 | {vis:.2f} |" in table
    assert "| `physical` |" in table and "| -20.00 | -2.00 | -0.50 |" in table
    assert "the oracle was not in this report" in channel_cost_table({}, ("suctionnet",))


def test_paper_compatible_table_and_its_sentences_come_from_the_numbers(two_definitions: dict, tmp_path: Path):
    rows = two_definitions["paper_compat"]
    table = paper_compat_table(rows)
    results = rows[0]["results"]
    for variant in PAPER_COMPAT_VARIANTS:
        assert f"| {LABEL_ORACLE} | {variant.description} | {format_interval(results[variant.name]['intervals']['AP'])}"\
            in table
    assert "Diffusion-Suction | not available: no checkpoint |" in table
    sentences = paper_compat_sentences(rows)
    base = results["suctionnet"]["AP"]
    for variant, line in zip(PAPER_COMPAT_VARIANTS[1:], sentences):
        diff = results[variant.name]["AP"] - base
        assert diff > 0 and f"raises its Top-50 AP from {base:.2f} to {results[variant.name]['AP']:.2f} " \
                             f"({diff:+.2f} points; paired over the same scenes" in line
        assert line.startswith(f"- {LABEL_ORACLE}, {variant.description}:")
    assert "94.42" in sentences[-1]
    md = render_markdown(two_definitions, {}, tmp_path / "RESULTS.md")
    assert "## Paper-compatible (not a measure of picking)" in md and sentences[0] in md
    lowered = {**rows[0], "results": {**results, "nms": results["suctionnet"], "suctionnet": results["nms"]}}
    assert "lowers its Top-50 AP" in paper_compat_sentences([lowered])[0]


def test_label_physics_section_reads_the_summary(two_definitions: dict, tmp_path: Path):
    out = tmp_path / "results" / "RESULTS.md"
    path = tmp_path / "results" / "label_physics.json"
    md = render_markdown({**two_definitions, "label_physics": orchestration.read_label_physics(path)}, {}, out)
    assert "## Labels vs physics\n\nNot measured" in md
    path.parent.mkdir(parents=True)
    path.write_text(json.dumps({"picks": 3000, "auc": {"estimate": 0.874, "low": 0.85, "high": 0.9},
                                "auc_by_layout": {"stacked": {"estimate": 0.8}},
                                "confusion": {"precision": 0.7, "recall": 0.9, "hold_failure": 5, "fail_success": 2}}))
    path.with_suffix(".png").write_bytes(PNG_MAGIC)
    found = orchestration.read_label_physics(path)
    assert found["auc"] == pytest.approx(0.874) and found["picks"] == 3000
    md = render_markdown({**two_definitions, "label_physics": found}, {}, out)
    assert "**0.874** [0.850, 0.900] (falls short of the goal of 0.9); by layout stacked 0.800" in md
    assert "over 3000 random candidate picks" in md and "precision 0.700, recall 0.900" in md
    assert "](label_physics.png)" in md
    path.write_text(json.dumps({"picks": 3}))
    assert "not an eval/label_physics.py summary" in render_markdown(
        {**two_definitions, "label_physics": orchestration.read_label_physics(path)}, {}, out)
    path.write_text("{not json")
    assert "could not be read" in render_markdown(
        {**two_definitions, "label_physics": orchestration.read_label_physics(path)}, {}, out)


def test_each_quality_is_evaluated_and_the_paper_compatible_variants_are_the_right_protocols(tmp_path: Path,
                                                                                             monkeypatch):
    import eval.ap

    calls = []

    def fake_evaluate_ap(policy, data_dir, scenes=None, config=APConfig(), progress=False):
        calls.append((policy.name, config.quality, config.nms_radius))
        if config.quality == "physical" and policy.name == "random":
            raise RuntimeError("physical broke")
        return {"policy": policy.name, "quality": config.quality, "nms_radius": config.nms_radius,
                **dict.fromkeys(("AP", "AP0.8", "AP0.4", "top1_AP", "top1_AP0.8", "top1_AP0.4", "AP+vis"), 1.0)}

    monkeypatch.setattr(eval.ap, "evaluate_ap", fake_evaluate_ap)
    config = ReportConfig(test_data=str(tmp_path), policies=("oracle", "random"), skip_clearance=True,
                          progress=False)
    entries = {name: orchestration.evaluate_policy_ap(name, config) for name in config.policies}
    assert entries["oracle"]["ap"]["quality"] == "suctionnet"
    assert entries["oracle"]["ap"] is entries["oracle"]["ap_by_quality"]["suctionnet"]
    assert entries["oracle"]["ap_by_quality"]["physical"]["quality"] == "physical"
    assert entries["random"]["ap_by_quality"]["physical"] is None
    assert "physical broke" in entries["random"]["ap_errors"]["physical"] and entries["random"]["ap_error"] is None
    assert "failed: RuntimeError: physical broke" in table_ii(entries, "physical")
    calls.clear()
    rows = orchestration.evaluate_paper_compat(config, entries)
    assert [row["name"] for row in rows] == ["oracle"]  # random is not a paper-compatible method; diffusion absent
    results = rows[0]["results"]
    assert results["suctionnet"] is entries["oracle"]["ap"]  # (a) is the entry's own run, not run again
    default_nms = APConfig().nms_radius
    assert sorted(calls) == sorted([("oracle", "suctionnet", PAPER_COMPAT_NMS_RADIUS),
                                    ("oracle", "paper_compat", default_nms),
                                    ("oracle", "paper_compat", PAPER_COMPAT_NMS_RADIUS)])
    assert (results["nms"]["quality"], results["nms"]["nms_radius"]) == ("suctionnet", PAPER_COMPAT_NMS_RADIUS)
    assert (results["wrench"]["quality"], results["wrench"]["nms_radius"]) == ("paper_compat", default_nms)


def test_clearance_reused_from_an_earlier_report_is_labelled_as_such(report, tmp_path: Path):
    """--clearance-from: the earlier report's clearance fills each entry by policy name, a policy it lacks says so,
    and the page names the source, its date and its settings; an unusable file is one clear error."""
    earlier = tmp_path / "earlier.json"
    earlier.write_text(json.dumps({"generated": "2026-11-30T10:00:00+00:00",
                                   "config": {"episodes": 2, "parcels": 10, "seed": 0},
                                   "policies": {"cao": {"clearance": _clearance(2, 4, 2, 4)}}}))
    config = ReportConfig(test_data=str(tmp_path), clearance_from=str(earlier), out=str(tmp_path / "R.md"))
    policies = {name: dict(entry, clearance=None) for name, entry in report["policies"].items() if name != "dexnet"}
    orchestration.reuse_clearance(policies, orchestration.load_clearance_source(str(earlier)), config)
    assert policies["cao"]["clearance"]["overall"]["successes"] == 2
    assert policies["diffusion"]["clearance"] is None and "not in" in policies["diffusion"]["clearance_error"]
    page = render_markdown({**report, "policies": policies, "config": asdict(config),
                            "clearance_source": {"path": str(earlier), "generated": "2026-11-30T10:00:00+00:00",
                                                 "episodes": 2, "parcels": 10, "seed": 0}}, {}, tmp_path / "R.md")
    assert f"clearance **reused from `{earlier}`** (generated 2026-11-30T10:00:00+00:00; 10 parcels" in page
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(ValueError, match="bad.json: not a readable report JSON"):
        orchestration.load_clearance_source(str(tmp_path / "bad.json"))
    with pytest.raises(ValueError, match="exclude each other"):
        ReportConfig(test_data=str(tmp_path), clearance_from=str(earlier), skip_clearance=True)


def test_paired_comparisons_cover_every_quality_definition():
    """Diffusion-Suction ahead under suctionnet but behind under physical: each definition gets its own verdict."""
    from eval.report.tables import comparison_table

    def scored(qualities):  # an AP result with its scenes' indices, which paired comparisons match on
        return {**_ap(qualities), "scenes": [{"index": i} for i in range(len(qualities))]}

    good, bad = [[0.9, 0.9], [0.9, 0.8], [0.95, 0.9]], [[0.1, 0.0], [0.2, 0.1], [0.0, 0.1]]
    first = _entry("diffusion", "Diffusion-Suction", scored(good))
    second = _entry("dexnet", "Dex-Net 3.0", scored(bad))
    first["ap_by_quality"] = {"suctionnet": first["ap"], "physical": scored(bad)}
    second["ap_by_quality"] = {"suctionnet": second["ap"], "physical": scored(good)}
    row = compare(first, second)
    assert row["AP"]["verdict"] == "Diffusion-Suction ahead" and row["AP:physical"]["verdict"] == "Dex-Net 3.0 ahead"
    table = comparison_table([row], {"diffusion": first, "dexnet": second})
    assert "Top-50 AP (suctionnet) diff" in table and "Top-50 AP (physical) verdict" in table
    assert "Dex-Net 3.0 ahead" in table
