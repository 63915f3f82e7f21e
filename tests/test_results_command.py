"""`make results` (eval.results): interrupted and re-run, it redoes only the parts that had not finished."""

from __future__ import annotations

import hashlib
import json
from collections import Counter
from dataclasses import asdict
from pathlib import Path

import numpy as np
import pytest

from eval import results
from eval.clearance import ClearanceConfig, EpisodeResult, attempt_record, summarise, tool_check_settings
from eval.metrics import aggregate_ap, scene_ap
from eval.report import orchestration
from eval.report.config import ReportConfig


def _part(name: str, tmp_path: Path, calls: Counter, fail: set[str]) -> results.Part:
    def run():
        calls[name] += 1
        if name in fail:
            raise KeyboardInterrupt  # the user's Ctrl-C, mid-run
        return {"name": name}
    return results.Part(name, tmp_path / f"{name}.json", run)


def test_an_interrupted_run_redoes_only_the_unfinished_parts(tmp_path: Path):
    calls: Counter = Counter()
    parts = [_part(n, tmp_path, calls, fail={"b"}) for n in "abc"]
    with pytest.raises(KeyboardInterrupt):
        results.run_parts(parts, log=lambda _: None)
    assert calls == {"a": 1, "b": 1} and (tmp_path / "a.json").is_file() and not (tmp_path / "b.json").exists()
    (tmp_path / "c.json.tmp").write_text("{")  # a write killed half way never marks a part done
    parts = [_part(n, tmp_path, calls, fail=set()) for n in "abc"]
    assert results.run_parts(parts, log=lambda _: None) == {"a": "skipped", "b": "ran", "c": "ran"}
    assert calls == {"a": 1, "b": 2, "c": 1}
    assert results.run_parts(parts, log=lambda _: None) == dict.fromkeys("abc", "skipped")
    assert results.run_parts(parts, force=["b"], log=lambda _: None)["b"] == "ran" and calls["b"] == 3
    assert json.loads((tmp_path / "c.json").read_text())["value"] == {"name": "c"}


def _fake_ap(name: str, config: ReportConfig) -> dict:
    rng = np.random.default_rng(len(name))
    ap = aggregate_ap([scene_ap(np.linspace(1, 0, 5), rng.random(5)) for _ in range(6)])
    ap["scenes"] = [{"index": i, "seconds": 0.1} for i in range(6)]
    return {**orchestration._entry(name), "ap": ap}


def _fake_clearance(calls: Counter, interrupt_at: str | None):
    def run(name, config, objects, layouts):
        cell = f"{name}/{objects[0]}-{layouts[0]}"
        calls[cell] += 1
        if cell == interrupt_at:
            raise KeyboardInterrupt
        episodes = [EpisodeResult(objects=objects[0], layout=layouts[0], episode=e, seed=e, attempts=3, successes=1,
                                  parcels_placed=2, parcels_cleared=1, reason="consecutive_failures",
                                  outcomes={"success": 1, "dropped": 2}, replay=None, wall_time_s=1.0,
                                  attempt_log=[attempt_record({"outcome": "success"})] + 2 * [attempt_record(
                                      {"outcome": "dropped", "failure_cause": "suction", "failure_phase": "lift"})])
                    for e in range(config.episodes)]
        summary = summarise(episodes)
        summary["episodes"] = [asdict(e) for e in episodes]
        summary.update(tool_check_settings(ClearanceConfig(policy=name)))  # as evaluate_clearance records it
        summary["config"] = asdict(ClearanceConfig(policy=name, objects=objects, layouts=layouts,
                                                   episodes=config.episodes))
        return summary, None
    return run


def _config(tmp_path: Path, bench_dir: Path) -> results.ResultsConfig:
    report = ReportConfig(test_data=str(tmp_path / "data"), policies=("diffusion", "cao"),
                          objects=("rectangular",), layouts=("scattered", "stacked"), episodes=2,
                          out=str(tmp_path / "results" / "RESULTS.md"), progress=False,
                          label_physics=str(tmp_path / "results" / "label_physics.json"))
    return results.ResultsConfig(report=report, work=str(tmp_path / "work"), bench_dir=str(bench_dir))


def test_the_whole_command_resumes_after_an_interrupt_and_writes_both_pages(tmp_path: Path, monkeypatch):
    bench_dir = tmp_path / "benchmarks"
    bench_dir.mkdir()
    (bench_dir / "bench_tiny.py").write_text("print('| metric | value |')\nprint('| x | 1 |')\n")
    (bench_dir / "RESULTS.md").write_text("# Benchmarks\n\nHand-written goals: keep me.\n")
    monkeypatch.setattr(results, "REPO", tmp_path)
    calls: Counter = Counter()
    monkeypatch.setattr(results, "_generate", lambda out, n, args, cfg, fresh=False: lambda: calls.update(["data"]) or {})
    monkeypatch.setattr(orchestration, "evaluate_policy_ap", lambda name, cfg: calls.update([f"ap/{name}"])
                        or _fake_ap(name, cfg))
    monkeypatch.setattr(orchestration, "evaluate_ablations",
                        lambda cfg, main_ap, part=None: calls.update([f"ablations/{part}"]) or [])
    monkeypatch.setattr(orchestration, "evaluate_paper_compat", lambda cfg, entries: calls.update(["paper_compat"])
                        or [{"name": n, "label": e["label"], "status": "ok", "reason": None, "errors": {},
                             "results": {"suctionnet": e["ap"], "nms": e["ap"]}} for n, e in entries.items()])
    monkeypatch.setattr(orchestration, "evaluate_policy_clearance", _fake_clearance(calls, "cao/rectangular-stacked"))
    cfg = _config(tmp_path, bench_dir)
    names = [p.name for p in results.plan(cfg)]
    assert names == ["data/test", "ap/diffusion", "ap/cao", "clearance/diffusion/rectangular-scattered",
                     "clearance/diffusion/rectangular-stacked", "clearance/cao/rectangular-scattered",
                     "clearance/cao/rectangular-stacked", "paper_compat", "ablations/main", "ablations/trained",
                     "bench/bench_tiny"]
    with pytest.raises(KeyboardInterrupt):
        results.regenerate(cfg, log=lambda _: None)
    first = Counter(calls)
    monkeypatch.setattr(orchestration, "evaluate_policy_clearance", _fake_clearance(calls, None))
    out = results.regenerate(cfg, log=lambda _: None)
    redone = calls - first
    # the interrupted cell and what came after
    assert redone == {"cao/rectangular-stacked": 1, "paper_compat": 1, "ablations/main": 1, "ablations/trained": 1}
    assert [n for n, s in out["status"].items() if s == "ran"] == ["clearance/cao/rectangular-stacked", "paper_compat",
                                                                    "ablations/main", "ablations/trained",
                                                                    "bench/bench_tiny"]
    md = Path(out["paths"]["markdown"]).read_text()
    assert "### Cao et al." in md and "33.33 [" in md and "dropped: lift" in md  # 1/3 pooled, with its interval
    # the paper-compatible rows of the methods it takes (Diffusion-Suction here, from its AP part)
    assert "## Paper-compatible (not a measure of picking)" in md and "| Diffusion-Suction | (b) NMS at" in md
    assert "## Labels vs physics\n\nNot measured" in md
    dump = json.loads(Path(out["paths"]["json"]).read_text())
    assert len(dump["policies"]["cao"]["clearance"]["episodes"]) == 4  # both cells, 2 episodes each
    clearance = dump["policies"]["cao"]["clearance"]
    assert clearance["tool_check"] is True and clearance["seal_check"] is True  # as the cells ran them
    assert clearance["retry_radius"] == 0.05
    # one config over both cells, so any episode of the report can be rebuilt (eval/rebuild.py)
    assert clearance["config"]["layouts"] == ["scattered", "stacked"] and clearance["config"]["policy"] == "cao"
    assert "Acting through the cell's tool check" in md and "does not go back within 0.05 m" in md
    assert "| x | 1 |" in (bench_dir / "RESULTS.md").read_text()
    # Nothing left to do: a third run only re-renders the pages.
    before = Counter(calls)
    assert set(results.regenerate(cfg, log=lambda _: None)["status"].values()) == {"skipped"} and calls == before
    page = (bench_dir / "RESULTS.md").read_text()  # regenerated twice: the hand-written text stays, once
    assert page.count("keep me") == 1 and page.count(results.GENERATED_BEGIN) == 1 and page.count("| x | 1 |") == 1


def test_the_report_claims_the_tool_check_its_cells_recorded_and_refuses_to_pool_cells_that_differ():
    seal, tool_only = {"tool_check": True, "seal_check": True}, {"tool_check": True, "seal_check": False}
    assert results.cell_checks("cao", [{"checks": seal}, {"checks": seal}]) == (seal, None)
    unknown = {"tool_check": None, "seal_check": None, "retry_radius": None}
    assert results.cell_checks("cao", [{"episodes": []}, {}]) == (unknown, None)  # finished before cells recorded
    retried = dict(seal, retry_radius=0.05)
    for cells in ([{"checks": seal}, {"checks": tool_only}], [{"checks": seal}, {}],
                  [{"checks": retried}, {"checks": seal}], [{"checks": retried}, {"checks": dict(seal, retry_radius=0.0)}]):
        flags, why = results.cell_checks("cao", cells)
        assert flags == unknown and "different tool checks" in why and "--force clearance/cao" in why
    assert "not recorded" in results.cell_checks("cao", [{"checks": seal}, {}])[1]


def test_a_forced_data_part_generates_anew_and_keeps_the_old_set_beside_it(tmp_path: Path, monkeypatch):
    """``--force data/test`` regenerates (``dataset.generate`` alone would resume a complete set and keep it); the
    old set is moved aside, never deleted. Unforced, an existing set is handed to the generator as it is."""
    monkeypatch.setattr(results, "REPO", tmp_path)
    old = tmp_path / "data" / "test"
    old.mkdir(parents=True)
    (old / "manifest.json").write_text('{"old": true}')
    seen: list[bool] = []

    def generate(argv):
        seen.append(old.exists())
        old.mkdir(parents=True, exist_ok=True)
        (old / "manifest.json").write_text('{"new": true}')
        return {"argv": list(argv), "stdout": ""}

    monkeypatch.setattr(results, "_subprocess", generate)
    cfg = results.ResultsConfig(report=results.ReportConfig(test_data="data/test"))
    results._generate("data/test", 2, ["--seed", "1"], cfg)()
    assert seen == [True] and not list(old.parent.glob("test.replaced-*"))
    assert results.forced("data/test", ("data",)) and not results.forced("data/test", ("ap",))
    (old / "manifest.json").write_text('{"old": true}')
    value = results._generate("data/test", 2, ["--seed", "1"], cfg, fresh=True)()
    assert seen == [True, False]
    kept = list(old.parent.glob("test.replaced-*"))
    assert len(kept) == 1 and json.loads((kept[0] / "manifest.json").read_text()) == {"old": True}
    assert json.loads((old / "manifest.json").read_text()) == {"new": True}
    assert value["manifest_sha256"] == hashlib.sha256(b'{"new": true}').hexdigest()


def test_make_results_tests_on_big_piles_under_both_definitions(tmp_path: Path):
    args = results.TEST_DATA_ARGS
    assert args[args.index("--parcels") + 1: args.index("--parcels") + 3] == ("10", "50")
    assert args[args.index("--layout") + 1] == "random"  # stacked and scattered, drawn per scene
    cfg = results.config_from_args(results.build_parser().parse_args(["--test-data", str(tmp_path)]))
    assert cfg.test_scenes >= 50 and cfg.report.ap_qualities == ("suctionnet", "physical")


def test_list_shows_done_and_todo(tmp_path: Path, capsys):
    assert results.main(["--test-data", str(tmp_path / "d"), "--work", str(tmp_path / "w"), "--policies", "random",
                         "--objects", "mixed", "--layouts", "stacked", "--skip-benchmarks", "--list"]) == 0
    listed = capsys.readouterr().out.splitlines()
    # no paper_compat part: neither the label oracle nor Diffusion-Suction is asked for
    assert listed == ["todo  data/test", "todo  ap/random", "todo  clearance/random/mixed-stacked", "todo  ablations/main",
                      "todo  ablations/trained"]


def test_training_generates_each_variants_own_split_once_before_the_runs_that_read_it(tmp_path: Path):
    cfg = results.config_from_args(results.build_parser().parse_args(
        ["--test-data", str(tmp_path / "d"), "--work", str(tmp_path / "w"), "--policies", "random", "--train",
         "--ablation-seeds", "0", "--skip-benchmarks"]))
    parts = results.plan(cfg)
    names = [p.name for p in parts]
    own = ["data/variants/train4k400", "data/variants/test8k", "data/variants/train8k"]
    assert [n for n in names if n.startswith("data/")] == ["data/test", "data/train", *own]
    assert max(names.index(n) for n in own) < min(i for i, n in enumerate(names) if n.startswith("train/"))
    after = {p.name: p.after for p in parts}
    assert after["train/points8192/seed0"] == ("data/variants/train8k",)
    assert after["train/reference/seed0"] == ("data/train",)
    # forcing the report's test split does not regenerate the variants' (a prefix of 'data/test8k' would)
    assert not any(results.forced(n, ("data/test",)) for n in own)
    # the pair's splits are the report's, at another density: the same seeds and piles
    from eval.report.splits import TEST_MORE_POINTS, TRAIN_MORE_POINTS, TRAIN_MORE_POINTS_BASELINE

    test = list(TEST_MORE_POINTS.generate_args())
    assert test[test.index("--points") + 1] == "8192"
    test[test.index("--points") + 1] = "4096"
    assert tuple(test) == results.TEST_DATA_ARGS
    assert TRAIN_MORE_POINTS.scenes == TRAIN_MORE_POINTS_BASELINE.scenes
    assert results.TRAIN_DATA_ARGS == TRAIN_MORE_POINTS_BASELINE.generate_args()


def _fake_everything(monkeypatch, tmp_path: Path, calls: Counter, split: dict[str, str] | None = None) -> None:
    """Every part faked; the test split generated has ``split['sha']`` as its manifest hash (read when it runs)."""
    split = {"sha": "split-1"} if split is None else split
    monkeypatch.setattr(results, "REPO", tmp_path)
    monkeypatch.setattr(results, "_generate", lambda out, n, args, cfg, fresh=False: lambda: calls.update(["data"])
                        or {"manifest_sha256": split["sha"]})
    monkeypatch.setattr(orchestration, "evaluate_policy_ap", lambda name, cfg: calls.update([f"ap/{name}"])
                        or _fake_ap(name, cfg))
    def ablations(cfg, main_ap, part=None):  # one step-count row reads the main checkpoint, one variant does not
        calls.update([f"ablations/{part}"])
        kind, name = ("inference_steps", "infer5") if part == "main" else ("trained", "reference")
        return [{"name": name, "kind": kind, "description": name, "status": "ok", "reason": None, "ap": main_ap}]
    monkeypatch.setattr(orchestration, "evaluate_ablations", ablations)
    monkeypatch.setattr(orchestration, "evaluate_paper_compat", lambda cfg, entries: calls.update(["paper_compat"])
                        or [{"name": n, "label": e["label"], "status": "ok", "reason": None, "errors": {},
                             "results": {"suctionnet": e["ap"]}} for n, e in entries.items()])
    monkeypatch.setattr(orchestration, "evaluate_policy_clearance", _fake_clearance(calls, None))


def test_restore_reruns_only_the_clearance_and_the_report_names_what_it_restored(tmp_path: Path, monkeypatch):
    """After a change to the pick cell, ``--restore`` an earlier report's JSON: the test data, AP, paper-compatible
    rows and ablations come from it (the cell does not enter them), the clearance runs, and the page says which
    parts were restored."""
    calls: Counter = Counter()
    _fake_everything(monkeypatch, tmp_path, calls)
    cfg = _config(tmp_path, tmp_path / "no_benchmarks")
    earlier = json.loads(Path(results.regenerate(cfg, log=lambda _: None)["paths"]["json"]).read_text())
    source = tmp_path / "earlier.json"
    source.write_text(json.dumps(earlier))
    calls.clear()
    fresh = results.ResultsConfig(report=cfg.report, work=str(tmp_path / "work2"), bench_dir=cfg.bench_dir,
                                  restore=str(source), force=("clearance",))
    out = results.regenerate(fresh, log=lambda _: None)
    assert calls == {f"{n}/rectangular-{la}": 1 for n in ("diffusion", "cao") for la in ("scattered", "stacked")}
    dump = json.loads(Path(out["paths"]["json"]).read_text())
    restored = ["data/test", "ap/diffusion", "ap/cao", "paper_compat", "ablations/main", "ablations/trained"]
    assert dump["restored"]["sources"] == [{"path": str(source), "generated": earlier["generated"],
                                            "test_split_sha256": "split-1", "parts": restored}]
    assert dump["test_split"] == earlier["test_split"] == {"manifest_sha256": "split-1"}  # the restored split's
    for name in ("diffusion", "cao"):  # the AP is the earlier one, the clearance this run's
        assert dump["policies"][name]["ap"] == earlier["policies"][name]["ap"]
        assert dump["policies"][name]["clearance"]["overall"] == earlier["policies"][name]["clearance"]["overall"]
    assert dump["ablations"] == earlier["ablations"] and dump["paper_compat"] == earlier["paper_compat"]
    md = Path(out["paths"]["markdown"]).read_text()
    assert ("**Restored, not re-run:** `data/test`, `ap/diffusion`, `ap/cao`, `paper_compat`, `ablations/main`, "
            "`ablations/trained`, from "
            f"`{source}`") in md
    # A plain re-run of the restored work has nothing to do, and still names the restored parts.
    calls.clear()
    again = results.regenerate(results.ResultsConfig(report=cfg.report, work=fresh.work, bench_dir=cfg.bench_dir),
                               log=lambda _: None)
    assert not calls and "**Restored, not re-run:**" in Path(again["paths"]["markdown"]).read_text()
    # A forced part is never restored: it runs.
    redo = results.ResultsConfig(report=cfg.report, work=str(tmp_path / "work3"), bench_dir=cfg.bench_dir,
                                 restore=str(source), force=("ap/cao",))
    calls.clear()
    results.regenerate(redo, log=lambda _: None)
    assert calls["ap/cao"] == 1 and calls["ap/diffusion"] == 0
    # A new main checkpoint: its AP and the ablation rows that read it run again; the trained variants' rows (whose
    # checkpoints need not be on this machine) are restored, and the page keeps both, step counts first.
    new_main = results.ResultsConfig(report=cfg.report, work=str(tmp_path / "work4"), bench_dir=cfg.bench_dir,
                                     restore=str(source), force=("ap/diffusion", "ablations/main"))
    calls.clear()
    out = results.regenerate(new_main, log=lambda _: None)
    assert calls["ap/diffusion"] == 1 and calls["ablations/main"] == 1 and calls["ablations/trained"] == 0
    dump = json.loads(Path(out["paths"]["json"]).read_text())
    assert [row["name"] for row in dump["ablations"]] == ["infer5", "reference"]
    assert dump["ablations"][1] == earlier["ablations"][1]


def test_restored_rows_on_another_test_split_are_named_as_such(tmp_path: Path, monkeypatch):
    """The parcels changed, so the test split is generated anew while the trained ablation rows are restored: the
    page says those rows read the earlier split; restored onto the same split, it says they read this one."""
    calls: Counter = Counter()
    split = {"sha": "split-before"}
    _fake_everything(monkeypatch, tmp_path, calls, split)
    cfg = _config(tmp_path, tmp_path / "no_benchmarks")
    source = tmp_path / "earlier.json"
    source.write_text(Path(results.regenerate(cfg, log=lambda _: None)["paths"]["json"]).read_text())

    def rerun(work: str, sha: str, force: tuple[str, ...]) -> tuple[dict, str]:
        split["sha"] = sha
        out = results.regenerate(results.ResultsConfig(report=cfg.report, work=str(tmp_path / work),
                                                       bench_dir=cfg.bench_dir, restore=str(source), force=force),
                                 log=lambda _: None)
        return json.loads(Path(out["paths"]["json"]).read_text()), Path(out["paths"]["markdown"]).read_text()

    dump, md = rerun("resized", "split-after", ("data/test", "ap", "paper_compat", "ablations/main", "clearance"))
    assert dump["test_split"] == {"manifest_sha256": "split-after"}
    assert dump["restored"]["sources"][0]["parts"] == ["ablations/trained"]
    assert ("**They were measured on that report's test split (manifest split-before), not on this report's** "
            "(manifest split-after") in md
    dump, md = rerun("same", "split-before", ("data/test", "ap", "paper_compat", "ablations/main", "clearance"))
    assert "They were measured on this report's test split (the same manifest)." in md and "not on this" not in md


def test_restore_refuses_a_report_measured_on_other_test_scenes_or_not_a_report(tmp_path: Path, monkeypatch, capsys):
    calls: Counter = Counter()
    _fake_everything(monkeypatch, tmp_path, calls)
    cfg = _config(tmp_path, tmp_path / "no_benchmarks")
    other = {"generated": "x", "config": {"test_data": "data/elsewhere"}, "policies": {}}
    (tmp_path / "other.json").write_text(json.dumps(other))
    (tmp_path / "broken.json").write_text("{")
    with pytest.raises(ValueError, match=r"--restore .*other.json: measured with other settings \(test_data"):
        results.ResultsConfig(report=cfg.report, work=cfg.work, restore=str(tmp_path / "other.json"))
    with pytest.raises(ValueError, match=r"--restore .*broken.json: not a readable report JSON"):
        results.ResultsConfig(report=cfg.report, work=cfg.work, restore=str(tmp_path / "broken.json"))
    (tmp_path / "list.json").write_text("[1, 2]")
    with pytest.raises(ValueError, match=r"--restore .*list.json: not a report JSON \(no 'policies'\)"):
        results.ResultsConfig(report=cfg.report, work=cfg.work, restore=str(tmp_path / "list.json"))
    assert not calls and not Path(cfg.work).exists()  # refused before anything ran or was written
    with pytest.raises(ValueError, match="--restore .*missing.json: not a readable report JSON"):
        results.ResultsConfig(report=cfg.report, restore=str(tmp_path / "missing.json"))
    # On the command line: one line naming the flag and the file, and a non-zero exit.
    with pytest.raises(SystemExit) as exit_info:
        results.main(["--restore", str(tmp_path / "other.json"), "--test-data", str(tmp_path / "data"),
                      "--work", cfg.work])
    assert exit_info.value.code == 2 and "--restore" in capsys.readouterr().err


def test_a_policys_cells_pool_into_one_config_only_where_they_agree_beyond_their_cell():
    def cell(objects: str, layout: str, **kw) -> dict:
        return json.loads(json.dumps(asdict(ClearanceConfig(policy="cao", objects=(objects,), layouts=(layout,), **kw))))

    pooled = results.pooled_config([cell("mixed", "stacked"), cell("rectangular", "scattered")])
    assert pooled is not None and pooled["objects"] == ["rectangular", "mixed"]  # the grid's order
    assert pooled["layouts"] == ["scattered", "stacked"] and pooled["policy"] == "cao"
    assert results.pooled_config([cell("mixed", "stacked"), cell("mixed", "scattered", seed=1)]) is None
    assert results.pooled_config([cell("mixed", "stacked"), None]) is None  # a part from before configs were kept
    assert results.pooled_config([]) is None
