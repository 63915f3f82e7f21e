"""The oracle's shadow of the cell: the env's own code on the env's pile, followed step by step, whose rehearsal of
a pick is what the env then does, to the bit; and where it cannot follow, it says why and the twin takes over."""

from __future__ import annotations

import numpy as np
import pytest

from parcelpick_env.camera.config import CameraConfig
from parcelpick_env.envs.parcel_pick import ParcelPickEnv
from policies.oracle import OraclePolicy
from policies.shadow_cell import ShadowCell, shadow_config

SMALL = dict(camera=CameraConfig(width=160, height=120), num_points=256)


def stacked_env(action_mode: str = "pose_push", **kwargs) -> ParcelPickEnv:
    return ParcelPickEnv(object_set="rectangular", layout="stacked", num_parcels=5, obs_mode="state_dict",
                         action_mode=action_mode, **SMALL, **kwargs)


def test_the_shadow_foresees_each_step_of_the_env_exactly_and_stays_its_state():
    """Three of the oracle's decisions on a stacked pile: each rehearsal on the shadow gives the env's outcome, seal,
    failure and simulated time to the bit, the shadow is left as it was, and after the env's step the shadow,
    stepped alike, still has every parcel exactly where the env has it."""
    env, oracle = stacked_env(), OraclePolicy()
    try:
        obs, info = env.reset(seed=3)
        oracle.reset(3)
        for _ in range(3):
            action = oracle.act(obs, info)
            assert oracle.shadow.live and oracle.last_exact, oracle.shadow.why_not
            before = oracle.shadow.env.unwrapped.privileged_state()
            rehearsed = oracle.shadow.rehearse(action[:3], action[3:6])
            after = oracle.shadow.env.unwrapped.privileged_state()
            assert rehearsed is not None and np.array_equal(before["parcel_position"], after["parcel_position"])
            foreseen, lost = rehearsed
            lost_before = info["parcels_lost"]
            obs, _, terminated, truncated, info = env.step(action)
            if action[6] >= 0:  # a pick (the oracle pushes only at a dead end)
                assert (foreseen.outcome, foreseen.sim_time) == (info["outcome"], info["sim_time"])
                assert lost == info["parcels_lost"] - lost_before
                assert foreseen.peak_ratios == env.last_result.peak_ratios  # every ring load, to the bit
                assert (-1.0 if foreseen.seal is None else foreseen.seal) == info["seal"]
                assert (foreseen.failure.as_dict()["condition"] if foreseen.failure else None) \
                    == info["failure"]["condition"]
            if terminated or truncated:
                break
            assert oracle.shadow.track(obs, info)  # (the next act tracks again: nothing left to step)
    finally:
        env.close()
        oracle.shadow.close()


def test_the_shadow_counts_the_parcels_a_pick_knocks_out_of_the_tote_as_the_env_does(monkeypatch):
    """Each pick here also throws a parcel it did not take out of the tote (as the clearance test of the env's loss
    path does): the shadow's rehearsal counts that one parcel, whether or not the pick itself delivered its own."""
    from parcelpick_env.envs.grasp import PickExecutor

    real = PickExecutor.attempt

    def attempt(self, scene, point, normal):
        result = real(self, scene, point, normal)
        left = next(ps for ps in scene.parcels if self.sim.has_body(ps.body_id) and ps.body_id != result.body_id)
        self.sim.set_body_pose(left.body_id, [5.0, 5.0, 0.5], [0.0, 0.0, 0.0, 1.0])
        return result

    env, oracle = stacked_env(), OraclePolicy()
    try:
        obs, info = env.reset(seed=3)
        oracle.reset(3)
        action = oracle.act(obs, info)
        monkeypatch.setattr(PickExecutor, "attempt", attempt)
        rehearsed = oracle.shadow.rehearse(action[:3], action[3:6])
        assert rehearsed is not None and rehearsed[1] == 1 and rehearsed[0].outcome == "success"  # its own delivered
        info_after = env.step(action)[4]
        assert rehearsed[0].outcome == info_after["outcome"] and info_after["parcels_lost"] - info["parcels_lost"] == 1
    finally:
        env.close()
        oracle.shadow.close()


def test_the_shadow_stops_following_an_observation_it_does_not_match_and_the_twin_rehearses():
    env, oracle = stacked_env(), OraclePolicy()
    try:
        obs, info = env.reset(seed=1)
        oracle.reset(1)
        moved = {**obs, "parcel_position": obs["parcel_position"].copy()}
        moved["parcel_position"][0, 0] += 1e-3  # a pile the shadow's is not
        oracle.act(moved, info)
        assert not oracle.shadow.live and "differ" in oracle.shadow.why_not
        assert not oracle.last_exact and oracle.last_rehearsals  # rehearsed on the posed twin instead
        assert oracle.shadow.rehearse(np.zeros(3), np.array([0.0, 0.0, 1.0])) is None
        oracle.act(obs, info)  # it stays out for the rest of the episode, ...
        assert not oracle.last_exact
        oracle.reset(1)  # ... and follows the next one
        oracle.act(obs, info)
        assert oracle.last_exact
        shadow = ShadowCell()  # an attempt the env counted and the shadow did not (a refused action moves nothing)
        assert shadow.track(obs, info) and not shadow.track(obs, {**info, "attempts": info["attempts"] + 1})
        assert "counts" in shadow.why_not
        shadow.close()
    finally:
        env.close()
        oracle.shadow.close()


def test_the_shadow_needs_the_privileged_info_and_pose_actions():
    shadow = ShadowCell()
    assert not shadow.track({}, {"privileged": False}) and "env_config" in shadow.why_not
    env = stacked_env(action_mode="pixel")
    try:
        obs, info = env.reset(seed=0)
        shadow.new_episode()
        assert not shadow.track(obs, info) and "pixel" in shadow.why_not
    finally:
        env.close()
        shadow.close()


def test_exact_false_rehearses_on_the_twin_only():
    env, oracle = stacked_env(), OraclePolicy(exact=False)
    try:
        obs, info = env.reset(seed=0)
        oracle.reset(0)
        oracle.act(obs, info)
        assert oracle.shadow.env is None and not oracle.last_exact and oracle.last_rehearsals
    finally:
        env.close()
    with pytest.raises(ValueError, match="exact"):
        OraclePolicy(exact="yes")  # type: ignore[arg-type]


def test_the_shadow_is_the_env_config_without_replays_egl_or_a_real_camera():
    config = stacked_env(record_dir="runs/x").config
    shadow = shadow_config(config)
    assert shadow.record_dir is None and not shadow.sim.egl_rendering and shadow.obs_mode == "state_dict"
    assert (shadow.grasp, shadow.bin, shadow.suction, shadow.arm, shadow.num_parcels, shadow.action_mode) \
        == (config.grasp, config.bin, config.suction, config.arm, config.num_parcels, config.action_mode)
    assert shadow.sim.timestep == config.sim.timestep and shadow.camera.width < config.camera.width
    assert shadow.camera.renderer == "tiny"  # asked for: no warning that EGL is off


def test_reset_builds_the_pile_of_a_given_scene_seed():
    """``reset(options={'scene_seed': s})`` rebuilds the pile an episode logged as ``info['scene_seed']``, whatever
    the reset seed; a seed that is not a whole number in range is refused by name."""
    env = stacked_env()
    try:
        obs, info = env.reset(seed=7)
        again, info2 = env.reset(seed=123, options={"scene_seed": info["scene_seed"]})
        assert info2["scene_seed"] == info["scene_seed"]
        assert np.array_equal(obs["parcel_position"], again["parcel_position"])
        assert info2["env_config"] is env.config and info2["privileged"]
        for bad in (-1, 2**31, 1.5, True, "3"):
            with pytest.raises(ValueError, match="scene_seed"):
                env.reset(options={"scene_seed": bad})
    finally:
        env.close()


def test_looking_past_a_push_on_the_shadow_foresees_the_decision_the_env_then_meets():
    """A parting push looked past in the shadow's child (the push as the env steps it, then the oracle's decision
    there, rehearsed on the shadow) gives the push's outcome and the very rehearsals the oracle makes once the
    env has taken that push."""
    import functools

    from parcelpick_env.assets.library import AssetLibrary
    from parcelpick_env.envs.observation import bin_from_vector
    from policies.oracle import ground_truth, pinned_parcels
    from policies.parting import push_candidates

    env, oracle = stacked_env(), OraclePolicy()
    try:
        obs, info = env.reset(seed=3)
        oracle.reset(3)
        assert oracle.shadow.track(obs, info)
        truth = ground_truth(obs, AssetLibrary.default(info["asset_seed"]))
        box = bin_from_vector(obs["bin"]).workspace(margin=env.config.action_margin)
        push = push_candidates(truth, pinned_parcels(truth), env.config.suction.cup_radius, 1, box)[0]
        action = np.concatenate([push.start, push.direction, [-1.0]]).astype(np.float32)
        answer = oracle.shadow.foresee(functools.partial(oracle._look_past, action=action))
        obs, _, _, _, info = env.step(action)
        assert answer is not None and answer["outcome"] == info["outcome"] == "pushed"
        oracle.shadow.expect(action)
        oracle.act(obs, info)
        assert oracle.last_exact and answer["rehearsals"] == oracle.last_rehearsals
        assert answer["holds"] == ("success" in oracle.last_rehearsals)
        assert answer["nearest"] == oracle.last_nearest and np.isfinite(oracle.last_nearest)  # a pick was held
    finally:
        env.close()
        oracle.shadow.close()


def test_at_a_dead_end_the_exact_oracle_looks_past_each_push_on_the_shadow_not_the_twin(monkeypatch):
    env, oracle = stacked_env(), OraclePolicy()
    try:
        obs, info = env.reset(seed=3)
        oracle.reset(3)
        assert oracle.shadow.track(obs, info)
        oracle.last_rehearsals = ["dropped"]  # a decision where nothing held
        asked: list[np.ndarray] = []

        def foresee(fn):
            asked.append(fn.keywords["action"])
            return {"outcome": "pushed", "holds": len(asked) == 2, "rehearsals": []}

        monkeypatch.setattr(oracle.shadow, "foresee", foresee)
        monkeypatch.setattr(oracle.twin, "rehearse_push", lambda *a: pytest.fail("the twin looked past a push"))
        action = oracle._parting_push(obs, info, exact=True)
        assert action is not None and action[6] < 0 and np.array_equal(action, asked[1])
        assert oracle.last_push_rehearsals == ["pushed", "pushed"]
    finally:
        env.close()
        oracle.shadow.close()


def test_at_a_dead_end_no_push_opens_the_oracle_spends_its_failing_pick_where_the_fall_opens_the_pile(monkeypatch):
    """The decision's failed rehearsals are looked past on the shadow in order, and the first after which a pick
    holds is made (tagged with its own parcel for the failed-pick memory); none is where one more failure ends the
    episode, and where none opens the pile the ranking's first stands."""
    env, oracle = stacked_env(), OraclePolicy()
    try:
        obs, info = env.reset(seed=3)
        oracle.reset(3)
        assert oracle.shadow.track(obs, info)
        first = np.zeros(6, np.float32)
        failed = [(np.full(6, k, np.float32), (np.full(3, k), np.zeros(3), (k, np.zeros(3)))) for k in (1, 2, 3)]
        oracle.last_rehearsals, oracle._failed_picks = ["dropped"] * 3, failed
        looked: list[np.ndarray] = []

        def foresee(fn):
            looked.append(fn.keywords["action"])
            return {"outcome": "dropped", "holds": float(fn.keywords["action"][0]) == 2.0, "rehearsals": []}

        monkeypatch.setattr(oracle.shadow, "foresee", foresee)
        made = oracle._opening_pick(info, first)
        assert np.array_equal(made, failed[1][0]) and oracle._aimed[2][0] == 2
        assert [a[0] for a in looked] == [1.0, 2.0] and all(a.shape == (7,) and a[6] > 0 for a in looked)
        assert oracle.last_opening_rehearsals == ["dropped", "dropped"]
        looked.clear()
        ending = {**info, "consecutive_failures": env.config.max_consecutive_failures - 1}
        assert oracle._opening_pick(ending, first) is first and not looked  # a failure here ends the episode
        oracle._failed_picks = failed[:1]
        assert oracle._opening_pick(info, first) is first and len(looked) == 1  # nothing opens: the first stands
    finally:
        env.close()
        oracle.shadow.close()


def _deciding(monkeypatch, oracle: OraclePolicy, pick: np.ndarray, rehearsals: list[str], lossy: bool,
              foresee) -> None:
    """``oracle`` on the shadow (``track``, ``expect`` stubbed) whose every decision rehearses ``rehearsals`` and ranks
    ``pick`` first, and whose look-pasts answer ``foresee(fn)``: a dead end, or a lossy hold, without a pile for it."""
    from types import SimpleNamespace

    def predict(obs, info=None, top_k=50):
        oracle.last_rehearsals, oracle.last_exact, oracle._failed_picks = list(rehearsals), True, []
        oracle.last_lossy = lossy
        return SimpleNamespace(best_action=lambda: pick)

    monkeypatch.setattr(oracle, "predict", predict)
    monkeypatch.setattr(oracle.shadow, "track", lambda *a: True)
    monkeypatch.setattr(oracle.shadow, "expect", lambda *a: None)
    monkeypatch.setattr(oracle.shadow, "foresee", foresee)


@pytest.mark.parametrize("allowed, listed, taken", [
    (2, ((3.0, True), (1.5, True), (2.0, True), (0.5, False), (np.inf, True)), 1),  # the nearest run cleanly
    (0, ((3.0, True), (1.5, True)), None),  # none allowed
    (1, ((0.5, False), (np.inf, True), (np.inf, True)), 1)])  # nothing lifted after any: the first run cleanly
def test_where_nothing_opens_the_pile_the_oracle_pushes_onward_nearest_to_holding_as_often_as_allowed(
        monkeypatch, allowed, listed, taken):
    """At a dead end where no push looked past holds and no failing pick opens the pile, the push run cleanly whose
    decision came nearest to holding (lowest peak ratio) is made instead of the failing pick, ``onward_pushes``
    times an episode; a push that did not run cleanly (no decision after it) is never taken, and where nothing after
    any push lifted (no ratio), the first run cleanly is."""
    env = stacked_env()
    try:
        obs, info = env.reset(seed=3)
        oracle = OraclePolicy(onward=allowed)
        oracle.reset(3)
        pick = np.arange(6, dtype=np.float32)
        calls: list[np.ndarray] = []
        first = [0]  # this act's first call

        def foresee(fn):
            value, clean = listed[(len(calls) - first[0]) % len(listed)]
            calls.append(fn.keywords["action"])
            answer = {"outcome": "pushed" if clean else "collision", "holds": False, "rehearsals": []}
            return {**answer, "nearest": value} if clean else answer

        _deciding(monkeypatch, oracle, pick, ["dropped"], False, foresee)
        for n in range(allowed + 1):
            start = first[0] = len(calls)
            made = oracle.act(obs, info)
            assert len(calls) - start >= len(listed)  # every push listed was looked past
            if n < allowed:
                assert oracle.last_onward and made[6] < 0 and np.array_equal(made, calls[start + taken])
            else:  # the budget spent (or none): the failing pick
                assert not oracle.last_onward and np.array_equal(made[:6], pick) and made[6] > 0
    finally:
        env.close()


def test_where_every_success_knocks_a_parcel_out_a_push_is_taken_only_if_a_pick_then_loses_none(monkeypatch):
    """A decision whose pick holds but knocks a parcel out of the tote (``last_lossy``) looks past the pushes on the
    shadow: one after which a pick holds losing none is made; one after which the pick still loses a parcel is not;
    where none helps the lossy pick stands, and no onward push is made in its place."""
    env = stacked_env()
    try:
        obs, info = env.reset(seed=3)
        pick = np.arange(6, dtype=np.float32)
        for answers, pushed in (([(True, True), (True, False)], 1), ([(True, True), (False, False)], None)):
            oracle = OraclePolicy()
            oracle.reset(3)
            calls: list[np.ndarray] = []

            def foresee(fn, calls=calls, answers=answers):
                holds, lossy = answers[min(len(calls), len(answers) - 1)]
                calls.append(fn.keywords["action"])
                return {"outcome": "pushed", "holds": holds, "lossy": lossy, "rehearsals": [], "nearest": 0.5}

            _deciding(monkeypatch, oracle, pick, ["success"], True, foresee)
            made = oracle.act(obs, info)
            if pushed is not None:
                assert made[6] < 0 and np.array_equal(made, calls[pushed]) and len(calls) == 2
            else:  # nothing loses less: the lossy pick, not an onward push
                assert made[6] > 0 and np.array_equal(made[:6], pick) and not oracle.last_onward and len(calls) >= 2
        oracle.last_rehearsals, oracle.last_lossy = ["success"], True
        assert oracle._parting_push(obs, info, exact=False) is None  # the twin counts no loss: nothing to look for
    finally:
        env.close()


def test_looking_past_a_pick_that_fails_gives_the_decision_on_the_pile_it_leaves():
    """A pick aimed at air above the pile touches nothing (``no_contact``) and leaves every parcel: looked past, the
    decision there is the decision here."""
    import functools

    env, oracle = stacked_env(), OraclePolicy()
    try:
        obs, info = env.reset(seed=3)
        oracle.reset(3)
        assert oracle.shadow.track(obs, info)
        oracle._exact = True  # as act has it on a pile the shadow follows
        oracle.predict(obs, info, top_k=1)
        oracle._exact = False
        here = list(oracle.last_rehearsals)
        top = float(obs["parcel_position"][: int(obs["parcel_count"]), 2].max())
        air = np.array([0.0, 0.0, top + 0.2, 0.0, 0.0, 1.0, 1.0], np.float32)  # above the pile's middle
        answer = oracle.shadow.foresee(functools.partial(oracle._look_past, action=air))
        assert answer is not None and answer["outcome"] == "no_contact"
        assert answer["rehearsals"] == here and answer["holds"] == ("success" in here)
    finally:
        env.close()
        oracle.shadow.close()
