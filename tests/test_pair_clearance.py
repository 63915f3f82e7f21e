"""eval/pair_clearance.py: two clearance runs paired by pile, on hand-made summaries (no simulation)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from eval.pair_clearance import load_episodes, main, pair
from eval.stats import TIE


def _episode(seed: int, successes: int, attempts: int, cleared: int, placed: int = 10, pushes: int = 0,
             layout: str = "stacked") -> dict:
    return {"objects": "mixed", "layout": layout, "episode": seed, "seed": seed, "attempts": attempts,
            "successes": successes, "parcels_placed": placed, "parcels_cleared": cleared,
            "reason": "cleared" if cleared == placed else "consecutive_failures",
            "push_log": [{"outcome": "pushed"}] * pushes}


def _write(path: Path, episodes: list[dict]) -> str:
    path.write_text(json.dumps({"overall": {}, "episodes": episodes}))
    return str(path)


def test_pairs_by_pile_and_calls_the_new_run_ahead_only_where_the_interval_excludes_zero(tmp_path: Path):
    # the same piles, listed in another order and split over two files: every pile clears one parcel more
    base = _write(tmp_path / "base.json", [_episode(s, 7, 10, 7) for s in (1, 2, 3, 4)])
    new_a = _write(tmp_path / "a.json", [_episode(s, 8, 9, 8, pushes=1) for s in (4, 2)])
    new_b = _write(tmp_path / "b.json", [_episode(s, 8, 9, 8) for s in (3, 1)])
    p = pair(load_episodes([new_a, new_b], "--new"), load_episodes([base], "--base"))
    assert p.episodes == 4 and (p.new.cleared, p.new.placed, p.base.cleared) == (32, 40, 28)
    assert (p.new.pushes, p.base.pushes, p.new.dead_ends, p.base.dead_ends) == (2, 0, 4, 4)
    assert (p.parcels.estimate, p.parcels.low, p.parcels.high) == (1.0, 1.0, 1.0)  # +1 on every pile
    assert p.r_object.estimate == pytest.approx(10.0) and p.r_grasp.estimate == pytest.approx(100 * (32 / 36 - 0.7))
    # a gain on one pile and the same loss on another: no one is ahead
    mixed = _write(tmp_path / "mixed.json", [_episode(1, 8, 10, 8), _episode(2, 6, 10, 6), _episode(3, 7, 10, 7),
                                             _episode(4, 7, 10, 7)])
    tie = pair(load_episodes([mixed], "--new"), load_episodes([base], "--base"))
    assert tie.parcels.estimate == 0.0 and tie.parcels.low < 0 < tie.parcels.high


def test_bad_input_is_one_clear_line_naming_the_argument(tmp_path: Path, capsys):
    base = _write(tmp_path / "base.json", [_episode(s, 7, 10, 7) for s in (1, 2)])
    other = _write(tmp_path / "other.json", [_episode(s, 7, 10, 7) for s in (1, 5)])
    with pytest.raises(ValueError, match="not on the same piles"):
        pair(load_episodes([other], "--new"), load_episodes([base], "--base"))
    with pytest.raises(ValueError, match="more than one episode"):
        load_episodes([base, base], "--new")
    (tmp_path / "corrupt.json").write_text('{"episodes": [')
    assert main(["--new", str(tmp_path / "corrupt.json"), "--base", base]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: --new ") and "corrupt.json: not an eval/clearance.py summary" in err
    assert len(err.strip().splitlines()) == 1
    assert main(["--new", str(tmp_path / "absent.json"), "--base", base]) == 2
    assert "--new " in capsys.readouterr().err
    (tmp_path / "short.json").write_text(json.dumps({"episodes": [{"objects": "mixed"}]}))
    assert main(["--new", str(tmp_path / "short.json"), "--base", base]) == 2
    assert "an episode lacks" in capsys.readouterr().err
    assert main(["--new", base, "--base", base]) == 0
    out = capsys.readouterr().out
    assert "| new | 14/20 | 14/20 |" in out and f"parcels cleared an episode: 0.00 [0.00, 0.00]  {TIE}" in out
