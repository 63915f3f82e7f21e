"""eval/twin_agreement.py: the twin's rehearsal and the env's attempt, side by side on the oracle's picks."""

from __future__ import annotations

from eval.clearance import ClearanceConfig, episode_tasks
from eval.twin_agreement import Agreement, Verdicts, episode_verdicts, main
from parcelpick_env.camera.config import CameraConfig
from parcelpick_env.envs.custom_scene import BoxScene, PlacedBox

SMALL = dict(camera=CameraConfig(width=160, height=120), num_points=256)


def test_a_lone_carton_is_carried_off_in_the_rehearsal_and_in_the_cell():
    scene = BoxScene([PlacedBox((0.25, 0.20, 0.12), 1.0, (0.05, -0.03), 0.4)])
    config = ClearanceConfig(policy="oracle", objects=("rectangular",), layouts=("stacked",), episodes=1,
                             num_parcels=1, env_kwargs={**SMALL, "scene_factory": scene})
    verdicts = episode_verdicts(episode_tasks(config)[0])
    assert [(v.twin, v.env, v.agree) for v in verdicts] == [("success", "success", True)]


def test_agreement_counts_what_the_twin_foresaw():
    def v(twin: str, env: str) -> Verdicts:
        return Verdicts("mixed", "stacked", 0, 0, twin, env)

    result = Agreement([v("success", "success"), v("dropped", "dropped"), v("no_seal", "dropped"),
                        v("success", "dropped"), v("collision", "success")])
    assert (result.agreed, result.env_failures, result.foreseen) == (3, 3, 2)


def test_a_bad_argument_is_one_line_and_exit_2(capsys):
    assert main(["--episodes", "0"]) == 2
    assert "episodes" in capsys.readouterr().err


def test_the_clearance_summary_tells_rehearsed_picks_that_held_from_dead_ends():
    from eval.clearance import EpisodeResult, format_table, summarise
    from eval.twin_agreement import rehearsal_counts

    log = [{"outcome": "success", "rehearsals": ["success"]},
           {"outcome": "dropped", "phase": "lift", "rehearsals": ["dropped", "success"]},  # twin and cell parted
           {"outcome": "success", "rehearsals": ["dropped", "dropped"]},  # a dead end the cell carried off
           {"outcome": "dropped", "phase": "lift", "rehearsals": ["collision"]},
           {"outcome": "success", "rehearsals": ["success", "dropped"], "exact": True},  # marginal, on the shadow
           {"outcome": "success"}]  # not rehearsed
    counts = rehearsal_counts([log])
    assert counts == {"held": 3, "held_failed": 1, "unheld": 2, "unheld_succeeded": 1, "exact": 1}
    assert rehearsal_counts([[{"outcome": "success"}]]) is None
    episode = EpisodeResult("mixed", "stacked", 0, 0, attempts=6, successes=4, parcels_placed=4, parcels_cleared=4,
                            reason="cleared", outcomes={"success": 4, "dropped": 2}, replay=None, wall_time_s=1.0,
                            attempt_log=log)
    summary = summarise([episode])
    assert summary["overall"]["rehearsals"] == counts
    assert "the shadow of the cell (1 of 5) or its twin: 3 picks held there, 1 of them failed here; 2 with none held" \
        in format_table(summary)
