"""eval/pick_audit.py: which parcel a pick took and whether another rested on it, read without changing the pick."""

from __future__ import annotations

import numpy as np
import pytest

from eval.clearance import ClearanceConfig, _audit, episode_tasks, format_table, run_episode, summarise
from eval.pick_audit import NO_PARCEL, audit_pick, audit_truth, cover_rates
from parcelpick_env.assets.library import AssetLibrary
from parcelpick_env.scene.scene import BinSpec
from parcelpick_env.envs.parcel_pick import ParcelPickEnv
from parcelpick_env.envs.custom_scene import BoxScene, PlacedBox
from policies.oracle import ground_truth
from tests.test_oracle import SMALL, STACK, state_obs


def test_the_audit_names_the_parcel_picked_and_whether_another_rests_on_it():
    """STACK: a carton (1) lies on the big one (0); a third (2) stands alone. Its COM is off its centre."""
    truth = ground_truth(state_obs(STACK), AssetLibrary.default(0))
    on_top = audit_truth(truth, np.array([0.07, 0.03, 0.18]))  # the top carton's top face, at its centre
    assert (on_top.parcel, on_top.covered, on_top.free_parcels) == (1, False, 2)
    assert on_top.off_com_mm == pytest.approx(1e3 * np.hypot(0.03, 0.02), abs=0.1)  # COM (0.10, 0.01)
    assert on_top.to_surface_mm == pytest.approx(0.0, abs=0.1)
    under = audit_truth(truth, np.array([-0.12, -0.07, 0.10]))  # the big carton's uncovered corner of its top
    assert (under.parcel, under.covered) == (0, True)
    assert under.off_com_mm == pytest.approx(1e3 * np.hypot(0.12, 0.07), abs=0.1)
    floor = audit_truth(truth, np.array([0.30, -0.20, 0.0]))  # the tote floor, 18 cm from any parcel
    assert (floor.parcel, floor.covered, floor.off_com_mm) == (NO_PARCEL, None, None)
    assert floor.to_surface_mm == pytest.approx(1e3 * np.hypot(0.15, 0.10), abs=0.5)


def test_the_env_audit_reads_the_live_scene():
    """Through the env: its privileged state rebuilt, in the camera's obs_mode; a carton on another covers it."""
    support = PlacedBox((0.30, 0.20, 0.10), 1.0, center=(0.0, 0.0, BinSpec().floor_z + 0.05))
    env = ParcelPickEnv(scene_factory=BoxScene([support, support.resting_on_top((0.14, 0.12, 0.08), 0.5)]), **SMALL)
    try:
        env.reset(seed=0)
        assert env.config.obs_mode == "pointcloud"
        state = env.privileged_state()
        assert int(state["parcel_count"]) == 2
        low, high = state["parcel_position"][:2].astype(np.float64)
        assert high[2] > low[2] + 0.05  # it stayed on top through the settle
        corner = np.array([low[0] - 0.12, low[1] - 0.07, low[2] + 0.05, 0.0, 0.0, 1.0])  # beside the top carton
        audit = audit_pick(env, corner)
        assert (audit.parcel, audit.covered, audit.free_parcels) == (0, True, 1)
        assert audit.to_surface_mm < 3.0
        assert audit_pick(env, np.array([*high[:2], high[2] + 0.04, 0.0, 0.0, 1.0])).covered is False
        with pytest.raises(ValueError, match="finite 'pose' action"):
            audit_pick(env, np.full(6, np.nan))
    finally:
        env.close()


def test_a_pose_push_pick_is_audited_as_its_pose_and_a_push_is_not():
    """The clearance audit in ``action_mode="pose_push"`` (the oracle's parting pushes): a pick (seventh number
    >= 0) is audited as the ``pose`` action of its first six numbers; a push is no pick and has no audit."""
    support = PlacedBox((0.30, 0.20, 0.10), 1.0, center=(0.0, 0.0, BinSpec().floor_z + 0.05))
    env = ParcelPickEnv(scene_factory=BoxScene([support, support.resting_on_top((0.14, 0.12, 0.08), 0.5)]),
                        action_mode="pose_push", **SMALL)
    try:
        env.reset(seed=0)
        low = env.privileged_state()["parcel_position"][0].astype(np.float64)
        corner = np.array([low[0] - 0.12, low[1] - 0.07, low[2] + 0.05, 0.0, 0.0, 1.0])
        audited = _audit(env, np.append(corner, 1.0))
        assert audited == audit_pick(env, corner).to_dict() and (audited["parcel"], audited["covered"]) == (0, True)
        assert _audit(env, np.array([*corner[:3], 1.0, 0.0, 0.0, -1.0])) is None
    finally:
        env.close()


def test_cover_rates_count_success_on_free_and_covered_parcels():
    def attempt(outcome, parcel, covered, free):
        return {"outcome": outcome, "audit": {"parcel": parcel, "covered": covered, "free_parcels": free}}
    logs = [[attempt("success", 1, False, 2), attempt("dropped", 0, True, 1), attempt("success", 0, True, 0)],
            [attempt("collision", NO_PARCEL, None, 3), {"outcome": "success"}]]  # the last one not audited
    assert cover_rates(logs) == {"free": {"attempts": 1, "successes": 1, "while_free_left": 0},
                                 "covered": {"attempts": 2, "successes": 1, "while_free_left": 1},
                                 "none": {"attempts": 1, "successes": 0, "while_free_left": 0}}
    assert cover_rates([[{"outcome": "success"}]]) is None


def test_auditing_picks_changes_no_pick_and_is_summarised():
    """The audit only reads: the same episode with and without it takes the same picks to the same outcomes."""
    config = dict(policy="random", objects=("rectangular",), layouts=("stacked",), episodes=1, num_parcels=3,
                  max_attempts=3, env_kwargs=SMALL)
    plain = run_episode(episode_tasks(ClearanceConfig(**config))[0])
    audited = run_episode(episode_tasks(ClearanceConfig(**config, audit_picks=True))[0])
    assert [{k: v for k, v in a.items() if k != "audit"} for a in audited.attempt_log] == plain.attempt_log
    assert all("audit" in a for a in audited.attempt_log) and not any("audit" in a for a in plain.attempt_log)
    summary = summarise([audited])
    by_cover = summary["overall"]["by_cover"]
    assert sum(row["attempts"] for row in by_cover.values()) == audited.attempts
    assert sum(row["successes"] for row in by_cover.values()) == audited.successes
    assert summary["cells"]["rectangular/stacked"]["by_cover"] == by_cover
    assert "Picks (--audit-picks)" in format_table(summary, ("rectangular",), ("stacked",))
    assert "Picks" not in format_table(summarise([plain]), ("rectangular",), ("stacked",))
