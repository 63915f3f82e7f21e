"""eval/label_physics.py: the rank AUC on known answers, the tables, determinism of a tiny run, and its CLI errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from eval.label_physics import (LabelPhysicsConfig, bootstrap_auc, confusion, evaluate, load_from_above, main, plan_jobs,
                                reliability, resting_load_quality, roc_auc, summarise)
from parcelpick_env.cli import run_cli

TINY = dict(num_parcels=2, camera_size=(160, 120), layouts=("scattered",), objects=("rectangular",))


def test_auc_known_answers():
    y = np.array([0, 0, 1, 1], dtype=bool)
    assert roc_auc([0.1, 0.2, 0.8, 0.9], y) == 1.0  # every success above every failure
    assert roc_auc([0.9, 0.8, 0.2, 0.1], y) == 0.0  # inverted
    assert roc_auc([0.5, 0.5, 0.5, 0.5], y) == 0.5  # all tied: each pair counts half
    # hand count: pairs (success, failure) = (0.35, 0.1) win, (0.35, 0.4) lose, (0.8, .) win twice -> 3/4
    assert roc_auc([0.1, 0.4, 0.35, 0.8], y) == pytest.approx(0.75)
    # a tie between a success and a failure: (0.4, 0.4) half, (0.4, 0.1) win, (0.9, .) win twice -> 3.5/4
    assert roc_auc([0.1, 0.4, 0.4, 0.9], y) == pytest.approx(0.875)
    assert np.isnan(roc_auc([0.1, 0.2], [True, True]))  # one class only: undefined


def test_auc_matches_pair_count_and_rows():
    rng = np.random.default_rng(3)
    s = rng.integers(0, 5, size=60) / 4.0  # many ties
    y = rng.random(60) < 0.4
    wins = (s[y][:, None] > s[~y][None, :]).sum() + 0.5 * (s[y][:, None] == s[~y][None, :]).sum()
    assert roc_auc(s, y) == pytest.approx(wins / (y.sum() * (~y).sum()))
    rows = roc_auc(np.stack([s, -s]), np.stack([y, y]))  # rows independently: the second is the mirror
    assert rows == pytest.approx([wins / (y.sum() * (~y).sum()), 1 - wins / (y.sum() * (~y).sum())])


def test_bootstrap_interval_brackets_estimate_and_repeats():
    rng = np.random.default_rng(0)
    y = rng.random(200) < 0.5
    s = y + rng.normal(0, 0.7, 200)
    a, b = bootstrap_auc(s, y), bootstrap_auc(s, y)
    assert a == b
    assert a.low < a.estimate < a.high and 0.7 < a.estimate < 0.95


def test_reliability_and_confusion_counts():
    q = np.array([0.0, 0.0, 0.1, 0.5, 0.95, 1.0])
    y = np.array([False, True, False, True, True, True])
    rows = {r["bin"]: r for r in reliability(q, y)}
    assert rows["0"]["count"] == 2 and rows["0"]["success_rate"] == 0.5
    assert rows["(0.0, 0.2]"]["success_rate"] == 0.0 and rows["(0.8, 1.0]"]["count"] == 2
    assert sum(r["count"] for r in rows.values()) == len(q)
    c = confusion(q, y)
    assert (c["hold_success"], c["hold_failure"], c["fail_success"], c["fail_failure"]) == (3, 1, 1, 1)


def test_jobs_balance_cells():
    jobs = plan_jobs(LabelPhysicsConfig(picks=20, picks_per_reset=3))
    assert sum(sum(j.picks) for j in jobs) == 20
    episodes = sorted(e for j in jobs for e in j.episodes)
    assert episodes == list(range(7))  # ceil(20 / 3), each once
    per_cell = {}
    for j in jobs:
        per_cell[(j.layout, j.objects)] = per_cell.get((j.layout, j.objects), 0) + len(j.episodes)
    assert max(per_cell.values()) - min(per_cell.values()) <= 1


def test_two_pick_run_is_deterministic(tmp_path):
    config = LabelPhysicsConfig(picks=2, seed=5, **TINY)
    first, summary = evaluate(config, progress=False, picks_path=tmp_path / "a.jsonl")
    second, _ = evaluate(config, progress=False)
    assert len(first) == 2
    strip = [{k: v for k, v in r.items() if k != "seconds"} for r in first]
    assert strip == [{k: v for k, v in r.items() if k != "seconds"} for r in second]
    for r in first:  # a label in [0, 1], 0 exactly when a channel is 0; an env outcome
        assert 0.0 <= r["quality"] <= 1.0
        assert (r["quality"] == 0.0) == (min(r["seal"], r["wrench"], r["collision"]) == 0.0)
        assert r["success"] == (r["outcome"] == "success")
    assert summary["picks"] == 2 and len((tmp_path / "a.jsonl").read_text().splitlines()) == 2
    other, _ = evaluate(LabelPhysicsConfig(picks=2, seed=6, **TINY), progress=False)
    assert [r["point"] for r in other] != [r["point"] for r in first]


def _records(n=40):
    rng = np.random.default_rng(1)
    q = np.where(rng.random(n) < 0.5, 0.0, rng.random(n))
    return [{"layout": "stacked" if k % 2 else "scattered", "objects": "mixed", "quality": float(q[k]),
             "seal": float(q[k] > 0), "wrench": float(q[k]), "collision": 1.0, "success": bool(q[k] > 0.3),
             "failure": None if q[k] > 0.3 else "no_seal: seal", "failure_detail": None if q[k] > 0.3 else
             "no_seal: seal (suction_cup)", "delivered_labelled": bool(q[k] > 0.3), "seconds": 1.0}
            for k in range(n)]


def test_summary_from_picks_file(tmp_path, capsys):
    records = _records()
    path = tmp_path / "picks.jsonl"
    path.write_text("".join(json.dumps(r) + "\n" for r in records))
    out = tmp_path / "out.json"
    assert main(["--from-picks", str(path), "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["auc"]["estimate"] == pytest.approx(1.0)  # success iff q > 0.3: a perfect ranking
    assert result["picks"] == len(records) and result["picks_file"] == str(path) and "records" not in result
    assert "| overall |" in capsys.readouterr().out
    assert summarise(records)["confusion"]["hold_failure"] == sum(0 < r["quality"] <= 0.3 for r in records)


@pytest.mark.parametrize("argv, names", [(["--picks", "0"], "--picks"), (["--parcels", "99"], "--parcels"),
                                         (["--plot", "fig.pdf"], "--plot"), (["--layout", "heap"], "--layout"),
                                         (["--camera", "big"], "--camera")])
def test_bad_argument_is_one_clear_line(tmp_path, capsys, argv, names):
    with pytest.raises(SystemExit) as exit_info:
        run_cli(main, argv + ["--out", str(tmp_path / "x.json")])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and names in err


def test_load_from_above_is_the_weight_on_top():
    """Two stacked boxes: the bottom one carries the top one's weight (m g), the top one carries nothing."""
    import gymnasium as gym

    import parcelpick_env  # noqa: F401
    from parcelpick_env.camera.config import CameraConfig
    from parcelpick_env.envs.custom_scene import BoxScene, PlacedBox

    bottom = PlacedBox((0.20, 0.15, 0.10), 1.0, center=(0.0, 0.0, 0.05))
    scene = BoxScene([bottom, bottom.resting_on_top((0.12, 0.10, 0.06), 0.5)])
    env = gym.make("ParcelPick-v0", scene_factory=scene, camera=CameraConfig(width=160, height=120), num_points=256)
    try:
        env.reset(seed=0)
        bodies = [ps.body_id for ps in env.unwrapped.scene.parcels]
        gravity = env.unwrapped.sim.config.gravity
        assert load_from_above(env, bodies[0]) == pytest.approx(0.5 * gravity, rel=0.05)
        assert load_from_above(env, bodies[1]) == 0.0
    finally:
        env.close()


def test_resting_load_what_if_scales_the_worst_ratio():
    from parcelpick_env.suction.config import SuctionConfig

    g = SuctionConfig().gravity
    base = dict(seal=0.8, collision=1.0, worst_ratio=0.3, mass=0.5)
    records = [dict(base, load_from_above=0.0), dict(base, load_from_above=0.5 * g),  # L = W: twice the ratio
               dict(base, load_from_above=3 * 0.5 * g), dict(base, worst_ratio=None, load_from_above=0.0)]
    assert resting_load_quality(records) == pytest.approx([0.8 * 0.7, 0.8 * 0.4, 0.0, 0.0])
