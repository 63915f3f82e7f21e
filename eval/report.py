"""One report for every policy: offline AP (Table II), closed-loop clearance (Table V) and the
Diffusion-Suction ablations (Tables III and IV), each beside the paper's numbers, with plots and a JSON dump.

    python -m eval.report --test-data data/test --ap-scenes 100 --episodes 2 --out results/RESULTS.md

Every policy sees the same held-out test scenes and the same clearance seeds. A policy that cannot be
built (no checkpoint, not implemented) is listed as 'not available: <reason>'; one that fails while
being evaluated is listed as 'failed: <reason>'; neither stops the report. The numbers are whatever
the runs give: the text lists every gap to the paper as it is.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import sys
import traceback
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable

if __package__ in (None, ""):  # allow `python eval/report.py` as well as `python -m eval.report`
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from eval.clearance import LAYOUTS, OBJECT_SETS, OUTCOMES  # noqa: E402
from eval.paper_results import (METHOD_LABELS, TABLE_II_TOP1, TABLE_II_TOP50, TABLE_III_ABLATION,  # noqa: E402
                                TABLE_IV_STEPS, TABLE_V)
from parcelpick_env.parallel import BACKENDS  # noqa: E402

DEFAULT_POLICIES: tuple[str, ...] = ("diffusion", "cao", "normal_std", "dexnet", "random", "sb3")
AP_METRICS: tuple[str, ...] = ("AP", "AP0.8", "AP0.4")  # the paper's Table II columns, in its order
DIFFUSION = "diffusion"


def _train_args(steps: int) -> str:
    """The shipped Diffusion-Suction run's training flags at ``steps`` optimisation steps."""
    return f"--preset cpu --steps {steps} --batch-size 4 --lr 1e-3 --seed 0 --threads 1 --workers 0"


# How the shipped Diffusion-Suction checkpoint was trained (README, "Reproducing the checkpoints").
MAIN_TRAIN_ARGS = _train_args(5000)
# The trained ablations: the main run's settings on a shorter, matched budget (one hour each would not fit a
# 2-core day); the 'reference' variant changes nothing, so each ablation is read against it, not the main model.
ABLATION_TRAIN_ARGS = _train_args(1000)


@dataclass(frozen=True)
class TrainedVariant:
    """A Diffusion-Suction ablation that needs its own training run (runs/ablations/<name>/best.pt)."""

    name: str
    description: str
    train_flags: tuple[str, ...]
    paper: tuple[float, ...] | None  # (AP, AP0.8, AP0.4[, ms]) from the paper's Table III / IV
    steps: int | None = None  # the DDIM step count a step-count variant trains and samples with


TRAINED_VARIANTS: tuple[TrainedVariant, ...] = (
    TrainedVariant("reference", "reference: the main settings at the ablation budget", (),
                   TABLE_III_ABLATION["full"]),
    TrainedVariant("no_segment_levers", "w/o surface-segment lever arms (not in the paper)", ("--no-segment-levers",),
                   None),
    TrainedVariant("no_normals", "w/o normals", ("--no-normals",), TABLE_III_ABLATION["no_normals"]),
    TrainedVariant("no_visibility", "w/o visibility", ("--no-visibility",), TABLE_III_ABLATION["no_visibility"]),
    TrainedVariant("pointnet", "PointNet encoder", ("--encoder", "pointnet"), TABLE_III_ABLATION["pointnet"]),
    *(TrainedVariant(f"steps{k}", f"trained and sampled with {k} DDIM steps", ("--inference-steps", str(k)),
                     TABLE_IV_STEPS[(k, k)], steps=k) for k in (5, 10, 15)),
)


@dataclass(frozen=True)
class ReportConfig:
    test_data: str
    policies: tuple[str, ...] = DEFAULT_POLICIES
    ap_scenes: int | None = None  # None: every stored test scene
    episodes: int = 1  # clearance episodes per (object set, layout) cell
    parcels: int = 8
    objects: tuple[str, ...] = OBJECT_SETS
    layouts: tuple[str, ...] = LAYOUTS
    seed: int = 0
    workers: int = 1
    backend: str = "local"
    out: str = "results/RESULTS.md"
    figures: str | None = None  # None: <out's folder>/figures
    skip_clearance: bool = False
    skip_ablations: bool = False
    diffusion_checkpoint: str | None = None  # None: the policy's shipped checkpoint
    ablation_dir: str = "runs/ablations"
    ablation_steps: tuple[int, ...] = (5, 10, 15, 20)  # inference-only step counts on the main checkpoint
    train_data: str = "data/train"  # only printed in the training commands of missing ablations
    train_args: str = ABLATION_TRAIN_ARGS  # the same settings for every variant, so each changes one thing only
    progress: bool = True

    def __post_init__(self) -> None:
        if not self.policies:
            raise ValueError("policies must name at least one policy")
        if self.ap_scenes is not None and self.ap_scenes < 1:
            raise ValueError(f"ap_scenes must be >= 1 or None, got {self.ap_scenes}")
        if self.episodes < 1:
            raise ValueError(f"episodes must be >= 1, got {self.episodes}")
        if not 1 <= self.parcels <= 50:
            raise ValueError(f"parcels must be in [1, 50], got {self.parcels}")
        if self.seed < 0:
            raise ValueError(f"seed must be >= 0, got {self.seed}")
        if self.workers < 1:
            raise ValueError(f"workers must be >= 1, got {self.workers}")
        if self.backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {self.backend!r}")
        if any(k < 1 for k in self.ablation_steps):
            raise ValueError(f"ablation_steps must be >= 1, got {self.ablation_steps}")
        for name, values, allowed in (("objects", self.objects, OBJECT_SETS), ("layouts", self.layouts, LAYOUTS)):
            if not values or any(v not in allowed for v in values):
                raise ValueError(f"{name} must be a non-empty subset of {allowed}, got {values}")

    @property
    def figures_dir(self) -> Path:
        return Path(self.figures) if self.figures else Path(self.out).parent / "figures"


def label(name: str) -> str:
    return METHOD_LABELS.get(name, name)


def _reason(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {exc}".strip().replace("\n", " ")


def load_policy(name: str, **kwargs: Any) -> tuple[Any, str | None]:
    """(policy, None) or (None, why it cannot be built). Any error counts: the report must go on."""
    from policies.registry import make_policy

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return make_policy(name, **kwargs), None
    except Exception as exc:  # noqa: BLE001  a missing model, an unimplemented policy, a corrupt checkpoint...
        return None, _reason(exc)


def _policy_kwargs(name: str, config: ReportConfig) -> dict[str, Any]:
    return {"checkpoint": config.diffusion_checkpoint} if name == DIFFUSION and config.diffusion_checkpoint else {}


def _guarded(what: str, fn: Callable[[], Any]) -> tuple[Any, str | None]:
    """Run one evaluation; a failure becomes a reason in the report instead of losing the other runs."""
    try:
        return fn(), None
    except Exception as exc:  # noqa: BLE001
        print(f"[report] {what} failed:\n{traceback.format_exc()}", file=sys.stderr)
        return None, _reason(exc)


def _policy_ap(policy: Any, why: str | None, what: str, config: ReportConfig) -> tuple[Any, str | None]:
    """(AP result, None), or (None, why) when the policy could not be built or its evaluation failed."""
    from eval.ap import evaluate_ap

    if policy is None:
        return None, why
    return _guarded(f"AP of {what}", lambda: evaluate_ap(policy, config.test_data, scenes=config.ap_scenes,
                                                         progress=config.progress))


def evaluate_policy(name: str, config: ReportConfig) -> dict[str, Any]:
    """AP on the test scenes and clearance on the shared seeds for one policy; never raises."""
    from eval.clearance import ClearanceConfig, evaluate_clearance

    entry: dict[str, Any] = {"name": name, "label": label(name), "status": "ok", "reason": None,
                             "ap": None, "ap_error": None, "clearance": None, "clearance_error": None}
    kwargs = _policy_kwargs(name, config)
    policy, why = load_policy(name, **kwargs)
    if policy is None:
        entry.update(status="not available", reason=why)
        return entry
    print(f"[report] AP of {name} on {config.test_data}", file=sys.stderr)
    entry["ap"], entry["ap_error"] = _policy_ap(policy, None, name, config)
    if not config.skip_clearance:
        print(f"[report] clearance of {name}", file=sys.stderr)
        clearance = ClearanceConfig(policy=name, objects=config.objects, layouts=config.layouts,
                                    episodes=config.episodes, num_parcels=config.parcels, seed=config.seed,
                                    workers=config.workers, backend=config.backend,
                                    checkpoint=kwargs.get("checkpoint"))
        entry["clearance"], entry["clearance_error"] = _guarded(
            f"clearance of {name}", lambda: evaluate_clearance(clearance, progress=config.progress))
    if entry["ap"] is None and (config.skip_clearance or entry["clearance"] is None):
        entry.update(status="failed", reason=entry["ap_error"] or entry["clearance_error"])
    return entry


def train_command(variant: TrainedVariant, config: ReportConfig) -> str:
    return " ".join([".venv/bin/python -m policies.diffusion.train", "--data", config.train_data, "--out",
                     str(Path(config.ablation_dir) / variant.name), *config.train_args.split(),
                     *variant.train_flags])


def evaluate_ablations(config: ReportConfig, main_ap: dict[str, Any] | None = None) -> list[dict[str, Any]]:
    """Inference-step counts on the main checkpoint (no retraining), then every trained variant found.

    ``main_ap``: the main Diffusion-Suction AP already computed on the same scenes, reused for the row
    whose step count is the trained one instead of running it twice.
    """
    rows: list[dict[str, Any]] = []
    base, why = load_policy(DIFFUSION, **_policy_kwargs(DIFFUSION, config))
    trained_with = int(base.config.inference_steps) if base is not None else None
    for k in config.ablation_steps:
        row = {"name": f"infer{k}", "kind": "inference_steps", "inference_steps": k,
               "description": f"main checkpoint, sampled with {k} DDIM steps"
                              + (f" (trained with {trained_with})" if trained_with else ""),
               "paper": list(TABLE_IV_STEPS[(trained_with, k)]) if (trained_with, k) in TABLE_IV_STEPS else None,
               "checkpoint": config.diffusion_checkpoint or "(shipped)", "command": None, "ap": None}
        if base is None:
            row.update(status="not available", reason=why)
        elif k == trained_with and main_ap is not None:
            row.update(ap=main_ap, status="ok", reason=None)
        else:
            policy, why_k = load_policy(DIFFUSION, inference_steps=k, **_policy_kwargs(DIFFUSION, config))
            row["ap"], error = _policy_ap(policy, why_k, f"diffusion with {k} steps", config)
            row.update(status="ok" if row["ap"] is not None else "failed", reason=error)
        rows.append(row)
    sampled = {row["inference_steps"]: row for row in rows if row["ap"] is not None}
    # Without the loss on the sampled map, training never runs the sampler: a model 'trained with k steps' is the
    # same network as the main one, so the step-count variants are the inference rows, not new runs.
    step_free = base is not None and base.config.map_loss_weight == 0
    for variant in TRAINED_VARIANTS:
        checkpoint = Path(config.ablation_dir) / variant.name / "best.pt"
        row = {"name": variant.name, "kind": "trained", "description": variant.description,
               "paper": list(variant.paper) if variant.paper else None, "checkpoint": str(checkpoint),
               "command": train_command(variant, config), "ap": None, "reason": None}
        if variant.steps is not None and step_free and variant.steps in sampled:
            row.update(kind="same_as_inference", checkpoint=sampled[variant.steps]["checkpoint"], command=None,
                       ap=sampled[variant.steps]["ap"], status="ok",
                       reason=f"the main network sampled with {variant.steps} steps: its training never runs the "
                              f"sampler, as map_loss_weight = 0")
        elif not checkpoint.is_file():
            row["status"] = "not trained"
        else:
            policy, why_v = load_policy(DIFFUSION, checkpoint=str(checkpoint))
            row["ap"], error = _policy_ap(policy, why_v, f"ablation {variant.name}", config)
            row.update(status="ok" if row["ap"] is not None else "failed", reason=error)
        rows.append(row)
    return rows


def run_report(config: ReportConfig) -> dict[str, Any]:
    if not Path(config.test_data).is_dir():
        raise FileNotFoundError(f"test data directory {config.test_data} does not exist")
    policies = {name: evaluate_policy(name, config) for name in config.policies}
    main_ap = policies.get(DIFFUSION, {}).get("ap")
    return {"generated": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "config": asdict(config), "policies": policies,
            "ablations": [] if config.skip_ablations else evaluate_ablations(config, main_ap)}


# ---------------------------------------------------------------------------------------------- tables

def _fmt(value: float | None) -> str:
    return "–" if value is None else f"{value:.2f}"


def _pair(ours: float | None, paper: float | None) -> str:
    return f"{_fmt(ours)} / {_fmt(paper)}"


def _unavailable(entry: dict[str, Any]) -> str | None:
    if entry["status"] == "ok":
        return None
    return f"{entry['status']}: {entry['reason']}"


def table_ii(policies: dict[str, dict[str, Any]]) -> str:
    """Paper Table II layout, every cell 'ours / paper'."""
    head = ["method"] + [f"Top-50 {m}" for m in AP_METRICS] + [f"Top-1 {m}" for m in AP_METRICS]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for name, entry in policies.items():
        ap = entry.get("ap")
        paper50, paper1 = TABLE_II_TOP50.get(name, (None,) * 3), TABLE_II_TOP1.get(name, (None,) * 3)
        method = entry.get("label", label(name))
        if ap is None:
            method += f" ({_unavailable(entry) or 'failed: ' + str(entry.get('ap_error'))})"
            cells = [_pair(None, p) for p in (*paper50, *paper1)]
        else:
            cells = [_pair(ap[m], p) for m, p in zip(AP_METRICS, paper50)]
            cells += [_pair(ap[f"top1_{m}"], p) for m, p in zip(AP_METRICS, paper1)]
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def table_v(entry: dict[str, Any], objects=OBJECT_SETS, layouts=LAYOUTS) -> str:
    """Paper Table V layout for one policy: R_grasp / R_object (%) per cell, ours beside the paper's robot."""
    summary = entry["clearance"]
    head = ["object set"] + [f"{layout} {who}" for layout in layouts for who in ("(ours)", "(paper robot)")]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for obj in objects:
        cells = []
        for layout in layouts:
            cell = summary["cells"].get(f"{obj}/{layout}")
            paper = TABLE_V.get((obj, layout))
            cells.append("–" if cell is None else f"{cell['R_grasp']:.2f} / {cell['R_object']:.2f}")
            cells.append("–" if paper is None else f"{paper[0]:.2f} / {paper[1]:.2f}")
        lines.append(f"| {obj} | " + " | ".join(cells) + " |")
    o = summary["overall"]
    lines.append(f"\nOverall (ours): R_grasp {o['R_grasp']:.2f}%, R_object {o['R_object']:.2f}% "
                 f"({o['successes']}/{o['attempts']} attempts, {o['cleared']}/{o['placed']} parcels).")
    return "\n".join(lines)


def outcome_table(policies: dict[str, dict[str, Any]]) -> str:
    """Where the attempts went, per policy: the failure modes the rates hide."""
    head = ["method", "attempts", *OUTCOMES]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for entry in policies.values():
        if entry.get("clearance") is None:
            continue
        o = entry["clearance"]["overall"]
        lines.append(f"| {entry['label']} | {o['attempts']} | "
                     + " | ".join(str(o["outcomes"].get(k, 0)) for k in OUTCOMES) + " |")
    return "\n".join(lines)


def ablation_table(rows: list[dict[str, Any]]) -> str:
    head = ["variant", "status", "AP (ours / paper)", "AP0.8", "AP0.4", "Top-1 AP (ours)"]
    lines = ["| " + " | ".join(head) + " |", "|---" * len(head) + "|"]
    for row in rows:
        paper = row.get("paper") or (None, None, None)
        ap = row.get("ap")
        if ap is None:
            status = row["status"] + (f": {row['reason']}" if row.get("reason") else "")
            if row["status"] == "not trained":
                status += f" — train with `{row['command']}`"
            cells = [_pair(None, p) for p in paper[:3]] + ["–"]
        else:
            status = "ok" + (f" ({row['reason']})" if row.get("reason") else "")
            cells = [_pair(ap[m], p) for m, p in zip(AP_METRICS, paper[:3])] + [_fmt(ap["top1_AP"])]
        lines.append(f"| {row['description']} | {status} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _gap(what: str, ours: float, paper: float) -> str:
    diff = ours - paper
    word = "above" if diff > 0 else "below" if diff < 0 else "equal to"
    return f"- {what}: ours {ours:.2f}, paper {paper:.2f} ({diff:+.2f} points, {word} the paper)."


def differences(report: dict[str, Any]) -> list[str]:
    """Every number we can set beside the paper's, and whether the methods rank as in the paper."""
    out: list[str] = []
    policies = report["policies"]
    for name, entry in policies.items():
        ap = entry.get("ap")
        if ap is None:
            if name in TABLE_II_TOP50:
                why = _unavailable(entry) or f"failed: {entry.get('ap_error')}"
                out.append(f"- {label(name)}: no AP of ours to compare ({why}).")
            continue
        for table, prefix in ((TABLE_II_TOP50, ""), (TABLE_II_TOP1, "top1_")):
            if name in table:
                for metric, paper in zip(AP_METRICS, table[name]):
                    out.append(_gap(f"{label(name)} {'Top-1' if prefix else 'Top-50'} {metric}",
                                    ap[prefix + metric], paper))
    ours = {n: e["ap"]["AP"] for n, e in policies.items() if e.get("ap") is not None and n in TABLE_II_TOP50}
    if len(ours) >= 2:
        our_rank = sorted(ours, key=lambda n: -ours[n])
        paper_rank = sorted(ours, key=lambda n: -TABLE_II_TOP50[n][0])
        same = "the same as" if our_rank == paper_rank else "NOT the same as"
        out.append(f"- Top-50 AP ranking: ours {' > '.join(map(label, our_rank))}; this is {same} the paper's "
                   f"({' > '.join(map(label, paper_rank))}).")
    diffusion = policies.get(DIFFUSION, {})
    if diffusion.get("clearance") is not None:
        for (obj, layout), (grasp, obj_rate) in TABLE_V.items():
            cell = diffusion["clearance"]["cells"].get(f"{obj}/{layout}")
            if cell is not None:
                out.append(_gap(f"Diffusion-Suction clearance {obj}/{layout} R_grasp (simulation vs real robot)",
                                cell["R_grasp"], grasp))
                out.append(_gap(f"Diffusion-Suction clearance {obj}/{layout} R_object (simulation vs real robot)",
                                cell["R_object"], obj_rate))
    for row in report.get("ablations", []):
        if row.get("ap") is not None and row.get("paper"):
            for metric, paper in zip(AP_METRICS, row["paper"][:3]):
                out.append(_gap(f"ablation '{row['description']}' {metric}", row["ap"][metric], paper))
    return out


# ---------------------------------------------------------------------------------------------- plots

def plot_precision_at_k(policies: dict[str, dict[str, Any]], path: Path) -> Path | None:
    """Mean P@k against k, one panel per quality threshold, one line per policy."""
    curves = {n: e["ap"] for n, e in policies.items() if e.get("ap") is not None and "precision_at_k" in e["ap"]}
    if not curves:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    thresholds = next(iter(curves.values()))["thresholds"]
    fig, axes = plt.subplots(1, len(thresholds), figsize=(3.6 * len(thresholds), 3.4), sharey=True, squeeze=False)
    for t, (ax, theta) in enumerate(zip(axes[0], thresholds)):
        for name, ap in curves.items():
            p = np.asarray(ap["precision_at_k"], dtype=float)
            ax.plot(np.arange(1, len(p) + 1), p[:, t], label=label(name))
        ax.set_title(f"quality ≥ {theta:g}")
        ax.set_xlabel("k")
        ax.set_ylim(0, 100)
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel("precision@k (%)")
    axes[0][-1].legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def plot_clearance(policies: dict[str, dict[str, Any]], path: Path) -> Path | None:
    """R_grasp and R_object per (object set, layout) cell: a bar per policy, hatched grey for the paper's robot."""
    runs = {n: e["clearance"] for n, e in policies.items() if e.get("clearance") is not None}
    if not runs:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    cells = [f"{o}/{la}" for o in OBJECT_SETS for la in LAYOUTS
             if any(f"{o}/{la}" in s["cells"] for s in runs.values())]
    series = [(label(n), [s["cells"].get(c) for c in cells]) for n, s in runs.items()]
    paper = [TABLE_V.get(tuple(c.split("/"))) for c in cells]
    width = 0.8 / (len(series) + 1)
    x = np.arange(len(cells))
    fig, axes = plt.subplots(2, 1, figsize=(max(6.0, 1.2 * len(cells) + 2), 6.5), sharex=True)
    for row, (ax, key) in enumerate(zip(axes, ("R_grasp", "R_object"))):
        for i, (name, values) in enumerate(series):
            ax.bar(x + i * width, [np.nan if v is None else v[key] for v in values], width, label=name)
        ax.bar(x + len(series) * width, [np.nan if p is None else p[row] for p in paper], width, color="0.75",
               hatch="//", edgecolor="0.4", label="Diffusion-Suction (paper, real robot)")
        ax.set_ylabel(f"{key} (%)")
        ax.set_ylim(0, 120)  # headroom for the legend
        ax.grid(axis="y", alpha=0.3)
    axes[1].set_xticks(x + 0.4 - width / 2, cells, rotation=30, ha="right")
    axes[0].legend(fontsize=7, ncol=2, loc="upper center")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


# ---------------------------------------------------------------------------------------------- writing

def render_markdown(report: dict[str, Any], figures: dict[str, Path | None], out: Path) -> str:
    cfg = report["config"]
    policies = report["policies"]
    lines = ["# ParcelPick evaluation report", "",
             f"Generated {report['generated']}. Offline AP on `{cfg['test_data']}` "
             f"({'all' if cfg['ap_scenes'] is None else cfg['ap_scenes']} test scenes, the same for every method); "
             + ("clearance skipped." if cfg["skip_clearance"] else
                f"clearance with {cfg['parcels']} parcels, {cfg['episodes']} episode(s) per cell, seed {cfg['seed']} "
                "(the same piles for every method)."),
             "Every cell reads **ours / paper**. Our numbers come from simulated ParcelPick scenes and the "
             "simulated robot; the paper's from its Parcel-Suction-Dataset and, for clearance, its real robot.", "",
             "## Offline AP (paper Table II layout)", "", table_ii(policies), ""]
    if figures.get("precision_at_k"):
        rel = os.path.relpath(figures["precision_at_k"], out.parent)
        lines += [f"![precision@k per policy]({rel})", ""]
    lines += ["## Closed-loop clearance (paper Table V layout)", "",
              "Entries are R_grasp / R_object (%). '(paper robot)' is the paper's real-robot Diffusion-Suction, "
              "given beside every method for reference.", ""]
    if cfg["skip_clearance"]:
        lines += ["Skipped (--skip-clearance).", ""]
    else:
        for name, entry in policies.items():
            lines.append(f"### {entry['label']}")
            lines.append("")
            if entry.get("clearance") is None:
                why = _unavailable(entry) or f"failed: {entry.get('clearance_error')}"
                lines += [why, ""]
            else:
                lines += [table_v(entry, tuple(cfg["objects"]), tuple(cfg["layouts"])), ""]
        lines += ["### Attempt outcomes", "", outcome_table(policies), ""]
        if figures.get("clearance"):
            rel = os.path.relpath(figures["clearance"], out.parent)
            lines += [f"![clearance per cell]({rel})", ""]
    lines += ["## Diffusion-Suction ablations (paper Tables III and IV)", ""]
    if cfg["skip_ablations"]:
        lines += ["Skipped (--skip-ablations).", ""]
    else:
        lines += ["Inference-step rows reuse the main checkpoint; the other rows need their own training run "
                  f"under `{cfg['ablation_dir']}/<name>/best.pt`, all with the same settings (`{cfg['train_args']}` "
                  "plus the variant's flag), so read them against the 'reference' row, not the main checkpoint, "
                  "which trained longer. The paper's DGCNN row has no counterpart here.", "",
                  ablation_table(report.get("ablations", [])), ""]
    lines += ["## Where our numbers differ from the paper's", ""]
    gaps = differences(report)
    lines += gaps if gaps else ["Nothing to compare: no run produced a number with a counterpart in the paper."]
    lines.append("")
    return "\n".join(lines)


def write_report(report: dict[str, Any], out: str | os.PathLike, figures_dir: str | os.PathLike) -> dict[str, Path]:
    """Write the plots, the markdown and the JSON dump; return their paths."""
    out, figures_dir = Path(out), Path(figures_dir)
    out.parent.mkdir(parents=True, exist_ok=True)
    figures = {"precision_at_k": plot_precision_at_k(report["policies"], figures_dir / "precision_at_k.png"),
               "clearance": plot_clearance(report["policies"], figures_dir / "clearance.png")}
    out.write_text(render_markdown(report, figures, out))
    json_path = out.with_suffix(".json")
    json_path.write_text(json.dumps({**report, "figures": {k: str(v) if v else None for k, v in figures.items()}},
                                    indent=2, default=str))
    return {"markdown": out, "json": json_path, **{k: v for k, v in figures.items() if v is not None}}


def build_parser() -> argparse.ArgumentParser:
    d = ReportConfig(test_data="")
    p = argparse.ArgumentParser(prog="python -m eval.report", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--test-data", required=True, help="held-out test scenes (python -m dataset.generate)")
    p.add_argument("--policies", nargs="+", default=list(d.policies), help="registered policy names")
    p.add_argument("--ap-scenes", type=int, default=None,
                   help="evaluate only the first N test scenes (all when omitted)")
    p.add_argument("--episodes", type=int, default=d.episodes, help="clearance episodes per cell")
    p.add_argument("--parcels", type=int, default=d.parcels, help="parcels per clearance pile")
    p.add_argument("--objects", nargs="+", default=list(d.objects), choices=OBJECT_SETS)
    p.add_argument("--layouts", nargs="+", default=list(d.layouts), choices=LAYOUTS)
    p.add_argument("--seed", type=int, default=d.seed)
    p.add_argument("--workers", type=int, default=d.workers, help="parallel clearance episodes")
    p.add_argument("--backend", default=d.backend, choices=BACKENDS)
    p.add_argument("--out", default=d.out, help="markdown report; the JSON dump goes beside it")
    p.add_argument("--figures", default=None, help="PNG folder (<out folder>/figures when omitted)")
    p.add_argument("--skip-clearance", action="store_true")
    p.add_argument("--skip-ablations", action="store_true")
    p.add_argument("--diffusion-checkpoint", default=None,
                   help="Diffusion-Suction weights (the shipped ones when omitted)")
    p.add_argument("--ablation-dir", default=d.ablation_dir, help="trained ablations: <dir>/<name>/best.pt")
    p.add_argument("--ablation-steps", nargs="+", type=int, default=list(d.ablation_steps),
                   help="DDIM step counts tried on the main checkpoint")
    p.add_argument("--train-data", default=d.train_data, help="training data named in the ablation commands")
    p.add_argument("--train-args", default=d.train_args, help="main-run training flags repeated in those commands")
    p.add_argument("--quiet", action="store_true", help="no per-scene / per-episode progress on stderr")
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not Path(args.test_data).is_dir():
        parser.error(f"test data directory {args.test_data} does not exist")
    try:
        config = ReportConfig(test_data=args.test_data, policies=tuple(args.policies), ap_scenes=args.ap_scenes,
                              episodes=args.episodes, parcels=args.parcels, objects=tuple(args.objects),
                              layouts=tuple(args.layouts), seed=args.seed, workers=args.workers,
                              backend=args.backend, out=args.out, figures=args.figures,
                              skip_clearance=args.skip_clearance, skip_ablations=args.skip_ablations,
                              diffusion_checkpoint=args.diffusion_checkpoint, ablation_dir=args.ablation_dir,
                              ablation_steps=tuple(args.ablation_steps), train_data=args.train_data,
                              train_args=args.train_args, progress=not args.quiet)
    except ValueError as exc:
        parser.error(str(exc))
    report = run_report(config)
    paths = write_report(report, config.out, config.figures_dir)
    print(Path(paths["markdown"]).read_text())
    print("wrote " + ", ".join(str(p) for p in paths.values()), file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
