"""Offline AP of a policy on stored test scenes (SuctionNet-1Billion's protocol; docs/protocols.md).

    python eval/ap.py --policy normal_std --data data/test --scenes 100 --out results/normal_std_ap.json
    python -m eval.ap --policy diffusion --data data/test --checkpoint runs/diffusion/best.pt
    python -m eval.ap --policy diffusion --data data/test --quality physical   # would the picks hold in the env?
    python -m eval.ap --policy oracle --data data/test     # the label oracle: the best stored labels
    python -m eval.ap --policy cao --data data/test --dump runs/dumps/cao        # SuctionNet N x 7 files
    python -m eval.ap --predictions runs/dumps/cao --data data/test             # score a dump, any code base's

Per scene: the policy sees an observation rebuilt from the stored capture (the labelled cloud, RGB-D
and calibration; never the labels; the privileged ``oracle`` alone is given the stored labels, and submits the
best-labelled points). Its candidates go through NMS (0.02 m), each is assigned to the nearest true parcel
surface (none farther than ``max_distance``: such a prediction scores 0), the 10 best per parcel are kept, and
every kept candidate is re-scored online on the TRUE meshes, rebuilt from the stored asset ids and poses, by the
shared suction scorer under the chosen quality definition (``--quality``, ``parcelpick_env/suction/quality.py``):
``suctionnet`` (SuctionNet's evaluator: seal x wrench x collision), ``physical`` (the env's cup, real masses,
Dex-Net's ring conditions), or ``paper_compat`` (SuctionNet's lenient label-time wrench; with ``--nms-radius
0.00002`` also the NMS of the public Diffusion_Suction test script: how a 94-point AP can arise). ``AP+vis`` multiplies in each parcel's
visibility, as the paper does for parcel scenes. ``eval.metrics`` turns the ranked qualities into AP.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

if __package__ in (None, ""):  # run as a script: make the repository root importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from dataset.scene_record import bin_from_record, require_keys, scene_from_record  # noqa: E402
from dataset.storage import Record, ShardedDataset, open_dataset  # noqa: E402
from eval.metrics import (  # noqa: E402
    DEFAULT_MAX_K,
    DEFAULT_THRESHOLDS,
    SceneAP,
    aggregate_ap,
    scene_ap,
    select_predictions,
)
from eval.stats import format_interval  # noqa: E402
from eval.suctionnet_format import from_suctionnet, read_view, to_suctionnet, view_path, write_view  # noqa: E402
from parcelpick_env.assets.library import AssetLibrary  # noqa: E402
from parcelpick_env.cli import (  # noqa: E402
    POLICY_ARG,
    UsageError,
    add_policy_arg,
    check_input_dir,
    check_output_path,
    check_policy,
    parse_policy_args,
    run_cli,
    usage_exit,
)
from parcelpick_env.scene.scene import Scene  # noqa: E402
from parcelpick_env.suction.quality import AP_DEFINITIONS, check_definition, definition_scorer, score_definition  # noqa: E402
from parcelpick_env.suction.visibility import object_visibility  # noqa: E402
from policies.base import Candidates, Policy  # noqa: E402
from policies.postprocess import select_candidates  # noqa: E402

# m: the NMS of the public Diffusion_Suction test script, which passes a 0.02 radius with coordinates in mm
# (the report's paper-compatible row: --quality paper_compat --nms-radius 0.00002)
PAPER_COMPAT_NMS_RADIUS = 2e-5
# The AP's q = 1 ceiling and every AP figure's components: quality drops each channel in turn (docs/protocols.md).
CHANNELS = ("seal", "wrench", "collision")
# What the evaluator reads from each stored scene (dataset/annotate.py writes them).
# The bin is the cell's known geometry, as in the env's info['workspace'], not ground truth about the pile.
OBSERVATION_KEYS = ("points", "normals", "rgb", "depth", "intrinsics", "extrinsics", "bin_spec")


@dataclass(frozen=True)
class APConfig:
    """Protocol constants; the defaults are SuctionNet's."""

    quality: str = "suctionnet"  # AP_DEFINITIONS
    nms_radius: float = 0.02
    max_distance: float = 0.005  # m: a prediction farther than this from every true parcel surface scores 0
    per_object: int = 10
    max_k: int = DEFAULT_MAX_K
    thresholds: tuple[float, ...] = DEFAULT_THRESHOLDS
    candidates: int = 1024  # top_k asked of the policy, before NMS and the per-object cap
    num_points: int | None = None  # cloud size shown to the policy; None: the policy's own, else all stored
    seed: int = 0

    def __post_init__(self) -> None:
        check_definition(self.quality, AP_DEFINITIONS, "APConfig.quality")
        if not self.nms_radius >= 0:
            raise ValueError(f"APConfig.nms_radius must be >= 0, got {self.nms_radius!r}")
        if not self.max_distance > 0:
            raise ValueError(f"APConfig.max_distance must be > 0, got {self.max_distance!r}")
        for name in ("per_object", "max_k", "candidates"):
            if getattr(self, name) < 1:
                raise ValueError(f"APConfig.{name} must be >= 1, got {getattr(self, name)!r}")
        if self.num_points is not None and self.num_points < 1:
            raise ValueError(f"APConfig.num_points must be >= 1 or None, got {self.num_points!r}")
        if self.seed < 0:
            raise ValueError(f"APConfig.seed must be >= 0, got {self.seed!r}")
        if not self.thresholds or any(not 0 <= t <= 1 for t in self.thresholds):
            raise ValueError(f"APConfig.thresholds must be non-empty and in [0, 1], got {self.thresholds!r}")


def observation_from_record(record: Record, num_points: int | None, rng: np.random.Generator
                            ) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """The env-style (obs, info) of a stored capture; the cloud is resampled to ``num_points``.

    ``info`` holds what the env gives policies: the camera, and the bin as ``workspace``.
    """
    require_keys(record, OBSERVATION_KEYS, "scene record")
    points = np.asarray(record["points"], dtype=np.float32)
    normals = np.asarray(record["normals"], dtype=np.float32)
    if num_points is not None and num_points != len(points):
        pick = rng.choice(len(points), size=num_points, replace=num_points > len(points))
        points, normals = points[pick], normals[pick]
    depth = np.asarray(record["depth"], dtype=np.float32)
    obs = {"points": points, "normals": normals, "rgb": np.asarray(record["rgb"], dtype=np.uint8),
           "depth": depth[..., None] if depth.ndim == 2 else depth}
    info = {"intrinsics": np.asarray(record["intrinsics"], dtype=np.float64),
            "extrinsics": np.asarray(record["extrinsics"], dtype=np.float64),
            "workspace": bin_from_record(record).workspace()}
    return obs, info


def _checked(candidates: Candidates, policy: Policy) -> Candidates:
    """Reject malformed predictions with the policy's name rather than failing inside the scorer."""
    pts, nrm, scores = (np.asarray(a, dtype=np.float64) for a in (candidates.points, candidates.normals,
                                                                  candidates.scores))
    if pts.ndim != 2 or pts.shape[1] != 3 or nrm.shape != pts.shape or scores.shape != (len(pts),):
        raise ValueError(f"policy {policy.name!r} returned candidates of shapes {pts.shape}, {nrm.shape}, "
                         f"{scores.shape}")
    norms = np.linalg.norm(nrm, axis=1)
    if not (np.all(np.isfinite(pts)) and np.all(np.isfinite(scores)) and np.all(np.abs(norms - 1) < 1e-2)):
        raise ValueError(f"policy {policy.name!r} returned non-finite candidates or non-unit normals")
    return Candidates(points=pts.astype(np.float32), normals=(nrm / norms[:, None]).astype(np.float32),
                      scores=scores.astype(np.float32))


def _policy_num_points(policy: Policy) -> int | None:
    """The cloud size a policy was built for (``num_points`` on it or its config), if it declares one."""
    for owner in (policy, getattr(policy, "config", None)):
        value = getattr(owner, "num_points", None)
        if isinstance(value, (int, np.integer)) and value > 0:
            return int(value)
    return None


# The label set whose stored score the label oracle ranks by, per quality definition (docs/labels.md, "Label sets").
LABEL_SET_OF_QUALITY = {"suctionnet": "paper", "paper_compat": "paper", "physical": "physical"}


def label_score_key(record: Record, quality: str) -> str:
    """The stored score matching ``quality``: the main ``score`` if its set is the one wanted, else ``score_<set>``
    if the record carries that set too, else the main ``score`` (older records: the paper's labels)."""
    wanted = LABEL_SET_OF_QUALITY[quality]
    main = str(record["label_set"]) if "label_set" in record else "paper"
    return "score" if main == wanted or f"score_{wanted}" not in record else f"score_{wanted}"


def label_observation(record: Record, quality: str = "suctionnet") -> dict[str, np.ndarray]:
    """The AP's privileged channel (``policies.oracle.LABEL_KEYS``): the stored labelled points and the stored label
    score of the set matching ``quality``. Given to privileged policies only (the registered ``oracle``)."""
    require_keys(record, ("points", "normals", "score"), "scene record")
    return {"labelled_points": np.asarray(record["points"], dtype=np.float32),
            "labelled_normals": np.asarray(record["normals"], dtype=np.float32),
            "label_score": np.asarray(record[label_score_key(record, quality)], dtype=np.float32)}


def predict_scene(policy: Policy, record: Record, config: APConfig, rng: np.random.Generator) -> Candidates:
    """The policy's checked candidates for one stored capture (world frame, descending score)."""
    if getattr(policy, "privileged", False):
        return _checked(policy.predict(label_observation(record, config.quality), {}, top_k=config.candidates), policy)
    num_points = config.num_points or _policy_num_points(policy)
    obs, info = observation_from_record(record, num_points, rng)
    return _checked(policy.predict(obs, info, top_k=config.candidates), policy)


def evaluate_scene(policy: Policy, record: Record, config: APConfig, rng: np.random.Generator,
                   library: AssetLibrary | None = None) -> tuple[dict[str, SceneAP], dict[str, Any]]:
    """AP curves and a per-scene summary for one stored scene."""
    return score_scene(predict_scene(policy, record, config, rng), record, config, library)


def _visibility(record: Record, scene: Scene) -> np.ndarray:
    if "object_visibility" in record:
        return np.asarray(record["object_visibility"], dtype=np.float64)
    depth = np.asarray(record["depth"])  # older records: recompute with the same rays the labels used
    return np.asarray(object_visibility(scene.world_meshes(), np.asarray(record["intrinsics"], dtype=np.float64),
                                        np.asarray(record["extrinsics"], dtype=np.float64), depth.shape[1],
                                        depth.shape[0], occluders=scene.bin.meshes()), dtype=np.float64)


def score_scene(candidates: Candidates, record: Record, config: APConfig,
                library: AssetLibrary | None = None) -> tuple[dict[str, SceneAP], dict[str, Any]]:
    """The protocol on given candidates (a policy's, or read from a SuctionNet dump): NMS, assignment (with the
    distance cutoff), the per-object cap, re-scoring on the true meshes under ``config.quality``, and the precision
    curves. Curves: ``"AP"`` (seal x wrench x collision), ``"AP+vis"`` (times visibility), ``"ceiling"`` (q = 1 on
    every slot the protocol can keep), and ``"without_<channel>"`` (that channel left out: what it costs)."""
    kept = select_candidates(candidates.points, candidates.normals, candidates.scores, top_k=len(candidates),
                             nms_radius=config.nms_radius)
    scene = scene_from_record(record, library)
    scorer = definition_scorer(config.quality, scene)
    object_ids, distances = scorer.nearest_object(kept.points)
    chosen = select_predictions(kept.points, kept.normals, kept.scores, object_ids, per_object=config.per_object)
    categories = np.asarray(record["object_categories"]).reshape(-1).astype(str)
    channels = {name: np.zeros(len(chosen), dtype=np.float32) for name in CHANNELS + ("visibility",)}
    on_surface = np.zeros(len(chosen), dtype=np.float32)
    if len(chosen):
        quality = score_definition(config.quality, scorer, chosen.points, chosen.normals, chosen.object_ids,
                                   visibility=_visibility(record, scene))
        channels = {name: getattr(quality, name) for name in channels}
        on_surface = (distances[chosen.index] <= config.max_distance).astype(np.float32)
    q = on_surface * channels["seal"] * channels["wrench"] * channels["collision"]
    variants = {"AP": q, "AP+vis": q * channels["visibility"]}
    for name in CHANNELS:
        variants[f"without_{name}"] = on_surface * np.prod([channels[c] for c in CHANNELS if c != name], axis=0)
    curves = {name: scene_ap(chosen.scores, values, categories=categories[chosen.object_ids],
                             scene_categories=list(categories), thresholds=config.thresholds, max_k=config.max_k)
              for name, values in variants.items()}
    curves["ceiling"] = ceiling_ap(len(categories), config)
    summary = {
        "num_objects": int(len(categories)),
        "num_candidates": int(len(candidates)),
        "num_after_nms": int(len(kept)),
        "num_scored": int(len(chosen)),
        "num_off_surface": int(len(chosen) - on_surface.sum()),
        "AP": 100.0 * float(curves["AP"].precision.mean()),
        "AP+vis": 100.0 * float(curves["AP+vis"].precision.mean()),
        "mean_quality": float(q.mean()) if len(q) else 0.0,
        "mean_components": {name: float(v.mean()) for name, v in channels.items()} if len(chosen) else {},
    }
    return curves, summary


def ceiling_ap(num_objects: int, config: APConfig) -> SceneAP:
    """The q = 1 ceiling of one scene: ``per_object`` perfect predictions on each of its parcels, and no more (the
    protocol keeps no more), so P@k = min(k, per_object * parcels) / k."""
    slots = config.per_object * num_objects
    return scene_ap(np.ones(slots), np.ones(slots), thresholds=config.thresholds, max_k=config.max_k)


def _open(data_dir: str | os.PathLike) -> ShardedDataset:
    path = Path(data_dir)
    if not path.is_dir():
        raise FileNotFoundError(f"dataset directory {path} does not exist")
    return open_dataset(path)


PREDICTIONS_PREFIX = "predictions:"  # the name a scored dump is reported under


def evaluate_ap(policy: Policy | str | None, data_dir: str | os.PathLike, scenes: int | None = None,
                config: APConfig = APConfig(), progress: bool = False, dump_dir: str | os.PathLike | None = None,
                predictions_dir: str | os.PathLike | None = None) -> dict[str, Any]:
    """Run the protocol on the first ``scenes`` stored scenes (all by default); return the results dict.

    ``policy`` is a Policy or a registered name; or None with ``predictions_dir``, a SuctionNet-format dump
    (``eval.suctionnet_format``) whose per-view predictions are scored instead, the best ``config.candidates``
    of each view, as a policy is asked for. ``dump_dir`` writes every scene's predictions in that format.
    Keys: everything ``aggregate_ap`` returns for the quality without visibility (``AP``, ``AP0.4``, ``AP0.8``,
    ``top1_*``, ``intervals``, ``per_scene``, ``per_category``, ...); ``AP+vis`` and ``with_visibility`` (the same
    figures with visibility multiplied in); ``ceiling`` (the figures at q = 1 on every slot the protocol keeps);
    ``channel_cost`` (AP with each channel left out, minus AP: what it costs); plus ``quality``, ``policy``,
    ``data``, ``split``, ``config``, ``seconds`` and ``scenes`` (one summary per scene, with its stored ``index``,
    the unit paired comparisons match on).
    """
    if (policy is None) == (predictions_dir is None):
        raise ValueError("evaluate_ap needs exactly one of a policy and predictions_dir")
    if isinstance(policy, str):
        policy = _make_policy(policy, None)
    if predictions_dir is not None and not Path(predictions_dir).is_dir():
        raise FileNotFoundError(f"predictions directory {predictions_dir} does not exist")
    store = _open(data_dir)
    try:
        total = len(store) if scenes is None else min(int(scenes), len(store))
        if total < 1:
            raise ValueError(f"nothing to evaluate: {data_dir} holds {len(store)} scenes, asked for {scenes}")
        split = str(store.config.get("split") or "test")
        per_scene, summaries = [], []
        started = time.perf_counter()
        for i in range(total):
            t0 = time.perf_counter()
            record = store.scene(i)
            index = int(store.scene_indices[i])
            extrinsics = np.asarray(record["extrinsics"], dtype=np.float64)
            if policy is not None:
                policy.reset(seed=config.seed + i)
                candidates = predict_scene(policy, record, config, np.random.default_rng([config.seed, i]))
            elif predictions_dir is not None:  # (checked above: exactly one of the two is set)
                path = view_path(predictions_dir, index, split)
                read = from_suctionnet(read_view(path), extrinsics, where=str(path))
                candidates = Candidates(read.points[: config.candidates], read.normals[: config.candidates],
                                        read.scores[: config.candidates])
            if dump_dir is not None:
                write_view(view_path(dump_dir, index, split), to_suctionnet(candidates, extrinsics))
            curves, summary = score_scene(candidates, record, config)
            summary.update(index=index, seconds=time.perf_counter() - t0)
            per_scene.append(curves)
            summaries.append(summary)
            if progress:
                print(f"scene {i + 1}/{total}: AP {summary['AP']:.1f} ({summary['num_scored']} scored, "
                      f"{summary['seconds']:.1f} s)", file=sys.stderr)
    finally:
        store.close()
    result = aggregate_ap([c["AP"] for c in per_scene])
    with_vis = aggregate_ap([c["AP+vis"] for c in per_scene])
    result["with_visibility"] = _headline(with_vis, per_scene=True)
    result["AP+vis"] = with_vis["AP"]
    result["intervals"]["AP+vis"] = with_vis["intervals"]["AP"]
    result["ceiling"] = _headline(aggregate_ap([c["ceiling"] for c in per_scene]))
    result["channel_cost"] = {name: aggregate_ap([c[f"without_{name}"] for c in per_scene])["AP"] - result["AP"]
                              for name in CHANNELS}
    result["quality"] = config.quality
    name = policy.name if policy is not None else PREDICTIONS_PREFIX + str(predictions_dir)
    result.update(policy=name, data=str(data_dir), split=store.config.get("split"),
                  config=dataclasses.asdict(config),
                  seconds=time.perf_counter() - started, scenes=summaries)
    if dump_dir is not None:
        result["dump"] = str(dump_dir)
    return result


def _headline(aggregate: dict[str, Any], per_scene: bool = False) -> dict[str, Any]:
    """The scalar figures and their intervals of an ``aggregate_ap`` result (and its per-scene values if asked)."""
    keys = [k for k, v in aggregate.items() if isinstance(v, float)] + ["num_scenes", "intervals"]
    return {k: aggregate[k] for k in keys + (["per_scene"] if per_scene else [])}


def format_table(result: dict[str, Any]) -> str:
    """Markdown table: overall and per category, in percent."""
    columns = [("AP", "AP"), ("AP0.8", "AP0.8"), ("AP0.4", "AP0.4"), ("AP+vis", "AP+vis"), ("top1_AP", "Top-1 AP"),
               ("top1_AP0.8", "Top-1 AP0.8"), ("top1_AP0.4", "Top-1 AP0.4"), ("num_scenes", "scenes")]
    lines = [f"Offline AP of {result.get('policy', '?')} on {result.get('data', '?')}, quality "
             f"`{result.get('quality', '?')}`; [95% bootstrap interval over scenes]", "",
             "| subset | " + " | ".join(title for _, title in columns) + " |",
             "|---|" + "---|" * len(columns)]
    rows = [("overall", result)] + list(result.get("per_category", {}).items())
    if "ceiling" in result:
        rows.append(("q = 1 ceiling", result["ceiling"]))
    for name, row in rows:
        intervals = row.get("intervals", {})
        cells = [str(row.get(key, "-")) if key == "num_scenes" else
                 (format_interval(intervals[key]) if key in intervals else f"{row[key]:.2f}" if key in row else "-")
                 for key, _ in columns]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    if "channel_cost" in result:
        costs = ", ".join(f"{name} {-cost:+.2f}" for name, cost in result["channel_cost"].items())
        lines += ["", f"What each channel costs (AP with it, minus AP without it): {costs}"]
    return "\n".join(lines)


def _make_policy(name: str, checkpoint: str | None) -> Policy:
    from policies.registry import make_policy

    kwargs = {"checkpoint": checkpoint} if checkpoint else {}
    return make_policy(name, **kwargs)


def build_parser() -> argparse.ArgumentParser:
    d = APConfig()
    p = argparse.ArgumentParser(prog="python -m eval.ap", description=__doc__.split("\n\n")[0])
    p.add_argument("--policy", default=None, help="registered policy name (policies/registry.py); 'oracle' is the "
                   "label oracle (the best stored labels)")
    p.add_argument("--quality", default=d.quality, choices=AP_DEFINITIONS,
                   help="what a good suction is (docs/protocols.md): SuctionNet's evaluator, the env's physics, or "
                   "the paper-compatible row")
    p.add_argument("--nms-radius", type=float, default=d.nms_radius,
                   help=f"m (SuctionNet: 0.02; the public Diffusion_Suction script in effect {PAPER_COMPAT_NMS_RADIUS})")
    p.add_argument("--max-distance", type=float, default=d.max_distance,
                   help="m: predictions farther than this from every true surface score 0")
    p.add_argument("--predictions", type=Path, default=None,
                   help="score a SuctionNet-format dump (<dir>/<split>/scene_XXXX/...) instead of a policy")
    p.add_argument("--dump", type=Path, default=None,
                   help="write every scene's predictions here in SuctionNet-1Billion's per-view N x 7 format")
    p.add_argument("--data", required=True, type=Path, help="dataset directory (python -m dataset.generate)")
    p.add_argument("--scenes", type=int, default=None, help="evaluate only the first N scenes")
    p.add_argument("--out", type=Path, default=None, help="write the results JSON here")
    p.add_argument("--checkpoint", default=None, help="weights for learned policies")
    add_policy_arg(p)
    p.add_argument("--candidates", type=int, default=d.candidates, help="top_k asked of the policy")
    p.add_argument("--num-points", type=int, default=None, help="cloud size shown to the policy")
    p.add_argument("--seed", type=int, default=d.seed)
    p.add_argument("--quiet", action="store_true", help="no per-scene progress on stderr")
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.scenes is not None and args.scenes < 1:
        usage_exit(parser.prog, f"--scenes must be >= 1, got {args.scenes}")
    if (args.policy is None) == (args.predictions is None):
        usage_exit(parser.prog, "give exactly one of --policy and --predictions")
    try:  # every path and the policy are checked before the first scene is read; each error is one line
        check_input_dir(args.data, "--data (dataset directory)")
        if args.predictions is not None:
            check_input_dir(args.predictions, "--predictions")
        if args.out is not None:
            check_output_path(args.out, "--out")
        if args.dump is not None:
            check_output_path(args.dump, "--dump", directory=True)
        config = APConfig(quality=args.quality, nms_radius=args.nms_radius, max_distance=args.max_distance,
                          candidates=args.candidates,
                          num_points=args.num_points, seed=args.seed)
        policy_kwargs = parse_policy_args(args.policy_arg)
        if policy_kwargs and args.policy is None:
            raise UsageError(f"{POLICY_ARG} needs --policy")
        policy = None if args.policy is None else check_policy(args.policy, args.checkpoint, **policy_kwargs)
    except ValueError as exc:  # UsageError from the checks, or a bad APConfig field
        usage_exit(parser.prog, exc)
    try:
        result = evaluate_ap(policy, args.data, scenes=args.scenes, config=config, progress=not args.quiet,
                             dump_dir=args.dump, predictions_dir=args.predictions)
    except (ValueError, FileNotFoundError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    if policy_kwargs:
        result["policy_kwargs"] = policy_kwargs  # what the policy was made with, beside its name
    print(format_table(result))
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=2))
        print(f"\nwrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
