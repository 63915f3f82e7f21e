"""Per-call cost of the arm's kinematics (parcelpick_env/robot/kinematics.py, on pinocchio).

    .venv/bin/python benchmarks/bench_kinematics.py [--repeats 5] [--calls 2000]

The hold check asks for the tool's motion at every carrying step (about 500 a pick), the IK refinement for a
Jacobian at every iteration, the planner and the moves for forward kinematics. Random joint states within the
Gen3's limits; each call is timed in rounds that take every call in turn (``timing.interleaved_times``), and the
fastest round is kept.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from parcelpick_env.robot.arm import ArmConfig  # noqa: E402
from parcelpick_env.robot.gen3 import JOINT_LOWER, JOINT_UPPER, SuctionToolSpec  # noqa: E402
from parcelpick_env.robot.kinematics import Gen3Kinematics  # noqa: E402
from timing import interleaved_times  # noqa: E402


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5, help="rounds; the fastest is kept")
    ap.add_argument("--calls", type=int, default=2000, help="calls of each cheap function per round")
    args = ap.parse_args(argv)
    cfg = ArmConfig()
    kin = Gen3Kinematics(cfg.base_position, cfg.base_yaw, SuctionToolSpec().length)
    rng = np.random.default_rng(0)
    lower, upper = JOINT_LOWER, JOINT_UPPER
    q = rng.uniform(lower, upper)
    qd, qdd = rng.uniform(-1.0, 1.0, 7), rng.uniform(-3.0, 3.0, 7)
    many = rng.uniform(lower, upper, (300, 7))
    target, axis = kin.forward(q + 0.05)[:2]  # a reachable goal a little way off: a few refinement iterations

    def repeated(fn, n):
        return lambda: [fn() for _ in range(n)]

    cheap = {"forward (tip, axes, origins)": lambda: kin.forward(q), "tool_pose": lambda: kin.tool_pose(q),
             "jacobian": lambda: kin.jacobian(q), "tool_motion (the hold check's)": lambda: kin.tool_motion(q, qd, qdd)}
    slow = {"tips, 300 configurations": lambda: kin.tips(many),
            "refine (damped least squares)": lambda: kin.refine(q, target, axis, q, lower, upper, 1e-4, 1e-3)}
    n = {**{name: args.calls for name in cheap}, **{name: max(1, args.calls // 100) for name in slow}}
    calls = {name: repeated(fn, n[name]) for name, fn in {**cheap, **slow}.items()}
    times = interleaved_times(calls, args.repeats)
    print(f"\nGen3 kinematics, per call (fastest of {args.repeats} rounds)\n")
    print("| call | us |")
    print("|---|---|")
    for name, samples in times.items():
        print(f"| {name} | {min(samples) * 1e3 / n[name]:.1f} |")


if __name__ == "__main__":
    main()
