"""The deployment check a real cell runs before it commits to a pick: is the tool clear of what the camera sees?

A learned policy ranks suction points; the paper's labels (and SuctionNet's) judge the tool with a 10 mm probe
that ignores the cell's 40 mm cup, its flange and the wrist above it, so a top-ranked point beside a wall or a tall
neighbour can be one the arm cannot come down to (`unreachable: descend`). ``ToolCheckedPolicy`` keeps the wrapped
policy's ranking and moves the candidates whose physical tool meets the observed scene behind the rest.

It sees only what any policy sees: the depth image and the camera calibration. The depth image becomes a surface
mesh (``observed_mesh``: one vertex per ``stride`` pixels, two triangles per pixel quad), with the triangles that
bridge a depth jump kept: they close the camera's shadow behind an edge, so what the camera cannot see counts as
occupied, as a heightmap planner takes it. The tool is the physical one (``suction.physical.physical_tool``: the
cup's radius up to the flange, then the flange and wrist, plus the motion planner's clearance), probed with the
shared scorer's ``collision_scores``, so labels, oracle and this check use one definition of a free tool.

With ``seal`` (on by default) it also asks whether the cell's cup would seal where it lands, judged on the same observed
surface with the shared bellows seal (``suction.cup_seal.bellows_seal``, the cup pressed to first touch as the
labels place it): a pick whose 40 mm lip hangs over a face's edge fails it, as it fails in the env (`no_seal:
miss` or `edge`). The paper's labels score the seal with a 10 mm cup, so a model trained on them ranks points
10-20 mm from an edge that the cell's cup cannot seal.

With ``covered_factor`` below 1 (off by default) a passing pick on a surface that the observed pile rises above
(``policies/exposure.py``: a parcel under another) has its score scaled by it, so the top layer goes first.

With ``retry_radius`` above 0 (0.05 m by default, ``RETRY_RADIUS``; 0 turns it off) the cell does not go back where
a pick failed while it has another passing pick: a candidate within that distance of a pick that failed since the
last success (where the cup touched, read from the env's ``info``, else the pick the check chose) counts as not
passing. A failed pick mostly leaves the pile as it was, so a policy that reads the same geometry takes the same
pick again; on the report's piles the rule raised R_object for every policy it wraps but random (docs/evaluation.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from numbers import Real
from typing import Any, Mapping

import numpy as np
import trimesh

from parcelpick_env.envs.config import EnvConfig
from parcelpick_env.suction.collision import collision_scores
from parcelpick_env.suction.config import SuctionConfig
from parcelpick_env.suction.cup_seal import bellows_seal
from parcelpick_env.suction.physical import physical_tool
from parcelpick_env.suction.seal import SealScene
from policies.base import Candidates, Policy
from policies.exposure import ExposureConfig, check_covered_factor, exposed_picks
from policies.failed_picks import FailedPicks
from policies.heatmap import pixels_to_world
from policies.observation import camera, depth_image

DEPTH_OBS_MODES: tuple[str, ...] = ("pointcloud", "rgbd")  # the env's observation modes that carry obs['depth']
# m: the cell's retry rule's radius, chosen before it was measured and not tuned: on the report's stacked cells it
# raised R_object by 6.5 to 30 points for each wrapped policy it was measured on (docs/evaluation.md)
RETRY_RADIUS = 0.05


@dataclass(frozen=True)
class ToolCheckConfig:
    """``candidates``: how many of the wrapped policy's ranked picks are checked (the rest keep their order);
    ``stride``: depth pixels between mesh vertices (3 at 640x480 is about 5 mm on the pile, the probe's own ring
    spacing: on 30-parcel piles 1 verdict in 200 differs from every pixel's mesh, at a tenth of its time;
    ``benchmarks/bench_tool_check.py``); ``seal``: also require the cup to seal on the observed surface, with at
    least the env's ``seal_threshold``."""

    candidates: int = 50
    stride: int = 3
    seal: bool = True
    # a passing pick on a surface that something observed rises above (a parcel under another, policies/exposure.py)
    # has its score multiplied by this, so the top layer goes first; 1.0: not judged
    covered_factor: float = 1.0
    exposure: ExposureConfig = field(default_factory=ExposureConfig)
    # m: a passing pick this close to one that failed since the last success counts as not passing, while another
    # passes (the cell does not go back where it just failed); 0: off
    retry_radius: float = RETRY_RADIUS
    suction: SuctionConfig = field(default_factory=lambda: EnvConfig().suction)  # the cell's cup, as shipped
    seal_threshold: float = field(default_factory=lambda: float(EnvConfig().grasp.seal_threshold))

    def __post_init__(self) -> None:
        for name in ("candidates", "stride"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"ToolCheckConfig.{name} must be an int >= 1, got {value!r}")
        check_covered_factor("ToolCheckConfig", self.covered_factor)
        check_retry_radius("ToolCheckConfig", self.retry_radius)
        if not isinstance(self.exposure, ExposureConfig):
            raise ValueError(f"ToolCheckConfig.exposure must be an ExposureConfig, got {type(self.exposure).__name__}")
        if not isinstance(self.seal, bool):
            raise ValueError(f"ToolCheckConfig.seal must be a bool, got {self.seal!r}")
        if not isinstance(self.suction, SuctionConfig):
            raise ValueError(f"ToolCheckConfig.suction must be a SuctionConfig, got {type(self.suction).__name__}")
        if self.seal and self.suction.seal_model != "bellows":
            raise ValueError("ToolCheckConfig.seal needs the cell's bellows cup (suction.seal_model='bellows'), "
                             f"got {self.suction.seal_model!r}")
        if not 0.0 <= self.seal_threshold <= 1.0:
            raise ValueError(f"ToolCheckConfig.seal_threshold must be in [0, 1], got {self.seal_threshold!r}")


def check_retry_radius(owner: str, value: object) -> None:
    """``value`` is a retry radius, a finite number of metres >= 0 (0: off); else one ValueError naming ``owner``."""
    ok = isinstance(value, Real) and not isinstance(value, bool) and math.isfinite(value) and float(value) >= 0.0
    if not ok:
        raise ValueError(f"{owner}.retry_radius must be a finite number of metres >= 0 (0: off), got {value!r}")


def observed_mesh(depth: np.ndarray, intrinsics: np.ndarray, extrinsics: np.ndarray, stride: int = 3
                  ) -> trimesh.Trimesh:
    """The surface the depth image sees (world frame): a vertex every ``stride`` pixels, two triangles per quad of
    four valid vertices (a pixel without depth leaves a hole), triangles across depth jumps included."""
    rows, cols = np.mgrid[0:depth.shape[0]:stride, 0:depth.shape[1]:stride]
    h, w = rows.shape
    valid = depth[rows, cols] > 0
    vertices = pixels_to_world(rows.ravel(), cols.ravel(), depth, intrinsics, extrinsics)
    index = np.arange(h * w).reshape(h, w)
    a, b, c, d = index[:-1, :-1], index[:-1, 1:], index[1:, :-1], index[1:, 1:]
    quad = (valid[:-1, :-1] & valid[:-1, 1:] & valid[1:, :-1] & valid[1:, 1:]).ravel()
    triangles = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3)[quad],
                                np.stack([b, c, d], -1).reshape(-1, 3)[quad]])
    return trimesh.Trimesh(vertices, triangles, process=False)


class ObservedSurface:
    """The observed surface in one ray scene that serves both probes, the tool's and the cup's."""

    def __init__(self, mesh: trimesh.Trimesh, suction: SuctionConfig):
        self.suction = suction
        self._seal_scene = SealScene.of_surface(mesh, suction) if len(mesh.faces) else None

    def tool_clear(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """(K,) bool: the physical tool on each candidate's approach axis meets none of the surface."""
        if self._seal_scene is None:
            return np.ones(len(points), dtype=bool)
        return collision_scores(self._seal_scene.scene, points, normals, physical_tool(self.suction)) > 0.5

    def seal(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """(K,) the cup's bellows seal quality, pressed along -normal to first touch on the surface."""
        if self._seal_scene is None:
            return np.zeros(len(points), dtype=np.float32)
        return bellows_seal(self._seal_scene, points, -normals, np.zeros(len(points), dtype=np.int64),
                            measure_gap=False).quality


def check_picks(obs: Mapping[str, Any], info: Mapping[str, Any] | None, points: np.ndarray, normals: np.ndarray,
                config: ToolCheckConfig = ToolCheckConfig()) -> np.ndarray:
    """(K,) bool: each candidate passes the cell's check (its tool is clear and, with ``config.seal``, its cup
    seals), judged on the surface the depth image sees."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    if len(points) == 0:
        return np.zeros(0, dtype=bool)
    K, T = camera(info, "the tool check")
    surface = ObservedSurface(observed_mesh(depth_image(obs, "the tool check"), K, T, config.stride), config.suction)
    passed = surface.tool_clear(points, normals)
    if config.seal:
        passed &= surface.seal(points, normals) >= config.seal_threshold
    return passed


def tool_clear(obs: Mapping[str, Any], info: Mapping[str, Any] | None, points: np.ndarray, normals: np.ndarray,
               config: ToolCheckConfig = ToolCheckConfig()) -> np.ndarray:
    """(K,) bool: the cell's physical tool, on each candidate's approach axis, is clear of the observed surface."""
    return check_picks(obs, info, points, normals, replace(config, seal=False))


def tool_check_refusal(policy: Policy | type[Policy]) -> str | None:
    """Why ``policy`` (an instance or its class) cannot be wrapped, or None: the check needs the depth image, and
    re-ranks what ``predict`` returns, so a policy with its own ``act`` is out. The oracle is out by design: it
    reads the privileged ground truth and checks its tool against the true scene itself."""
    cls = policy if isinstance(policy, type) else type(policy)
    name = getattr(policy, "name", cls.__name__)
    if cls.act is not Policy.act:
        return f"policy {name!r} acts otherwise (its own act); the tool check re-ranks predicted candidates"
    mode = getattr(policy, "obs_mode", "pointcloud")
    if mode not in DEPTH_OBS_MODES:
        return f"policy {name!r} observes obs_mode={mode!r}, which has no depth image for the tool check"
    return None


class ToolCheckedPolicy(Policy):
    """``inner``'s ranking with the cell's check applied to its first ``candidates``: a pick whose tool meets the
    observed scene (or, with ``seal``, whose cup would not seal) scores 0 (the suction quality is a product with
    its collision and seal scores), so it goes behind every passing one, in its old order, and ``act`` takes the
    best passing pick (with none passing, the first as before). With ``retry_radius`` a passing pick near one that
    failed since the last success scores as a failing one while another passes. ``last_passed`` and
    ``last_retried`` hold the last call's verdicts, in the returned order."""

    def __init__(self, inner: Policy, config: ToolCheckConfig | None = None):
        why = tool_check_refusal(inner)
        if why is not None:
            raise ValueError(why)
        self.inner = inner
        self.config = config or ToolCheckConfig()
        if self.config.covered_factor < 1.0 and inner.obs_mode != "pointcloud":
            raise ValueError(f"policy {inner.name!r} observes obs_mode={inner.obs_mode!r}; ToolCheckConfig.covered_factor "
                             "< 1 judges covered surfaces on the observed cloud, which needs obs_mode='pointcloud'")
        self.name = f"{inner.name}+tool_check"
        self.obs_mode = inner.obs_mode
        self.last_passed = np.zeros(0, dtype=bool)
        self.last_retried = np.zeros(0, dtype=bool)
        self.failed = FailedPicks()
        self._offered: np.ndarray | None = None

    def reset(self, seed: int | None = None) -> None:
        self.inner.reset(seed)
        self.failed.clear()
        self._offered = None

    def predict(self, obs: Mapping[str, np.ndarray], info: Mapping[str, Any] | None = None,
                top_k: int = 50) -> Candidates:
        if self.config.retry_radius > 0:
            self.failed.note(info, self._offered)
        ranked = self.inner.predict(obs, info, top_k=max(top_k, self.config.candidates))
        checked = min(len(ranked), self.config.candidates)
        passed = np.ones(len(ranked), dtype=bool)
        passed[:checked] = check_picks(obs, info, ranked.points[:checked], ranked.normals[:checked], self.config)
        retried = passed & self.failed.near(ranked.points, self.config.retry_radius)
        if not (passed & ~retried).any():  # every passing pick is where one failed: go back rather than give up
            retried[:] = False
        floor = min(0.0, float(ranked.scores.min())) if len(ranked) else 0.0
        scores = np.where(passed & ~retried, ranked.scores, floor).astype(np.float32)
        if self.config.covered_factor < 1.0 and checked:
            exposed = np.ones(len(ranked), dtype=bool)
            exposed[:checked] = exposed_picks(obs, info, ranked.points[:checked], self.config.exposure)
            discounted = np.minimum(scores, scores * np.float32(self.config.covered_factor))
            scores = np.where(passed & ~exposed, discounted, scores).astype(np.float32)
        order = np.argsort(-scores, kind="stable")[:top_k]
        self.last_passed = passed[order]
        self.last_retried = retried[order]
        self._offered = ranked.points[order[0]].astype(np.float64) if len(order) else None
        return Candidates(points=ranked.points[order], normals=ranked.normals[order], scores=scores[order])
