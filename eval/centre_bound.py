"""How exact must a parcel's centre be? What any centre estimate can bring Diffusion-Suction's Top-50 AP.

Under SuctionNet's evaluator the wrench is the torque of a unit weight about the cup, with the lever from the cup to
the parcel's surface centroid, which a partial view does not show; the shipped model loses most of its gap to the
label oracle there (``eval/ap.py``'s ``channel_cost``). This analysis keeps the model's own seal and collision
(and visibility) channels and replaces its wrench channel by the evaluator's wrench formula about a centre taken
from the truth of each stored scene:

- ``true``: the true surface centroid of the parcel nearest each point (a bound, not a method);
- ``sigma=S``: that centroid moved horizontally by an error drawn once per parcel, N(0, S^2) on each axis: how
  good a centre estimate must be for a given AP;
- ``visible_top``: the centroid of the parcel's observed points on up-facing surfaces, each observed point given to
  its true parcel: a perfect instance segmentation that centres each parcel on what the camera shows of its top.

Reading the truth, it is an evaluation, never a policy. The ``model`` row is the shipped model as ``eval/ap.py``
scores it (same seeds), and ``label oracle`` the stored labels' best (the ceiling issue 14's goal is set against).

    python -m eval.centre_bound --data data/test
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from dataset.scene_record import scene_from_record
from eval.ap import APConfig, _open, predict_scene, score_scene
from eval.metrics import aggregate_ap
from parcelpick_env.cli import UsageError, check_input_dir, check_output_path, usage_exit
from parcelpick_env.config_checks import require, require_int, require_positive_numbers
from parcelpick_env.suction.quality import definition_config, definition_scorer
from parcelpick_env.suction.wrench import wrench_scores
from policies.base import Candidates
from policies.diffusion.policy import DiffusionSuctionPolicy
from policies.diffusion.vote_policy import WRENCH_CHANNEL
from policies.oracle import OraclePolicy
from policies.postprocess import select_candidates


@dataclass(frozen=True)
class CentreBoundConfig:
    """Which centres are scored, and what counts as a parcel's observed top."""

    sigmas: tuple[float, ...] = (0.005, 0.01, 0.015, 0.02, 0.03)  # m, per horizontal axis, drawn once per parcel
    up_cos: float = 0.9  # an observed point is on an up-facing surface where its normal's z is at least this
    on_surface: float = 0.003  # m: an observed point belongs to the nearest parcel within this distance
    min_top_points: int = 5  # a parcel showing fewer up-facing points is centred on all its observed points
    seed: int = 0  # of the per-parcel errors

    def __post_init__(self) -> None:
        owner = type(self).__name__
        require(isinstance(self.sigmas, tuple) and all(isinstance(s, (int, float)) and np.isfinite(s) and s >= 0
                                                       for s in self.sigmas), owner,
                f"sigmas must be a tuple of finite metres >= 0, got {self.sigmas!r}")
        require(-1.0 <= self.up_cos <= 1.0, owner, f"up_cos must be in [-1, 1], got {self.up_cos!r}")
        require_positive_numbers(self, ("on_surface",))
        require_int(owner, "min_top_points", self.min_top_points, lo=1)
        require_int(owner, "seed", self.seed, lo=0)


def jittered_centres(centres: np.ndarray, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """(P, 3) the centres moved horizontally by N(0, sigma^2) on x and y, one draw per parcel."""
    out = np.array(centres, dtype=np.float64, copy=True)
    out[:, :2] += rng.normal(0.0, sigma, size=(len(out), 2))
    return out


def visible_top_centres(points: np.ndarray, normals: np.ndarray, owner: np.ndarray, distance: np.ndarray,
                        num_parcels: int, config: CentreBoundConfig) -> np.ndarray:
    """(P, 3) each parcel's centroid of its observed up-facing points (``owner``: the true parcel of each point,
    within ``on_surface`` of it by ``distance``); with fewer than ``min_top_points`` of those, of all its observed
    points; with none at all, NaN (no point is ever given that parcel's centre: it owns none within reach)."""
    on = (owner >= 0) & (distance <= config.on_surface)
    up = on & (normals[:, 2] >= config.up_cos)
    out = np.full((num_parcels, 3), np.nan)
    for rows in (on, up):  # the up-facing centroid overwrites the all-points one where it has enough points
        count = np.bincount(owner[rows], minlength=num_parcels)
        sums = np.stack([np.bincount(owner[rows], points[rows, d], minlength=num_parcels) for d in range(3)], 1)
        enough = count >= (config.min_top_points if rows is up else 1)
        out[enough] = sums[enough] / count[enough, None]
    return out


class _ChannelCapture(DiffusionSuctionPolicy):
    """The shipped policy, keeping the decoded points and their sampled channels of its last prediction."""

    captured: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def quality(self, points: np.ndarray, normals: np.ndarray, features: torch.Tensor, channel_scores: np.ndarray,
                info: Mapping[str, Any] | None = None) -> np.ndarray:
        self.captured = (points, normals, channel_scores)
        return super().quality(points, normals, features, channel_scores, info)


def _centred(policy: _ChannelCapture, centres_of_points: np.ndarray, top_k: int) -> Candidates:
    """The last prediction's candidates re-ranked with the wrench channel replaced by SuctionNet's about the given
    per-point centres (a point whose parcel has no centre keeps its own position: the torque of a lever of 0)."""
    if policy.captured is None:
        raise RuntimeError("no prediction to re-rank")
    points, normals, channels = policy.captured
    centres = np.where(np.isfinite(centres_of_points), centres_of_points, points.astype(np.float64))
    wrench = wrench_scores(points.astype(np.float64), normals.astype(np.float64), centres,
                           definition_config("suctionnet"))
    score = np.delete(channels, WRENCH_CHANNEL, axis=1).prod(axis=1) * wrench
    return select_candidates(points, normals, score.astype(np.float32), top_k=top_k, nms_radius=policy.nms_radius)


def centre_bound(data_dir: str | Path, checkpoint: str | None = None, scenes: int | None = None,
                 config: CentreBoundConfig = CentreBoundConfig(), ap: APConfig = APConfig(),
                 progress: bool = True) -> dict[str, Any]:
    """Top-50 AP (``suctionnet``) of every centre variant on the first ``scenes`` stored scenes, with the shipped
    model's own row and the label oracle's; per variant the AP, its bootstrap interval, and its share of the
    label oracle's AP, plus the median horizontal error of the centres against the truth."""
    if ap.quality != "suctionnet":
        raise ValueError(f"the centre bound scores SuctionNet's wrench: APConfig.quality must be 'suctionnet', "
                         f"got {ap.quality!r}")
    policy = _ChannelCapture(checkpoint=checkpoint)
    oracle = OraclePolicy()
    rng = np.random.default_rng(config.seed)
    names = ["label oracle", "model", "true", *(f"sigma={s:g}" for s in config.sigmas), "visible_top"]
    curves: dict[str, list] = {name: [] for name in names}
    errors: dict[str, list[np.ndarray]] = {name: [] for name in names[2:]}
    store = _open(data_dir)
    try:
        total = len(store) if scenes is None else min(int(scenes), len(store))
        if total < 1:
            raise ValueError(f"nothing to score: {data_dir} holds {len(store)} scenes, asked for {scenes}")
        for i in tqdm(range(total), desc="centre bound", unit="scene", disable=not progress):
            record = store.scene(i)
            labels = predict_scene(oracle, record, ap, np.random.default_rng([ap.seed, i]))  # the best stored labels
            curves["label oracle"].append(score_scene(labels, record, ap)[0]["AP"])
            policy.reset(seed=ap.seed + i)  # eval/ap.py's seeds: the model row is its figure
            policy.captured = None
            model = predict_scene(policy, record, ap, np.random.default_rng([ap.seed, i]))
            curves["model"].append(score_scene(model, record, ap)[0]["AP"])
            scorer = definition_scorer("suctionnet", scene_from_record(record))
            truth = np.asarray(scorer.surface_centroids, dtype=np.float64).reshape(-1, 3)
            seen = np.asarray(record["points"], dtype=np.float64)
            seen_owner, seen_distance = scorer.nearest_object(seen)
            variants = {"true": truth, **{f"sigma={s:g}": jittered_centres(truth, s, rng) for s in config.sigmas},
                        "visible_top": visible_top_centres(seen, np.asarray(record["normals"], dtype=np.float64),
                                                           seen_owner, seen_distance, len(truth), config)}
            decoded = np.zeros((0, 3)) if policy.captured is None else policy.captured[0]  # none: too few points
            owner, _ = scorer.nearest_object(decoded)
            for name, centres in variants.items():
                per_point = np.where((owner >= 0)[:, None], centres[np.clip(owner, 0, None)], np.nan)
                candidates = model if policy.captured is None else _centred(policy, per_point, ap.candidates)
                curves[name].append(score_scene(candidates, record, ap)[0]["AP"])
                known = np.all(np.isfinite(centres), axis=1)
                errors[name].append(np.linalg.norm((centres - truth)[known, :2], axis=1))
    finally:
        store.close()
    aggregates = {name: aggregate_ap(c) for name, c in curves.items()}
    ceiling = aggregates["label oracle"]["AP"]
    rows = {}
    for name, agg in aggregates.items():
        interval = agg["intervals"]["AP"]
        rows[name] = {"AP": agg["AP"], "low": interval["low"], "high": interval["high"],
                      "share_of_label_oracle": agg["AP"] / ceiling if ceiling > 0 else float("nan")}
        if name in errors:
            err = np.concatenate(errors[name]) if errors[name] else np.zeros(0)
            rows[name]["median_error_m"] = float(np.median(err)) if len(err) else float("nan")
    return {"data": str(data_dir), "scenes": total, "checkpoint": checkpoint, "config": dataclasses.asdict(config),
            "ap_config": dataclasses.asdict(ap), "rows": rows}


def format_table(result: dict[str, Any]) -> str:
    lines = [f"Top-50 AP (suctionnet) on {result['scenes']} scenes of {result['data']}, the model's seal and collision "
             f"channels times the wrench about each centre:", "",
             "| centre | Top-50 AP [95% CI] | of the label oracle | median horizontal centre error |",
             "|---|---|---|---|"]
    for name, row in result["rows"].items():
        err = row.get("median_error_m")
        lines.append(f"| {name} | {row['AP']:.2f} [{row['low']:.2f}, {row['high']:.2f}] | "
                     f"{100 * row['share_of_label_oracle']:.1f}% | {'–' if err is None else f'{100 * err:.2f} cm'} |")
    return "\n".join(lines)


def build_parser() -> argparse.ArgumentParser:
    d = CentreBoundConfig()
    p = argparse.ArgumentParser(prog="python -m eval.centre_bound", description=__doc__.split("\n\n")[0])
    p.add_argument("--data", required=True, type=Path, help="dataset directory (python -m dataset.generate)")
    p.add_argument("--checkpoint", default=None, help="Diffusion-Suction weights (default: the shipped model)")
    p.add_argument("--scenes", type=int, default=None, help="score only the first N scenes")
    p.add_argument("--sigmas", type=float, nargs="+", default=list(d.sigmas),
                   help="m: per-parcel horizontal centre errors (std on each axis) to score")
    p.add_argument("--seed", type=int, default=d.seed, help="of the per-parcel errors")
    p.add_argument("--out", type=Path, default=None, help="write the results JSON here")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        check_input_dir(args.data, "--data (dataset directory)")
        if args.out is not None:
            check_output_path(args.out, "--out")
        if args.scenes is not None and args.scenes < 1:
            raise UsageError(f"--scenes must be >= 1, got {args.scenes}")
        config = CentreBoundConfig(sigmas=tuple(args.sigmas), seed=args.seed)
        if args.checkpoint is not None and not Path(args.checkpoint).is_file():
            raise UsageError(f"--checkpoint {args.checkpoint} does not exist")
    except ValueError as exc:
        usage_exit(parser.prog, exc)
    try:
        result = centre_bound(args.data, args.checkpoint, args.scenes, config, progress=not args.quiet)
    except (ValueError, FileNotFoundError, OSError) as exc:
        print(f"{parser.prog}: error: {exc}", file=sys.stderr)
        return 2
    print(format_table(result))
    if args.out is not None:
        args.out.write_text(json.dumps(result, indent=2))
        print(f"written to {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
