"""Does the oracle's twin foresee the cell? Each oracle pick is rehearsed on the twin, then made in the env.

    python -m eval.twin_agreement --objects cylindrical mixed --layout stacked --episodes 10 --parcels 10 --workers 2

The oracle decides without rehearsing (``OracleConfig(rehearsals=0)``), so the picks are the ones its geometry
alone chooses; the twin (``policies/cell_twin.py``, ``CellTwin.rehearse``) then runs each one whole, dynamics and
all, and the env makes it. Printed: how often the two verdicts (success or not) agree, how many of the env's
failures the twin foresaw, and every attempt where they part. This is the evidence behind the oracle's rehearsal
(results/ORACLE.md, 'The oracle rehearses its pick on the twin').
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict, dataclass, field
from typing import Any

from eval.clearance import ClearanceConfig, EpisodeTask, episode_env_kwargs, episode_tasks
from parcelpick_env.assets.library import OBJECT_SETS
from parcelpick_env.parallel import BACKENDS, parallel_map
from parcelpick_env.scene.config import LAYOUTS


@dataclass
class Verdicts:
    """One attempt: what the twin's rehearsal and the env's attempt made of the same pick."""

    objects: str
    layout: str
    episode: int
    attempt: int
    twin: str  # outcome
    env: str
    twin_failure: dict[str, Any] | None = None
    env_failure: dict[str, Any] | None = None

    @property
    def agree(self) -> bool:
        return (self.twin == "success") == (self.env == "success")


@dataclass
class Agreement:
    """Every attempt's verdicts, and how often the twin's success-or-not matched the env's."""

    verdicts: list[Verdicts] = field(default_factory=list)

    @property
    def agreed(self) -> int:
        return sum(v.agree for v in self.verdicts)

    @property
    def env_failures(self) -> int:
        return sum(v.env != "success" for v in self.verdicts)

    @property
    def foreseen(self) -> int:
        return sum(v.env != "success" and v.twin != "success" for v in self.verdicts)


def rehearsal_counts(attempt_logs: list[list[dict[str, Any]]]) -> dict[str, int] | None:
    """How a rehearsing policy's picks (attempt records with ``rehearsals``, ``eval/clearance.py``) went in the
    env: ``held`` picks made after a rehearsal that succeeded (the clean one, or the least loaded success where
    none was clean, which may come before later failed rehearsals), and ``held_failed`` of them the env failed
    (where twin and cell part); ``unheld`` picks for which no rehearsal succeeded (a dead end: the ranking's first
    was made), and ``unheld_succeeded`` of them the env carried off; ``exact`` of all of them were rehearsed on the
    shadow of the cell (``exact`` records), the rest on its posed twin. None where no attempt was rehearsed."""
    rehearsed = [a for log in attempt_logs for a in log if a.get("rehearsals")]
    if not rehearsed:
        return None
    held = [a for a in rehearsed if "success" in a["rehearsals"]]
    unheld = [a for a in rehearsed if "success" not in a["rehearsals"]]
    return {"held": len(held), "held_failed": sum(a["outcome"] != "success" for a in held),
            "unheld": len(unheld), "unheld_succeeded": sum(a["outcome"] == "success" for a in unheld),
            "exact": sum(bool(a.get("exact")) for a in rehearsed)}


def episode_verdicts(task: EpisodeTask) -> list[Verdicts]:
    """The twin's and the env's verdicts on every pick of one oracle episode; top-level for process pools."""
    import gymnasium as gym
    import numpy as np

    import parcelpick_env  # noqa: F401  (registers ParcelPick-v0)
    from policies.oracle import OracleConfig, OraclePolicy

    env = gym.make("ParcelPick-v0", **episode_env_kwargs(task), obs_mode="state_dict")
    # the posed twin's verdicts on picks alone (no shadow of the cell: it is the twin that is measured)
    oracle = OraclePolicy(OracleConfig(rehearsals=0), parting_pushes=False, exact=False)
    out: list[Verdicts] = []
    try:
        obs, info = env.reset(seed=task.seed)
        oracle.reset(task.seed)
        while info.get("reason") != "cleared":
            action = oracle.act(obs, info)
            rehearsal = oracle.twin.rehearse(action[:3].astype(np.float64), action[3:6].astype(np.float64))
            obs, _, terminated, truncated, info = env.step(action)
            out.append(Verdicts(task.objects, task.layout, task.episode, len(out), rehearsal.outcome, info["outcome"],
                                None if rehearsal.failure is None else rehearsal.failure.as_dict(),
                                info.get("failure")))
            if terminated or truncated:
                break
    finally:
        oracle.twin.close()
        env.close()
    return out


def measure(config: ClearanceConfig, progress: bool = True) -> Agreement:
    tasks = episode_tasks(config)
    runs = parallel_map(episode_verdicts, tasks, workers=config.workers, backend=config.backend,
                        ray_address=config.ray_address, desc="twin vs cell", progress=progress)
    return Agreement([v for episode in runs for v in episode])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--objects", nargs="+", default=["cylindrical", "mixed"], choices=OBJECT_SETS)
    p.add_argument("--layout", nargs="+", default=["stacked"], choices=LAYOUTS)
    p.add_argument("--episodes", type=int, default=10, help="episodes per (object set, layout) cell")
    p.add_argument("--parcels", type=int, default=10, help="parcels per pile")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workers", type=int, default=1)
    p.add_argument("--backend", default="local", choices=BACKENDS)
    p.add_argument("--ray-address", default=None, help="Ray cluster address, e.g. 'auto'; default: local Ray")
    p.add_argument("--out", default=None, help="write every attempt's verdicts here (JSON)")
    args = p.parse_args(argv)
    from parcelpick_env.cli import UsageError, check_output_path

    try:
        if args.out is not None:
            check_output_path(args.out, "--out")
        config = ClearanceConfig(policy="oracle", objects=tuple(args.objects), layouts=tuple(args.layout),
                                 episodes=args.episodes, num_parcels=args.parcels, seed=args.seed,
                                 workers=args.workers, backend=args.backend, ray_address=args.ray_address)
    except (UsageError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    result = measure(config)
    n = len(result.verdicts)
    print(f"verdicts agree (success or not): {result.agreed}/{n}; env failures the twin foresaw: "
          f"{result.foreseen}/{result.env_failures}")
    for v in result.verdicts:
        if not v.agree:
            print(f"  {v.objects} {v.layout} episode {v.episode} attempt {v.attempt}: twin {v.twin} "
                  f"{v.twin_failure or ''}, env {v.env} {v.env_failure or ''}")
    if args.out:
        with open(args.out, "w") as f:
            json.dump([asdict(v) for v in result.verdicts], f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
