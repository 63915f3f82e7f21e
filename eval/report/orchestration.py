"""What the report runs: every policy's AP and clearance, the ablations, and the provenance of what was run.

Nothing here formats anything: ``run_report`` returns the plain dict that ``eval.report.markdown`` renders
and the JSON dump stores. A policy that cannot be built, or fails while being evaluated, becomes a reason
in that dict instead of stopping the other runs.
"""

from __future__ import annotations

import datetime as _dt
import json
import sys
import traceback
import warnings
from collections.abc import Callable, Sequence
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

from eval.paper_results import TABLE_IV_STEPS
from eval.report.config import (
    DIFFUSION,
    HEADLINE_QUALITY,
    PAPER_COMPAT_POLICIES,
    PAPER_COMPAT_VARIANTS,
    APVariant,
    ReportConfig,
    label,
)
from eval.report.seed_runs import seed_mean_ap
from parcelpick_env.parallel import parallel_map
from eval.report.variants import TRAINED_VARIANTS, TrainedVariant


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


def _ap_config(variant: APVariant | None):
    """The eval.ap protocol of one (quality, NMS) variant (None: SuctionNet's), all else at APConfig's defaults."""
    from eval.ap import APConfig

    if variant is None:
        return APConfig()
    return APConfig(quality=variant.quality, **({} if variant.nms_radius is None else
                                                 {"nms_radius": variant.nms_radius}))


def _policy_ap(policy: Any, why: str | None, what: str, config: ReportConfig,
               variant: APVariant | None = None) -> tuple[Any, str | None]:
    """(AP result, None), or (None, why) when the policy could not be built or its evaluation failed."""
    from eval.ap import evaluate_ap

    if policy is None:
        return None, why
    return _guarded(f"AP of {what}", lambda: evaluate_ap(policy, config.test_data, scenes=config.ap_scenes,
                                                         config=_ap_config(variant), progress=config.progress))


def _entry(name: str) -> dict[str, Any]:
    return {"name": name, "label": label(name), "status": "ok", "reason": None,
            "ap": None, "ap_error": None, "ap_by_quality": {}, "ap_errors": {},
            "clearance": None, "clearance_error": None}


def evaluate_policy_ap(name: str, config: ReportConfig) -> dict[str, Any]:
    """A report entry with the policy's AP under every ``config.ap_qualities`` definition (``ap_by_quality``;
    ``ap`` is the headline suctionnet one) filled in, or why not; never raises."""
    entry = _entry(name)
    policy, why = load_policy(name, **_policy_kwargs(name, config))
    if policy is None:
        entry.update(status="not available", reason=why)
        return entry
    for quality in config.ap_qualities:
        print(f"[report] AP of {name} on {config.test_data}, quality {quality}", file=sys.stderr)
        result, error = _policy_ap(policy, None, f"{name} ({quality})", config,
                                   APVariant(quality, f"quality {quality}", quality=quality))
        entry["ap_by_quality"][quality] = result
        if error is not None:
            entry["ap_errors"][quality] = error
    entry["ap"] = entry["ap_by_quality"].get(HEADLINE_QUALITY)
    entry["ap_error"] = entry["ap_errors"].get(HEADLINE_QUALITY)
    return entry


def evaluate_paper_compat(config: ReportConfig, policies: dict[str, dict[str, Any]]) -> list[dict[str, Any]]:
    """The paper-compatible rows: each of ``PAPER_COMPAT_POLICIES`` in the report, under every
    ``PAPER_COMPAT_VARIANTS`` protocol; variant (a) reuses the policy's suctionnet AP. Never raises."""
    rows = []
    for name in PAPER_COMPAT_POLICIES:
        entry = policies.get(name)
        if entry is None:
            continue
        row = {"name": name, "label": entry.get("label", label(name)), "status": "ok", "reason": None,
               "results": {}, "errors": {}}
        if entry.get("ap") is None:
            row.update(status="not available", reason=entry.get("reason") or entry.get("ap_error")
                       or "no suctionnet AP")
            rows.append(row)
            continue
        policy, why = load_policy(name, **_policy_kwargs(name, config))
        for variant in PAPER_COMPAT_VARIANTS:
            if variant.quality == HEADLINE_QUALITY and variant.nms_radius is None:
                result, error = entry["ap"], None
            else:
                result, error = _policy_ap(policy, why, f"{name} ({variant.name}, paper-compatible)", config,
                                           variant)
            row["results"][variant.name] = result
            if error is not None:
                row["errors"][variant.name] = error
        rows.append(row)
    return rows


def read_label_physics(path: str | Path) -> dict[str, Any] | None:
    """``eval/label_physics.py``'s summary (ROC-AUC of the physical label against the env's verdict, with its
    interval, per layout, and the confusion at label > 0), or None when it was not measured; one reason if the file
    cannot be used."""
    path = Path(path)
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text())
        auc = data["auc"]
        found = {"path": str(path), "auc": float(auc["estimate"]), "low": float(auc["low"]),
                 "high": float(auc["high"]), "picks": int(data["picks"]),
                 "by_layout": {k: float(v["estimate"]) for k, v in data.get("auc_by_layout", {}).items()},
                 "confusion": data.get("confusion"), "error": None}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        return {"path": str(path), "auc": None, "error": f"not an eval/label_physics.py summary ({_reason(exc)})"}
    plot = path.with_suffix(".png")
    found["plot"] = str(plot) if plot.is_file() else None
    return found


def evaluate_policy_clearance(name: str, config: ReportConfig, objects: tuple[str, ...] | None = None,
                              layouts: tuple[str, ...] | None = None) -> tuple[Any, str | None]:
    """(clearance summary, None) or (None, why) on the shared seeds, over the config's grid or a part of it."""
    from eval.clearance import ClearanceConfig, evaluate_clearance

    print(f"[report] clearance of {name}", file=sys.stderr)
    clearance = ClearanceConfig(policy=name, objects=objects or config.objects, layouts=layouts or config.layouts,
                                episodes=config.episodes, num_parcels=config.parcels, seed=config.seed,
                                workers=config.workers, backend=config.backend, ray_address=config.ray_address,
                                checkpoint=_policy_kwargs(name, config).get("checkpoint"),
                                audit_picks=config.audit_picks)
    return _guarded(f"clearance of {name}", lambda: evaluate_clearance(clearance, progress=config.progress))


def finish_entry(entry: dict[str, Any], config: ReportConfig) -> dict[str, Any]:
    """Mark an entry failed when nothing it was asked for produced a number."""
    if entry["status"] == "ok" and entry["ap"] is None and (config.skip_clearance or entry["clearance"] is None):
        entry.update(status="failed", reason=entry["ap_error"] or entry["clearance_error"])
    return entry


def evaluate_policy(name: str, config: ReportConfig) -> dict[str, Any]:
    """AP on the test scenes and clearance on the shared seeds for one policy; never raises."""
    entry = evaluate_policy_ap(name, config)
    if entry["status"] == "ok" and not config.skip_clearance and config.clearance_from is None:
        entry["clearance"], entry["clearance_error"] = evaluate_policy_clearance(name, config)
    return finish_entry(entry, config)


def ablation_run_dir(variant: TrainedVariant, seed: int, config: ReportConfig) -> Path:
    return Path(config.ablation_dir) / variant.name / f"seed{seed}"


def train_command(variant: TrainedVariant, config: ReportConfig, seed: int) -> str:
    data = config.train_data if variant.train_split is None else variant.train_split.path
    return " ".join([".venv/bin/python -m policies.diffusion.train", "--data", data, "--out",
                     str(ablation_run_dir(variant, seed, config)), *config.train_args.split(), "--seed", str(seed),
                     *variant.train_flags])


def best_validation(run_dir: Path) -> float | None:
    """The best validation top-k precision a training run logged (its best.pt's), or None without a log; a line
    cut short by a run still writing is skipped."""
    log = run_dir / "log.jsonl"
    if not log.is_file():
        return None
    values = []
    for line in log.read_text().splitlines():
        try:
            row = json.loads(line)
        except ValueError:
            continue
        if isinstance(row, dict) and isinstance(row.get("val_ap_proxy"), (int, float)):
            values.append(float(row["val_ap_proxy"]))
    return max(values) if values else None


def _file_sha256(path: Path) -> str:
    import hashlib

    return hashlib.sha256(path.read_bytes()).hexdigest()


def _run_ap_key(checkpoint: Path, config: ReportConfig) -> dict[str, Any]:
    """What one run's AP depends on: its weights, the test scenes and how many of them are scored."""
    from policies.provenance import manifest_sha256

    return {"checkpoint_sha256": _file_sha256(checkpoint), "test_data_manifest_sha256": manifest_sha256(config.test_data),
            "ap_scenes": config.ap_scenes, "quality": HEADLINE_QUALITY}


def run_ap(job: tuple[str, ReportConfig]) -> tuple[dict[str, Any] | None, str | None]:
    """(AP, None) or (None, why) of one trained ablation run; kept beside its checkpoint (``ap.json``) and reused
    while the weights, the test scenes and the scene count are the same. A pool worker's job: picklable."""
    checkpoint, config = Path(job[0]), job[1]
    cache = checkpoint.with_name("ap.json")
    key = _run_ap_key(checkpoint, config)
    if cache.is_file():
        try:
            stored = json.loads(cache.read_text())
        except ValueError:
            stored = None
        if isinstance(stored, dict) and stored.get("key") == key:
            return stored["ap"], None
    policy, why = load_policy(DIFFUSION, checkpoint=str(checkpoint))
    ap, error = _policy_ap(policy, why, f"ablation {checkpoint.parent}", config)
    if ap is not None:
        text = json.dumps({"key": key, "ap": ap})
        ap = json.loads(text)["ap"]  # as a later read of the cache gives it (lists, not tuples)
        partial = cache.with_suffix(".json.partial")
        partial.write_text(text)
        partial.replace(cache)  # never a half-written cache
    return ap, error


def variant_config(variant: TrainedVariant, config: ReportConfig) -> ReportConfig:
    """The report's settings with the variant's own test split, where it has one."""
    return config if variant.test_split is None else replace(config, test_data=variant.test_split.path)


def _trained_runs(variant: TrainedVariant, config: ReportConfig) -> list[dict[str, Any]]:
    """One entry per seed: its checkpoint, command, test split and best validation figure; ``status`` 'not trained'
    without a checkpoint, 'failed' when its own test split is missing, else 'pending' until ``evaluate_ablations``
    fills in its AP."""
    test = variant_config(variant, config).test_data
    missing_test = None
    if variant.test_split is not None and not Path(test).is_dir():
        missing_test = f"its test split {test} is missing: generate it with `{variant.test_split.command()}`"
    runs = []
    for seed in config.ablation_seeds:
        run_dir = ablation_run_dir(variant, seed, config)
        checkpoint = run_dir / "best.pt"
        status = "not trained" if not checkpoint.is_file() else "failed" if missing_test else "pending"
        runs.append({"seed": seed, "checkpoint": str(checkpoint), "command": train_command(variant, config, seed),
                     "test_data": test, "val_ap_proxy": best_validation(run_dir), "ap": None,
                     "reason": missing_test if status == "failed" else None, "status": status})
    return runs


ABLATION_PARTS = ("main", "trained")  # the rows that read the main checkpoint, and those of variants trained apart
MAIN_ABLATION_KINDS = ("inference_steps", "same_as_inference")  # the kinds of row the 'main' part gives


def evaluate_ablations(config: ReportConfig, main_ap: dict[str, Any] | None = None,
                       part: str | None = None) -> list[dict[str, Any]]:
    """Inference-step counts on the main checkpoint (no retraining), then every trained variant found, per seed.

    ``main_ap``: the main Diffusion-Suction AP already computed on the same scenes, reused for the row
    whose step count is the trained one instead of running it twice. A trained variant's ``ap`` is the mean over
    its measured seeds (``seed_runs.seed_mean_ap``); each seed's own result is under ``runs``.
    ``part`` 'main' gives only the rows that read the main checkpoint (the step counts, and the step-count variants
    that are the same network), 'trained' only the others: a new main checkpoint re-runs the first alone
    (``merge_ablations`` puts them back in order). None: all.
    """
    if part is not None and part not in ABLATION_PARTS:
        raise ValueError(f"part must be one of {ABLATION_PARTS} or None, got {part!r}")
    rows: list[dict[str, Any]] = []
    base, why = load_policy(DIFFUSION, **_policy_kwargs(DIFFUSION, config))
    trained_with = int(base.config.inference_steps) if base is not None else None
    for k in (() if part == "trained" else config.ablation_steps):
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
        row = {"name": variant.name, "kind": "trained", "description": variant.description,
               "paper": list(variant.paper) if variant.paper else None, "ap": None, "reason": None, "runs": [],
               "baseline": variant.baseline, "test_data": variant_config(variant, config).test_data}
        reads_main = variant.steps is not None and step_free and variant.steps in config.ablation_steps
        if reads_main != (part == "main") and part is not None:
            continue
        if reads_main:
            found = sampled.get(variant.steps)
            row.update(kind="same_as_inference", checkpoint=config.diffusion_checkpoint or "(shipped)", command=None,
                       ap=None if found is None else found["ap"], status="ok" if found else "failed",
                       reason=f"the main network sampled with {variant.steps} steps: its training never runs the "
                              f"sampler, as map_loss_weight = 0" if found else
                              f"the main network sampled with {variant.steps} steps has no AP")
            rows.append(row)
            continue
        row["runs"] = _trained_runs(variant, config)
        rows.append(row)
    pending = [run for row in rows for run in row.get("runs", []) if run["status"] == "pending"]
    jobs = [(run["checkpoint"], replace(config, test_data=run["test_data"])) for run in pending]
    results = parallel_map(run_ap, jobs, workers=config.workers,
                           backend=config.backend, ray_address=config.ray_address, desc="ablation AP",
                           progress=config.progress)
    for run, (ap, error) in zip(pending, results):
        run.update(ap=ap, status="ok" if ap is not None else "failed", reason=error)
    for row in rows:
        if row["kind"] != "trained":
            continue
        runs = row["runs"]
        measured = [run for run in runs if run["ap"] is not None]
        if measured:
            row["ap"] = seed_mean_ap([run["ap"] for run in measured], [run["seed"] for run in measured])
        if len(measured) == len(runs):
            row["status"] = "ok"
        elif measured:
            row["status"] = f"{len(measured)} of {len(runs)} seeds measured"
        else:
            row["status"] = "not trained" if all(r["status"] == "not trained" for r in runs) else "failed"
        failed = [f"seed {r['seed']}: {r['reason']}" for r in runs if r["status"] == "failed"]
        row["reason"] = "; ".join(failed) or None
    return rows


def merge_ablations(main: Sequence[dict[str, Any]], trained: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """``evaluate_ablations``'s rows from its two parts: the step counts first, then the variants in
    ``TRAINED_VARIANTS`` order, each from whichever part measured it."""
    by_name = {row["name"]: row for row in [*main, *trained]}
    steps = [row for row in main if row.get("kind") == "inference_steps"]
    return steps + [by_name[v.name] for v in TRAINED_VARIANTS if v.name in by_name]


def run_report(config: ReportConfig) -> dict[str, Any]:
    if not Path(config.test_data).is_dir():
        raise FileNotFoundError(f"test data directory {config.test_data} does not exist")
    source = None if config.clearance_from is None else load_clearance_source(config.clearance_from)
    policies = {name: evaluate_policy(name, config) for name in config.policies}
    if source is not None:
        reuse_clearance(policies, source, config)
    main_ap = policies.get(DIFFUSION, {}).get("ap")
    return {"generated": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "config": asdict(config), "policies": policies,
            "clearance_source": None if source is None else {
                "path": config.clearance_from, "generated": source.get("generated"),
                **{k: source.get("config", {}).get(k) for k in ("episodes", "parcels", "seed")}},
            "ablations": [] if config.skip_ablations else evaluate_ablations(config, main_ap),
            "paper_compat": [] if config.skip_paper_compat else evaluate_paper_compat(config, policies),
            "label_physics": read_label_physics(config.label_physics),
            "table_one": None if config.graspnet_root is None else evaluate_table_one(config),
            "provenance": provenance(config)}


def evaluate_table_one(config: ReportConfig) -> dict[str, Any]:
    """Table I (eval/table_one.py) for the report's policies that are among its rows, or the one line saying the
    data is absent; a policy that cannot be made is left out with its reason. Never raises."""
    from eval.table_one import POLICIES, absent_line, present_test_scenes, table_one_section

    if not present_test_scenes(config.graspnet_root):  # before any policy is loaded
        return {"absent": absent_line(config.graspnet_root)}
    made = {name: load_policy(name, **_policy_kwargs(name, config)) for name in config.policies if name in POLICIES}
    policies = {name: policy for name, (policy, _) in made.items() if policy is not None}
    if not policies:
        return {"error": f"none of {list(POLICIES)} could be made: "
                         + "; ".join(f"{name}: {why}" for name, (_, why) in made.items())}
    result, error = _guarded("Table I", lambda: table_one_section(
        config.graspnet_root, policies,
        progress=(lambda line: print(f"[report] Table I {line}", file=sys.stderr)) if config.progress else None))
    if result is None:
        return {"error": error}
    result["not_available"] = {name: why for name, (policy, why) in made.items() if policy is None}
    return result


def load_report_json(path: str, flag: str) -> dict[str, Any]:
    """An earlier report's JSON dump (``write_report``), read before anything runs: one clear error naming the
    command-line ``flag`` that gave it if unusable."""
    import json

    try:
        source = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise ValueError(f"{flag} {path}: not a readable report JSON ({exc})") from exc
    if not isinstance(source, dict) or not isinstance(source.get("policies"), dict):
        raise ValueError(f"{flag} {path}: not a report JSON (no 'policies')")
    return source


def load_clearance_source(path: str) -> dict[str, Any]:
    """The report whose clearance ``--clearance-from`` reuses (``load_report_json``)."""
    return load_report_json(path, "--clearance-from")


def reuse_clearance(policies: dict[str, dict[str, Any]], source: dict[str, Any], config: ReportConfig) -> None:
    """Fill each entry's clearance from ``source`` (by policy name); a policy it lacks says so."""
    for name, entry in policies.items():
        old = source["policies"].get(name, {}).get("clearance")
        if old is None:
            entry["clearance_error"] = f"not in {config.clearance_from}"
        else:
            entry["clearance"] = old
        finish_entry(entry, config)


def provenance(config: ReportConfig) -> dict[str, dict[str, Any]]:
    """Where each evaluated checkpoint came from (``policies.provenance``), by policy name."""
    from policies.provenance import checkpoint_provenance, shipped_provenance

    records = {name: rec for name, rec in shipped_provenance().items() if name in config.policies}
    if config.diffusion_checkpoint and DIFFUSION in config.policies:
        records[DIFFUSION] = checkpoint_provenance(config.diffusion_checkpoint)
    return records
