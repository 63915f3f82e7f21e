"""The report's command line: ``python -m eval.report`` parses flags into a ReportConfig, runs, and writes."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from eval.clearance import LAYOUTS, OBJECT_SETS
from eval.report.config import DIFFUSION, HEADLINE_QUALITY, ReportConfig
from eval.report.markdown import write_report
from eval.report.orchestration import run_report
from parcelpick_env.parallel import BACKENDS
from parcelpick_env.suction.quality import AP_DEFINITIONS

DESCRIPTION = ("One report for every policy: offline AP (Table II), closed-loop clearance (Table V) and the "
               "Diffusion-Suction ablations (Tables III and IV), each beside the paper's numbers, with bootstrap "
               "intervals, paired comparisons, failure anatomy, checkpoint provenance, plots and a JSON dump.")


def build_parser() -> argparse.ArgumentParser:
    d = ReportConfig(test_data="")
    p = argparse.ArgumentParser(prog="python -m eval.report", description=DESCRIPTION,
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--test-data", required=True, help="held-out test scenes (python -m dataset.generate)")
    p.add_argument("--policies", nargs="+", default=list(d.policies), help="registered policy names")
    p.add_argument("--ap-scenes", type=int, default=None,
                   help="evaluate only the first N test scenes (all when omitted)")
    p.add_argument("--ap-qualities", nargs="+", default=list(d.ap_qualities), choices=AP_DEFINITIONS,
                   help=f"quality definitions, one AP table each (docs/protocols.md); must include "
                   f"{HEADLINE_QUALITY} (the paper's protocol)")
    p.add_argument("--episodes", type=int, default=d.episodes, help="clearance episodes per cell")
    p.add_argument("--parcels", type=int, default=d.parcels, help="parcels per clearance pile")
    p.add_argument("--objects", nargs="+", default=list(d.objects), choices=OBJECT_SETS)
    p.add_argument("--layouts", nargs="+", default=list(d.layouts), choices=LAYOUTS)
    p.add_argument("--seed", type=int, default=d.seed)
    p.add_argument("--workers", type=int, default=d.workers, help="parallel clearance episodes")
    p.add_argument("--backend", default=d.backend, choices=BACKENDS)
    p.add_argument("--ray-address", default=None, help="Ray cluster for clearance, e.g. 'auto'; default: local Ray")
    p.add_argument("--out", default=d.out, help="markdown report; the JSON dump goes beside it")
    p.add_argument("--figures", default=None, help="PNG folder (<out folder>/figures when omitted)")
    p.add_argument("--skip-clearance", action="store_true")
    p.add_argument("--no-audit-picks", dest="audit_picks", action="store_false",
                   help="do not record which parcel each clearance pick took (eval/pick_audit.py)")
    p.add_argument("--clearance-from", default=None, metavar="JSON",
                   help="reuse the clearance results of an earlier report's JSON (labelled as reused) instead of "
                   "re-running them")
    p.add_argument("--skip-ablations", action="store_true")
    p.add_argument("--skip-paper-compat", action="store_true",
                   help="no paper-compatible rows (the label oracle and Diffusion-Suction under the public "
                   "script's NMS and SuctionNet's label-time wrench)")
    p.add_argument("--label-physics", default=d.label_physics,
                   help="eval/label_physics.py's JSON; its AUC is reported when the file exists")
    p.add_argument("--diffusion-checkpoint", default=None,
                   help="Diffusion-Suction weights (the shipped ones when omitted)")
    p.add_argument("--ablation-dir", default=d.ablation_dir, help="trained ablations: <dir>/<name>/seed<k>/best.pt")
    p.add_argument("--ablation-seeds", nargs="+", type=int, default=list(d.ablation_seeds),
                   help="training seeds of every ablation variant")
    p.add_argument("--ablation-steps", nargs="+", type=int, default=list(d.ablation_steps),
                   help="DDIM step counts tried on the main checkpoint")
    p.add_argument("--train-data", default=d.train_data, help="training data named in the ablation commands")
    p.add_argument("--train-args", default=d.train_args, help="main-run training flags repeated in those commands")
    p.add_argument("--graspnet-root", default=None,
                   help="SuctionNet-1Billion root: adds the paper's Table I (python -m eval.table_one)")
    p.add_argument("--quiet", action="store_true", help="no per-scene / per-episode progress on stderr")
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not Path(args.test_data).is_dir():
        parser.error(f"test data directory {args.test_data} does not exist")
    try:
        config = ReportConfig(test_data=args.test_data, policies=tuple(args.policies), ap_scenes=args.ap_scenes,
                              ap_qualities=tuple(args.ap_qualities),
                              episodes=args.episodes, parcels=args.parcels, objects=tuple(args.objects),
                              layouts=tuple(args.layouts), seed=args.seed, workers=args.workers,
                              backend=args.backend, ray_address=args.ray_address, out=args.out, figures=args.figures,
                              skip_clearance=args.skip_clearance, audit_picks=args.audit_picks,
                              clearance_from=args.clearance_from,
                              skip_ablations=args.skip_ablations,
                              skip_paper_compat=args.skip_paper_compat, label_physics=args.label_physics,
                              diffusion_checkpoint=args.diffusion_checkpoint, ablation_dir=args.ablation_dir,
                              ablation_steps=tuple(args.ablation_steps), ablation_seeds=tuple(args.ablation_seeds),
                              train_data=args.train_data,
                              train_args=args.train_args, progress=not args.quiet,
                              graspnet_root=args.graspnet_root)
    except ValueError as exc:
        parser.error(str(exc))
    from parcelpick_env.cli import (
        UsageError,
        check_output_path,
        check_policy,
        usage_exit,
    )

    # Hours of evaluation follow: fail now on an unwritable output or a bad checkpoint given by the user.
    # (A policy that cannot be made is not an error here: the report lists it as not available.)
    try:
        check_output_path(config.out, "--out")
        check_output_path(config.figures_dir, "--figures", directory=True)
        if config.diffusion_checkpoint:
            check_policy(DIFFUSION, config.diffusion_checkpoint, checkpoint_arg="--diffusion-checkpoint")
    except UsageError as exc:
        usage_exit(parser.prog, exc)
    report = run_report(config)
    paths = write_report(report, config.out, config.figures_dir)
    print(Path(paths["markdown"]).read_text())
    print("wrote " + ", ".join(str(p) for p in paths.values()), file=sys.stderr)
    return 0


if __name__ == "__main__":
    from parcelpick_env.cli import run_cli

    sys.exit(run_cli(main))
