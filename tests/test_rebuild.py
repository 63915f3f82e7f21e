"""Rebuilding a logged episode's state from its clearance summary: step order, replay checks, the CLI."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest

from eval.clearance import ClearanceConfig, evaluate_clearance, logged_action
from eval.rebuild import ReplayDiverged, act_here, episode_task, logged_steps, main, rebuild
from parcelpick_env.camera.config import CameraConfig

CAMERA = CameraConfig(width=96, height=72)
TINY = dict(policy="random", objects=("rectangular",), layouts=("scattered",), episodes=1, num_parcels=2,
            max_attempts=3, env_kwargs=dict(camera=CAMERA, num_points=256))


@pytest.fixture(scope="module")
def summary() -> dict:
    """One tiny episode's summary, through JSON as ``eval/clearance.py --out`` writes it."""
    run = evaluate_clearance(ClearanceConfig(**TINY), progress=False)
    return json.loads(json.dumps(run, default=str))


def test_every_step_logs_the_action_the_env_received_and_the_episode_its_modes(summary):
    (episode,) = summary["episodes"]
    assert (episode["action_mode"], episode["obs_mode"]) == ("pose", "pointcloud")
    assert all(len(a["action"]) == 6 for a in episode["attempt_log"])  # a pose: point and normal
    assert logged_action(np.array([0.1, np.nan, -np.inf], np.float32)) == [float(np.float32(0.1)), None, None]
    assert logged_action(["a", "b"]) is None  # no array of numbers: not replayable, and the rebuild says so


def test_each_push_is_replayed_before_the_attempt_it_preceded():
    record = {"objects": "mixed", "layout": "stacked", "episode": 0,
              "attempt_log": [{"outcome": "success", "action": [0.0]}, {"outcome": "dropped", "action": [1.0]}],
              "push_log": [{"outcome": "pushed", "before": 1, "action": [2.0]},
                           {"outcome": "pushed", "before": 1, "action": [3.0]},
                           {"outcome": "pushed", "before": 2, "action": [None]}]}
    steps = logged_steps(record)
    assert [(s.kind, s.index) for s in steps] == [("attempt", 0), ("push", 0), ("push", 1), ("attempt", 1), ("push", 2)]
    assert [float(s.action[0]) for s in steps[:4]] == [0.0, 2.0, 3.0, 1.0] and np.isnan(steps[4].action[0])


def test_a_summary_without_actions_is_refused_naming_the_step(summary):
    record = copy.deepcopy(summary["episodes"][0])
    del record["attempt_log"][0]["action"]
    with pytest.raises(ValueError, match="rectangular/scattered episode 0: attempt 0 has no logged action"):
        logged_steps(record)


def test_the_stored_config_draws_the_logged_pile_with_its_env_keywords(summary):
    task = episode_task(summary, summary["episodes"][0])
    assert task.seed == summary["episodes"][0]["seed"]
    assert task.config.env_kwargs == {"camera": CAMERA, "num_points": 256}  # the camera back as its dataclass
    edited = copy.deepcopy(summary)
    edited["config"]["seed"] = 1
    with pytest.raises(ValueError, match="draws pile seed"):
        episode_task(edited, edited["episodes"][0])


def test_a_rebuilt_episode_counts_what_the_log_counts_at_every_step(summary):
    (episode,) = summary["episodes"]
    total = len(episode["attempt_log"])
    assert total >= 2  # the check below needs a step left over
    default = rebuild(summary, "rectangular", "scattered", 0)
    try:  # by default the state the last decision met
        assert default.replayed == total - 1 and default.info["attempts"] == total - 1
        assert default.next_step is not None and default.next_step.index == total - 1
    finally:
        default.env.close()
    whole = rebuild(summary, "rectangular", "scattered", 0, steps=total)
    try:
        for key in ("attempts", "successes", "parcels_placed", "parcels_cleared"):
            assert whole.info[key] == episode[key], key
        assert whole.next_step is None
    finally:
        whole.env.close()


def test_a_step_that_ends_otherwise_than_logged_stops_the_rebuild_naming_it(summary):
    edited = copy.deepcopy(summary)
    first = edited["episodes"][0]["attempt_log"][0]
    first["outcome"] = "no_contact" if first["outcome"] != "no_contact" else "success"
    with pytest.raises(ReplayDiverged, match=r"step 0 \(attempt 0\) diverged"):
        rebuild(edited, "rectangular", "scattered", 0, steps=1)
    with pytest.raises(ValueError, match="steps must be within 0-"):
        rebuild(summary, "rectangular", "scattered", 0, steps=99)


def test_the_policy_replayed_along_acts_as_logged_and_a_policy_that_does_not_is_named(summary):
    total = len(summary["episodes"][0]["attempt_log"])
    rebuilt = rebuild(summary, "rectangular", "scattered", 0, steps=total - 1, with_policy=True)
    try:  # the random policy's draws follow its seed, so with its memory it takes the logged last action
        assert rebuilt.policy is not None and "(as logged)" in act_here(rebuilt)
    finally:
        rebuilt.env.close()
    fresh = rebuild(summary, "rectangular", "scattered", 0, steps=total - 1)
    try:  # made afresh, it draws its first action again
        assert fresh.policy is None and "made afresh" in (text := act_here(fresh)) and "(logged: " in text
    finally:
        fresh.env.close()
    edited = copy.deepcopy(summary)
    edited["episodes"][0]["attempt_log"][0]["action"][0] += 1e-9
    with pytest.raises(ReplayDiverged, match=r"step 0 \(attempt 0\): the policy acts otherwise than logged"):
        rebuild(edited, "rectangular", "scattered", 0, steps=1, with_policy=True)


def test_cli_rebuilds_reports_and_acts_or_exits_2_naming_the_argument(summary, tmp_path: Path, capsys):
    path = tmp_path / "summary.json"
    path.write_text(json.dumps(summary))
    total = len(summary["episodes"][0]["attempt_log"])
    assert main([str(path), "--before-attempt", "1", "--act"]) == 0
    out = capsys.readouterr().out
    assert f"1 of {total} logged steps replayed (1 attempts, 0 pushes)" in out
    assert "Next in the log: attempt 1" in out and "made afresh" in out
    assert main([str(path), "--before-attempt", str(total)]) == 2
    assert "--before-attempt must be an attempt of the episode" in capsys.readouterr().err
    assert main([str(path), "--episode", "3"]) == 2
    assert "no episode 3 of rectangular/scattered" in capsys.readouterr().err
    (tmp_path / "bad.json").write_text("{}")
    assert main([str(tmp_path / "bad.json")]) == 2
    assert "not an eval/clearance.py summary" in capsys.readouterr().err


def test_an_episode_of_a_report_is_rebuilt_from_its_methods_clearance(summary, tmp_path: Path, capsys):
    report = tmp_path / "RESULTS.json"
    report.write_text(json.dumps({"policies": {"random": {"clearance": summary}, "cao": {"clearance": None}}}))
    assert main([str(report), "--policy", "random", "--steps", "1"]) == 0
    assert "1 of" in capsys.readouterr().out
    assert main([str(report)]) == 2
    assert "a report; name its method with --policy (one of ['cao', 'random'])" in capsys.readouterr().err
    assert main([str(report), "--policy", "cao"]) == 2
    assert "keeps no clearance config for 'cao'" in capsys.readouterr().err
