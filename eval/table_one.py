"""The paper's Table I: every policy on SuctionNet-1Billion's test splits, by camera, Top-50 and Top-1.

    python -m eval.table_one --graspnet-root DIR
    python -m eval.table_one --graspnet-root DIR --camera realsense --scenes 2 --views 4      # a quick run
    python -m eval.table_one --graspnet-root DIR --checkpoint diffusion=runs/sn_realsense/best.pt \\
        --out results/table_one.json --markdown results/TABLE_ONE.md

For each split (seen / similar / novel: ``dataset.suctionnet.layout.TEST_SPLITS``, scenes 100-129, 130-159,
160-189) and camera, each view is read straight from the tree (``dataset.suctionnet.reader.read_view``: nothing
is imported or cached) and every policy is scored on it by ``eval.ap.evaluate_scene`` under the ``suctionnet``
quality definition, on the view's own SuctionNet models (``dataset.scene_record.scene_from_record``). As suctionnetAPI does,
a scene's precision curve is the mean of its views' curves and a split's figures the mean over its scenes
(``eval.metrics.aggregate_ap``), so the bootstrap 95% intervals resample scenes, not the correlated views of one
scene. Where DIR is absent or holds no test scene, one line says so and the command exits 0.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dataset.suctionnet.convert import split_views
from dataset.suctionnet.layout import CAMERAS, SPLITS, TEST_SPLITS, SuctionNetLayoutError, is_suctionnet_root
from dataset.suctionnet.reader import ReaderConfig, read_view
from eval.ap import APConfig, evaluate_scene
from eval.metrics import SceneAP, aggregate_ap
from eval.paper_results import METHOD_LABELS, TABLE_I
from eval.stats import format_interval
from policies.base import Policy

POLICIES: tuple[str, ...] = ("diffusion", "normal_std", "dexnet", "cao")  # the paper's Table I rows
# Top-50 and Top-1, each with the paper's three columns, as keys of an aggregate_ap result.
TOPS: dict[str, tuple[str, ...]] = {"Top-50": ("AP", "AP0.8", "AP0.4"), "Top-1": ("top1_AP", "top1_AP0.8",
                                                                                  "top1_AP0.4")}
COLUMNS = ("AP", "AP0.8", "AP0.4")
QUALITIES = ("suctionnet", "paper_compat")  # definitions that need no masses (SuctionNet has none)


def absent_line(root: str | Path | None) -> str:
    return f"SuctionNet-1Billion not present at {root}: Table I not produced"


@dataclass(frozen=True)
class TableOneConfig:
    """What one Table I run covers; ``scenes`` / ``views`` limit it for a quick run (None: all present)."""

    graspnet_root: str
    cameras: tuple[str, ...] = CAMERAS
    splits: tuple[str, ...] = tuple(TEST_SPLITS)
    scenes: int | None = None  # the first N scenes of each split
    views: int | None = None  # N annotation ids per scene, evenly spaced over those present
    ap: APConfig = field(default_factory=APConfig)
    reader: ReaderConfig = field(default_factory=ReaderConfig)

    def __post_init__(self) -> None:
        unknown = [c for c in self.cameras if c not in CAMERAS] + [s for s in self.splits if s not in TEST_SPLITS]
        if unknown or not self.cameras or not self.splits:
            raise ValueError(f"TableOneConfig: cameras must be among {list(CAMERAS)} and splits among "
                             f"{list(TEST_SPLITS)}, got {list(self.cameras)} / {list(self.splits)}")
        for name in ("scenes", "views"):
            value = getattr(self, name)
            if value is not None and (not isinstance(value, int) or value < 1):
                raise ValueError(f"TableOneConfig.{name} must be a positive int or None, got {value!r}")
        if self.ap.quality not in QUALITIES:
            raise ValueError(f"TableOneConfig.ap.quality must be one of {QUALITIES} (SuctionNet objects have no "
                             f"masses), got {self.ap.quality!r}")


def present_test_scenes(root: str | Path | None) -> list[int]:
    """Scene ids of the test range (100-189) with a view of either camera under ``root``; [] if none or no tree."""
    if root is None or not is_suctionnet_root(root):
        return []
    test = SPLITS["test"]
    return [s for s in test if any((Path(root) / "scenes" / f"scene_{s:04d}" / c / "meta").is_dir() for c in CAMERAS)]


def plan_views(root: str | Path, camera: str, split: str, scenes: int | None = None, views: int | None = None
               ) -> dict[int, list[int]]:
    """{scene: annotation ids} of ``split`` ('seen', 'similar', 'novel') for ``camera``: the first ``scenes``
    scenes, each with ``views`` ids evenly spaced over those present; {} if the split has none."""
    try:
        pairs = split_views(root, camera, TEST_SPLITS[split])
    except SuctionNetLayoutError:
        return {}
    plan: dict[int, list[int]] = {}
    for scene, ann_id in pairs:
        plan.setdefault(scene, []).append(ann_id)
    chosen = list(plan)[:scenes] if scenes is not None else list(plan)
    out = {}
    for scene in chosen:
        ids = plan[scene]
        if views is not None and views < len(ids):
            ids = [ids[i] for i in np.unique(np.linspace(0, len(ids) - 1, views).round().astype(int))]
        out[scene] = ids
    return out


def _figures(aggregate: dict[str, Any]) -> dict[str, Any]:
    """The Top-50 / Top-1 figures of an aggregate_ap result, their intervals and per-scene values."""
    keys = [key for top in TOPS.values() for key in top]
    return {**{key: aggregate[key] for key in keys}, "num_scenes": aggregate["num_scenes"],
            "intervals": {key: aggregate["intervals"][key] for key in keys},
            "per_scene": {key: aggregate["per_scene"][key] for key in keys}}


def evaluate_split(policies: Mapping[str, Policy], root: str | Path, camera: str, plan: Mapping[int, Sequence[int]],
                   config: TableOneConfig, progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Each policy's figures over ``plan``'s scenes: a scene's curve is the mean of its views' (suctionnetAPI)."""
    curves: dict[str, list[SceneAP]] = {name: [] for name in policies}
    view = 0
    for scene, ann_ids in plan.items():
        per_view: dict[str, list[SceneAP]] = {name: [] for name in policies}
        for ann_id in ann_ids:
            record = read_view(root, scene, camera, ann_id, config.reader)
            for name, policy in policies.items():
                policy.reset(seed=config.ap.seed + view)
                scene_curves, summary = evaluate_scene(policy, record, config.ap,
                                                       np.random.default_rng([config.ap.seed, view]))
                per_view[name].append(scene_curves["AP"])
                if progress is not None:
                    progress(f"{camera} scene {scene} view {ann_id}: {name} AP {summary['AP']:.1f}")
            view += 1
        for name, views in per_view.items():
            curves[name].append(SceneAP(precision=np.mean([c.precision for c in views], axis=0),
                                        thresholds=views[0].thresholds, num_predictions=sum(c.num_predictions
                                                                                            for c in views)))
    return {name: _figures(aggregate_ap(scene_curves)) for name, scene_curves in curves.items()}


def run_table_one(config: TableOneConfig, policies: Mapping[str, Policy],
                  progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Every (camera, split) cell for ``policies``; a cell whose split has no views there is recorded as such."""
    started = time.perf_counter()
    cells: dict[str, dict[str, Any]] = {}
    for camera in config.cameras:
        cells[camera] = {}
        for split in config.splits:
            plan = plan_views(config.graspnet_root, camera, split, config.scenes, config.views)
            if not plan:
                cells[camera][split] = {"status": "no views", "scenes": [], "views": 0}
                continue
            cells[camera][split] = {"status": "ok", "scenes": list(plan), "views": sum(map(len, plan.values())),
                                    "policies": evaluate_split(policies, config.graspnet_root, camera, plan,
                                                               config, progress)}
    return {"graspnet_root": str(config.graspnet_root), "config": asdict(config), "policies": list(policies),
            "quality": config.ap.quality, "cells": cells, "seconds": time.perf_counter() - started,
            "paper": {"|".join(key): list(value) for key, value in TABLE_I.items()}}


def _paper_cells(camera: str, split: str, top: str, name: str) -> list[str]:
    values = TABLE_I.get((camera, split, top, name))
    return [f"{v:.2f}" for v in values] if values is not None else ["–"] * len(COLUMNS)


def format_markdown(result: dict[str, Any]) -> str:
    """One table per camera and Top-k: a row per policy (ours, with intervals) and the paper's beside it."""
    splits = [s for s in TEST_SPLITS if s in result["config"]["splits"]]
    lines = [f"SuctionNet-1Billion at `{result['graspnet_root']}`, quality `{result['quality']}` on each view's own "
             "models; a scene is the mean of its views, [95% bootstrap interval over scenes]."]
    for camera, cells in result["cells"].items():
        if all(cells[s]["status"] == "no views" for s in splits):
            lines += ["", f"**{camera}**: no test views in this tree."]
            continue
        for top, keys in TOPS.items():
            lines += ["", f"**{camera}, {top}**", "",
                      "| method | " + " | ".join(f"{s} {c}" for s in splits for c in COLUMNS) + " |",
                      "|---|" + "---|" * (len(splits) * len(COLUMNS))]
            for name in result["policies"]:
                ours = []
                for split in splits:
                    cell = cells[split]
                    figures = cell.get("policies", {}).get(name)
                    ours += ([format_interval(figures["intervals"][k]) for k in keys] if figures else
                             [cell["status"]] * len(keys))
                lines.append(f"| {METHOD_LABELS.get(name, name)} | " + " | ".join(ours) + " |")
                paper = [c for split in splits for c in _paper_cells(camera, split, top, name)]
                lines.append(f"| {METHOD_LABELS.get(name, name)} (paper) | " + " | ".join(paper) + " |")
            counts = ", ".join(f"{s} {len(cells[s]['scenes'])} scenes / {cells[s]['views']} views" for s in splits)
            lines.append(f"\n{counts}.")
    return "\n".join(lines)


def table_one_section(root: str | Path | None, policies: Mapping[str, Policy], config: TableOneConfig | None = None,
                      progress: Callable[[str], None] | None = None) -> dict[str, Any]:
    """For the report: the Table I result, or ``{"absent": line}`` where ``root`` holds no test scene."""
    if not present_test_scenes(root):
        return {"absent": absent_line(root)}
    return run_table_one(config or TableOneConfig(graspnet_root=str(root)), policies, progress)


def build_parser() -> argparse.ArgumentParser:
    d = APConfig()
    p = argparse.ArgumentParser(prog="python -m eval.table_one", description=__doc__.split("\n\n")[0])
    p.add_argument("--graspnet-root", required=True, help="GraspNet-1Billion root with SuctionNet-1Billion's labels")
    p.add_argument("--camera", nargs="+", choices=CAMERAS, default=list(CAMERAS))
    p.add_argument("--splits", nargs="+", choices=list(TEST_SPLITS), default=list(TEST_SPLITS))
    p.add_argument("--policies", nargs="+", default=list(POLICIES), help="registered policy names")
    p.add_argument("--checkpoint", action="append", default=[], metavar="POLICY=PATH",
                   help="weights for a learned policy (repeatable); the shipped ones when omitted")
    p.add_argument("--scenes", type=int, default=None, help="first N scenes of each split (all when omitted)")
    p.add_argument("--views", type=int, default=None, help="N views per scene, evenly spaced (all 256 when omitted)")
    p.add_argument("--points", type=int, default=ReaderConfig().num_points, help="points read per view")
    p.add_argument("--quality", choices=QUALITIES, default=d.quality)
    p.add_argument("--seed", type=int, default=d.seed)
    p.add_argument("--out", type=Path, default=None, help="results JSON")
    p.add_argument("--markdown", type=Path, default=None, help="the tables as markdown")
    p.add_argument("--quiet", action="store_true", help="no per-view progress on stderr")
    return p


def main(argv: list[str] | None = None) -> int:
    from parcelpick_env.cli import check_output_path, check_policy, usage_exit

    parser = build_parser()
    args = parser.parse_args(argv)
    if not present_test_scenes(args.graspnet_root):
        print(absent_line(args.graspnet_root))
        return 0
    try:
        for path, flag in ((args.out, "--out"), (args.markdown, "--markdown")):
            if path is not None:
                check_output_path(path, flag)
        checkpoints = dict(item.split("=", 1) for item in args.checkpoint if "=" in item)
        if len(checkpoints) != len(args.checkpoint) or set(checkpoints) - set(args.policies):
            raise ValueError(f"--checkpoint takes POLICY=PATH for one of {args.policies}, got {args.checkpoint}")
        config = TableOneConfig(graspnet_root=args.graspnet_root, cameras=tuple(args.camera),
                                splits=tuple(args.splits), scenes=args.scenes, views=args.views,
                                ap=APConfig(quality=args.quality, seed=args.seed),
                                reader=ReaderConfig(num_points=args.points, seed=args.seed))
        policies = {name: check_policy(name, checkpoints.get(name), arg="--policies",
                                       checkpoint_arg=f"--checkpoint {name}")
                    for name in args.policies}
    except ValueError as exc:  # UsageError from the checks, or a bad config field
        usage_exit(parser.prog, exc)
    progress = None if args.quiet else (lambda line: print(line, file=sys.stderr))
    result = run_table_one(config, policies, progress)
    result["checkpoints"] = {name: checkpoints.get(name, "shipped") for name in policies}
    text = format_markdown(result)
    print(text)
    for path, content in ((args.out, json.dumps(result)), (args.markdown, "# Table I\n\n" + text + "\n")):
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(content)
            print(f"wrote {path}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    from parcelpick_env.cli import run_cli

    sys.exit(run_cli(main))
