"""Does the ``physical`` label predict the env's pick? Random candidates, labelled, then picked in ParcelPick-v0.

    python -m eval.label_physics --picks 1000 --workers 2 --out results/label_physics.json \
        --plot results/label_physics.png
    python -m eval.label_physics --from-picks results/label_physics.picks.jsonl   # re-summarise a (partial) run

For each pick an env is reset on a seeded pile (cells of layout x object set in turn, so every cell gets the same
number of picks give or take one). A candidate is drawn **uniformly** among the camera cloud's points that lie on
a parcel (the frame's segmentation) and inside the action box, with the camera's own normal estimate: what a
policy reading the cloud could submit. Uniform, not stratified on the label, so the ROC-AUC and the success rates
are those of the candidates as they come; about a third of them carry a label above 0 (both classes appear).
Its ``physical`` quality (``suction/quality.py``: seal x holding margin x tool clearance, 0 exactly where the env is
predicted to fail) is computed on the env's TRUE scene, the parcels' simulated poses, BEFORE the pick; then the
candidate is executed as one env step, and ``info['outcome'] == 'success'`` is the truth. With
``--picks-per-reset K > 1`` an episode makes K picks and the label is recomputed on the current true scene before
each (the pile state is then the one the previous pick left).

Reported: ROC-AUC of quality vs success (Mann-Whitney, ties counted half) with a bootstrap 95% interval over picks
(stratified by cell, ``eval.stats``), AUC per layout, object set and cell, a reliability table (success rate per
quality bin, with counts), the confusion at quality > 0 (predicted hold) vs success, and which failure kinds the
label predicted to hold (what it misses) and which channel zeroed the successes it predicted to fail.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from scipy.stats import rankdata

if __package__ in (None, ""):  # run as a script: make the repository root importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from eval.clearance import attempt_record, failure_detail, failure_kind  # noqa: E402  (how an attempt went)
from eval.stats import CONFIDENCE, RESAMPLES, SEED, Interval, format_interval, resample_indices  # noqa: E402
from parcelpick_env.assets.library import OBJECT_SETS  # noqa: E402
from parcelpick_env.cli import UsageError, check_input_file, check_output_path, run_cli, usage_exit  # noqa: E402
from parcelpick_env.parallel import parallel_map  # noqa: E402
from parcelpick_env.scene.config import LAYOUTS, MAX_PARCELS  # noqa: E402

# Reliability bins of the label: exactly 0 (predicted to fail), then fifths of (0, 1].
BIN_EDGES: tuple[float, ...] = (0.0, 0.2, 0.4, 0.6, 0.8, 1.0)
EPISODES_PER_JOB = 4  # episodes one worker job runs on one env (the env is built once per job)
CHANNELS = ("seal", "wrench", "collision")
ABOVE_COS = 0.5  # a contact whose normal is within 60 degrees of straight down comes from a parcel on top


@dataclass(frozen=True)
class LabelPhysicsConfig:
    """One label-vs-physics run; defaults in one place (the CLI's defaults are these)."""

    picks: int = 1000
    layouts: tuple[str, ...] = LAYOUTS
    objects: tuple[str, ...] = OBJECT_SETS
    num_parcels: int = 10
    picks_per_reset: int = 1
    seed: int = 0
    workers: int = 1
    # The env's camera at a quarter of its pixels: the candidates' points and normals are the camera's, and the
    # label is computed at the same (p, n), so resolution changes which candidates appear, not their agreement.
    camera_size: tuple[int, int] = (320, 240)
    env_kwargs: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name in ("picks", "picks_per_reset", "workers"):
            value = getattr(self, name)
            if not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
        if not 1 <= self.num_parcels <= MAX_PARCELS:
            raise ValueError(f"num_parcels must be in [1, {MAX_PARCELS}], got {self.num_parcels!r}")
        for name, allowed in (("layouts", LAYOUTS), ("objects", OBJECT_SETS)):
            values = getattr(self, name)
            if not values or any(v not in allowed for v in values):
                raise ValueError(f"{name} must be a non-empty subset of {', '.join(allowed)}, got {values!r}")
        if len(self.camera_size) != 2 or min(self.camera_size) < 8:
            raise ValueError(f"camera_size must be (width, height) of at least 8 pixels, got {self.camera_size!r}")

    @property
    def cells(self) -> list[tuple[str, str]]:
        return [(layout, objects) for layout in self.layouts for objects in self.objects]

    @property
    def episodes(self) -> int:
        return math.ceil(self.picks / self.picks_per_reset)


@dataclass(frozen=True)
class EpisodeJob:
    """Episodes of one cell, run on one env; each episode carries its own seed (results ignore the grouping)."""

    layout: str
    objects: str
    episodes: tuple[int, ...]
    picks: tuple[int, ...]  # picks in each episode
    config: LabelPhysicsConfig


def episode_seed(seed: int, episode: int) -> int:
    return int(np.random.SeedSequence([seed, episode]).generate_state(1)[0])


def plan_jobs(config: LabelPhysicsConfig) -> list[EpisodeJob]:
    """Episode ``e`` runs in cell ``e mod cells``; jobs group a cell's episodes, ordered so cells advance together."""
    cells = config.cells
    per_cell: dict[int, list[tuple[int, int]]] = {c: [] for c in range(len(cells))}
    for e in range(config.episodes):
        per_cell[e % len(cells)].append((e, min(config.picks_per_reset, config.picks - e * config.picks_per_reset)))
    jobs: list[tuple[int, int, EpisodeJob]] = []
    for c, rows in per_cell.items():
        for start in range(0, len(rows), EPISODES_PER_JOB):
            chunk = rows[start:start + EPISODES_PER_JOB]
            jobs.append((start, c, EpisodeJob(*cells[c], tuple(e for e, _ in chunk), tuple(k for _, k in chunk),
                                              config)))
    return [job for _, _, job in sorted(jobs, key=lambda t: (t[0], t[1]))]


def _true_scene(env) -> Any:
    """The env's scene with every parcel at its simulated pose (a copy: the env's own is not touched)."""
    u = env.unwrapped
    parcels = [dataclasses.replace(ps, position=np.asarray(pos), orientation=np.asarray(orn))
               for ps in u.scene.parcels for pos, orn in [u.sim.body_pose(ps.body_id)]]
    return dataclasses.replace(u.scene, parcels=parcels)


def _candidates(env) -> np.ndarray:
    """Indices of the frame's cloud points on a parcel and inside the action box."""
    u = env.unwrapped
    frame = u.frame
    lo, hi = u.action_space.low[:3], u.action_space.high[:3]
    inside = np.all((frame.points >= lo) & (frame.points <= hi), axis=1)
    return np.flatnonzero((frame.point_object_ids >= 0) & inside)


def load_from_above(env, body: int) -> float:
    """N of normal force that other parcels resting on ``body`` press on it (pybullet's contacts at rest): the
    weight a lift must shift or drag, which the hanging-still label does not see. A diagnostic, never a label."""
    import pybullet as p

    u = env.unwrapped
    parcels = {ps.body_id for ps in u.scene.parcels} - {body}
    contacts = p.getContactPoints(bodyA=body, physicsClientId=u.sim.client)
    # contactNormalOnB points from the other body to this one: downwards when the other lies on top
    return float(sum(c[9] for c in contacts if c[2] in parcels and c[7][2] < -ABOVE_COS))


def label_pick(env, rng: np.random.Generator) -> dict[str, Any] | None:
    """Draw one candidate uniformly on the observed parcels and compute its ``physical`` label on the true scene."""
    from parcelpick_env.suction.cup import CONDITIONS
    from parcelpick_env.suction.quality import PhysicalCell, definition_scorer, score_definition

    pool = _candidates(env)
    if len(pool) == 0:
        return None
    frame = env.unwrapped.frame  # captured without normals: the camera estimates the drawn point's (normals_at)
    k = int(pool[rng.integers(len(pool))])
    point = frame.points[k:k + 1].astype(np.float64)
    normal = env.unwrapped.camera.normals_at(frame, np.array([k])).astype(np.float64)
    if abs(float(np.linalg.norm(normal)) - 1.0) > 1e-3:  # a degenerate neighbourhood has no normal
        return None
    object_id = frame.point_object_ids[k:k + 1].astype(np.int64)
    scene = _true_scene(env)
    cell = PhysicalCell(suction=env.unwrapped.config.suction, cup=env.unwrapped.config.grasp.cup,
                        seal_threshold=env.unwrapped.config.grasp.seal_threshold)
    scorer = definition_scorer("physical", scene, cell)
    scores = score_definition("physical", scorer, point, normal, object_id, cell=cell)
    grasp = scorer.physical(point, normal, object_id, cup=cell.cup)
    parcel = scene.parcels[int(object_id[0])]
    worst = float(grasp.worst[0])
    return {"point": point[0].tolist(), "normal": normal[0].tolist(), "object_id": int(object_id[0]),
            "body_id": int(parcel.body_id), "category": str(parcel.asset.category),
            "mass": float(parcel.asset.mass), "quality": float(scores.total[0]),
            **{name: float(getattr(scores, name)[0]) for name in CHANNELS},
            "load_from_above": load_from_above(env, int(parcel.body_id)), "raw_seal": float(grasp.seal[0]), "worst_ratio": worst if math.isfinite(worst) else None,
            "worst_condition": CONDITIONS[int(np.argmax(grasp.ratios[0]))] if math.isfinite(worst) else None}


def run_job(job: EpisodeJob) -> list[dict[str, Any]]:
    """Every pick of a job's episodes: reset on the episode's seed, then label and pick ``picks`` times."""
    import gymnasium as gym

    import parcelpick_env  # noqa: F401  (registers ParcelPick-v0)
    from parcelpick_env.camera.config import CameraConfig

    cfg = job.config
    width, height = cfg.camera_size
    camera = cfg.env_kwargs.get("camera", CameraConfig())
    env_kwargs = {**cfg.env_kwargs, "layout": job.layout, "object_set": job.objects, "num_parcels": cfg.num_parcels,
                  "camera": dataclasses.replace(camera, width=width, height=height),
                  # the episode ends when its picks are made, never early
                  "max_attempts": cfg.picks_per_reset + 1, "max_consecutive_failures": cfg.picks_per_reset + 1}
    records: list[dict[str, Any]] = []
    env = gym.make("ParcelPick-v0", **env_kwargs)
    try:
        for episode, picks in zip(job.episodes, job.picks):
            seed = episode_seed(cfg.seed, episode)
            rng = np.random.default_rng([cfg.seed, episode, 1])
            _, info = env.reset(seed=seed)
            for pick in range(picks):
                if not env.unwrapped.scene.parcels:
                    break
                t0 = time.perf_counter()
                label = label_pick(env, rng)
                if label is None:
                    break
                before = {ps.body_id for ps in env.unwrapped.scene.parcels}
                action = np.concatenate([label["point"], label["normal"]]).astype(np.float32)
                _, _, _, _, info = env.step(action)
                attempt = attempt_record(info)
                removed = before - {ps.body_id for ps in env.unwrapped.scene.parcels}
                records.append({"episode": episode, "pick": pick, "layout": job.layout, "objects": job.objects,
                                "seed": seed, "scene_seed": int(info["scene_seed"]), **label,
                                "env_seal": None if info["seal"] < 0 else float(info["seal"]),  # as judged
                                "outcome": attempt["outcome"], "success": attempt["outcome"] == "success",
                                "failure": failure_kind(attempt), "failure_detail": failure_detail(attempt),
                                "delivered_labelled": attempt["outcome"] == "success" and label["body_id"] in removed,
                                "seconds": time.perf_counter() - t0})
    finally:
        env.close()
    return records


# ------------------------------------------------------------------------------------------------ statistics
def roc_auc(scores: Any, labels: Any) -> float:
    """ROC-AUC by ranks (Mann-Whitney U / (n1 n0)): the chance that a random success outscores a random failure,
    ties counted half. NaN when either class is empty. Rows of 2-D inputs are scored independently."""
    s = np.asarray(scores, dtype=np.float64)
    y = np.asarray(labels, dtype=bool)
    if s.shape != y.shape:
        raise ValueError(f"scores {s.shape} and labels {y.shape} must have the same shape")
    if not np.all(np.isfinite(s)):
        raise ValueError("scores contain NaN or inf")
    s2, y2 = np.atleast_2d(s), np.atleast_2d(y)
    ranks = rankdata(s2, axis=1)  # average ranks: a tie contributes one half
    n1 = y2.sum(axis=1).astype(np.float64)
    n0 = y2.shape[1] - n1
    u = np.sum(ranks * y2, axis=1) - n1 * (n1 + 1) / 2
    with np.errstate(invalid="ignore", divide="ignore"):
        auc = np.where((n1 > 0) & (n0 > 0), u / (n1 * n0), np.nan)
    return float(auc[0]) if s.ndim <= 1 else auc


def bootstrap_auc(scores: Any, labels: Any, strata: Any = None, resamples: int = RESAMPLES,
                  confidence: float = CONFIDENCE, seed: int = SEED) -> Interval:
    """AUC with its percentile bootstrap interval over picks (``eval.stats.resample_indices``, by stratum)."""
    s, y = np.asarray(scores, dtype=np.float64), np.asarray(labels, dtype=bool)
    estimate = roc_auc(s, y)
    if len(s) < 2:
        return Interval(estimate, float("nan"), float("nan"), len(s), confidence, resamples)
    idx = resample_indices(len(s), resamples, seed, strata)
    stats = roc_auc(s[idx], y[idx])
    finite = stats[np.isfinite(stats)]
    if finite.size == 0:
        return Interval(estimate, float("nan"), float("nan"), len(s), confidence, resamples)
    low, high = np.quantile(finite, [(1 - confidence) / 2, (1 + confidence) / 2])
    return Interval(estimate, float(low), float(high), len(s), confidence, resamples)


def reliability(quality: np.ndarray, success: np.ndarray, edges: Sequence[float] = BIN_EDGES) -> list[dict[str, Any]]:
    """Success rate per label bin: q = 0 exactly, then (edges[i], edges[i+1]]."""
    q, y = np.asarray(quality, dtype=np.float64), np.asarray(success, dtype=bool)
    bins = [("0", q <= 0.0)] + [(f"({lo:.1f}, {hi:.1f}]", (q > lo) & (q <= hi)) for lo, hi in zip(edges[:-1], edges[1:])]
    rows = []
    for name, mask in bins:
        n = int(mask.sum())
        rows.append({"bin": name, "count": n, "successes": int(y[mask].sum()),
                     "success_rate": float(y[mask].mean()) if n else None,
                     "mean_quality": float(q[mask].mean()) if n else None})
    return rows


def confusion(quality: np.ndarray, success: np.ndarray) -> dict[str, Any]:
    """Predicted hold (quality > 0) against the env's success."""
    hold, y = np.asarray(quality) > 0, np.asarray(success, dtype=bool)
    c = {"hold_success": int(np.sum(hold & y)), "hold_failure": int(np.sum(hold & ~y)),
         "fail_success": int(np.sum(~hold & y)), "fail_failure": int(np.sum(~hold & ~y))}
    n = max(1, len(y))
    c["accuracy"] = (c["hold_success"] + c["fail_failure"]) / n
    c["precision"] = c["hold_success"] / max(1, c["hold_success"] + c["hold_failure"])  # of predicted holds
    c["recall"] = c["hold_success"] / max(1, c["hold_success"] + c["fail_success"])  # of real successes
    return c


def resting_load_quality(records: list[dict[str, Any]]) -> np.ndarray:
    """What-if label: the hanging-still worst ring ratio scaled by ``(W + L) / W``, as if the cup also carried the
    load ``L`` that other parcels rest on the picked one with (weight ``W``). First order only: it takes every ratio
    as linear in the load, which ignores that the pull also lowers the friction capacity."""
    from parcelpick_env.suction.config import SuctionConfig

    gravity = SuctionConfig().gravity
    worst = np.array([np.inf if r["worst_ratio"] is None else r["worst_ratio"] for r in records], dtype=np.float64)
    scale = 1.0 + np.array([r["load_from_above"] / (r["mass"] * gravity) for r in records])
    margin = np.clip(1.0 - worst * scale, 0.0, 1.0)
    return np.array([r["seal"] * r["collision"] for r in records]) * margin


def _zeroed_by(record: dict[str, Any]) -> str:
    """Which channels put a label at 0 (e.g. 'seal+collision')."""
    return "+".join(name for name in CHANNELS if record[name] <= 0.0) or "none"


def summarise(records: list[dict[str, Any]]) -> dict[str, Any]:
    """Every figure of the report from the pick records."""
    if not records:
        raise ValueError("no picks to summarise")
    q = np.array([r["quality"] for r in records], dtype=np.float64)
    y = np.array([r["success"] for r in records], dtype=bool)
    cells = np.array([f"{r['layout']}/{r['objects']}" for r in records])
    out: dict[str, Any] = {"picks": len(records), "success_rate": float(y.mean()),
                           "predicted_hold_rate": float(np.mean(q > 0)),
                           "auc": bootstrap_auc(q, y, strata=cells).to_dict()}
    for key in ("layout", "objects"):
        values = np.array([r[key] for r in records])
        out[f"auc_by_{key}"] = {v: {**bootstrap_auc(q[values == v], y[values == v]).to_dict(),
                                    "success_rate": float(y[values == v].mean())}
                                for v in sorted(set(values.tolist()))}
    out["auc_by_cell"] = {c: {**bootstrap_auc(q[cells == c], y[cells == c]).to_dict(),
                              "success_rate": float(y[cells == c].mean())} for c in sorted(set(cells.tolist()))}
    out["reliability"] = reliability(q, y)
    out["confusion"] = confusion(q, y)
    hold = q > 0
    out["missed_failures"] = dict(Counter(r["failure_detail"] for r, h in zip(records, hold) if h and not r["success"])
                                  .most_common())
    out["failures_predicted"] = dict(Counter(r["failure"] for r, h in zip(records, hold) if not h and not r["success"])
                                     .most_common())
    out["failures_all"] = dict(Counter(r["failure"] for r in records if not r["success"]).most_common())
    out["successes_predicted_to_fail"] = dict(Counter(_zeroed_by(r) for r, h in zip(records, hold)
                                                      if not h and r["success"]).most_common())
    out["successes_on_another_parcel"] = int(sum(r["success"] and not r["delivered_labelled"] for r in records))
    judged = [(r["raw_seal"], r["env_seal"]) for r, h in zip(records, hold) if h and r.get("env_seal") is not None]
    if judged:  # the label's seal (cup seated on the hull) against the env's, at the lip where the cup came to rest
        gap = np.abs(np.subtract(*np.array(judged).T))
        out["seal_difference"] = {"picks": len(judged), "mean_abs": float(gap.mean()),
                                  "p90_abs": float(np.quantile(gap, 0.9))}
    if all("load_from_above" in r for r in records):  # do the misses lie under other parcels?
        covered = np.array([r["load_from_above"] > 0 for r in records])
        out["by_cover"] = {name: {"picks": int(mask.sum()), "success_rate": float(y[mask].mean()) if mask.any() else None,
                                  "auc": bootstrap_auc(q[mask], y[mask]).to_dict() if mask.any() else None,
                                  "hold_failure": int(np.sum(mask & hold & ~y)), "hold": int(np.sum(mask & hold))}
                           for name, mask in (("uncovered", ~covered), ("covered", covered))}
        out["auc_resting_load"] = bootstrap_auc(resting_load_quality(records), y, strata=cells).to_dict()
    out["seconds_per_pick"] = float(np.mean([r["seconds"] for r in records]))
    # what each channel alone predicts (AUC of the channel's value vs success)
    out["channel_auc"] = {name: roc_auc(np.array([r[name] for r in records]), y) for name in CHANNELS}
    return out


# ------------------------------------------------------------------------------------------------ report
def _row(name: str, iv: dict[str, Any], extra: str = "") -> str:
    return f"| {name} | {format_interval(iv, 3)} | {iv['n']} | {extra} |"


def format_report(summary: dict[str, Any]) -> str:
    """Markdown tables: AUC (overall, per layout, object set, cell), reliability, confusion, what the label misses."""
    lines = [f"Label vs physics: {summary['picks']} random picks, env success rate {summary['success_rate']:.3f}, "
             f"label > 0 on {summary['predicted_hold_rate']:.3f}; [95% bootstrap interval over picks]", "",
             "| subset | ROC-AUC | picks | success rate |", "|---|---|---|---|",
             _row("overall", summary["auc"], f"{summary['success_rate']:.3f}")]
    for key in ("auc_by_layout", "auc_by_objects", "auc_by_cell"):
        for name, iv in summary[key].items():
            lines.append(_row(name, iv, f"{iv['success_rate']:.3f}"))
    channels = ", ".join(f"{k} {v:.3f}" for k, v in summary["channel_auc"].items())
    lines += ["", f"AUC of each channel alone: {channels}", "",
              "| label bin | picks | successes | success rate | mean label |", "|---|---|---|---|---|"]
    for r in summary["reliability"]:
        rate = "–" if r["success_rate"] is None else f"{r['success_rate']:.3f}"
        mean = "–" if r["mean_quality"] is None else f"{r['mean_quality']:.3f}"
        lines.append(f"| {r['bin']} | {r['count']} | {r['successes']} | {rate} | {mean} |")
    c = summary["confusion"]
    lines += ["", "| | env success | env failure |", "|---|---|---|",
              f"| label > 0 (hold) | {c['hold_success']} | {c['hold_failure']} |",
              f"| label = 0 (fail) | {c['fail_success']} | {c['fail_failure']} |", "",
              f"accuracy {c['accuracy']:.3f}, precision {c['precision']:.3f}, recall {c['recall']:.3f}; "
              f"{summary['successes_on_another_parcel']} successes delivered another parcel than the labelled one", "",
              "| failures the label predicted to hold | picks |", "|---|---|"]
    if "seal_difference" in summary:
        d = summary["seal_difference"]
        lines[-3:-3] = [f"label seal vs the env's judged seal on {d['picks']} predicted holds: mean |difference| "
                        f"{d['mean_abs']:.3f}, 90th percentile {d['p90_abs']:.3f}", ""]
    lines += [f"| {k} | {v} |" for k, v in summary["missed_failures"].items()]
    if "by_cover" in summary:
        lines += ["", "| parcel picked | picks | success rate | ROC-AUC | label > 0 | of which failed |",
                  "|---|---|---|---|---|---|"]
        for name, row in summary["by_cover"].items():
            rate = "–" if row["success_rate"] is None else f"{row['success_rate']:.3f}"
            lines.append(f"| {name} (another parcel rests on it: {name == 'covered'}) | {row['picks']} | {rate} | "
                         f"{format_interval(row['auc'], 3)} | {row['hold']} | {row['hold_failure']} |")
        lines += ["", "ROC-AUC if the cup also carried the load resting on the parcel (first-order estimate, "
                      f"`resting_load_quality`): {format_interval(summary['auc_resting_load'], 3)}"]
    lines += ["", "| successes the label predicted to fail, zeroed by | picks |", "|---|---|"]
    lines += [f"| {k} | {v} |" for k, v in summary["successes_predicted_to_fail"].items()]
    lines += ["", "| all failures | picks | of which label = 0 |", "|---|---|---|"]
    lines += [f"| {k} | {v} | {summary['failures_predicted'].get(k, 0)} |" for k, v in summary["failures_all"].items()]
    return "\n".join(lines)


def require_matplotlib(arg: str = "--plot") -> None:
    """Fail early, in one line, when the [report] extra is missing."""
    try:
        import matplotlib  # noqa: F401
    except ImportError as exc:
        raise UsageError(f"{arg} needs matplotlib, the [report] extra: pip install 'parcelpick[report]'") from exc


def plot(records: list[dict[str, Any]], summary: dict[str, Any], path: str | Path) -> None:
    """Reliability (success rate per label bin, with counts) beside the ROC curve."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    q = np.array([r["quality"] for r in records], dtype=np.float64)
    y = np.array([r["success"] for r in records], dtype=bool)
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4.2))
    rows = [r for r in summary["reliability"] if r["count"]]
    x = [r["mean_quality"] for r in rows]
    ax1.plot([0, 1], [0, 1], ":", color="grey", label="calibrated")
    ax1.plot(x, [r["success_rate"] for r in rows], "o-", label="env success rate")
    for xi, r in zip(x, rows):
        ax1.annotate(f"n={r['count']}", (xi, r["success_rate"]), textcoords="offset points", xytext=(4, -12),
                     fontsize=8)
    ax1.set(xlabel="physical label (bin mean)", ylabel="success rate", xlim=(-0.03, 1.03), ylim=(-0.03, 1.03),
            title="Reliability")
    ax1.legend(loc="lower right")
    thresholds = np.r_[np.inf, np.unique(q)[::-1]]
    tpr = [(q[y] >= t).mean() if y.any() else np.nan for t in thresholds]
    fpr = [(q[~y] >= t).mean() if (~y).any() else np.nan for t in thresholds]
    ax2.plot([0, 1], [0, 1], ":", color="grey")
    ax2.plot(np.r_[fpr, 1.0], np.r_[tpr, 1.0], "-")
    ax2.set(xlabel="false positive rate", ylabel="true positive rate",
            title=f"ROC, AUC {format_interval(summary['auc'], 3)}")
    fig.suptitle(f"physical label vs env success, {summary['picks']} random picks")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


# ------------------------------------------------------------------------------------------------ command
def evaluate(config: LabelPhysicsConfig, progress: bool = True, picks_path: Path | None = None
             ) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """Run every pick (appending each job's records to ``picks_path`` as JSON lines as they come) and summarise."""
    records: list[dict[str, Any]] = []
    started = time.perf_counter()
    handle = open(picks_path, "w") if picks_path is not None else None
    try:
        for job_records in parallel_map(run_job, plan_jobs(config), workers=config.workers, desc="label_physics",
                                        progress=progress):
            records.extend(job_records)
            if handle is not None:
                handle.writelines(json.dumps(r) + "\n" for r in job_records)
                handle.flush()
    finally:
        if handle is not None:
            handle.close()
    summary = summarise(records)
    summary["wall_seconds"] = time.perf_counter() - started
    return records, summary


def read_picks(path: Path) -> list[dict[str, Any]]:
    with open(path) as handle:
        return [json.loads(line) for line in handle if line.strip()]


def _camera_size(text: str) -> tuple[int, int]:
    try:
        width, height = (int(v) for v in text.lower().split("x"))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT (e.g. 320x240), got {text!r}") from exc
    return width, height


def build_parser() -> argparse.ArgumentParser:
    d = LabelPhysicsConfig()
    p = argparse.ArgumentParser(prog="python -m eval.label_physics", description=__doc__.split("\n\n")[0])
    p.add_argument("--picks", type=int, default=d.picks, help="random candidate picks in all")
    p.add_argument("--layout", nargs="+", choices=LAYOUTS, default=list(d.layouts), help="layouts (default: all)")
    p.add_argument("--objects", nargs="+", choices=OBJECT_SETS, default=list(d.objects),
                   help="object sets (default: all); picks are balanced over layout x object set")
    p.add_argument("--parcels", type=int, default=d.num_parcels, help="parcels per pile")
    p.add_argument("--picks-per-reset", type=int, default=d.picks_per_reset,
                   help="picks per episode (the label is recomputed on the current pile before each)")
    p.add_argument("--camera", type=_camera_size, default=d.camera_size, help="camera WIDTHxHEIGHT")
    p.add_argument("--seed", type=int, default=d.seed)
    p.add_argument("--workers", type=int, default=d.workers, help="local worker processes")
    p.add_argument("--out", type=Path, default=Path("results/label_physics.json"), help="results JSON")
    p.add_argument("--plot", type=Path, default=None, help="write the reliability and ROC figure here (.png)")
    p.add_argument("--from-picks", type=Path, default=None,
                   help="summarise the pick records of an earlier (or partial) run instead of running picks")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    for flag, value, hi in (("--picks", args.picks, None), ("--picks-per-reset", args.picks_per_reset, None),
                            ("--workers", args.workers, None), ("--parcels", args.parcels, MAX_PARCELS)):
        if value < 1 or (hi is not None and value > hi):
            usage_exit(parser.prog, f"{flag} must be in [1, {hi}], got {value}" if hi else
                       f"{flag} must be >= 1, got {value}")
    try:  # every argument and path is checked before the first pile is built
        config = LabelPhysicsConfig(picks=args.picks, layouts=tuple(dict.fromkeys(args.layout)),
                                    objects=tuple(dict.fromkeys(args.objects)), num_parcels=args.parcels,
                                    picks_per_reset=args.picks_per_reset, seed=args.seed, workers=args.workers,
                                    camera_size=args.camera)
        check_output_path(args.out, "--out")
        if args.plot is not None:
            if args.plot.suffix.lower() != ".png":
                raise UsageError(f"--plot {args.plot} must be a .png path")
            check_output_path(args.plot, "--plot")
            require_matplotlib()
        if args.from_picks is not None:
            check_input_file(args.from_picks, "--from-picks")
    except ValueError as exc:  # UsageError, or a bad LabelPhysicsConfig field (named)
        usage_exit(parser.prog, f"{exc}")
    if args.from_picks is not None:
        records = read_picks(args.from_picks)
        summary = summarise(records)
        picks_path = args.from_picks
    else:
        picks_path = args.out.with_suffix(".picks.jsonl")
        records, summary = evaluate(config, progress=not args.quiet, picks_path=picks_path)
        summary["config"] = {k: v for k, v in dataclasses.asdict(config).items() if k != "env_kwargs"}
    print(format_report(summary))
    # the summary only: every pick's record is in the picks file (JSON lines), which --from-picks reads back
    args.out.write_text(json.dumps({**summary, "picks_file": str(picks_path)}, indent=1))
    print(f"\nwrote {args.out}")
    if args.plot is not None:
        plot(records, summary, args.plot)
        print(f"wrote {args.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
