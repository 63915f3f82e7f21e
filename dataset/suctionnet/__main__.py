"""Two commands between ParcelPick datasets and the GraspNet/SuctionNet layout.

    python -m dataset.suctionnet import --graspnet-root DIR --camera kinect --split train --out data/sn_kinect_train
    python -m dataset.suctionnet export --data data/test --out runs/parcel_suctionnet --first-scene 100
"""

from __future__ import annotations

import argparse
import sys

from dataset.suctionnet.layout import CAMERAS, SPLITS


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m dataset.suctionnet", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    imp = sub.add_parser("import", help="SuctionNet views -> a ParcelPick dataset directory (HDF5 shards)")
    imp.add_argument("--graspnet-root", required=True, help="holds scenes/, models/, seal_label/, ...")
    imp.add_argument("--camera", choices=CAMERAS, default="kinect")
    imp.add_argument("--split", choices=sorted(SPLITS), required=True)
    imp.add_argument("--views", type=int, nargs="+", help="annotation ids (default: every one present)")
    imp.add_argument("--out", required=True)
    imp.add_argument("--points", type=int, default=16384, help="points per view")
    imp.add_argument("--seed", type=int, default=0)
    imp.add_argument("--scenes-per-shard", type=int, default=100)
    imp.add_argument("--no-images", action="store_true", help="store only the labelled points, not RGB-D")
    exp = sub.add_parser("export", help="a ParcelPick dataset directory -> the SuctionNet layout")
    exp.add_argument("--data", required=True, help="dataset directory made by python -m dataset.generate")
    exp.add_argument("--out", required=True, help="new SuctionNet root")
    exp.add_argument("--scenes", type=int, help="first N scenes (default: all)")
    exp.add_argument("--first-scene", type=int, default=0, help="SuctionNet scene id of the first (100: test_seen)")
    exp.add_argument("--camera", choices=CAMERAS, default="realsense")
    return parser


def main(argv: list[str]) -> int:
    from parcelpick_env.cli import check_input_dir, check_output_path

    args = build_parser().parse_args(argv)
    if args.command == "import":
        from dataset.suctionnet.convert import import_views, split_views
        from dataset.suctionnet.reader import ReaderConfig

        check_input_dir(args.graspnet_root, "--graspnet-root")
        check_output_path(args.out, "--out", directory=True)
        views = split_views(args.graspnet_root, args.camera, args.split, args.views)
        manifest = import_views(args.graspnet_root, args.out, args.camera, views, split=args.split,
                                config=ReaderConfig(num_points=args.points, seed=args.seed),
                                scenes_per_shard=args.scenes_per_shard, images=not args.no_images,
                                progress=lambda i, n: print(f"\rview {i}/{n}", end="", file=sys.stderr))
        print(f"\n{manifest['num_scenes']} views of {args.camera} {args.split} -> {args.out}", file=sys.stderr)
    else:
        from dataset.suctionnet.writer import WriterConfig, export_dataset

        check_input_dir(args.data, "--data")
        check_output_path(args.out, "--out", directory=True)
        written = export_dataset(args.data, args.out, args.scenes, args.first_scene, WriterConfig(camera=args.camera))
        print(f"{len(written)} scenes ({sum(map(len, written.values()))} objects) -> {args.out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    from parcelpick_env.cli import run_cli

    sys.exit(run_cli(main, prog="python -m dataset.suctionnet"))
