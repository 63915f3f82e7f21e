"""Label pipeline cost per stage in a warm process: pile -> render + normals -> FPS -> scoring, CPU and wall s.

    .venv/bin/python benchmarks/bench_label_stages.py                                  # 4,096 pts at 320x240
    .venv/bin/python benchmarks/bench_label_stages.py --points 16384 --width 640 --height 480
    .venv/bin/python benchmarks/bench_label_stages.py --root /tmp/head   # another checkout (a before/after)

``bench_dataset.py`` times short runs end to end, so its stages also carry each process's one-off costs (the
asset library, the simulator, every parcel's first collision hull and visual files), spread over a few scenes.
This one annotates one scene first to pay those, then reports the mean over ``--scenes`` 30-parcel stacked
mixed scenes (``dataset.annotate.annotate_scene_timed``), which is what each scene of a long run costs.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

STAGES = ("pile", "render", "fps", "scoring")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--points", type=int, default=4096)
    parser.add_argument("--width", type=int, default=320)
    parser.add_argument("--height", type=int, default=240)
    parser.add_argument("--parcels", type=int, default=30)
    parser.add_argument("--scenes", type=int, default=6)
    parser.add_argument("--root", type=Path, default=Path(__file__).resolve().parents[1],
                        help="checkout whose dataset/annotate.py to time (default: this one)")
    args = parser.parse_args()
    if args.scenes < 1:
        parser.error("--scenes must be >= 1")
    if not (args.root / "dataset" / "annotate.py").is_file():
        parser.error(f"--root {args.root} has no dataset/annotate.py")
    sys.path.insert(0, str(args.root.resolve()))
    from dataset.annotate import annotate_scene_timed
    from dataset.config import GenerationConfig

    config = GenerationConfig(scenes=args.scenes + 1, min_parcels=args.parcels, max_parcels=args.parcels,
                              layout="stacked", object_set="mixed", annotation_points=args.points,
                              width=args.width, height=args.height)
    annotate_scene_timed(config.scene_seed(args.scenes), config)  # warm-up: the one-off costs
    load_before = os.getloadavg()[0]
    total: dict[str, float] = {}
    for i in range(args.scenes):
        _, timings = annotate_scene_timed(config.scene_seed(i), config)
        for key, value in timings.items():
            total[key] = total.get(key, 0.0) + value / args.scenes
    print(f"\n### Label stages, warm process: {args.parcels}-parcel stacked mixed, {args.points} points, "
          f"{args.width}x{args.height}, mean of {args.scenes} scenes (load average {load_before:.1f} / "
          f"{os.getloadavg()[0]:.1f}; root {args.root})\n")
    print("| " + " | ".join(STAGES) + " | sum |")
    print("|" + "---|" * (len(STAGES) + 1))
    print("| " + " | ".join(f"{total[s]:.2f} / {total[s + '_cpu']:.2f}" for s in STAGES)
          + f" | {sum(total[s] for s in STAGES):.2f} / {sum(total[s + '_cpu'] for s in STAGES):.2f} |")
    print("\n(wall s / CPU s per scene; CPU counts every thread of this process)")


if __name__ == "__main__":
    main()
