"""Closed-loop clearance evaluator: backend-independent episodes, Table V pooling, validation, replays."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from eval.clearance import (OUTCOMES, ClearanceConfig, EpisodeResult, attempt_record, decision_notes, episode_tasks,
                            evaluate_clearance, failure_detail, failure_kind, format_table, main, summarise,
                            tool_check_applies, tool_check_line, tool_check_settings)
from fresh_process import in_fresh_process
from parcelpick_env.envs.push import is_push_action
from parcelpick_env.camera.config import CameraConfig
from policies.tool_check import RETRY_RADIUS

# Two parcels, a tiny camera and cloud, three attempts: a few seconds per episode on one core.
TINY = dict(policy="random", objects=("rectangular",), layouts=("scattered",), episodes=1, num_parcels=2,
            max_attempts=3, env_kwargs=dict(camera=CameraConfig(width=96, height=72), num_points=256))
EPISODE_FIELDS = ("objects", "layout", "episode", "seed", "attempts", "successes", "parcels_placed",
                  "parcels_cleared", "reason", "outcomes")


def _episodes(summary: dict) -> list[dict]:
    return [{k: e[k] for k in EPISODE_FIELDS} for e in summary["episodes"]]


def test_local_and_ray_backends_give_identical_episodes(monkeypatch):
    monkeypatch.setenv("RAY_USAGE_STATS_ENABLED", "0")
    pytest.importorskip("ray")
    local = evaluate_clearance(ClearanceConfig(**TINY, workers=1, backend="local"), progress=False)
    remote = in_fresh_process(evaluate_clearance, ClearanceConfig(**TINY, workers=1, backend="ray"), progress=False)
    assert _episodes(local) == _episodes(remote)
    (ep,) = local["episodes"]
    assert 1 <= ep["attempts"] <= 3 and 0 <= ep["successes"] <= ep["attempts"]
    assert ep["parcels_placed"] >= 1 and ep["parcels_cleared"] == ep["successes"]
    assert sum(ep["outcomes"].values()) == ep["attempts"] and set(ep["outcomes"]) <= set(OUTCOMES)
    # Every attempt is kept, in order, with how it failed.
    assert len(ep["attempt_log"]) == ep["attempts"]
    assert [a["outcome"] for a in ep["attempt_log"]].count("success") == ep["successes"]
    assert all(set(a) >= {"outcome", "cause", "phase", "link", "condition"} for a in ep["attempt_log"])
    assert ep["seed"] == episode_tasks(ClearanceConfig(**TINY))[0].seed
    assert local["overall"]["attempts"] == ep["attempts"]


def test_episode_seeds_depend_on_grid_position_not_workers():
    base = dict(TINY, objects=("rectangular", "mixed"), layouts=("scattered", "stacked"), episodes=2)
    one, many = episode_tasks(ClearanceConfig(**base)), episode_tasks(ClearanceConfig(**base, workers=4))
    assert [t.seed for t in one] == [t.seed for t in many]
    assert len({t.seed for t in one}) == 8
    # A cell keeps its seeds when the grid around it shrinks.
    mixed_only = episode_tasks(ClearanceConfig(**dict(base, objects=("mixed",))))
    assert [t.seed for t in mixed_only] == [t.seed for t in one if t.objects == "mixed"]
    assert episode_tasks(ClearanceConfig(**dict(base, seed=1)))[0].seed != one[0].seed


def _result(objects, layout, attempts, successes, placed, cleared, outcomes, episode=0):
    return EpisodeResult(objects=objects, layout=layout, episode=episode, seed=episode, attempts=attempts,
                         successes=successes, parcels_placed=placed, parcels_cleared=cleared,
                         reason="cleared" if placed == cleared else "consecutive_failures",
                         outcomes=outcomes, replay=None, wall_time_s=0.0)


def test_summarise_pools_episodes_per_cell_and_overall():
    results = [
        _result("rectangular", "scattered", 4, 3, 3, 3, {"success": 3, "no_seal": 1}, episode=0),
        _result("rectangular", "scattered", 6, 2, 4, 2, {"success": 2, "collision": 3, "dropped": 1}, episode=1),
        _result("planar", "stacked", 5, 1, 2, 1, {"success": 1, "unreachable": 4}),
    ]
    s = summarise(results)
    rect = s["cells"]["rectangular/scattered"]
    # Pooled, not averaged per episode: 5/10 attempts and 5/7 parcels.
    assert (rect["attempts"], rect["successes"], rect["placed"], rect["cleared"], rect["episodes"]) == (10, 5, 7, 5, 2)
    assert rect["R_grasp"] == pytest.approx(50.0)
    assert rect["R_object"] == pytest.approx(100.0 * 5 / 7)
    assert rect["outcomes"] == {"success": 5, "no_seal": 1, "collision": 3, "dropped": 1}
    planar = s["cells"]["planar/stacked"]
    assert planar["R_grasp"] == pytest.approx(20.0) and planar["R_object"] == pytest.approx(50.0)
    o = s["overall"]
    assert (o["attempts"], o["successes"], o["placed"], o["cleared"]) == (15, 6, 9, 6)
    assert o["R_grasp"] == pytest.approx(40.0)
    assert o["R_object"] == pytest.approx(100.0 * 6 / 9)
    assert o["outcomes"]["unreachable"] == 4 and o["outcomes"]["success"] == 6

    table = format_table(s)
    lines = table.splitlines()
    assert lines[0] == "| object set | scattered | stacked |"
    # Each rate with its bootstrap interval over the cell's episodes: 3/4 and 2/6 successes pool to 5/10; a
    # resample of the two episodes gives 4/8, 5/10 or 6/12 ... so the interval runs from 2/6 to 3/4.
    assert "| rectangular | 50.00 [33.33, 75.00] / 71.43 [50.00, 100.00] | – |" in lines
    assert "| planar | – | 20.00 [no interval, n=1] / 50.00 [no interval, n=1] |" in lines  # one episode: no spread
    assert [ln.split(" | ")[0] for ln in lines[2:6]] == ["| rectangular", "| planar", "| cylindrical", "| mixed"]
    assert "R_grasp 40.00 [" in table and "R_object 66.67 [" in table and "(6/15 attempts, 6/9 parcels;" in table
    assert "unreachable 4" in table and "invalid_action 0" in table


def test_parting_pushes_are_counted_apart_from_attempts():
    """A pose_push push (the seventh number negative) is no attempt: the summary counts it under ``pushes``, and the
    rates, outcomes and failures are the picks' alone."""
    assert is_push_action(np.array([0, 0, 0.1, 1, 0, 0, -1.0])) and not is_push_action(np.array([0, 0, 0.1, 0, 0, 1, 0.0]))
    assert not is_push_action(np.zeros(6))
    pushed = _result("mixed", "stacked", 2, 2, 2, 2, {"success": 2})
    pushed.push_log = [{"outcome": "pushed", "cause": None, "phase": None, "link": None, "condition": None,
                        "body": None, "before": 1},
                       {"outcome": "unreachable", "cause": None, "phase": "descend", "link": None,
                        "condition": "blocked", "body": None, "before": 1}]
    s = summarise([pushed, _result("mixed", "stacked", 3, 1, 3, 1, {"success": 1, "dropped": 2}, episode=1)])
    cell, o = s["cells"]["mixed/stacked"], s["overall"]
    assert (cell["pushes"], o["pushes"], o["attempts"], o["successes"]) == (2, 2, 5, 3)
    assert o["outcomes"] == {"success": 3, "dropped": 2} and "unreachable: descend" not in o["failures"]
    assert "Parting pushes (no attempts): 2" in format_table(s)
    assert "Parting pushes" not in format_table(summarise([_result("mixed", "stacked", 1, 1, 1, 1, {"success": 1})]))


def test_decision_notes_keep_what_the_oracle_tried_at_a_dead_end_even_where_no_push_was_made():
    """The pushes rehearsed at a dead end go into the record of the pick that followed them, not only of a push made;
    ``exact`` goes with rehearsals alone, and a policy that rehearses nothing adds nothing."""
    from types import SimpleNamespace

    oracle = SimpleNamespace(last_rehearsals=("dropped", "dropped"), last_exact=True, last_confirmations=[],
                             last_push_rehearsals=["pushed", "unreachable"], last_opening_rehearsals=["dropped"])
    assert decision_notes(oracle) == {"rehearsals": ["dropped", "dropped"], "exact": True,
                                      "push_rehearsals": ["pushed", "unreachable"], "opening_rehearsals": ["dropped"]}
    oracle.last_rehearsals = []
    assert decision_notes(oracle) == {"push_rehearsals": ["pushed", "unreachable"], "opening_rehearsals": ["dropped"]}
    oracle.last_onward = True  # a push made though nothing was foreseen to hold after it
    assert decision_notes(oracle)["onward"] is True
    assert decision_notes(SimpleNamespace()) == {}


def test_parcels_lost_are_counted_by_the_step_that_lost_them():
    dropped = {"outcome": "dropped", "cause": None, "phase": "lift", "link": None, "condition": None, "body": None}
    success = {"outcome": "success", "cause": None, "phase": None, "link": None, "condition": None, "body": None}
    lossy = _result("mixed", "stacked", 3, 2, 5, 2, {"success": 2, "dropped": 1})
    lossy.attempt_log = [success, {**dropped, "lost": 2}, {**success, "lost": 1}]
    lossy.push_log = [{**success, "outcome": "pushed", "before": 1, "lost": 1}]
    lossy.parcels_lost = 4
    s = summarise([lossy, _result("mixed", "stacked", 1, 1, 1, 1, {"success": 1}, episode=1)])
    cell, o = s["cells"]["mixed/stacked"], s["overall"]
    assert cell["lost"] == o["lost"] == 4
    assert cell["lost_by"] == o["lost_by"] == {"dropped: lift": 2, "success": 1, "push": 1}
    assert ("Parcels lost from the bin (count against R_object): 4, by the step that lost them: dropped: lift 2, "
            "success 1, push 1") in format_table(s)
    assert "Parcels lost" not in format_table(summarise([_result("mixed", "stacked", 1, 1, 1, 1, {"success": 1})]))


def test_a_parcel_knocked_out_of_the_bin_is_charged_to_the_attempt_that_lost_it(monkeypatch):
    """The env's own loss path (a parcel whose centre of mass leaves the bin is removed and counted): the parcel
    the first attempt leaves standing is thrown out after it, and the log charges that attempt alone."""
    from parcelpick_env.envs.grasp import PickExecutor

    real, calls = PickExecutor.attempt, []

    def attempt(self, scene, point, normal):
        result = real(self, scene, point, normal)
        if not calls:
            left = next(ps for ps in scene.parcels if self.sim.has_body(ps.body_id))
            self.sim.set_body_pose(left.body_id, [5.0, 5.0, 0.5], [0.0, 0.0, 0.0, 1.0])
        calls.append(result.outcome)
        return result

    monkeypatch.setattr(PickExecutor, "attempt", attempt)
    summary = evaluate_clearance(ClearanceConfig(**dict(TINY, max_attempts=3)), progress=False)
    (ep,) = summary["episodes"]
    assert ep["parcels_lost"] == 1 and ep["attempt_log"][0]["lost"] == 1
    assert all("lost" not in a for a in ep["attempt_log"][1:])
    assert summary["overall"]["lost"] == 1 and sum(summary["overall"]["lost_by"].values()) == 1
    assert ep["parcels_cleared"] <= ep["parcels_placed"] - 1


def test_summarise_of_episode_without_attempts_is_not_a_division_by_zero():
    s = summarise([_result("mixed", "stacked", 0, 0, 0, 0, {})])
    assert s["cells"]["mixed/stacked"]["R_grasp"] == 0.0 and s["overall"]["R_object"] == 0.0


@pytest.mark.parametrize("bad", [dict(objects=("spheres",)), dict(objects=()), dict(layouts=("piled",)),
                                 dict(episodes=0), dict(num_parcels=0), dict(num_parcels=51),
                                 dict(backend="spark"), dict(workers=0), dict(seed=-1), dict(max_attempts=0),
                                 dict(env_kwargs={"num_parcels": 3}), dict(env_kwargs={"heavy_first_mass": -1.0}),
                                 dict(covered_factor=1.5),
                                 dict(covered_factor=0.5, tool_check=False)])
def test_config_rejects_bad_values(bad):
    with pytest.raises(ValueError):
        ClearanceConfig(**bad)


def test_cli_unknown_policy_exits_2_with_message(capsys):
    assert main(["--policy", "nope"]) == 2
    err = capsys.readouterr().err
    assert "unknown policy 'nope'" in err and "random" in err


def test_episodes_run_with_the_tool_check_unless_it_is_off_or_the_policy_is_the_oracle():
    on = evaluate_clearance(ClearanceConfig(**dict(TINY, max_attempts=2)), progress=False)
    assert on["tool_check"] is True and on["seal_check"] is True and on["retry_radius"] == RETRY_RADIUS > 0
    assert on["overall"]["outcomes"].get("invalid_action", 0) == 0
    off = evaluate_clearance(ClearanceConfig(**dict(TINY, max_attempts=1), tool_check=False), progress=False)
    assert off["tool_check"] is False and off["seal_check"] is False and off["retry_radius"] == 0.0
    assert tool_check_applies(ClearanceConfig(**dict(TINY, policy="oracle"))) is False
    assert tool_check_settings(ClearanceConfig(**dict(TINY, policy="oracle")))["retry_radius"] == 0.0
    assert tool_check_settings(ClearanceConfig(**TINY, seal_check=False, retry_radius=0.0)) == {
        "tool_check": True, "seal_check": False, "retry_radius": 0.0}


def test_cli_bad_value_exits_2(capsys):
    assert main(["--policy", "random", "--episodes", "0"]) == 2
    assert "episodes must be >= 1" in capsys.readouterr().err


def test_cli_covered_factor_out_of_range_exits_2_naming_it(capsys):
    assert main(["--policy", "random", "--covered-factor", "-0.5"]) == 2
    assert "covered_factor must be a number in [0, 1]" in capsys.readouterr().err


def test_cli_retry_radius_negative_or_without_the_tool_check_exits_2_naming_it(capsys):
    assert main(["--policy", "random", "--retry-radius", "-0.05"]) == 2
    assert "retry_radius must be a finite number of metres >= 0" in capsys.readouterr().err
    assert main(["--policy", "random", "--retry-radius", "0.05", "--no-tool-check"]) == 2
    assert "retry_radius > 0 works within the tool check" in capsys.readouterr().err
    ClearanceConfig(**TINY, tool_check=False)  # the cell's own radius (None) leaves a run without the check valid


def test_the_tool_check_line_says_which_rules_ran():
    on = tool_check_line({"tool_check": True, "seal_check": True, "retry_radius": 0.05})
    assert "whose cup seals on it" in on and "does not go back within 0.05 m" in on
    bare = tool_check_line({"tool_check": True, "seal_check": False, "retry_radius": 0.0})
    assert "seals" not in bare and bare.endswith("No retry rule.")
    off = {"tool_check": False, "seal_check": False, "retry_radius": 0.0}
    assert tool_check_line({**off, "config": {"tool_check": False}}) == (
        "Acting on its top candidate as ranked (`--no-tool-check`).")
    assert tool_check_line({**off, "config": {"tool_check": True}}).startswith("Without the tool check: it does not apply")


def test_covered_factor_reaches_the_tool_check_and_is_recorded(monkeypatch):
    import policies.tool_check as tool_check

    seen = []
    real = tool_check.ToolCheckedPolicy.__init__

    def spy(self, inner, config=None):
        seen.append((config.covered_factor, config.retry_radius))
        real(self, inner, config)

    monkeypatch.setattr(tool_check.ToolCheckedPolicy, "__init__", spy)
    summary = evaluate_clearance(ClearanceConfig(**dict(TINY, max_attempts=1), covered_factor=0.5, retry_radius=0.04),
                                 progress=False)
    assert seen == [(0.5, 0.04)] and summary["config"]["covered_factor"] == 0.5
    assert summary["config"]["retry_radius"] == 0.04


def test_record_dir_writes_one_replay_per_episode(tmp_path: Path):
    summary = evaluate_clearance(ClearanceConfig(**dict(TINY, max_attempts=1), record_dir=str(tmp_path)),
                                 progress=False)
    (ep,) = summary["episodes"]
    replay = Path(ep["replay"])
    assert replay.suffix == ".rrd" and replay.is_file() and replay.stat().st_size > 0
    assert tmp_path in replay.parents and replay.parent.name == "rectangular-scattered-ep000"


def test_diffusion_replay_shows_the_denoising_trajectory(tmp_path: Path):
    """The main job's replay: Diffusion-Suction's first attempt logs its DDIM steps (noise to scores)."""
    from rerun.chunk import RrdReader

    config = ClearanceConfig(**dict(TINY, policy="diffusion", max_attempts=1), record_dir=str(tmp_path))
    replay = evaluate_clearance(config, progress=False)["episodes"][0]["replay"]
    summary = RrdReader(replay).store().summary()
    assert "/policy/denoising " in summary and "denoise_step" in summary


def test_attempt_record_reads_typed_failures_and_the_older_strings():
    typed = attempt_record({"outcome": "collision", "failure_cause": "free-space: tool_rod",
                            "failure": {"move": "transfer", "link": "tool_rod", "condition": None, "body": "bin"}})
    assert (typed["phase"], typed["link"], typed["body"]) == ("transfer", "tool_rod", "bin")
    legacy = attempt_record({"outcome": "collision", "failure_cause": "free-space: suction_cup"})
    assert (legacy["phase"], legacy["link"]) == ("free-space", "suction_cup")
    drop = attempt_record({"outcome": "dropped", "failure_cause": "suction", "failure_phase": "transport",
                           "failure": None})
    assert (drop["phase"], drop["condition"]) == ("transport", "suction")
    assert failure_kind(drop) == "dropped: transport" and failure_detail(legacy) == "collision: free-space (suction_cup)"
    assert failure_kind(attempt_record({"outcome": "success"})) is None


def test_summaries_count_failures_per_cell_and_overall():
    log = [attempt_record(i) for i in ({"outcome": "collision", "failure_cause": "free-space: tool_rod"},
                                       {"outcome": "collision", "failure_cause": "approach: suction_cup"},
                                       {"outcome": "dropped", "failure_cause": "suction", "failure_phase": "lift"},
                                       {"outcome": "success"})]
    r = _result("mixed", "stacked", 4, 1, 3, 1, {"success": 1, "collision": 2, "dropped": 1})
    r.attempt_log = log
    s = summarise([r, _result("mixed", "scattered", 2, 2, 2, 2, {"success": 2})])
    cell = s["cells"]["mixed/stacked"]
    assert cell["failures"] == {"collision: free-space": 1, "collision: approach": 1, "dropped: lift": 1}
    assert cell["causes"]["dropped: lift (suction)"] == 1
    assert s["overall"]["failures"] == cell["failures"] and s["cells"]["mixed/scattered"]["failures"] == {}
    # The overall interval resamples within cells: both cells keep one episode, so it has no spread.
    iv = s["overall"]["intervals"]["R_grasp"]
    assert iv["low"] == iv["high"] == pytest.approx(50.0) and iv["n"] == 2
    assert "Failures: " in format_table(s) and "collision: free-space (tool_rod) 1" in format_table(s)


def test_policy_kwargs_reach_every_episode_and_the_summary(capsys):
    summary = evaluate_clearance(ClearanceConfig(**dict(TINY, max_attempts=1), policy_kwargs={"seed": 5}),
                                 progress=False)
    assert summary["config"]["policy_kwargs"] == {"seed": 5}
    with pytest.raises(TypeError, match="bogus"):  # made in the episode itself, with the keywords given
        evaluate_clearance(ClearanceConfig(**dict(TINY, max_attempts=1), policy_kwargs={"bogus": 1}), progress=False)
    assert main(["--policy", "random", "--policy-arg", "bogus=1"]) == 2
    assert "--policy-arg bogus=1" in capsys.readouterr().err
