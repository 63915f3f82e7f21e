"""The parting push: the tool, vacuum off, comes down beside a parcel and pushes the pile sideways.

Why a cell needs it: in a 30-parcel heap every parcel left can bear or lean on another, and no top-down pick
lifts one without dragging what rests on it past the cup's torsion capacity, so the oracle's episodes end on
three failed picks with parcels left (results/ORACLE.md, 'A parting move'). A real induction cell parts such a
pile with its tool. Measured there with hindsight, one push of the topmost free parcel opened most of those dead
ends.

The push is a step of ``action_mode="pose_push"`` (``parcel_pick.py``): the tool tip comes straight down, cup
first, to ``start``, then moves ``GraspConfig.push_distance`` along the horizontal part of ``direction``, then
rises and goes home. Every move is the pick's own kind (``grasp.py``): a planned free move to the hover, lines
along which the arm is driven by its motors with dynamics, the tool links (cup, rod, flange) allowed to touch
the pile and any other link's contact a ``collision``. The descent is guarded: it ends where the tool presses on
something with ``push_touch_force``; if that is more than ``PUSH_START_TOLERANCE`` above ``start``, the push is
refused (``unreachable``, condition ``blocked``), since it would push whatever lies above the start instead.
The push ends early where the tool meets ``push_max_force`` (a parcel jammed against a wall). A completed push
is the outcome ``pushed``; it is not a pick attempt (docs/cell.md, 'The parting push').
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from parcelpick_env.envs.grasp import Failure, PickExecutor, PickResult
from parcelpick_env.robot.arm import Contact
from parcelpick_env.scene.scene import Scene

PUSH_START_TOLERANCE = 0.01  # m: a descent that stops higher than this above the start refuses the push
DOWN = np.array([0.0, 0.0, -1.0])  # the tool's axis throughout: cup first, straight down


def is_push_action(action: np.ndarray) -> bool:
    """Whether an action is a ``pose_push`` parting push: seven numbers, the last (the kind) negative."""
    a = np.asarray(action)
    return a.shape == (7,) and bool(a[6] < 0)


def pick_action(pose: np.ndarray, action_mode: str) -> np.ndarray:
    """A pick's ``pose`` action (point, outward normal) as the env's ``action_mode`` takes it: float32, with the kind
    (1, a pick) appended in ``pose_push``."""
    pose = np.asarray(pose, dtype=np.float32)
    return np.append(pose, np.float32(1.0)) if action_mode == "pose_push" else pose


def horizontal_direction(direction: np.ndarray) -> np.ndarray | None:
    """The unit horizontal part of ``direction``, or None where it has (almost) none."""
    d = np.array([float(direction[0]), float(direction[1]), 0.0])
    norm = float(np.linalg.norm(d))
    return None if norm < 1e-3 else d / norm


def push(executor: PickExecutor, scene: Scene, start: np.ndarray, direction: np.ndarray) -> PickResult:
    """One parting push from ``start`` (the tool tip's lowest point, world frame) along the horizontal part of
    ``direction`` (``horizontal_direction`` must give one). Returns the moves as a pick's ``PickResult``."""
    ex, arm, g, sim = executor, executor.arm, executor.grasp, executor.sim
    d = horizontal_direction(direction)
    if d is None:
        raise ValueError("push direction has no horizontal part")
    start = np.asarray(start, dtype=np.float64)
    ex.begin()
    tool = arm.tool_links | {arm.tip_link}
    above = ex._obstacle_top(scene, start[:2], g.hover_corridor) + g.hover_clearance
    hover = np.array([start[0], start[1], max(above, start[2] + g.pregrasp_distance)])
    q_hover = arm.ik(hover, DOWN, seed=ex.ready_q, valid=lambda q: ex.planner.collision(q, margin=0.0) is None)
    if q_hover is None:
        return ex._result("unreachable", Failure("hover", condition="ik"))
    rep = ex._free_move("hover", q_hover)
    if not rep.ok:
        ex._retreat()
        return ex._result(rep.outcome, rep.failure)
    dt = sim.config.timestep

    def pressing(force: float) -> Callable[[list[Contact]], Contact | None]:
        """A stop rule: the first contact of a tool link pressing harder than ``force``."""
        return lambda contacts: next((c for c in contacts if c.link in tool and c.normal_force > force), None)

    failure = _driven_line(ex, "descend", start, g.approach_speed, stop=pressing(g.push_touch_force))
    if failure is None and float(ex.kin.tool_pose(arm.q)[0][2]) > start[2] + PUSH_START_TOLERANCE:
        failure = ("unreachable", Failure("descend", condition="blocked"))
    if failure is None:
        tip = ex.kin.tool_pose(arm.q)[0]
        failure = _driven_line(ex, "push", tip + g.push_distance * d, g.push_speed, stop=pressing(g.push_max_force))
    # rise clear of the pile before going home: whatever the tool still touches is not judged on the way up
    tip = ex.kin.tool_pose(arm.q)[0]
    up, _ = ex._line(arm.q, np.array([tip[0], tip[1], hover[2]]), DOWN, dt, g.approach_speed)
    if up is not None:
        ex._move = "rise"
        ex._execute(up, allowed_links=set(arm.link_names) | {-1})
    ex._retreat()
    if failure is not None:
        return ex._result(*failure)
    return ex._result("pushed")


def _driven_line(ex: PickExecutor, move: str, end: np.ndarray, speed: float, stop) -> tuple[str, Failure] | None:
    """The tip on a straight line to ``end``, tool down, driven with dynamics (tool links may touch); None
    where it ran (to its end, or until ``stop``), else the outcome and failure that end the push."""
    arm = ex.arm
    t0 = arm.sim_time
    ex._move = move
    line, why = ex._line(arm.q, end, DOWN, ex.sim.config.timestep, speed)
    if line is None:
        failure = Failure(move, condition=why)
        ex._report(move, "unreachable", failure, t_start=t0)
        return "unreachable", failure
    res = ex._execute(line, stop=stop, allowed_links=arm.tool_links | {arm.tip_link})
    if res.collision is not None:
        failure = Failure(move, res.link, body=res.collision.body)
        ex._report(move, "collision", failure, res.steps, t0)
        return "collision", failure
    ex._report(move, "stopped" if res.stopped_by is not None else "ok", steps=res.steps, t_start=t0)
    return None
