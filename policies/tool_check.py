"""The deployment check a real cell runs before it commits to a pick: is the tool clear of what the camera sees?

A learned policy ranks suction points; the paper's labels (and SuctionNet's) judge the tool with a 10 mm probe
that ignores the cell's 40 mm cup, its flange and the wrist above it, so a top-ranked point beside a wall or a tall
neighbour can be one the arm cannot come down to (`unreachable: descend`). ``ToolCheckedPolicy`` keeps the wrapped
policy's ranking and moves the candidates whose physical tool meets the observed scene behind the rest.

It sees only what any policy sees: the depth image and the camera calibration. The depth image becomes a surface
mesh (``observed_surface``: one vertex per ``stride`` pixels, two triangles per pixel quad), with the triangles that
bridge a depth jump kept: they close the camera's shadow behind an edge, so what the camera cannot see counts as
occupied, as a heightmap planner takes it. The tool is the physical one (``suction.physical.physical_tool``: the
cup's radius up to the flange, then the flange and wrist, plus the motion planner's clearance), probed with the
shared scorer's ``collision_scores``, so labels, oracle and this check use one definition of a free tool.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np
import open3d as o3d

from parcelpick_env.envs.config import EnvConfig
from parcelpick_env.suction.collision import collision_scores
from parcelpick_env.suction.config import SuctionConfig
from parcelpick_env.suction.geometry import o3d_tensor
from parcelpick_env.suction.physical import physical_tool
from policies.base import Candidates, Policy
from policies.heatmap import pixels_to_world
from policies.observation import camera, depth_image

DEPTH_OBS_MODES: tuple[str, ...] = ("pointcloud", "rgbd")  # the env's observation modes that carry obs['depth']


@dataclass(frozen=True)
class ToolCheckConfig:
    """``candidates``: how many of the wrapped policy's ranked picks are checked (the rest keep their order);
    ``stride``: depth pixels between mesh vertices (3 at 640x480 is about 5 mm on the pile, the probe's own ring
    spacing: on 30-parcel piles 1 verdict in 200 differs from every pixel's mesh, at a tenth of its time;
    ``benchmarks/bench_tool_check.py``)."""

    candidates: int = 50
    stride: int = 3
    suction: SuctionConfig = field(default_factory=lambda: EnvConfig().suction)  # the cell's cup, as shipped

    def __post_init__(self) -> None:
        for name in ("candidates", "stride"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"ToolCheckConfig.{name} must be an int >= 1, got {value!r}")
        if not isinstance(self.suction, SuctionConfig):
            raise ValueError(f"ToolCheckConfig.suction must be a SuctionConfig, got {type(self.suction).__name__}")


def observed_surface(depth: np.ndarray, intrinsics: np.ndarray, extrinsics: np.ndarray, stride: int = 3
                     ) -> o3d.t.geometry.RaycastingScene:
    """A ray scene of the surface the depth image sees: a vertex every ``stride`` pixels, two triangles per quad of
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
    scene = o3d.t.geometry.RaycastingScene()
    if len(triangles):
        scene.add_triangles(o3d_tensor(np.ascontiguousarray(vertices, dtype=np.float32)),
                            o3d_tensor(np.ascontiguousarray(triangles, dtype=np.uint32)))
    return scene


def tool_clear(obs: Mapping[str, Any], info: Mapping[str, Any] | None, points: np.ndarray, normals: np.ndarray,
               config: ToolCheckConfig = ToolCheckConfig()) -> np.ndarray:
    """(K,) bool: the cell's physical tool, on each candidate's approach axis, is clear of the observed surface."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(points) == 0:
        return np.zeros(0, dtype=bool)
    K, T = camera(info, "the tool check")
    scene = observed_surface(depth_image(obs, "the tool check"), K, T, config.stride)
    free = collision_scores(scene, points, np.asarray(normals, dtype=np.float64).reshape(-1, 3),
                            physical_tool(config.suction))
    return free > 0.5


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
    """``inner``'s ranking with the physical tool's collision check applied to its first ``candidates``: a pick
    whose tool meets the observed scene scores 0 (the suction quality is a product with its collision score), so
    it goes behind every clear one, in its old order, and ``act`` takes the best clear pick (with none clear, the
    first as before). ``last_clear`` holds the verdicts of the last call, in the returned order."""

    def __init__(self, inner: Policy, config: ToolCheckConfig | None = None):
        why = tool_check_refusal(inner)
        if why is not None:
            raise ValueError(why)
        self.inner = inner
        self.config = config or ToolCheckConfig()
        self.name = f"{inner.name}+tool_check"
        self.obs_mode = inner.obs_mode
        self.last_clear = np.zeros(0, dtype=bool)

    def reset(self, seed: int | None = None) -> None:
        self.inner.reset(seed)

    def predict(self, obs: Mapping[str, np.ndarray], info: Mapping[str, Any] | None = None,
                top_k: int = 50) -> Candidates:
        ranked = self.inner.predict(obs, info, top_k=max(top_k, self.config.candidates))
        checked = min(len(ranked), self.config.candidates)
        clear = np.ones(len(ranked), dtype=bool)
        clear[:checked] = tool_clear(obs, info, ranked.points[:checked], ranked.normals[:checked], self.config)
        floor = min(0.0, float(ranked.scores.min())) if len(ranked) else 0.0
        scores = np.where(clear, ranked.scores, floor).astype(np.float32)
        order = np.argsort(-scores, kind="stable")[:top_k]
        self.last_clear = clear[order]
        return Candidates(points=ranked.points[order], normals=ranked.normals[order], scores=scores[order])
