"""One command that regenerates every published number: ``make results`` (or ``python -m eval.results``).

It generates the held-out test scenes, optionally trains (``--train``: the ablation variants; nothing that is
shipped is ever overwritten), then runs AP and closed-loop clearance for every policy, the Diffusion-Suction
ablations and the benchmarks, and writes ``results/RESULTS.md`` (+ JSON and figures) and
``benchmarks/RESULTS.md``. Locally, or with ``--backend ray`` on a Ray cluster (clearance episodes and data
generation are spread over its CPUs).

It is resumable. The work is a list of small parts (the test data, one AP run per policy, one clearance run
per policy and cell, the ablations in two (the rows that read the main checkpoint, and the variants trained on
their own), one benchmark script each); a finished part writes its JSON under
``--work`` atomically, and a re-run skips every part whose JSON exists, so an interrupted run redoes only
what was unfinished. ``--force PREFIX`` redoes the parts whose names start with it.

``--restore RESULTS.json`` seeds the unfinished parts that do not run the pick cell (the test data, AP,
the paper-compatible rows, the ablations) from an earlier report's JSON, so that a change to the cell re-runs
only the clearance; the report names every restored part, where it came from, and whether its rows read this
report's test split (a change to the parcels generates the split anew: ``--force data/test ...``).

    python -m eval.results                       # everything, 2 local workers
    python -m eval.results --backend ray --workers 32 --ray-address auto
    python -m eval.results --list                # the parts and which are done
    python -m eval.results --restore results/RESULTS.json --force clearance   # the cell changed: clearance only
    python -m eval.results --restore results/RESULTS.json \
        --force ap/diffusion ablations/main paper_compat clearance/diffusion      # a new shipped Diffusion-Suction
"""

from __future__ import annotations

import argparse
import datetime as _dt
import json
import os
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

if __package__ in (None, ""):  # allow `python eval/results.py` as well as `python -m eval.results`
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from eval.clearance import CHECK_SETTINGS, LAYOUTS, OBJECT_SETS, EpisodeResult, summarise  # noqa: E402
from eval.report import orchestration  # noqa: E402
from eval.report.config import DEFAULT_POLICIES, DIFFUSION, PAPER_COMPAT_POLICIES, ReportConfig  # noqa: E402
from eval.report.markdown import write_report  # noqa: E402
from eval.report.splits import TEST_DATA_ARGS, TRAIN_DATA_ARGS, DataSplit, report_split_sha  # noqa: E402
from eval.report.variants import TRAINED_VARIANTS  # noqa: E402
from parcelpick_env.parallel import BACKENDS  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class ResultsConfig:
    """What ``make results`` runs; the evaluation settings are the report's (``report``)."""

    report: ReportConfig
    work: str = "runs/results"  # finished parts (JSON); ignored by git
    test_scenes: int = 64
    train_scenes: int = 1700  # only with train=True
    train: bool = False
    benchmarks: bool = True
    bench_dir: str = "benchmarks"
    force: tuple[str, ...] = ()
    restore: str | None = None  # an earlier report's JSON: its cell-independent parts seed the unfinished ones

    def __post_init__(self) -> None:
        if self.test_scenes < 1 or self.train_scenes < 1:
            raise ValueError(f"test_scenes and train_scenes must be >= 1, got {self.test_scenes}, {self.train_scenes}")
        if self.restore is not None:
            load_restore_source(self.restore, self.report)  # refused at once, before any part runs


@dataclass(frozen=True)
class Part:
    """One resumable unit of work: done when ``output`` (its JSON) exists."""

    name: str
    output: Path
    run: Callable[[], Any]
    after: tuple[str, ...] = field(default=())  # informational: the parts whose outputs it reads


def write_json_atomic(path: Path, value: Any) -> Path:
    """Write-then-rename: a part killed mid-write never looks finished."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(value, indent=1, default=str))
    os.replace(tmp, path)
    return path


def read_json(path: Path) -> Any:
    return json.loads(path.read_text())


def forced(name: str, force: Sequence[str]) -> bool:
    """Whether ``--force`` names the part ``name`` (by a prefix of it)."""
    return any(name.startswith(prefix) for prefix in force)


def run_parts(parts: Sequence[Part], force: Sequence[str] = (), log: Callable[[str], None] = print
              ) -> dict[str, str]:
    """Run every unfinished part in order; ``{name: 'ran' | 'skipped'}``. An exception stops the run (the
    finished parts stay finished)."""
    status: dict[str, str] = {}
    for part in parts:
        if part.output.is_file() and not forced(part.name, force):
            status[part.name] = "skipped"
            continue
        log(f"[results] {part.name}")
        started = time.perf_counter()
        value = part.run()
        write_json_atomic(part.output, {"part": part.name, "seconds": time.perf_counter() - started,
                                        "value": value})
        status[part.name] = "ran"
    return status


def _subprocess(argv: Sequence[str]) -> dict[str, Any]:
    done = subprocess.run([sys.executable, *argv], cwd=REPO, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"`{' '.join(argv)}` failed ({done.returncode}): {done.stderr[-2000:]}")
    return {"argv": list(argv), "stdout": done.stdout}


def _generate(out: str, scenes: int, args: Sequence[str], cfg: ResultsConfig, fresh: bool = False
              ) -> Callable[[], Any]:
    """The part that generates a data split. ``fresh`` (the part is forced): an existing set is moved aside, never
    deleted, and generated again; otherwise ``dataset.generate`` resumes it, and keeps a complete one as it is."""
    def run() -> dict[str, Any]:
        from policies.provenance import manifest_sha256

        root = Path(REPO, out)
        if fresh and root.exists():
            aside = root.with_name(f"{root.name}.replaced-{time.strftime('%Y%m%dT%H%M%S')}")
            root.rename(aside)
            print(f"[results] {out} moved to {aside} (forced: generated again)")

        argv = ["-m", "dataset.generate", "--out", out, "--scenes", str(scenes), *args,
                "--workers", str(cfg.report.workers), "--backend", cfg.report.backend, "--no-progress"]
        if cfg.report.ray_address:
            argv += ["--ray-address", cfg.report.ray_address]
        result = _subprocess(argv)
        return {"argv": result["argv"], "manifest_sha256": manifest_sha256(root)}
    return run


def _train_variant(variant, seed: int, cfg: ResultsConfig) -> Callable[[], Any]:
    def run() -> dict[str, Any]:
        command = orchestration.train_command(variant, cfg.report, seed).split()
        return _subprocess(command[command.index("-m"):])  # this interpreter, not the command's .venv path
    return run


def _ap_part(name: str, report: ReportConfig) -> Callable[[], Any]:
    return lambda: orchestration.evaluate_policy_ap(name, report)


def _clearance_part(name: str, report: ReportConfig, objects: str, layout: str, ap_part: Path
                    ) -> Callable[[], Any]:
    def run() -> dict[str, Any]:
        entry = _value(ap_part) or {}
        if entry.get("status") == "not available":  # the AP part could not build it: no episode would run
            return {"episodes": None, "error": entry.get("reason")}
        summary, error = orchestration.evaluate_policy_clearance(name, report, (objects,), (layout,))
        if summary is None:
            return {"episodes": None, "error": error}
        return {"episodes": summary["episodes"], "error": error,
                "checks": {k: summary.get(k) for k in CHECK_SETTINGS},  # as this cell ran: the report says so
                "config": summary.get("config")}  # so each episode can be rebuilt (eval/rebuild.py)
    return run


def pooled_config(configs: Sequence[dict[str, Any] | None]) -> dict[str, Any] | None:
    """One ``ClearanceConfig`` dict for a policy's cells: the cells' own, over every object set and layout they
    ran (an episode's pile seed depends on its cell, not on the grid around it); None where a cell kept none (a
    part from before configs were kept) or the cells differ in anything else."""
    ran = [c for c in configs if c is not None]
    if not ran or len(ran) < len(configs):
        return None
    rest = [{k: v for k, v in c.items() if k not in ("objects", "layouts")} for c in ran]
    if any(r != rest[0] for r in rest):
        return None
    return {**rest[0], "objects": [o for o in OBJECT_SETS if any(o in c["objects"] for c in ran)],
            "layouts": [la for la in LAYOUTS if any(la in c["layouts"] for c in ran)]}


def cell_checks(name: str, cells: Sequence[dict[str, Any]]) -> tuple[dict[str, Any], str | None]:
    """(the tool check flags a policy's finished cells ran with, None) or (unknown flags, why not one set).

    A cell finished before the cells recorded them is unknown (None, so the report claims nothing); cells that ran
    with different checks (parts kept from before the check changed, say) cannot be pooled into one row."""
    found = {json.dumps(c.get("checks"), sort_keys=True) for c in cells}
    unknown = dict.fromkeys(CHECK_SETTINGS)
    if len(found) > 1:
        shown = sorted(f.replace("null", "not recorded") for f in found)
        return unknown, (f"its cells ran with different tool checks ({'; '.join(shown)}): "
                         f"re-run them with --force clearance/{name}")
    return (json.loads(found.pop()) if found else None) or unknown, None


def _bench_part(script: Path) -> Callable[[], Any]:
    return lambda: _subprocess([str(script.relative_to(REPO))])


def _split_part(split: DataSplit) -> str:
    """A variant's own split's part: not under 'data/test' or 'data/train', which --force names alone."""
    return f"data/variants/{Path(split.path).name}"


def plan(cfg: ResultsConfig) -> list[Part]:
    """Every part, in the order they run."""
    work, r = Path(cfg.work), cfg.report
    parts = [Part("data/test", work / "data" / "test.json",
                  _generate(r.test_data, cfg.test_scenes, TEST_DATA_ARGS, cfg, forced("data/test", cfg.force)))]
    if cfg.train:
        parts.append(Part("data/train", work / "data" / "train.json",
                          _generate(r.train_data, cfg.train_scenes, TRAIN_DATA_ARGS, cfg, forced("data/train", cfg.force))))
        # The variants' own splits (more points per scene), each once however many variants read it.
        own = {split.path: split for v in TRAINED_VARIANTS for split in (v.train_split, v.test_split) if split}
        parts += [Part(_split_part(split), work / f"{_split_part(split)}.json",
                       _generate(split.path, split.scenes, split.generate_args(), cfg,
                                 forced(_split_part(split), cfg.force)))
                  for split in own.values()]
        parts += [Part(f"train/{v.name}/seed{seed}", work / "train" / v.name / f"seed{seed}.json",
                       _train_variant(v, seed, cfg), (_split_part(v.train_split) if v.train_split else "data/train",))
                  for seed in r.ablation_seeds for v in TRAINED_VARIANTS]
    parts += [Part(f"ap/{name}", work / "ap" / f"{name}.json", _ap_part(name, r), ("data/test",))
              for name in r.policies]
    if not r.skip_clearance:
        parts += [Part(f"clearance/{name}/{o}-{la}", work / "clearance" / name / f"{o}-{la}.json",
                       _clearance_part(name, r, o, la, work / "ap" / f"{name}.json"), (f"ap/{name}",))
                  for name in r.policies for o in r.objects for la in r.layouts]
    if not r.skip_paper_compat and set(PAPER_COMPAT_POLICIES) & set(r.policies):
        parts.append(Part("paper_compat", work / "paper_compat.json", lambda: _paper_compat(cfg),
                          tuple(f"ap/{name}" for name in PAPER_COMPAT_POLICIES if name in r.policies)))
    if not r.skip_ablations:  # the rows that read the main checkpoint re-run with it; the trained variants' do not
        parts += [Part("ablations/main", work / "ablations" / "main.json", lambda: _ablations(cfg, "main"),
                       (f"ap/{DIFFUSION}",)),
                  Part("ablations/trained", work / "ablations" / "trained.json", lambda: _ablations(cfg, "trained"),
                       ("data/test",))]
    if cfg.benchmarks:
        parts += [Part(f"bench/{s.stem}", work / "bench" / f"{s.stem}.json", _bench_part(s))
                  for s in sorted((REPO / cfg.bench_dir).glob("bench_*.py"))]
    return parts


def _value(path: Path) -> Any:
    return read_json(path)["value"] if path.is_file() else None


# The parts whose results do not depend on the pick cell (grasp execution, motion, holding physics): a report's
# JSON holds all of them, so --restore can seed them. Clearance and the benchmarks are never restored.
RESTORABLE = ("data/test", "ap/", "paper_compat", "ablations")
# The report settings that the restorable parts were measured under: a source that differs is refused.
RESTORE_MUST_MATCH = ("test_data", "ap_scenes", "ap_qualities", "ablation_steps", "ablation_seeds")


def _restored_value(name: str, source: dict[str, Any]) -> tuple[bool, Any]:
    """(found, the part's value) rebuilt from a report JSON; ``found`` is False where the source lacks it."""
    if name == "data/test":  # not generated here: the AP parts were measured on the source's split
        return True, {"argv": None, "manifest_sha256": report_split_sha(source)}
    if name.startswith("ap/"):
        entry = source["policies"].get(name.split("/", 1)[1])
        return entry is not None, None if entry is None else {**entry, "clearance": None, "clearance_error": None}
    if name.startswith("ablations/"):  # a report holds one list: each part takes the rows it measures
        rows = [row for row in source.get("ablations") or []
                if (row.get("kind") in orchestration.MAIN_ABLATION_KINDS) == name.endswith("/main")]
        return bool(rows), rows
    rows = source.get(name)
    return bool(rows), rows


def load_restore_source(source_path: str, config: ReportConfig) -> dict[str, Any]:
    """The report JSON at ``source_path``, or one ValueError naming it: unreadable, not a report, or measured
    with other test scenes or AP settings than ``config`` (``RESTORE_MUST_MATCH``)."""
    source = orchestration.load_report_json(source_path, "--restore")
    theirs, ours = source.get("config", {}), json.loads(json.dumps(asdict(config)))  # tuples as the JSON has them
    differ = [k for k in RESTORE_MUST_MATCH if k in theirs and theirs[k] != ours[k]]
    if differ:
        raise ValueError(f"--restore {source_path}: measured with other settings ("
                         + ", ".join(f"{k} {theirs[k]!r}, not {ours[k]!r}" for k in differ) + ")")
    return source


def restore_parts(parts: Sequence[Part], source_path: str, config: ReportConfig,
                  log: Callable[[str], None] = print) -> list[str]:
    """Seed each unfinished restorable part from the report JSON at ``source_path``; the names restored.

    Each restored part's JSON says where it came from (``restored_from``), so the report can say so too."""
    source = load_restore_source(source_path, config)
    origin = {"path": source_path, "generated": source.get("generated"),
              "test_split_sha256": report_split_sha(source)}
    restored = []
    for part in parts:
        if part.output.is_file() or not part.name.startswith(RESTORABLE):
            continue
        found, value = _restored_value(part.name, source)
        if found:
            write_json_atomic(part.output, {"part": part.name, "seconds": 0.0, "value": value,
                                            "restored_from": origin})
            restored.append(part.name)
    log(f"[results] restored {len(restored)} part(s) from {source_path}: {', '.join(restored) or 'none'}")
    return restored


def restored_parts(parts: Sequence[Part]) -> dict[str, Any] | None:
    """Which finished parts were restored rather than run, and from where (the report's 'restored' entry)."""
    found: dict[str, Any] = {}
    for part in parts:
        origin = read_json(part.output).get("restored_from") if part.output.is_file() else None
        if origin:
            found.setdefault(origin["path"], {**origin, "parts": []})["parts"].append(part.name)
    return {"sources": list(found.values())} if found else None


def _ablations(cfg: ResultsConfig, part: str) -> list[dict[str, Any]]:
    main = _value(Path(cfg.work) / "ap" / f"{DIFFUSION}.json")
    return orchestration.evaluate_ablations(cfg.report, (main or {}).get("ap"), part=part)


def _paper_compat(cfg: ResultsConfig) -> list[dict[str, Any]]:
    entries = {name: _value(Path(cfg.work) / "ap" / f"{name}.json") for name in PAPER_COMPAT_POLICIES
               if name in cfg.report.policies}
    return orchestration.evaluate_paper_compat(cfg.report, {n: e for n, e in entries.items() if e is not None})


def assemble(cfg: ResultsConfig) -> dict[str, Any]:
    """The report dict ``run_report`` would return, from the finished parts (unfinished ones are missing)."""
    work, r = Path(cfg.work), cfg.report
    policies = {}
    for name in r.policies:
        entry = _value(work / "ap" / f"{name}.json") or {**orchestration._entry(name), "status": "failed",
                                                         "reason": "its AP part did not finish"}
        if entry["status"] == "ok" and not r.skip_clearance:
            cells = [_value(work / "clearance" / name / f"{o}-{la}.json") for o in r.objects for la in r.layouts]
            errors = [c["error"] for c in cells if c is not None and c["error"]]
            episodes = [e for c in cells if c is not None and c["episodes"] for e in c["episodes"]]
            checks, mixed = cell_checks(name, [c for c in cells if c is not None and c["episodes"]])
            if mixed:
                errors.append(mixed)
            elif episodes:
                summary = summarise([EpisodeResult(**e) for e in episodes])
                summary["episodes"] = episodes
                summary.update(checks)
                if (config := pooled_config([c.get("config") for c in cells if c is not None and c["episodes"]])):
                    summary["config"] = config
                entry["clearance"] = summary
            missing = sum(c is None for c in cells)
            if errors or missing:
                entry["clearance_error"] = "; ".join(errors + ([f"{missing} cell(s) unfinished"] if missing else []))
        policies[name] = orchestration.finish_entry(entry, r)
    return {"generated": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"), "config": asdict(r),
            "policies": policies, "ablations": [] if r.skip_ablations else orchestration.merge_ablations(
                *(_value(work / "ablations" / f"{part}.json") or [] for part in orchestration.ABLATION_PARTS)),
            "paper_compat": [] if r.skip_paper_compat else (_value(work / "paper_compat.json") or []),
            "label_physics": orchestration.read_label_physics(r.label_physics),
            "provenance": orchestration.provenance(r), "restored": restored_parts(plan(cfg)),
            # which test split the AP rows read, so a later --restore can tell whether its split is the same
            "test_split": {"manifest_sha256": (_value(work / "data" / "test.json") or {}).get("manifest_sha256")}}


GENERATED_BEGIN = "<!-- make results: generated tables begin (edits between these markers are overwritten) -->"
GENERATED_END = "<!-- make results: generated tables end -->"


def write_benchmarks(cfg: ResultsConfig) -> Path | None:
    """The generated section of ``benchmarks/RESULTS.md``: each finished benchmark script's printed tables.

    Only the text between ``GENERATED_BEGIN`` and ``GENERATED_END`` is replaced (appended when absent), so
    the hand-written goals, analysis and machine notes around it survive a regeneration."""
    runs = sorted((Path(cfg.work) / "bench").glob("*.json"))
    if not runs:
        return None
    import platform

    lines = [GENERATED_BEGIN, "## Regenerated benchmark tables", "",
             f"Regenerated by `make results` on {time.strftime('%Y-%m-%d', time.gmtime())}: {os.cpu_count()} CPUs, "
             f"Python {platform.python_version()}, {platform.machine()}. Each section is one script's output.", ""]
    for path in runs:
        part = read_json(path)
        lines += [f"### {part['part'].split('/', 1)[1]} ({part['seconds']:.0f} s)", "", "```",
                  part["value"]["stdout"].rstrip(), "```", ""]
    lines.append(GENERATED_END)
    out = REPO / cfg.bench_dir / "RESULTS.md"
    text = out.read_text() if out.exists() else "# Benchmark results\n"
    if GENERATED_BEGIN in text and GENERATED_END in text:
        head, rest = text.split(GENERATED_BEGIN, 1)
        text = head + "\n".join(lines) + rest.split(GENERATED_END, 1)[1]
    else:
        text = text.rstrip("\n") + "\n\n" + "\n".join(lines) + "\n"
    out.write_text(text)
    return out


def regenerate(cfg: ResultsConfig, log: Callable[[str], None] = print) -> dict[str, Any]:
    """Restore what ``cfg.restore`` offers, run the unfinished parts, then write the report and the benchmark page
    from everything finished."""
    parts = plan(cfg)
    if cfg.restore is not None:
        restore_parts([p for p in parts if not forced(p.name, cfg.force)], cfg.restore, cfg.report, log)
    status = run_parts(parts, cfg.force, log)
    report = assemble(cfg)
    paths = write_report(report, cfg.report.out, cfg.report.figures_dir)
    bench = write_benchmarks(cfg)
    return {"status": status, "paths": {k: str(v) for k, v in paths.items()}, "benchmarks": str(bench) if bench
            else None}


def build_parser() -> argparse.ArgumentParser:
    d = ResultsConfig(report=ReportConfig(test_data="data/test"))
    p = argparse.ArgumentParser(prog="python -m eval.results", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--test-data", default="data/test", help="test scenes (generated here when missing)")
    p.add_argument("--test-scenes", type=int, default=d.test_scenes)
    p.add_argument("--train", action="store_true", help="also generate data/train and train the ablation variants")
    p.add_argument("--train-data", default=d.report.train_data)
    p.add_argument("--policies", nargs="+", default=list(DEFAULT_POLICIES))
    p.add_argument("--episodes", type=int, default=d.report.episodes, help="clearance episodes per cell")
    p.add_argument("--parcels", type=int, default=6, help="parcels per clearance pile")
    p.add_argument("--objects", nargs="+", default=list(OBJECT_SETS), choices=OBJECT_SETS)
    p.add_argument("--layouts", nargs="+", default=list(LAYOUTS), choices=LAYOUTS)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--workers", type=int, default=2, help="local processes, or Ray CPUs")
    p.add_argument("--backend", default="local", choices=BACKENDS)
    p.add_argument("--ray-address", default=None)
    p.add_argument("--out", default="results/RESULTS.md")
    p.add_argument("--work", default=d.work, help="finished parts are kept here")
    p.add_argument("--ablation-dir", default=d.report.ablation_dir)
    p.add_argument("--ablation-seeds", nargs="+", type=int, default=list(d.report.ablation_seeds),
                   help="training seeds of every ablation variant (--train trains each)")
    p.add_argument("--skip-clearance", action="store_true")
    p.add_argument("--no-audit-picks", dest="audit_picks", action="store_false",
                   help="do not record which parcel each clearance pick took (eval/pick_audit.py)")
    p.add_argument("--skip-ablations", action="store_true")
    p.add_argument("--skip-benchmarks", action="store_true")
    p.add_argument("--force", nargs="*", default=[], metavar="PREFIX", help="redo the parts whose names start so")
    p.add_argument("--restore", default=None, metavar="REPORT_JSON",
                   help="seed the unfinished parts that do not depend on the pick cell (test data, AP, paper-compatible "
                        "rows, ablations) from an earlier report's JSON; the report names them")
    p.add_argument("--list", action="store_true", help="list the parts and whether each is done, then stop")
    return p


def config_from_args(args: argparse.Namespace) -> ResultsConfig:
    report = ReportConfig(test_data=args.test_data, policies=tuple(args.policies), episodes=args.episodes,
                          parcels=args.parcels, objects=tuple(args.objects), layouts=tuple(args.layouts),
                          seed=args.seed, workers=args.workers, backend=args.backend,
                          ray_address=args.ray_address, out=args.out,
                          skip_clearance=args.skip_clearance, audit_picks=args.audit_picks,
                          skip_ablations=args.skip_ablations,
                          ablation_dir=args.ablation_dir, ablation_seeds=tuple(args.ablation_seeds),
                          train_data=args.train_data, progress=False)
    return ResultsConfig(report=report, work=args.work, test_scenes=args.test_scenes, train=args.train,
                         benchmarks=not args.skip_benchmarks, force=tuple(args.force), restore=args.restore)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        cfg = config_from_args(args)
    except ValueError as exc:
        parser.error(str(exc))
    if args.list:
        for part in plan(cfg):
            print(f"{'done' if part.output.is_file() else 'todo'}  {part.name}")
        return 0
    result = regenerate(cfg)
    ran = [k for k, v in result["status"].items() if v == "ran"]
    print(f"[results] ran {len(ran)} part(s), skipped {len(result['status']) - len(ran)}; wrote "
          + ", ".join(list(result["paths"].values()) + ([result["benchmarks"]] if result["benchmarks"] else [])))
    return 0


if __name__ == "__main__":
    sys.exit(main())
