"""Closed-loop clearance: the paper's real-robot protocol (Table V), run in ParcelPick-v0.

Each episode builds a pile and lets a policy pick until the bin is clear or three consecutive attempts
fail. ``R_grasp = successes / attempts`` and ``R_object = parcels cleared / parcels placed`` are pooled
per (object set, layout) cell. Every episode has its own seed, derived from ``--seed`` and its place in
the grid, so the numbers do not depend on the worker count or the backend. Each rate carries a bootstrap
95% interval over episodes (``eval.stats``), and every attempt's outcome, cause, phase, link and condition
is kept per episode (``attempt_log``), so the summaries can say which moves fail and how.

    python eval/clearance.py --policy diffusion --episodes 2 --record runs/replays
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections import Counter
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if __package__ in (None, ""):  # allow `python eval/clearance.py` as well as `python -m eval.clearance`
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from parcelpick_env.envs.grasp import OUTCOMES  # noqa: E402  (one list of pick outcomes, the env's)
from parcelpick_env.envs.parcel_pick import NO_BODY  # noqa: E402  (info["failure"]["body"] when none)
from parcelpick_env.envs.push import is_push_action  # noqa: E402  (the env's rule: a pick or a push)
from eval.stats import bootstrap_ratio, format_interval  # noqa: E402
from parcelpick_env.parallel import BACKENDS, parallel_map  # noqa: E402

if TYPE_CHECKING:  # the policies import torch and the suction stack: loaded where an episode runs
    from policies.base import Policy

OBJECT_SETS: tuple[str, ...] = ("rectangular", "planar", "cylindrical", "mixed")
LAYOUTS: tuple[str, ...] = ("scattered", "stacked")  # the paper's Table V column order
# Set per episode from the grid; passing them in env_kwargs as well would be silently overridden.
# obs_mode is the policy's own (Policy.obs_mode; only the oracle reads the privileged "state_dict").
RESERVED_ENV_KWARGS: tuple[str, ...] = ("object_set", "layout", "num_parcels", "max_attempts", "record_dir",
                                        "obs_mode")
# 10 episodes per cell: 80 per method, about 280 attempts at 6 parcels. Scaled from the 3-per-cell report
# (results/RESULTS.json: Diffusion-Suction - Cao R_object +3.0 [-5.8, +12.5]), a pooled rate near 30% then
# carries a 95% interval of about +-3 to 5 points and a paired difference about +-5 to 6: gaps of 3 points stay
# unresolved, gaps of 6 or more resolve. An episode takes about 7 s at 6 parcels on one core (144 episodes, 1,028 s).
DEFAULT_EPISODES = 10


@dataclass(frozen=True)
class ClearanceConfig:
    policy: str = "diffusion"
    objects: tuple[str, ...] = OBJECT_SETS
    layouts: tuple[str, ...] = LAYOUTS
    episodes: int = DEFAULT_EPISODES  # per (object set, layout) cell
    num_parcels: int = 8
    seed: int = 0
    workers: int = 1
    backend: str = "local"
    ray_address: str | None = None
    record_dir: str | None = None
    checkpoint: str | None = None
    policy_kwargs: dict[str, Any] = field(default_factory=dict)  # more keywords for the policy (--policy-arg)
    max_attempts: int | None = None
    # the cell's deployment check: every policy that ranks candidates from the camera acts on its best one whose
    # physical tool is clear of the observed scene (policies/tool_check.py); the oracle checks the true scene itself
    tool_check: bool = True
    # with the tool check, also require the cell's cup to seal on the observed surface (policies/tool_check.py);
    # without the tool check there is no check to add it to
    seal_check: bool = True
    # with the tool check, multiply the score of a pick on a surface that something observed rises above (a parcel
    # under another; policies/exposure.py) by this, so the top layer goes first; 1.0 (the default): off. Measured
    # on the report's stacked episodes: no change overall (README, 'Where the stacked cells' attempts go')
    covered_factor: float = 1.0
    # with the tool check, m: a passing pick this close to one that failed since the last success counts as not
    # passing while another passes (policies/tool_check.py); 0: off; None: the cell's own (RETRY_RADIUS, 0.05 m),
    # which leaves a run without the tool check valid
    retry_radius: float | None = None
    # record, per attempt, which parcel the pick took and whether others rested on it (eval/pick_audit.py: the
    # evaluator reads the true scene; the pick and the policy's input are unchanged)
    audit_picks: bool = False
    env_kwargs: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name, values, allowed in (("objects", self.objects, OBJECT_SETS), ("layouts", self.layouts, LAYOUTS)):
            bad = [v for v in values if v not in allowed]
            if bad or not values:
                raise ValueError(f"{name} must be a non-empty subset of {allowed}, got {values}")
        if self.episodes < 1:
            raise ValueError(f"episodes must be >= 1, got {self.episodes}")
        if not 1 <= self.num_parcels <= 50:
            raise ValueError(f"num_parcels must be in [1, 50], got {self.num_parcels}")
        if self.backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {self.backend!r}")
        if self.workers < 1:
            raise ValueError(f"workers must be >= 1, got {self.workers}")
        if self.seed < 0:
            raise ValueError(f"seed must be >= 0, got {self.seed}")
        if self.max_attempts is not None and self.max_attempts < 1:
            raise ValueError(f"max_attempts must be >= 1 or None, got {self.max_attempts}")
        from policies.exposure import check_covered_factor

        check_covered_factor("ClearanceConfig", self.covered_factor)
        if self.covered_factor < 1.0 and not self.tool_check:
            raise ValueError("covered_factor < 1 re-ranks within the tool check, which is off (--no-tool-check)")
        from policies.tool_check import check_retry_radius

        if self.retry_radius is not None:
            check_retry_radius("ClearanceConfig", self.retry_radius)
        if self.retry_radius and not self.tool_check:
            raise ValueError("retry_radius > 0 works within the tool check, which is off (--no-tool-check)")
        clash = sorted(set(self.env_kwargs) & set(RESERVED_ENV_KWARGS))
        if clash:
            raise ValueError(f"env_kwargs may not set {clash}: use the ClearanceConfig fields instead")
        from parcelpick_env.envs.config import EnvConfig

        options = {f.name for f in fields(EnvConfig)}  # a bad env option fails here, before any pile is built
        EnvConfig(**{k: v for k, v in self.env_kwargs.items() if k in options})


@dataclass(frozen=True)
class EpisodeTask:
    index: int
    objects: str
    layout: str
    episode: int
    seed: int
    config: ClearanceConfig


@dataclass
class EpisodeResult:
    objects: str
    layout: str
    episode: int
    seed: int
    attempts: int
    successes: int
    parcels_placed: int
    parcels_cleared: int
    reason: str
    outcomes: dict[str, int]
    replay: str | None
    wall_time_s: float
    # one attempt_record per attempt, in order, with the ``action`` the env received (logged_action)
    attempt_log: list[dict[str, Any]] = field(default_factory=list)
    # parting pushes (action_mode="pose_push", the oracle's parting_pushes): no attempts, so kept apart; each
    # record is attempt_record's with ``before``, the number of attempts made before it
    push_log: list[dict[str, Any]] = field(default_factory=list)
    # parcels that left the bin during the episode (the env's ``parcels_lost``); the step that lost them carries
    # ``lost`` in its attempt or push record
    parcels_lost: int = 0
    # the env's modes the policy ran in; with each record's ``action`` they rebuild any step's state (eval/rebuild.py)
    action_mode: str = "pose"
    obs_mode: str = "pointcloud"


def episode_tasks(config: ClearanceConfig) -> list[EpisodeTask]:
    """The evaluation grid, with one independent seed per episode."""
    tasks = []
    for objects in config.objects:
        for layout in config.layouts:
            for episode in range(config.episodes):
                cell = (OBJECT_SETS.index(objects), LAYOUTS.index(layout), episode)
                seed = int(np.random.SeedSequence([config.seed, *cell]).generate_state(1)[0])
                tasks.append(EpisodeTask(len(tasks), objects, layout, episode, seed, config))
    return tasks


def attempt_record(info: dict[str, Any]) -> dict[str, Any]:
    """What one attempt's ``info`` says about how it went: outcome, cause, phase, link, condition (and body).

    The env's typed ``info['failure']`` (move, link, condition, body) is used where it exists; otherwise the
    older ``failure_cause`` / ``failure_phase`` strings, read as the env writes them: 'free-space: tool_rod'
    names the move and the link, and a drop's cause is the holding condition that failed.
    """
    failure = info.get("failure") or {}
    outcome, cause = str(info["outcome"]), info.get("failure_cause")
    record = {"outcome": outcome, "cause": cause, "phase": failure.get("move") or info.get("failure_phase"),
              "link": failure.get("link"), "condition": failure.get("condition"),
              "body": None if failure.get("body") in (None, NO_BODY) else failure.get("body")}
    if not failure and isinstance(cause, str):
        if ": " in cause and record["phase"] is None:
            record["phase"], record["link"] = cause.split(": ", 1)
        elif outcome == "dropped":
            record["condition"] = cause
    return record


def failure_kind(attempt: dict[str, Any]) -> str | None:
    """'outcome: phase' (or 'outcome: cause') for a failed attempt; None for a success."""
    if attempt["outcome"] == "success":
        return None
    detail = attempt.get("phase") or attempt.get("cause")
    return f"{attempt['outcome']}: {detail}" if detail else attempt["outcome"]


def failure_detail(attempt: dict[str, Any]) -> str | None:
    """The failure kind with the link or condition that failed, e.g. 'collision: free-space (tool_rod)'."""
    kind = failure_kind(attempt)
    extra = [str(attempt[k]) for k in ("link", "condition") if attempt.get(k)]
    return None if kind is None else kind + (f" ({', '.join(extra)})" if extra else "")


def logged_action(action: Any) -> list[float | None] | None:
    """The action as the env received it, for the step's record: float64 numbers (JSON keeps them to the bit), None
    for a non-finite one (a policy with no candidate acts with NaN; the env refuses it either way); None for an
    action that is no array of numbers (the env refuses it as invalid, and it cannot be replayed)."""
    try:
        numbers = np.asarray(action, dtype=np.float64).ravel()
    except (TypeError, ValueError):
        return None
    return [float(x) if np.isfinite(x) else None for x in numbers]


def decision_notes(policy: Any) -> dict[str, Any]:
    """What a rehearsing policy (the oracle) says of the decision behind its last action, for the attempt's or push's
    record; each entry only where it has something: ``rehearsals`` (on the cell's twin or shadow), ``exact`` (on the
    shadow, the env's own state), ``confirmations`` (on jittered twins), ``push_rehearsals`` (the parting pushes
    tried at a dead end, whether or not one was made), ``opening_rehearsals`` (failed picks looked past there) and
    ``onward`` (a push made there though no pick was foreseen to hold after it)."""
    notes: dict[str, Any] = {}
    if rehearsals := getattr(policy, "last_rehearsals", None):
        notes["rehearsals"] = list(rehearsals)
        if getattr(policy, "last_exact", False):
            notes["exact"] = True
    for key in ("confirmations", "push_rehearsals", "opening_rehearsals"):
        if value := getattr(policy, f"last_{key}", None):
            notes[key] = list(value)
    if getattr(policy, "last_onward", False):
        notes["onward"] = True
    return notes


def episode_env_kwargs(task: EpisodeTask) -> dict[str, Any]:
    """The env's keywords for one episode of the grid: the config's own, the cell's pile and the attempt cap."""
    cfg = task.config
    kwargs = dict(cfg.env_kwargs, object_set=task.objects, layout=task.layout, num_parcels=cfg.num_parcels)
    if cfg.max_attempts is not None:
        kwargs["max_attempts"] = cfg.max_attempts
    return kwargs


def episode_policy(cfg: ClearanceConfig) -> Policy:
    """The policy an episode acts with: ``cfg.policy`` with its checkpoint and keywords, through the cell's tool check
    (with ``cfg``'s seal, covered factor and retry radius) wherever the check applies."""
    from policies.registry import make_policy
    from policies.tool_check import ToolCheckConfig, ToolCheckedPolicy, tool_check_refusal

    policy_kwargs = dict(cfg.policy_kwargs, **({"checkpoint": cfg.checkpoint} if cfg.checkpoint else {}))
    policy = make_policy(cfg.policy, **policy_kwargs)
    if cfg.tool_check and tool_check_refusal(policy) is None:
        policy = ToolCheckedPolicy(policy, ToolCheckConfig(seal=cfg.seal_check, covered_factor=cfg.covered_factor,
                                                           retry_radius=retry_radius(cfg)))
    return policy


def run_episode(task: EpisodeTask) -> EpisodeResult:
    """One closed-loop episode; top-level so process pools and Ray can ship it."""
    import gymnasium as gym

    import parcelpick_env  # noqa: F401  (registers ParcelPick-v0)
    from policies.registry import obs_mode_of

    cfg = task.config
    env_kwargs = episode_env_kwargs(task)
    if cfg.record_dir is not None:
        env_kwargs["record_dir"] = str(Path(cfg.record_dir) / f"{task.objects}-{task.layout}-ep{task.episode:03d}")
    policy = episode_policy(cfg)
    env_kwargs["action_mode"] = policy.action_mode  # the oracle, with its parting pushes, acts in "pose_push"

    start = time.perf_counter()
    env = gym.make("ParcelPick-v0", **env_kwargs, obs_mode=obs_mode_of(policy))  # what the policy reads
    try:
        obs, info = env.reset(seed=task.seed)
        policy.reset(task.seed)
        outcomes: Counter[str] = Counter()
        attempt_log: list[dict[str, Any]] = []
        push_log: list[dict[str, Any]] = []
        first = True
        while info.get("reason") != "cleared":  # an empty pile needs no attempt
            action = choose_action(policy, obs, info, env.unwrapped.action_space.shape)
            if first:
                _log_policy_extras(env.unwrapped, policy)
                first = False
            audit = _audit(env.unwrapped, action) if cfg.audit_picks else None
            logged = {"action": logged_action(action), **decision_notes(policy)}
            lost_before = int(info["parcels_lost"])
            obs, _, terminated, truncated, info = env.step(action)
            lost = {"lost": n} if (n := int(info["parcels_lost"]) - lost_before) else {}
            if is_push_action(action):
                push_log.append({**attempt_record(info), "before": len(attempt_log), **lost, **logged})
                if terminated or truncated:
                    break
                continue
            outcomes[info["outcome"]] += 1
            record = {**attempt_record(info), **lost, **({"audit": audit} if audit is not None else {}), **logged}
            attempt_log.append(record)
            if terminated or truncated:
                break
        replay = getattr(env.unwrapped, "replay_path", None)
    finally:
        env.close()
    return EpisodeResult(
        objects=task.objects, layout=task.layout, episode=task.episode, seed=task.seed,
        attempts=int(info["attempts"]), successes=int(info["successes"]),
        parcels_placed=int(info["parcels_placed"]), parcels_cleared=int(info["parcels_cleared"]),
        reason=str(info.get("reason", "truncated")), outcomes=dict(outcomes),
        replay=str(replay) if replay else None, wall_time_s=time.perf_counter() - start, attempt_log=attempt_log,
        push_log=push_log, parcels_lost=int(info["parcels_lost"]), action_mode=str(env_kwargs["action_mode"]),
        obs_mode=obs_mode_of(policy))


def _audit(env, action: np.ndarray) -> dict[str, Any] | None:
    """The pick's audit (eval/pick_audit.py), or None where there is no pick to read (a pixel action, a parting
    push, or none). A ``pose_push`` pick is its first six numbers, the ``pose`` action it stands for."""
    from eval.pick_audit import audit_pick

    if env.config.action_mode not in ("pose", "pose_push") or is_push_action(action) or not np.all(np.isfinite(action)):
        return None
    return audit_pick(env, np.asarray(action)[:6]).to_dict()


def choose_action(policy, obs, info, shape) -> np.ndarray:
    """A policy that finds no candidate still spends an attempt, as a real robot cycle would."""
    try:
        return policy.act(obs, info)
    except ValueError:
        return np.full(shape, np.nan, dtype=np.float32)


def _log_policy_extras(env, policy) -> None:
    """Put the Diffusion-Suction denoising trajectory of the first attempt into the replay."""
    recorder = getattr(env, "recorder", None)
    trajectory = getattr(getattr(policy, "inner", policy), "last_trajectory", None)  # under the tool check too
    if recorder is not None and trajectory is not None and hasattr(recorder, "log_denoising"):
        recorder.log_denoising(trajectory.points, trajectory.maps)


RATES: dict[str, tuple[str, str]] = {"R_grasp": ("successes", "attempts"), "R_object": ("cleared", "placed")}


def lost_by_step(result: EpisodeResult) -> Counter[str]:
    """Parcels ``result`` lost from the bin, by the step that lost them: its failure kind, 'success' or 'push'."""
    counts: Counter[str] = Counter()
    for record in result.attempt_log:
        counts[failure_kind(record) or "success"] += record.get("lost", 0)
    counts["push"] += sum(record.get("lost", 0) for record in result.push_log)
    return +counts  # without the zero counts


def _rate_intervals(episodes: list[EpisodeResult], strata: list[str] | None = None) -> dict[str, dict[str, Any]]:
    """Bootstrap 95% intervals of R_grasp and R_object (pooled ratios) over the given episodes."""
    fields = {"successes": "successes", "attempts": "attempts", "cleared": "parcels_cleared",
              "placed": "parcels_placed"}
    col = {k: np.array([getattr(r, f) for r in episodes], dtype=np.float64) for k, f in fields.items()}
    return {rate: bootstrap_ratio(col[num], col[den], scale=100.0, strata=strata).to_dict()
            for rate, (num, den) in RATES.items()}


def summarise(results: list[EpisodeResult]) -> dict[str, Any]:
    """Pool episodes per cell (the paper's Table V) and over everything, each rate with its bootstrap 95%
    interval over episodes (``intervals``; overall, resampled within each cell so every cell keeps its size),
    and the failed attempts counted by kind (``failures``: 'outcome: phase') and in detail (``causes``); parcels
    that left the bin (``lost``), counted by the step that lost them (``lost_by``: its failure kind, 'success' or
    'push'; runs logged before these counts existed read 0)."""
    cells: dict[str, dict[str, Any]] = {}
    members: dict[str, list[EpisodeResult]] = {}
    for r in results:
        key = f"{r.objects}/{r.layout}"
        members.setdefault(key, []).append(r)
        cell = cells.setdefault(key, {"objects": r.objects, "layout": r.layout, "attempts": 0, "successes": 0,
                                      "placed": 0, "cleared": 0, "episodes": 0, "pushes": 0, "lost": 0,
                                      "outcomes": Counter(), "failures": Counter(), "causes": Counter(),
                                      "lost_by": Counter()})
        cell["attempts"] += r.attempts
        cell["successes"] += r.successes
        cell["placed"] += r.parcels_placed
        cell["cleared"] += r.parcels_cleared
        cell["episodes"] += 1
        cell["pushes"] += len(r.push_log)
        cell["lost"] += r.parcels_lost
        cell["lost_by"].update(lost_by_step(r))
        cell["outcomes"].update(r.outcomes)
        cell["failures"].update(k for k in map(failure_kind, r.attempt_log) if k)
        cell["causes"].update(k for k in map(failure_detail, r.attempt_log) if k)
    total: dict[str, Any] = {"attempts": 0, "successes": 0, "placed": 0, "cleared": 0, "episodes": 0, "pushes": 0,
                             "lost": 0}
    counters: dict[str, Counter[str]] = {"outcomes": Counter(), "failures": Counter(), "causes": Counter(),
                                         "lost_by": Counter()}
    for key, cell in cells.items():
        cell["R_grasp"] = 100.0 * cell["successes"] / max(cell["attempts"], 1)
        cell["R_object"] = 100.0 * cell["cleared"] / max(cell["placed"], 1)
        cell["intervals"] = _rate_intervals(members[key])
        for k in ("attempts", "successes", "placed", "cleared", "episodes", "pushes", "lost"):
            total[k] += cell[k]
        for k, counter in counters.items():
            counter.update(cell[k])
            cell[k] = dict(cell[k])
    total["R_grasp"] = 100.0 * total["successes"] / max(total["attempts"], 1)
    total["R_object"] = 100.0 * total["cleared"] / max(total["placed"], 1)
    total["intervals"] = _rate_intervals(results, [f"{r.objects}/{r.layout}" for r in results]) if results else {}
    total.update({k: dict(v) for k, v in counters.items()})
    from eval.pick_audit import cover_rates

    for key, cell in cells.items():  # with --audit-picks: success on free parcels and on parcels others rest on
        if (by_cover := cover_rates([r.attempt_log for r in members[key]])) is not None:
            cell["by_cover"] = by_cover
    if (by_cover := cover_rates([r.attempt_log for r in results])) is not None:
        total["by_cover"] = by_cover
    from eval.twin_agreement import rehearsal_counts

    if (rehearsed := rehearsal_counts([r.attempt_log for r in results])) is not None:
        total["rehearsals"] = rehearsed
    return {"cells": cells, "overall": total}


def _with_interval(cell: dict[str, Any], rate: str) -> str:
    interval = cell.get("intervals", {}).get(rate)
    return format_interval(interval) if interval else f"{cell[rate]:.2f}"


def rate_pair(cell: dict[str, Any]) -> str:
    """'R_grasp [lo, hi] / R_object [lo, hi]' of one pooled cell (percent)."""
    return f"{_with_interval(cell, 'R_grasp')} / {_with_interval(cell, 'R_object')}"


def format_table(summary: dict[str, Any], objects=OBJECT_SETS, layouts=LAYOUTS) -> str:
    """Table V layout: rows are object sets, columns layouts, entries R_grasp / R_object (%)."""
    lines = ["| object set | " + " | ".join(layouts) + " |", "|---|" + "---|" * len(layouts)]
    for obj in objects:
        row = []
        for layout in layouts:
            cell = summary["cells"].get(f"{obj}/{layout}")
            row.append("–" if cell is None else rate_pair(cell))
        lines.append(f"| {obj} | " + " | ".join(row) + " |")
    o = summary["overall"]
    lines.append(f"\nOverall: R_grasp {_with_interval(o, 'R_grasp')}%  R_object {_with_interval(o, 'R_object')}%  "
                 f"({o['successes']}/{o['attempts']} attempts, {o['cleared']}/{o['placed']} parcels; "
                 "[95% bootstrap interval over episodes])")
    lines.append("Outcomes: " + ", ".join(f"{k} {o['outcomes'].get(k, 0)}" for k in OUTCOMES))
    if o.get("causes"):
        lines.append("Failures: " + ", ".join(f"{k} {n}" for k, n in sorted(o["causes"].items(), key=lambda kv: -kv[1])))
    if o.get("by_cover"):
        where = {"free": "on free parcels", "covered": "on parcels others rest on", "none": "off every parcel"}
        lines.append("Picks (--audit-picks), successes / attempts: " + ", ".join(
            f"{where[kind]} {row['successes']}/{row['attempts']}" for kind, row in o["by_cover"].items())
            + "; on a covered parcel while a free one was left: "
              f"{o['by_cover'].get('covered', {}).get('while_free_left', 0)}")
    if o.get("pushes"):
        lines.append(f"Parting pushes (no attempts): {o['pushes']}")
    if o.get("lost"):
        steps = ", ".join(f"{k} {n}" for k, n in sorted(o["lost_by"].items(), key=lambda kv: -kv[1]))
        lines.append(f"Parcels lost from the bin (count against R_object): {o['lost']}, by the step that lost them: "
                     f"{steps or 'not logged'}")
    if (r := o.get("rehearsals")):
        where = (f"on the shadow of the cell ({r['exact']} of {r['held'] + r['unheld']}) or its twin"
                 if r.get("exact") else "on the cell's twin")
        lines.append(f"Rehearsed {where}: {r['held']} picks held there, {r['held_failed']} of them failed "
                     f"here; {r['unheld']} with none held there (dead ends), {r['unheld_succeeded']} of them "
                     "succeeded here")
    return "\n".join(lines)


def evaluate_clearance(config: ClearanceConfig, progress: bool = True) -> dict[str, Any]:
    tasks = episode_tasks(config)
    results = list(parallel_map(run_episode, tasks, workers=config.workers, backend=config.backend,
                                ray_address=config.ray_address, desc=f"clearance[{config.policy}]",
                                progress=progress))
    summary = summarise(results)
    summary["episodes"] = [asdict(r) for r in results]
    summary["config"] = {k: v for k, v in asdict(config).items()}
    summary.update(tool_check_settings(config))
    return summary


def tool_check_applies(config: ClearanceConfig) -> bool:
    """Whether the episodes ran with the tool check: asked for, and the policy is one it wraps (not the oracle)."""
    from policies.registry import policy_class
    from policies.tool_check import tool_check_refusal

    return config.tool_check and tool_check_refusal(policy_class(config.policy)) is None


def retry_radius(config: ClearanceConfig) -> float:
    """The retry rule's radius the tool check runs with (m; 0: off): ``config.retry_radius``, else the cell's own."""
    if config.retry_radius is not None:
        return float(config.retry_radius)
    from policies.tool_check import RETRY_RADIUS

    return RETRY_RADIUS


# what a summary records of the tool check its episodes ran through: whether it ran, with the seal, and the retry
# rule's radius (0 where it did not run)
CHECK_SETTINGS = ("tool_check", "seal_check", "retry_radius")


def tool_check_settings(config: ClearanceConfig) -> dict[str, bool | float]:
    """What a summary records of the check its episodes ran through (``CHECK_SETTINGS``)."""
    applies = tool_check_applies(config)
    return dict(zip(CHECK_SETTINGS, (applies, applies and config.seal_check, retry_radius(config) if applies else 0.0)))


def tool_check_line(clearance: dict[str, Any]) -> str:
    """Whether a clearance summary's episodes ran through the cell's tool check (policies/tool_check.py), and with
    which rules, in words: the CLI prints it and the report quotes it."""
    if clearance.get("tool_check"):
        seal = " and whose cup seals on it" if clearance.get("seal_check") else ""
        radius = clearance.get("retry_radius")
        retry = ("" if radius is None else " No retry rule." if not radius else
                 f" It does not go back within {radius:g} m of a pick that failed since the last success while "
                 "another passes (the retry rule).")
        return ("Acting through the cell's tool check: the best of its candidates whose physical tool (cup, flange, "
                f"wrist) is clear of the observed scene{seal} (`policies/tool_check.py`).{retry}")
    if clearance.get("config", {}).get("tool_check") is False:
        return "Acting on its top candidate as ranked (`--no-tool-check`)."
    return ("Without the tool check: it does not apply (the oracle checks its tool on the true scene; a method with "
            "its own act), or the clearance predates it.")


def build_parser() -> argparse.ArgumentParser:
    from parcelpick_env.cli import add_policy_arg

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--policy", default="diffusion", help="registered policy name")
    p.add_argument("--checkpoint", default=None, help="checkpoint for learned policies (default: shipped)")
    add_policy_arg(p)
    p.add_argument("--objects", nargs="+", default=list(OBJECT_SETS), choices=OBJECT_SETS)
    p.add_argument("--layout", nargs="+", default=list(LAYOUTS), choices=LAYOUTS)
    p.add_argument("--episodes", type=int, default=DEFAULT_EPISODES, help="episodes per (object set, layout) cell")
    p.add_argument("--parcels", type=int, default=8, help="parcels per pile")
    p.add_argument("--max-attempts", type=int, default=None, help="truncate an episode after this many attempts")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workers", type=int, default=1)
    p.add_argument("--backend", default="local", choices=BACKENDS)
    p.add_argument("--ray-address", default=None, help="Ray cluster address, e.g. 'auto'; default: local Ray")
    p.add_argument("--no-tool-check", dest="tool_check", action="store_false",
                   help="act on the policy's top candidate as ranked, without the cell's check that the physical "
                        "tool (cup, flange, wrist) is clear of the observed scene (policies/tool_check.py)")
    p.add_argument("--no-seal-check", dest="seal_check", action="store_false",
                   help="check the tool only, not also that the cell's 40 mm cup seals on the observed surface "
                        "(the paper's labels score the seal with a 10 mm cup)")
    p.add_argument("--covered-factor", type=float, default=1.0, metavar="F",
                   help="with the tool check, multiply the score of a pick on a surface that something observed rises "
                        "above (a parcel under another; policies/exposure.py) by F in [0, 1], so the top layer goes "
                        "first; 1 is off")
    p.add_argument("--retry-radius", type=float, default=None, metavar="M",
                   help="with the tool check, do not go back within M metres of a pick that failed since the last "
                        "success while another pick passes (policies/tool_check.py); 0 is off (default: the "
                        "cell's 0.05)")
    p.add_argument("--heavy-first", type=float, default=None, metavar="KG",
                   help="stacked piles: parcels heavier than KG go down the chute first (EnvConfig.heavy_first_mass; "
                        "docs/piles.md, 'Heavy parcels first'); default: the cell's drawn order")
    p.add_argument("--audit-picks", action="store_true",
                   help="record per attempt which parcel the pick took and whether other parcels rested on it "
                        "(eval/pick_audit.py; the evaluator reads the true scene, the policy does not)")
    p.add_argument("--record", default=None, metavar="DIR", help="write one rerun .rrd replay per episode here")
    p.add_argument("--out", default=None, help="write the summary JSON here")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from parcelpick_env.cli import UsageError, check_output_path, check_policy, parse_policy_args

    try:  # before any pile is built: paths, the policy name and its checkpoint (the policy is made once here)
        if args.record is not None:
            check_output_path(args.record, "--record", directory=True)
        if args.out is not None:
            check_output_path(args.out, "--out")
        policy_kwargs = parse_policy_args(args.policy_arg)
        check_policy(args.policy, args.checkpoint, **policy_kwargs)
    except UsageError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    try:
        config = ClearanceConfig(policy=args.policy, objects=tuple(args.objects), layouts=tuple(args.layout),
                                 episodes=args.episodes, num_parcels=args.parcels, seed=args.seed,
                                 workers=args.workers, backend=args.backend, ray_address=args.ray_address,
                                 record_dir=args.record, checkpoint=args.checkpoint, policy_kwargs=policy_kwargs,
                                 max_attempts=args.max_attempts, tool_check=args.tool_check,
                                 seal_check=args.seal_check, covered_factor=args.covered_factor,
                                 retry_radius=args.retry_radius, audit_picks=args.audit_picks,
                                 env_kwargs={} if args.heavy_first is None else {"heavy_first_mass": args.heavy_first})
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    summary = evaluate_clearance(config)
    print(f"\nClosed-loop clearance, policy {config.policy!r}: R_grasp / R_object (%)\n")
    print(format_table(summary, config.objects, config.layouts))
    print(tool_check_line(summary))
    replays = [e["replay"] for e in summary["episodes"] if e["replay"]]
    if replays:
        print(f"\nReplays ({len(replays)}): open one with `rerun {replays[0]}`")
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(summary, indent=2, default=str))
        print(f"Summary written to {args.out}")
    return 0


if __name__ == "__main__":
    from parcelpick_env.cli import run_cli

    sys.exit(run_cli(main))
