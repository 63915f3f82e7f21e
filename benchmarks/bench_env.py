"""ParcelPick-v0 speed: reset (pile build + settle + render) and wall time per pick attempt.

A stacked mixed pile (30 parcels by default) is picked by the scripted top-patch picker (or, with
``--policy NAME``, by a registered policy as the clearance evaluation runs it, through the tool check) until
the bin is clear or ``--attempts`` attempts (the 3-consecutive-failure stop is off unless
``--max-failures`` is given). Prints a markdown table with the reset time, the mean wall
time per attempt (total, and the camera's share: render + normals + sampling), outcome counts and
peak RSS, then where an attempt's time goes: each of the cell's moves (its plan, free moves, driven moves,
the pile's settle after the attempt, the next observation), with its calls and simulator steps. The
policy's own decision time is not part of an attempt. The first reset of a process is shown apart: it pays for
first uses once; the renderer's start (the EGL plugin), which the simulator's first use pays, is timed before it.

    python benchmarks/bench_env.py --parcels 30 --attempts 20 --seed 0
    python benchmarks/bench_env.py --parcels 30 --attempts 20 --seed 0 --policy diffusion
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from parcelpick_env.camera.config import CameraConfig  # noqa: E402
from parcelpick_env.envs.config import ENV_CUP_RADIUS  # noqa: E402
from parcelpick_env.envs.grasp import PickExecutor  # noqa: E402
from parcelpick_env.envs.parcel_pick import ParcelPickEnv  # noqa: E402
from parcelpick_env.envs.scripted import top_patch_action  # noqa: E402
from parcelpick_env.sim.simulator import Simulator  # noqa: E402
from parcelpick_env.suction.config import SuctionConfig  # noqa: E402

# An attempt's parts, in the order they run (PickExecutor.attempt, then the env): the plan (IK, branch and
# collision checks), the planned free moves, the driven moves (dynamics), the pile's settle and the next observation
PHASES = (("plan", PickExecutor, "_plan"), ("hover (free move)", PickExecutor, "_hover"),
          ("descend (free move)", PickExecutor, "_descend"), ("approach (driven)", PickExecutor, "_approach"),
          ("seal (driven)", PickExecutor, "_seal"), ("lift (driven)", PickExecutor, "_lift"),
          ("transport (driven)", PickExecutor, "_transport"), ("set down", PickExecutor, "_set_down"),
          ("release", PickExecutor, "_release"), ("retreat (free move)", PickExecutor, "_retreat"),
          ("pile settle after the attempt", PickExecutor, "settle_pile"),
          ("next observation (render, normals, sampling)", ParcelPickEnv, "_observe"))


class PhaseClock:
    """Benchmark-only instrumentation: wall time, calls and simulator steps of each of ``PHASES`` while
    ``timing`` is on (inside ``env.step``), by wrapping the classes' methods for this process."""

    def __init__(self) -> None:
        self.timing = False
        self.steps = 0
        self.totals = {name: [0, 0.0, 0] for name, _, _ in PHASES}  # calls, seconds, simulator steps
        step = Simulator.step

        def counted_step(sim, n: int = 1) -> None:
            self.steps += n
            step(sim, n)
        setattr(Simulator, "step", counted_step)
        for name, cls, attr in PHASES:
            setattr(cls, attr, self._timed(name, getattr(cls, attr)))

    def _timed(self, name: str, method):
        def run(*a, **k):
            if not self.timing:
                return method(*a, **k)
            t0, s0 = time.perf_counter(), self.steps
            try:
                return method(*a, **k)
            finally:
                total = self.totals[name]
                total[0] += 1
                total[1] += time.perf_counter() - t0
                total[2] += self.steps - s0
        return run

    def table(self, attempts: int, attempt_seconds: float) -> str:
        rows = ["| part of an attempt | calls | wall per attempt (s) | share | wall per call (ms) | sim steps per call |",
                "|---|---|---|---|---|---|"]
        for name, (calls, seconds, steps) in self.totals.items():
            if calls:
                rows.append(f"| {name} | {calls} | {seconds / attempts:.3f} | {100 * seconds / attempt_seconds:.0f}% "
                            f"| {1000 * seconds / calls:.1f} | {steps / calls:.0f} |")
        rest = attempt_seconds - sum(t[1] for t in self.totals.values())
        rows.append(f"| the rest (the env's bookkeeping between them) | – | {rest / attempts:.3f} "
                    f"| {100 * rest / attempt_seconds:.0f}% | – | – |")
        return "\n".join(rows)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--parcels", type=int, default=30)
    ap.add_argument("--layout", default="stacked")
    ap.add_argument("--objects", default="mixed")
    ap.add_argument("--attempts", type=int, default=20, help="stop after this many attempts")
    ap.add_argument("--episodes", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--points", type=int, default=4096)
    ap.add_argument("--cup-radius", type=float, default=None,
                    help="suction cup radius r (m) for the seal and holding checks; default SuctionConfig's")
    ap.add_argument("--max-failures", type=int, default=1000,
                    help="consecutive failures that end an episode (the env's default is 3; the benchmark "
                         "keeps picking so it times more attempts)")
    ap.add_argument("--policy", default=None,
                    help="a registered policy picks (as eval/clearance.py runs it) instead of the scripted "
                         "top-patch picker; its mix of outcomes is the one its clearance meets")
    args = ap.parse_args(argv)
    policy = None
    if args.policy is not None:
        from eval.clearance import ClearanceConfig, choose_action, episode_policy
        from policies.registry import obs_mode_of

        try:  # as the clearance evaluation runs it: its checkpoint, through the cell's tool check
            policy = episode_policy(ClearanceConfig(policy=args.policy))
        except (KeyError, ValueError) as exc:
            ap.error(f"--policy: {exc}")
    modes = {} if policy is None else {"obs_mode": obs_mode_of(policy), "action_mode": policy.action_mode}

    env = ParcelPickEnv(num_parcels=args.parcels, layout=args.layout, object_set=args.objects,
                        camera=CameraConfig(width=args.width, height=args.height), num_points=args.points,
                        max_attempts=args.attempts, max_consecutive_failures=args.max_failures, **modes,
                        **({"suction": SuctionConfig(cup_radius=args.cup_radius)} if args.cup_radius else {}))
    clock = PhaseClock()
    capture_times: list[float] = []

    def timed(method):  # benchmark-only instrumentation of the camera's share
        def run(*a, **k):
            t0 = time.perf_counter()
            out = method(*a, **k)
            capture_times.append(time.perf_counter() - t0)
            return out
        return run

    # the render and back-projection, then the normals at the sampled points only (Camera.normals_at)
    env.camera.capture = timed(env.camera.capture)
    env.camera.normals_at = timed(env.camera.normals_at)
    # The simulator's renderer starts at its first use (sim/egl.py: the EGL plugin and its throw-away frames), once
    # per process, whatever the seed: timed apart, so that the first reset is the pile's own cost
    t0 = time.perf_counter()
    _ = env.sim.client
    renderer_start = time.perf_counter() - t0
    resets, steps, step_capture, sim_times, step_outcomes, decisions = [], [], [], [], [], []
    outcomes: Counter[str] = Counter()
    causes: Counter[str] = Counter()
    placed = cleared = 0
    for ep in range(args.episodes):
        t0 = time.perf_counter()
        obs, info = env.reset(seed=args.seed + ep)
        resets.append(time.perf_counter() - t0)
        placed += info["parcels_placed"]
        if policy is not None:
            policy.reset(args.seed + ep)
        done = False
        while not done and info.get("reason") != "cleared":
            if policy is None:
                action = top_patch_action(obs)
            else:
                t0 = time.perf_counter()
                action = choose_action(policy, obs, info, env.action_space.shape)
                decisions.append(time.perf_counter() - t0)
            n_cap = len(capture_times)
            t0 = time.perf_counter()
            clock.timing = True
            obs, _, term, trunc, info = env.step(action)
            clock.timing = False
            steps.append(time.perf_counter() - t0)
            step_capture.append(sum(capture_times[n_cap:]))
            sim_times.append(info["sim_time"])
            outcomes[info["outcome"]] += 1
            step_outcomes.append(info["outcome"])
            if info["failure_cause"]:
                phase = f' ({info["failure_phase"]})' if info.get("failure_phase") else ""
                causes[f'{info["outcome"]}: {info["failure_cause"]}{phase}'] += 1
            done = term or trunc
        cleared += info["parcels_cleared"]
    env.close()

    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    steps_a, cap_a = np.array(steps), np.array(step_capture)
    cup = args.cup_radius or ENV_CUP_RADIUS  # the env's default cup
    print(f"ParcelPick-v0, {args.parcels} parcels {args.layout} {args.objects}, camera {args.width}x{args.height}, "
          f"N={args.points}, cup r={cup * 1000:.0f} mm, "
          f"{'scripted top-patch picker' if policy is None else f'policy {args.policy!r}'}, "
          f"{args.episodes} episode(s)\n")
    print("| metric | value |")
    print("|---|---|")
    print(f"| the renderer's start, once per process (EGL plugin and warm-up frames) | {renderer_start:.2f} s |")
    print(f"| reset (build + settle + render), first of the process, after the renderer's start | {resets[0]:.2f} s |")
    if len(resets) > 1:  # the first pays once per process: imports, the first render's set-up, first uses
        print(f"| reset, later ones, mean | {np.mean(resets[1:]):.2f} s |")
    print(f"| pick attempt wall time, mean | {steps_a.mean():.3f} s |")
    print(f"| pick attempt wall time, median / max | {np.median(steps_a):.3f} / {steps_a.max():.3f} s |")
    # the mean hangs on the mix (a cheap `unreachable` plan against a whole pick), which another host's round-off
    # changes with its piles: each outcome's own mean makes hosts comparable
    by_outcome = {o: steps_a[[x == o for x in step_outcomes]] for o in sorted(outcomes)}
    print("| pick attempt wall time by outcome, mean (attempts) | "
          + ", ".join(f"{o} {t.mean():.3f} s ({len(t)})" for o, t in by_outcome.items()) + " |")
    print(f"| of which camera (render + normals), mean | {cap_a.mean():.3f} s |")
    print(f"| of which physics + planning, mean | {(steps_a - cap_a).mean():.3f} s |")
    print(f"| simulated time per attempt, mean | {np.mean(sim_times):.1f} s |")
    print(f"| attempts | {len(steps)} |")
    print(f"| outcomes | {', '.join(f'{k}: {v}' for k, v in sorted(outcomes.items()))} |")
    print(f"| failure causes | {'; '.join(f'{k} x{v}' for k, v in sorted(causes.items())) or '-'} |")
    print(f"| parcels cleared / placed | {cleared} / {placed} |")
    if decisions:
        print(f"| the policy's decision (not part of the attempt), mean | {np.mean(decisions):.3f} s |")
    print(f"| peak RSS | {peak_mb:.0f} MB |")
    print(f"\nWhere an attempt's {steps_a.mean():.3f} s go ({len(steps)} attempts):\n")
    print(clock.table(len(steps), float(steps_a.sum())))


if __name__ == "__main__":
    main()
