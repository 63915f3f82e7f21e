"""Two clearance runs on the same piles, paired episode by episode: which is ahead, and by how much.

    python -m eval.pair_clearance --new runs/push_s0.json runs/push_s1.json --base runs/base_s0.json runs/base_s1.json

Each file is an ``eval/clearance.py --out`` summary. Episodes are matched by object set, layout and pile seed
(the same ``--seed`` draws the same piles), so a change to a policy or to the cell is judged on the same piles,
as the report judges methods (docs/evaluation.md). Printed: each side's attempts, parcels, R_grasp and R_object
with 95% bootstrap intervals over episodes, the paired differences (new - base) of both rates and of the parcels
cleared an episode, with who is ahead only where the interval excludes 0, the episodes that ended on consecutive
failures, and the parting pushes. Piles on one side only are refused: the comparison would no longer be paired.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from eval.stats import (Interval, bootstrap_ratio, format_interval, paired_difference, paired_ratio_difference,
                        verdict)

Key = tuple[str, str, int]  # (object set, layout, pile seed)
FIELDS = ("objects", "layout", "seed", "attempts", "successes", "parcels_placed", "parcels_cleared", "reason")
DEAD_END = "consecutive_failures"  # the episode's end reason where the protocol's run of failures stopped it


def load_episodes(paths: Sequence[str | Path], arg: str) -> dict[Key, dict[str, Any]]:
    """Every episode of the clearance summaries at ``paths``, by pile; ``ValueError`` naming ``arg`` and the file
    for one that is not such a summary, an episode that lacks a field, or a pile met twice."""
    out: dict[Key, dict[str, Any]] = {}
    for path in paths:
        try:
            episodes = json.loads(Path(path).read_text())["episodes"]
            if not isinstance(episodes, list):
                raise TypeError("'episodes' is not a list")
        except FileNotFoundError:
            raise ValueError(f"{arg} {path}: no such file") from None
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise ValueError(f"{arg} {path}: not an eval/clearance.py summary ({type(exc).__name__}: {exc})") from None
        for e in episodes:
            missing = [k for k in FIELDS if k not in e]
            if missing:
                raise ValueError(f"{arg} {path}: an episode lacks {missing}")
            key = (str(e["objects"]), str(e["layout"]), int(e["seed"]))
            if key in out:
                raise ValueError(f"{arg} {path}: the pile {key} is in more than one episode")
            out[key] = e
    return out


@dataclass(frozen=True)
class Side:
    """One run's totals and rates over the paired episodes."""

    successes: int
    attempts: int
    cleared: int
    placed: int
    dead_ends: int
    pushes: int
    r_grasp: Interval
    r_object: Interval


@dataclass(frozen=True)
class Pairing:
    """Two runs on the same piles: each side, and the paired differences new - base."""

    episodes: int
    new: Side
    base: Side
    r_grasp: Interval  # points of R_grasp
    r_object: Interval  # points of R_object
    parcels: Interval  # parcels cleared an episode


def _side(episodes: list[dict[str, Any]]) -> tuple[Side, dict[str, np.ndarray]]:
    col = {k: np.array([e[k] for e in episodes], dtype=np.float64)
           for k in ("successes", "attempts", "parcels_cleared", "parcels_placed")}
    side = Side(successes=int(col["successes"].sum()), attempts=int(col["attempts"].sum()),
                cleared=int(col["parcels_cleared"].sum()), placed=int(col["parcels_placed"].sum()),
                dead_ends=sum(e["reason"] == DEAD_END for e in episodes),
                pushes=sum(len(e.get("push_log") or []) for e in episodes),
                r_grasp=bootstrap_ratio(col["successes"], col["attempts"], scale=100.0),
                r_object=bootstrap_ratio(col["parcels_cleared"], col["parcels_placed"], scale=100.0))
    return side, col


def pair(new: dict[Key, dict[str, Any]], base: dict[Key, dict[str, Any]]) -> Pairing:
    """The paired comparison; ``ValueError`` where the two runs are not on the same piles."""
    if set(new) != set(base):
        only = sorted(set(new) ^ set(base))
        raise ValueError(f"the runs are not on the same piles: {len(only)} pile(s) on one side only, e.g. {only[0]} "
                         "(give both runs the same object sets, layouts, --episodes and --seed)")
    if not new:
        raise ValueError("no episodes to pair")
    keys = sorted(new)
    (a, ca), (b, cb) = _side([new[k] for k in keys]), _side([base[k] for k in keys])
    return Pairing(
        episodes=len(keys), new=a, base=b,
        r_grasp=paired_ratio_difference(ca["successes"], ca["attempts"], cb["successes"], cb["attempts"], scale=100.0),
        r_object=paired_ratio_difference(ca["parcels_cleared"], ca["parcels_placed"], cb["parcels_cleared"],
                                         cb["parcels_placed"], scale=100.0),
        parcels=paired_difference(ca["parcels_cleared"], cb["parcels_cleared"]))


def format_pairing(p: Pairing) -> str:
    rows = ["| run | attempts | parcels | R_grasp | R_object | ended on consecutive failures | parting pushes |",
            "|---|---|---|---|---|---|---|"]
    for name, s in (("new", p.new), ("base", p.base)):
        rows.append(f"| {name} | {s.successes}/{s.attempts} | {s.cleared}/{s.placed} | {format_interval(s.r_grasp)} | "
                    f"{format_interval(s.r_object)} | {s.dead_ends} | {s.pushes} |")
    rows.append(f"\nPaired over {p.episodes} episodes (new - base, 95% bootstrap intervals over episodes):")
    for what, diff in (("R_grasp (points)", p.r_grasp), ("R_object (points)", p.r_object),
                       ("parcels cleared an episode", p.parcels)):
        rows.append(f"  {what}: {format_interval(diff)}  {verdict(diff, 'new', 'base')}")
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--new", nargs="+", required=True, metavar="JSON", help="clearance summaries of the run judged")
    p.add_argument("--base", nargs="+", required=True, metavar="JSON", help="clearance summaries it is judged against")
    args = p.parse_args(argv)
    try:
        result = pair(load_episodes(args.new, "--new"), load_episodes(args.base, "--base"))
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(format_pairing(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
