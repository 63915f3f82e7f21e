"""Rebuild the cell's state at any step of a logged clearance episode, from its summary alone.

    python -m eval.rebuild runs/oracle.json --objects mixed --layout stacked --episode 7 --before-attempt 22 --act

A clearance summary (``eval/clearance.py --out``) keeps each episode's pile seed, the env's modes and every action
the env received, parting pushes included. Resetting the same env to that seed and stepping those actions gives
the state any decision met: the way to take a dead end apart (results/ORACLE.md) without running the episode's
policy again. Physics is deterministic on one host; across CPUs a stacked pile can part at round-off
(docs/evaluation.md), so each replayed step's outcome is checked against the log and the first that differs
stops the rebuild, naming the step. A rebuilt state is never silently another one.

``--record DIR`` writes the replayed steps as a rerun replay. ``--act`` lets the episode's policy decide at the
rebuilt state and prints its action and what it tried (``decision_notes``). Made afresh there, its memory of the
episode (the picks it passes over after a failure) is empty, so it may choose otherwise than it did then; with
``--with-policy`` it acts at every replayed step as well (each action checked against the log, so as slow as
the episode), and decides with the memory it had.
"""

from __future__ import annotations

import argparse
import json
import sys
import typing
from collections.abc import Mapping
from dataclasses import dataclass, fields, is_dataclass
from pathlib import Path
from typing import Any

import numpy as np

if __package__ in (None, ""):  # allow `python eval/rebuild.py` as well as `python -m eval.rebuild`
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from eval.clearance import (ClearanceConfig, EpisodeTask, attempt_record, choose_action,  # noqa: E402
                            decision_notes, episode_env_kwargs, episode_policy, episode_tasks, failure_detail)
from parcelpick_env.config_checks import config_from_dict  # noqa: E402

COMPARED = ("outcome", "phase", "link", "condition", "body")  # what a replayed step must match in its logged record


class ReplayDiverged(RuntimeError):
    """A replayed step did not end as the log says: the state from there on is not the logged one."""


@dataclass(frozen=True)
class LoggedStep:
    """One step the env received, in order: an attempt or a parting push, its action and its logged record."""

    kind: str  # "attempt" or "push"
    index: int  # its place in the episode's attempt_log or push_log
    action: np.ndarray
    record: dict[str, Any]

    def describe(self) -> str:
        return f"{self.kind} {self.index}: {failure_detail(self.record) or self.record['outcome']}"


def logged_steps(episode: Mapping[str, Any]) -> list[LoggedStep]:
    """The episode's attempts and pushes in the order the env received them (a push record's ``before`` is the
    number of attempts made before it); ``ValueError`` where a step's action was not logged."""
    pushes: dict[int, list[int]] = {}
    for i, push in enumerate(episode.get("push_log", [])):
        pushes.setdefault(int(push["before"]), []).append(i)
    attempts = episode.get("attempt_log", [])
    order: list[tuple[str, int]] = []
    for k in range(len(attempts) + 1):
        order += [("push", i) for i in pushes.get(k, [])]
        if k < len(attempts):
            order.append(("attempt", k))
    steps = []
    for kind, i in order:
        record = (attempts if kind == "attempt" else episode["push_log"])[i]
        if record.get("action") is None:
            raise ValueError(f"{episode['objects']}/{episode['layout']} episode {episode['episode']}: {kind} {i} "
                             "has no logged action (a summary from before actions were kept, or an action that was "
                             "no array of numbers); run the episode again with this version")
        action = np.array([np.nan if x is None else x for x in record["action"]], dtype=np.float64)
        steps.append(LoggedStep(kind, i, action, record))
    return steps


def find_episode(summary: Mapping[str, Any], objects: str, layout: str, episode: int) -> dict[str, Any]:
    """The summary's record of one episode; ``ValueError`` naming what it holds instead."""
    for e in summary["episodes"]:
        if (e["objects"], e["layout"], int(e["episode"])) == (objects, layout, episode):
            return dict(e)
    held = sorted({(e["objects"], e["layout"]) for e in summary["episodes"]})
    counts = {cell: sum((e["objects"], e["layout"]) == cell for e in summary["episodes"]) for cell in held}
    raise ValueError(f"no episode {episode} of {objects}/{layout} in the summary; it holds "
                     + ", ".join(f"{o}/{l} episodes 0-{n - 1}" for (o, l), n in counts.items()))


def _from_json(cls: type, data: Mapping[str, Any]) -> Any:
    """``cls`` rebuilt from its JSON dict, nested dataclass fields included."""
    return config_from_dict(cls, data, nested=_nested_dataclasses(cls))


def _nested_dataclasses(cls: type) -> dict[str, type]:
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in fields(cls)
            if isinstance(hints[f.name], type) and is_dataclass(hints[f.name])}


def episode_task(summary: Mapping[str, Any], episode: Mapping[str, Any]) -> EpisodeTask:
    """The grid's task for a logged episode, from the summary's stored config (its env keywords' configs, such as
    ``camera``, stored as dicts); ``ValueError`` where that config does not draw the episode's pile (a summary
    edited or put together from several runs)."""
    from parcelpick_env.envs.config import EnvConfig

    stored = dict(summary["config"])
    nested = _nested_dataclasses(EnvConfig)
    env_kwargs = {k: _from_json(nested[k], v) if k in nested and isinstance(v, Mapping) else v
                  for k, v in (stored.get("env_kwargs") or {}).items()}
    config = config_from_dict(ClearanceConfig, {**stored, "env_kwargs": env_kwargs, "workers": 1})
    for task in episode_tasks(config):
        if (task.objects, task.layout, task.episode) == (episode["objects"], episode["layout"], episode["episode"]):
            if task.seed != int(episode["seed"]):
                raise ValueError(f"the summary's config draws pile seed {task.seed} for this episode, the log says "
                                 f"{episode['seed']}: the summary was not written by one eval/clearance.py run")
            return task
    raise ValueError(f"the summary's config has no {episode['objects']}/{episode['layout']} episode "
                     f"{episode['episode']}")


@dataclass
class Rebuilt:
    """The env at a logged step, with what led there: close ``env`` when done."""

    env: Any
    obs: Any
    info: dict[str, Any]
    task: EpisodeTask
    episode: dict[str, Any]
    steps: list[LoggedStep]
    replayed: int
    policy: Any = None  # the episode's policy where it acted along the replay (``with_policy``), else None

    @property
    def next_step(self) -> LoggedStep | None:
        return self.steps[self.replayed] if self.replayed < len(self.steps) else None


def rebuild(summary: Mapping[str, Any], objects: str, layout: str, episode: int, steps: int | None = None,
            record_dir: str | None = None, with_policy: bool = False) -> Rebuilt:
    """The env after the first ``steps`` logged steps of an episode (None: all but the last, the state its last
    decision met), each checked against its record; ``ReplayDiverged`` at the first that ends otherwise. With
    ``with_policy`` the episode's policy acts before each step too, and must act as logged."""
    import gymnasium as gym

    import parcelpick_env  # noqa: F401  (registers ParcelPick-v0)

    record = find_episode(summary, objects, layout, episode)
    logged = logged_steps(record)
    count = max(len(logged) - 1, 0) if steps is None else steps
    if not 0 <= count <= len(logged):
        raise ValueError(f"steps must be within 0-{len(logged)} (the episode's logged steps), got {count}")
    task = episode_task(summary, record)
    kwargs = dict(episode_env_kwargs(task), action_mode=record.get("action_mode", "pose"),
                  obs_mode=record.get("obs_mode", "pointcloud"))
    if record_dir is not None:
        kwargs["record_dir"] = str(Path(record_dir) / f"{objects}-{layout}-ep{episode:03d}-step{count:03d}")
    env = gym.make("ParcelPick-v0", **kwargs)
    policy = episode_policy(task.config) if with_policy else None
    try:
        obs, info = env.reset(seed=task.seed)
        if policy is not None:
            policy.reset(task.seed)
        for n, step in enumerate(logged[:count]):
            if policy is not None:
                action = np.asarray(choose_action(policy, obs, info, env.unwrapped.action_space.shape), np.float64)
                if not np.array_equal(action, step.action, equal_nan=True):
                    raise ReplayDiverged(f"step {n} ({step.kind} {step.index}): the policy acts otherwise than "
                                         "logged (another host or version than the episode's?)")
            obs, _, _, _, info = env.step(step.action)
            got, want = attempt_record(info), step.record
            if any(got[k] != want.get(k) for k in COMPARED):
                raise ReplayDiverged(f"step {n} ({step.kind} {step.index}) diverged: the log says "
                                     f"{failure_detail(want) or want['outcome']}, the replay "
                                     f"{failure_detail(got) or got['outcome']} (another host or version than the "
                                     "episode's?); the state from here is not the logged one")
    except BaseException:
        env.close()
        raise
    return Rebuilt(env, obs, info, task, record, logged, count, policy)


def steps_before_attempt(steps: list[LoggedStep], attempt: int) -> int:
    """How many logged steps come before attempt ``attempt`` (its parting pushes included)."""
    for n, step in enumerate(steps):
        if step.kind == "attempt" and step.index == attempt:
            return n
    raise ValueError(f"--before-attempt must be an attempt of the episode (0-"
                     f"{sum(s.kind == 'attempt' for s in steps) - 1}), got {attempt}")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("summary", help="an eval/clearance.py --out summary, or a report's RESULTS.json with --policy")
    p.add_argument("--policy", default=None, help="with a report (eval/results.py): the method whose episode it is")
    p.add_argument("--objects", default=None, help="the episode's object set (default: the summary's only one)")
    p.add_argument("--layout", default=None, help="the episode's layout (default: the summary's only one)")
    p.add_argument("--episode", type=int, default=0, help="the episode's number within its cell")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--steps", type=int, default=None, help="replay this many logged steps (pushes count)")
    where.add_argument("--before-attempt", type=int, default=None,
                       help="replay every step before this attempt (default: before the last step)")
    p.add_argument("--record", default=None, metavar="DIR", help="write the replayed steps as a rerun replay here")
    p.add_argument("--act", action="store_true", help="let the episode's policy decide here (made afresh)")
    p.add_argument("--with-policy", action="store_true",
                   help="the policy acts at every replayed step too (checked against the log; as slow as the "
                        "episode), so --act decides with the memory it had")
    return p


def _only(summary: Mapping[str, Any], key: str, given: str | None) -> str:
    if given is not None:
        return given
    held = sorted({str(e[key]) for e in summary["episodes"]})
    if len(held) != 1:
        raise ValueError(f"--{key} must be given: the summary holds {held}")
    return held[0]


def load_summary(path: str, policy: str | None = None) -> dict[str, Any]:
    """A clearance summary from ``path``: an ``eval/clearance.py --out`` file, or one method's clearance in a report
    (``eval/results.py``'s RESULTS.json, ``policy`` naming the method); ``ValueError`` naming the file otherwise."""
    try:
        summary = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise ValueError(f"summary {path}: no such file") from None
    except (OSError, ValueError) as exc:
        raise ValueError(f"summary {path}: not JSON ({type(exc).__name__}: {exc})") from None
    if isinstance(summary, dict) and isinstance(summary.get("policies"), dict):  # a report: one method's clearance
        if policy not in summary["policies"]:
            raise ValueError(f"summary {path}: a report; name its method with --policy (one of "
                             f"{sorted(summary['policies'])})")
        summary = summary["policies"][policy].get("clearance") or {}
        if "config" not in summary:
            raise ValueError(f"summary {path}: the report keeps no clearance config for {policy!r} (a report from "
                             "before 2026-12-06, or one whose clearance did not run); regenerate it with this version")
    if not (isinstance(summary, dict) and isinstance(summary.get("episodes"), list)
            and isinstance(summary.get("config"), dict)):
        raise ValueError(f"summary {path}: not an eval/clearance.py summary (no 'episodes' and 'config')")
    return summary


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        summary = load_summary(args.summary, args.policy)
        objects, layout = _only(summary, "objects", args.objects), _only(summary, "layout", args.layout)
        record = find_episode(summary, objects, layout, args.episode)
        steps = args.steps
        if args.before_attempt is not None:
            steps = steps_before_attempt(logged_steps(record), args.before_attempt)
        if args.record is not None:
            from parcelpick_env.cli import check_output_path

            check_output_path(args.record, "--record", directory=True)
        rebuilt = rebuild(summary, objects, layout, args.episode, steps, record_dir=args.record,
                          with_policy=args.with_policy)
    except (ValueError, ReplayDiverged) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    try:
        print(report(rebuilt))
        if args.act:
            print(act_here(rebuilt))
    finally:
        rebuilt.env.close()
    if (path := getattr(rebuilt.env.unwrapped, "replay_path", None)) is not None:
        print(f"Replay: rerun {path}")
    return 0


def report(rebuilt: Rebuilt) -> str:
    """What was replayed, what is in the bin, and what the log says came next."""
    e, info, steps = rebuilt.episode, rebuilt.info, rebuilt.steps[:rebuilt.replayed]
    pushes = sum(s.kind == "push" for s in steps)
    left = int(info["parcels_placed"]) - int(info["parcels_cleared"]) - int(info["parcels_lost"])
    lines = [f"{e['objects']}/{e['layout']} episode {e['episode']} (pile seed {e['seed']}): {rebuilt.replayed} of "
             f"{len(rebuilt.steps)} logged steps replayed ({len(steps) - pushes} attempts, {pushes} pushes), each "
             "ending as logged.",
             f"In the bin: {left} of {info['parcels_placed']} parcels placed ({info['parcels_cleared']} cleared, "
             f"{info['parcels_lost']} lost)."]
    nxt = rebuilt.next_step
    lines.append(f"Next in the log: {nxt.describe()}." if nxt else "The log ends here.")
    return "\n".join(lines)


def act_here(rebuilt: Rebuilt) -> str:
    """The episode's policy acting once at the rebuilt state (the one that acted along the replay, else made
    afresh): its action, whether it is the logged one, and its decision notes."""
    policy = rebuilt.policy
    if policy is None:
        policy = episode_policy(rebuilt.task.config)
        policy.reset(rebuilt.task.seed)
    action = np.asarray(choose_action(policy, rebuilt.obs, rebuilt.info, rebuilt.env.unwrapped.action_space.shape),
                        dtype=np.float64)
    notes = decision_notes(policy)
    nxt = rebuilt.next_step
    same = "" if nxt is None else (" (as logged)" if np.array_equal(action, nxt.action, equal_nan=True)
                                   else f" (logged: {np.array2string(nxt.action, precision=4, separator=', ')})")
    made = "with its memory of the replay" if rebuilt.policy is not None else "made afresh: no memory of the episode"
    lines = [f"The policy ({rebuilt.task.config.policy}, {made}) acts "
             f"{np.array2string(action, precision=4, separator=', ')}{same}"]
    lines += [f"  {key}: {value}" for key, value in notes.items()]
    return "\n".join(lines)


if __name__ == "__main__":
    from parcelpick_env.cli import run_cli

    sys.exit(run_cli(main))
