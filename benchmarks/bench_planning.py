"""Motion benchmark: collision checks, planning (straight fast path vs RRTConnect), trajectory timing, execute().

Scenes: a settled stacked mixed pile in the default bin with the arm beside it (the cell's free-space
moves: ready pose -> hover above each parcel), and a 60 cm column between two hover poses (a move
that needs RRTConnect), bare and with a held 25 cm parcel. Prints markdown tables of median wall
times. Run: ``.venv/bin/python benchmarks/bench_planning.py [--parcels 30] [--seeds 5]``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import pybullet as p

sys.path.insert(0, str(Path(__file__).resolve().parent))
from timing import time_calls  # benchmarks/timing.py, a sibling module

from parcelpick_env.robot.arm import Gen3Arm
from parcelpick_env.robot.planning import Attachment, MotionPlanner, PlannerConfig
from parcelpick_env.robot.timing import GEN3_LIMITS, joint_trajectory, path_trajectory
from parcelpick_env.scene.config import PileConfig
from parcelpick_env.scene.pile import build_pile
from parcelpick_env.sim.simulator import Simulator

DOWN = np.array([0.0, 0.0, -1.0])


def _ms(samples: list[float]) -> str:
    return f"{statistics.median(samples) * 1e3:.2f}" if samples else "-"


def pile_rows(parcels: int, seeds: int) -> list[tuple[str, str, str]]:
    """Collision checks, fast-path plans and execute() in a settled pile."""
    rows: list[tuple[str, str, str]] = []
    checks, straight, rrt, reasons, execute_240, execute_60 = [], [], [], [], [], []
    methods = {"straight": 0, "rrt": 0, "failed": 0}
    with Simulator() as sim:
        for seed in range(seeds):
            scene = build_pile(sim, PileConfig(num_parcels=parcels, layout="stacked", object_set="mixed"), seed=seed)
            arm = Gen3Arm(sim.client)
            rim = scene.bin.floor_z + scene.bin.wall_height
            ready = arm.ik([0.0, 0.0, rim + 0.25], DOWN, seed=np.asarray(arm.config.ik_seed))
            arm.set_joints(ready)
            planner = arm.planner
            for ps in scene.parcels:
                top = sim.aabb(ps.body_id)[1][2]
                pos = sim.body_pose(ps.body_id)[0]
                q_hover = arm.ik([pos[0], pos[1], max(top + 0.08, rim + 0.05)], DOWN, seed=ready)
                if q_hover is None:
                    continue
                start = time.perf_counter()
                planner.collision(q_hover)
                checks.append(time.perf_counter() - start)
                path = planner.plan(ready, q_hover)
                methods[planner.stats.method] += 1
                if path is None:
                    reasons.append(planner.last_failure)
                else:
                    (straight if planner.stats.method == "straight" else rrt).append(planner.stats.seconds)
            # execute(): a 2-segment move above the pile with contacts on, at 240 Hz and 60 Hz
            goal = arm.ik([0.25, 0.1, rim + 0.15], DOWN, seed=ready)
            for dt, out in ((1 / 240, execute_240), (1 / 60, execute_60)):
                p.setTimeStep(dt, physicsClientId=sim.client)
                arm.set_joints(ready)
                traj = joint_trajectory(ready, [goal, ready], GEN3_LIMITS, dt)
                stepping = [0.0]

                def step_world(stepping=stepping) -> None:
                    t = time.perf_counter()
                    sim.step(1)
                    stepping[0] += time.perf_counter() - t

                start = time.perf_counter()
                res = arm.execute(traj, step_world)
                wall = time.perf_counter() - start
                out.append((res.steps / wall, (wall - stepping[0]) / res.steps, res.tip_error))
            p.setTimeStep(sim.config.timestep, physicsClientId=sim.client)
    rows.append(("collision check, one configuration (pile)", _ms(checks), f"{len(checks)} hover poses"))
    rows.append(("plan ready -> hover, straight fast path", _ms(straight),
                 f"{methods['straight']} of {sum(methods.values())} moves"))
    rows.append(("plan ready -> hover, needed RRTConnect", _ms(rrt), f"{methods['rrt']} moves"))
    rows.append(("plan ready -> hover, refused", "-", f"{methods['failed']}: " + "; ".join(sorted(set(reasons)))))
    for hz, runs in ((240, execute_240), (60, execute_60)):
        rate, overhead, tip = (statistics.median(x) for x in zip(*runs))
        rows.append((f"execute() at {hz} Hz: steps/s (whole loop incl. physics)", f"{rate:.0f}",
                     f"arm overhead {overhead * 1e3:.2f} ms/step beyond the physics step; "
                     f"tip tracking {tip * 1e3:.2f} mm"))
    return rows


def column_rows(seeds: int) -> list[tuple[str, str, str]]:
    """RRTConnect around a tall column, bare and with a held parcel; and trajectory timing cost."""
    c = p.connect(p.DIRECT)
    try:
        arm = Gen3Arm(c)
        q_a = arm.ik([-0.3, 0.05, 0.2], DOWN, seed=np.asarray(arm.config.ik_seed))
        q_b = arm.ik([0.3, 0.05, 0.2], DOWN, seed=q_a)
        col = p.createCollisionShape(p.GEOM_BOX, halfExtents=[0.06, 0.06, 0.3], physicsClientId=c)
        p.createMultiBody(0, col, basePosition=[0.0, 0.05, 0.3], physicsClientId=c)
        arm.set_joints(q_a)
        tip = arm.kin.forward(q_a)[0]
        box = p.createCollisionShape(p.GEOM_BOX, halfExtents=[0.05, 0.05, 0.12], physicsClientId=c)
        parcel = p.createMultiBody(1.0, box, basePosition=(tip + [0, 0, -0.125]).tolist(), physicsClientId=c)
        held = Attachment.current(arm, parcel)
        rows = []
        for name, attached in (("bare arm", None), ("holding a 25 cm parcel", held)):
            times, checks, points = [], [], []
            for seed in range(1, seeds + 1):
                planner = MotionPlanner(arm, c, PlannerConfig(seed=seed))
                path = planner.plan(q_a, q_b, attached=attached, ignore_bodies=(parcel,))
                assert path is not None and planner.stats.method == "rrt", planner.last_failure
                times.append(planner.stats.seconds)
                checks.append(planner.stats.checks)
                points.append(0 if path is None else len(path))
            rows.append((f"plan around a 60 cm column, RRTConnect + shortcut, {name}", _ms(times),
                         f"{statistics.median(checks):.0f} checks, {statistics.median(points):.0f} waypoints"))
        path = arm.planner.plan(q_a, q_b, ignore_bodies=(parcel,))
        rows.append(("joint_trajectory of that plan (ruckig, 240 Hz samples)",
                     f"{time_calls(lambda: joint_trajectory(q_a, path[1:], GEN3_LIMITS, 1 / 240), 20):.2f}",
                     f"{len(joint_trajectory(q_a, path[1:], GEN3_LIMITS, 1 / 240))} samples"))
        corners = [[-0.3, 0.05, 0.5], [0.3, 0.2, 0.5]]
        x_axis = arm.kin.tip_x(q_a)
        traj, _ = arm.cartesian_trajectory(q_a, corners, DOWN, 1 / 60, x_axis=x_axis)
        cartesian_ms = time_calls(lambda: arm.cartesian_trajectory(q_a, corners, DOWN, 1 / 60, x_axis=x_axis), 5)
        rows.append(("cartesian_trajectory lift 0.3 m + carry 0.6 m (IK every 2 cm + timing, 60 Hz)",
                     f"{cartesian_ms:.2f}", f"{traj.duration:.2f} s of motion"))
        carry = np.array(arm.cartesian_path(traj.q[-1], np.linspace([0.3, 0.2, 0.5], [-0.3, 0.05, 0.5], 31), DOWN))
        rows.append(("path_trajectory alone on the 31 IK points of the carry",
                     f"{time_calls(lambda: path_trajectory(carry, GEN3_LIMITS, 1 / 60), 10):.2f}",
                     f"{path_trajectory(carry, GEN3_LIMITS, 1 / 60).duration:.2f} s of motion"))
        return rows
    finally:
        p.disconnect(c)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--parcels", type=int, default=30)
    parser.add_argument("--seeds", type=int, default=5)
    args = parser.parse_args()
    rows = column_rows(args.seeds) + pile_rows(args.parcels, min(args.seeds, 3))
    print(f"\n### Motion ({args.parcels}-parcel stacked mixed pile; median over seeds)\n")
    print("| what | median (ms, or steps/s) | notes |")
    print("|---|---|---|")
    for what, value, note in rows:
        print(f"| {what} | {value} | {note} |")


if __name__ == "__main__":
    main()
