"""Time-parameterised joint trajectories with bounded velocity, acceleration and jerk (ruckig).

Two kinds of motion, both sampled at a fixed control ``dt`` so a driven arm gets one target per
physics step:

- ``joint_trajectory``: straight joint-space segments through waypoints (free-space moves, e.g. an
  OMPL plan). Each segment is a rest-to-rest 1-D ruckig profile of the segment's progress, bounded by
  the tightest joint, so every joint follows the same normalised profile and the arm stays exactly on
  the segment's line (ruckig's own phase synchronisation falls back to time synchronisation when the
  joints' limits differ, which would leave the line).
- ``path_trajectory``: a dense geometric joint path (e.g. IK along a Cartesian line) fitted by a
  cubic spline in joint-space arc length ``s``; a 1-D ruckig time law ``s(t)`` whose bounds come from
  the path's derivatives keeps every joint within its limits, and the sampled result is verified
  numerically (and slowed down if a bound is exceeded). This keeps the tool on its Cartesian line,
  e.g. a vertical tool axis while carrying.

The community ruckig has no intermediate waypoints, hence segment-by-segment profiles.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
import ruckig
from scipy.interpolate import CubicSpline

from parcelpick_env.robot.kinematics import ARM_DOF

BOUND_TOL = 1e-6  # relative slack on velocity and acceleration bounds (float round-off)
JERK_TOL = 0.02  # relative slack on the finite-difference jerk (sampling of piecewise-constant jerk)
MIN_SPACING = 0.25  # path_trajectory: thin out points closer than this fraction of the median spacing
CORNER_ANGLE = np.radians(45.0)  # path_trajectory: a sharper turn of the joint path is a stop
MAX_SLOWDOWNS = 12  # path_trajectory: retries at 0.9x speed before giving up


@dataclass(frozen=True)
class JointLimits:
    """Per-joint bounds: velocity (rad/s), acceleration (rad/s^2) and jerk (rad/s^3)."""

    velocity: tuple[float, ...]
    acceleration: tuple[float, ...]
    jerk: tuple[float, ...]

    def __post_init__(self) -> None:
        for name in ("velocity", "acceleration", "jerk"):
            v = np.asarray(getattr(self, name), dtype=np.float64)
            if v.shape != (ARM_DOF,) or not np.all(np.isfinite(v)) or not np.all(v > 0):
                raise ValueError(f"JointLimits.{name} needs {ARM_DOF} finite values > 0, got {getattr(self, name)}")
            object.__setattr__(self, name, tuple(float(x) for x in v))

    def arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return np.array(self.velocity), np.array(self.acceleration), np.array(self.jerk)

    def scaled(self, speed_scale: float) -> JointLimits:
        """The same motion shape slowed in time by ``speed_scale`` (v*s, a*s^2, j*s^3)."""
        if not 0 < speed_scale <= 1.0:
            raise ValueError(f"speed_scale must be in (0, 1], got {speed_scale}")
        v, a, j = self.arrays()
        return JointLimits(tuple(v * speed_scale), tuple(a * speed_scale**2), tuple(j * speed_scale**3))

    def slowed(self, speed_scale: float) -> JointLimits:
        """Velocity bounds times ``speed_scale`` s and acceleration and jerk bounds times s^2 (s in (0, 1]).

        A slower move whose acceleration still builds up as quickly as at full speed: ``scaled``'s jerk s^3
        stretches every ramp by 1/s, so a payload slowed to s = 0.3 spent a third of a second on each of the
        four ramps of a rest-to-rest move. The result is no longer the full-speed move re-timed, so a caller
        bounding a tool quantity by it measures the slowed move again (``grasp.PickExecutor._timed_within``).
        """
        if not 0 < speed_scale <= 1.0:
            raise ValueError(f"speed_scale must be in (0, 1], got {speed_scale}")
        v, a, j = self.arrays()
        return JointLimits(tuple(v * speed_scale), tuple(a * speed_scale**2), tuple(j * speed_scale**2))


# Velocity and acceleration: Kinova's hard joint limits for the 7-DoF Gen3, 1.33 rad/s and 4.94 rad/s^2 on
# the large actuators J1-4, 1.16 rad/s and 9.5 rad/s^2 on the small J5-7 (hard_joint_limits.yaml of Kinova's
# ros_kortex MoveIt configuration, which plans at them with velocity and acceleration scaling 1). They override
# the URDF's V12 velocity (gen3.VELOCITY_LIMIT), as in that configuration. A carried parcel needs no margin
# here: the lift and the carry are timed by its predicted ring load (GraspConfig.carry_load_target). Jerk:
# Kinova publishes none; we allow the acceleration to build up in 0.1 s (jerk = acceleration / 0.1 s), a
# modelling choice.
_GEN3_VELOCITY = (1.33, 1.33, 1.33, 1.33, 1.16, 1.16, 1.16)
_GEN3_ACCEL = (4.94, 4.94, 4.94, 4.94, 9.5, 9.5, 9.5)
GEN3_LIMITS = JointLimits(velocity=_GEN3_VELOCITY, acceleration=_GEN3_ACCEL,
                          jerk=tuple(a / 0.1 for a in _GEN3_ACCEL))


@dataclass
class Trajectory:
    """Joint states sampled every ``dt`` from t = 0 to ``duration`` (= t[-1]); ends exactly at the goal."""

    t: np.ndarray  # (K,)
    q: np.ndarray  # (K, 7)
    qd: np.ndarray  # (K, 7)
    qdd: np.ndarray  # (K, 7)
    dt: float

    @property
    def duration(self) -> float:
        return float(self.t[-1])

    def __len__(self) -> int:
        return len(self.t)


def _check_dt(dt: float) -> None:
    if not (math.isfinite(dt) and 0 < dt <= 0.1):
        raise ValueError(f"dt must be in (0, 0.1] s, got {dt}")


def _as_q(q, name: str) -> np.ndarray:
    arr = np.asarray(q, dtype=np.float64)
    if arr.shape != (ARM_DOF,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be {ARM_DOF} finite joint values, got shape {arr.shape}")
    return arr


def _grid(duration: float, dt: float) -> np.ndarray:
    """Sample times 0, dt, ..., K dt with K dt >= duration (the last sample holds the goal)."""
    k = max(1, math.ceil(duration / dt - 1e-9))
    return np.arange(k + 1) * dt


def hold_trajectory(q, duration: float, dt: float) -> Trajectory:
    """Stand still at ``q`` for ``duration`` (e.g. a dwell while the vacuum builds), driven like any move."""
    _check_dt(dt)
    q = _as_q(q, "q")
    t = _grid(max(duration, dt), dt)
    zeros = np.zeros((len(t), ARM_DOF))
    return Trajectory(t, np.repeat(q[None], len(t), axis=0), zeros, zeros.copy(), dt)


def concatenate(trajectories: list[Trajectory]) -> Trajectory:
    """Rest-to-rest trajectories one after another (each must start where the previous one ends)."""
    if not trajectories:
        raise ValueError("concatenate needs at least one trajectory")
    dt = trajectories[0].dt
    parts = [trajectories[0]]
    for prev, nxt in itertools.pairwise(trajectories):
        if abs(nxt.dt - dt) > 1e-12:
            raise ValueError(f"concatenate: dt {nxt.dt} differs from {dt}")
        if np.abs(nxt.q[0] - prev.q[-1]).max() > 1e-6:
            raise ValueError("concatenate: a trajectory does not start where the previous one ends")
        parts.append(nxt)
    t = [parts[0].t]
    for part in parts[1:]:
        t.append(t[-1][-1] + part.t[1:])

    def joined(name: str) -> np.ndarray:  # each later part's first sample repeats the previous end
        return np.concatenate([getattr(parts[0], name)] + [getattr(x, name)[1:] for x in parts[1:]])

    return Trajectory(np.concatenate(t), joined("q"), joined("qd"), joined("qdd"), dt)


def joint_trajectory(start_q, waypoints, limits: JointLimits = GEN3_LIMITS, dt: float = 1.0 / 240.0
                     ) -> Trajectory:
    """Straight joint-space segments start -> waypoints[0] -> ..., each rest-to-rest and the fastest
    jerk-limited motion along its line under ``limits``."""
    _check_dt(dt)
    start = _as_q(start_q, "start_q")
    pts = np.asarray(waypoints, dtype=np.float64).reshape(-1, ARM_DOF)
    if not np.all(np.isfinite(pts)):
        raise ValueError("waypoints must be finite")
    points = [start]
    for w in pts:
        if np.abs(w - points[-1]).max() > 1e-9:
            points.append(w)
    if len(points) == 1:
        return hold_trajectory(start, 0.0, dt)
    v, a, j = limits.arrays()
    steps = [b - a_ for a_, b in itertools.pairwise(points)]
    # the segment's normalised progress u in [0, 1] gets the tightest of the joints' bounds, scaled by
    # their distances; q = q_a + (q_b - q_a) u(t) is then straight and within every joint's limits
    laws = [_time_law(1.0, *(float(np.min(lim / np.maximum(np.abs(d), 1e-300))) for lim in (v, a, j)))
            for d in steps]
    ends = np.cumsum([law.duration for law in laws])
    t = _grid(float(ends[-1]), dt)
    which = np.minimum(np.searchsorted(ends, t, side="right"), len(laws) - 1)
    starts = np.concatenate([[0.0], ends[:-1]])
    u = np.array([laws[seg].at_time(min(tk - starts[seg], laws[seg].duration)) for seg, tk in zip(which, t)])[:, :, 0]
    delta = np.array(steps)[which]
    q = np.array(points)[which] + delta * u[:, :1]
    qd, qdd = delta * u[:, 1:2], delta * u[:, 2:3]
    q[-1], qd[-1], qdd[-1] = points[-1], 0.0, 0.0  # exact goal
    return Trajectory(t, q, qd, qdd, dt)


def _thin(path: np.ndarray) -> np.ndarray:
    """The path without points crowded closer than ``MIN_SPACING`` of its median spacing (a spline
    through nearly coincident points takes their tiny offsets as sharp curvature); ends are kept."""
    seg = np.linalg.norm(np.diff(path, axis=0), axis=1)
    if seg.sum() <= 1e-9:
        return path[:1]
    s = np.concatenate([[0.0], np.cumsum(seg)])
    spacing = MIN_SPACING * float(np.median(seg[seg > 1e-9]))
    keep = np.unique(np.searchsorted(s, np.arange(0.0, s[-1], spacing)))
    keep = keep[s[keep] <= s[-1] - spacing]  # the goal itself is always kept, with room before it
    return path[np.append(keep, len(path) - 1)]


def _corners(pts: np.ndarray) -> np.ndarray:
    """Interior vertices where the joint path turns by more than ``CORNER_ANGLE`` (e.g. the end of a
    lift and the start of a carry): the path stops there rather than being rounded at a crawl."""
    d = np.diff(pts, axis=0)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    cos = np.sum(d[:-1] * d[1:], axis=1)
    return np.flatnonzero(cos < np.cos(CORNER_ANGLE)) + 1


def _path_spline(pts: np.ndarray) -> CubicSpline | None:
    """A C2 cubic spline q(s) through distinct points in joint-space arc length, or None for a point."""
    if len(pts) < 2:
        return None
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    return CubicSpline(s, pts, axis=0)


def _path_bounds(spline: CubicSpline, limits: JointLimits) -> tuple[float, float, float]:
    """Bounds (sd, sdd, sddd) on the 1-D time law such that every joint stays within ``limits``:
    qd = q' sd, qdd = q'' sd^2 + q' sdd, qddd = q''' sd^3 + 3 q'' sd sdd + q' sddd.

    q'' is piecewise linear and q''' piecewise constant on a cubic spline, so knots and interval
    midpoints give their exact maxima. Half of each acceleration and jerk budget goes to the path's
    curvature terms, the rest to the time law's own acceleration and jerk.
    """
    v, a, j = limits.arrays()
    knots = spline.x
    s = np.sort(np.concatenate([knots, 0.5 * (knots[:-1] + knots[1:])]))
    d1 = np.abs(spline(s, 1)).max(axis=0) + 1e-12
    d2 = np.abs(spline(s, 2)).max(axis=0)
    d3 = np.abs(spline(s, 3)).max(axis=0)
    sd = float(np.min(v / d1))
    sd = min(sd, float(np.min(np.sqrt(0.5 * a / np.maximum(d2, 1e-12)))))
    for _ in range(60):
        sdd = float(np.min((a - d2 * sd**2) / d1))
        curvature_jerk = d3 * sd**3 + 3 * d2 * sd * sdd
        if np.all(curvature_jerk <= 0.5 * j):
            return sd, sdd, float(np.min((j - curvature_jerk) / d1))
        sd *= 0.8
    raise RuntimeError("path_trajectory: the path's curvature leaves no jerk budget")


def _time_law(length: float, sd: float, sdd: float, sddd: float) -> ruckig.Trajectory:
    otg = ruckig.Ruckig(1)
    inp = ruckig.InputParameter(1)
    inp.current_position, inp.target_position = [0.0], [length]
    inp.current_velocity = inp.current_acceleration = inp.target_velocity = inp.target_acceleration = [0.0]
    inp.max_velocity, inp.max_acceleration, inp.max_jerk = [sd], [sdd], [sddd]
    out = ruckig.Trajectory(1)
    result = otg.calculate(inp, out)
    if result not in (ruckig.Result.Working, ruckig.Result.Finished):
        raise RuntimeError(f"ruckig could not time the path: {result}")
    return out


def bound_violation(traj: Trajectory, limits: JointLimits) -> float:
    """The largest ratio of |qd|, |qdd| or finite-difference |jerk| to its bound (<= 1 within limits;
    the jerk ratio is divided by 1 + JERK_TOL so that 1 means the tolerance is used up)."""
    v, a, j = limits.arrays()
    ratios = [np.abs(traj.qd).max(axis=0) / v, np.abs(traj.qdd).max(axis=0) / a]
    if len(traj) > 1:
        jerk = np.abs(np.diff(traj.qdd, axis=0)).max(axis=0) / traj.dt
        ratios.append(jerk / (j * (1 + JERK_TOL)))
    return float(np.max(np.concatenate(ratios)))


def path_trajectory(path, limits: JointLimits = GEN3_LIMITS, dt: float = 1.0 / 240.0,
                    speed_scale: float = 1.0) -> Trajectory:
    """Follow the dense joint path ``path`` (M, 7) from rest to rest, on a C2 spline through its points
    (with a stop at any corner sharper than ``CORNER_ANGLE``).

    The time law s(t) is a 1-D jerk-limited ruckig profile; the sampled trajectory is checked against
    ``limits`` and the law slowed by 0.9x until it holds (the spline's derivative bounds are exact,
    so this only absorbs sampling effects).
    """
    _check_dt(dt)
    pts = np.asarray(path, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != ARM_DOF or len(pts) < 1 or not np.all(np.isfinite(pts)):
        raise ValueError(f"path must be a finite (M, {ARM_DOF}) array, got shape {pts.shape}")
    pts = _thin(pts)
    if len(pts) < 2:
        return hold_trajectory(pts[0], 0.0, dt)
    cuts = [0, *_corners(pts).tolist(), len(pts) - 1]
    if len(cuts) > 2:
        return concatenate([_timed_path(pts[a:b + 1], limits, dt, speed_scale) for a, b in itertools.pairwise(cuts)])
    return _timed_path(pts, limits, dt, speed_scale)


def _timed_path(pts: np.ndarray, limits: JointLimits, dt: float, speed_scale: float) -> Trajectory:
    """path_trajectory on a thinned path without corners."""
    spline = _path_spline(pts)
    if spline is None:
        return hold_trajectory(pts[0], 0.0, dt)
    length = float(spline.x[-1])
    sd, sdd, sddd = _path_bounds(spline, limits.scaled(speed_scale))
    for _ in range(MAX_SLOWDOWNS):
        law = _time_law(length, sd, sdd, sddd)
        t = _grid(law.duration, dt)
        s, s1, s2 = (np.array(x)[:, 0] for x in zip(*(law.at_time(min(tk, law.duration)) for tk in t)))
        d1, d2 = spline(s, 1), spline(s, 2)
        traj = Trajectory(t, spline(s), d1 * s1[:, None], d2 * (s1**2)[:, None] + d1 * s2[:, None], dt)
        traj.q[-1], traj.qd[-1], traj.qdd[-1] = pts[-1], 0.0, 0.0
        if bound_violation(traj, limits) <= 1.0 + BOUND_TOL:
            return traj
        sd, sdd, sddd = 0.9 * sd, 0.81 * sdd, 0.729 * sddd
    raise RuntimeError(f"path_trajectory: bounds still exceeded after {MAX_SLOWDOWNS} slow-downs")
