"""Dex-Net 3.0 style suction policy: GQ-CNN quality on depth crops, searched by the cross-entropy method.

Candidates are the observed cloud's points (with their outward normals) that the depth image sees and
whose approach ``-n`` is within ``max_approach_angle_deg`` of vertical; their crops are cut at their
projections, as in training. CEM (Dex-Net 3.0): score ``num_seeds`` uniform seeds, then for
``cem_iterations`` rounds fit a GMM over the pixel positions of the best ``elite_fraction``, draw
``num_gmm_samples`` positions, snap each to the nearest eligible candidate pixel and score those.
Every scored candidate is ranked, and the shared NMS / top-k picks the output.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import torch
from scipy.spatial import cKDTree

from policies.base import Candidates, Policy
from policies.observation import camera, check_workspace, depth_image, in_box, point_cloud
from policies.postprocess import select_candidates

from .cem import fit_gmm
from .config import DexNetConfig
from .crops import DepthMosaic
from .network import load_checkpoint
from .projection import approach_angles, eligible_points

DEFAULT_CHECKPOINT = Path(__file__).with_name("checkpoint.pt")
# Search settings a caller may change; the rest of DexNetConfig is fixed by what the network was trained on.
SEARCH_FIELDS = ("max_approach_angle_deg", "num_seeds", "num_gmm_samples", "cem_iterations", "elite_fraction",
                 "gmm_component_fraction", "gmm_em_iterations", "gmm_reg_covar", "max_snap_distance", "nms_radius")


@dataclasses.dataclass
class EligibleSet:
    """Candidate points a suction may use, with what their crops need."""

    points: np.ndarray  # (E, 3) world
    normals: np.ndarray  # (E, 3) unit, outward
    uv: np.ndarray  # (E, 2) pixels
    depth: np.ndarray  # (E,) camera z
    extrinsics: np.ndarray  # (4, 4) camera -> world

    def __len__(self) -> int:
        return int(self.depth.shape[0])


def _observation(obs: Mapping[str, np.ndarray], info: Mapping[str, Any] | None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Validated (depth, points, normals, K, T); a clear ValueError for anything unusable."""
    depth = depth_image(obs, "DexNetPolicy")
    points, normals = point_cloud(obs, "DexNetPolicy")
    if len(points) == 0:
        raise ValueError("obs['points'] is empty")
    K, T = camera(info, "DexNetPolicy")
    return depth, points, normals, K, T


class DexNetPolicy(Policy):
    name = "dexnet"

    def __init__(self, checkpoint: str | Path | None = None, seed: int | None = 0,
                 workspace: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None,
                 **search: Any) -> None:
        """Load ``checkpoint`` (default: the one shipped next to this file); ``search`` overrides CEM
        settings (``SEARCH_FIELDS``) without touching what the network was trained on.

        ``workspace`` is a world box ((xmin, ymin, zmin), (xmax, ymax, zmax)) candidates must lie in,
        e.g. the bin for closed-loop runs: the network was trained on clouds cropped to the bin, so the
        floor around it, which the env's cloud includes, is unfamiliar and may score well.
        """
        unknown = set(search) - set(SEARCH_FIELDS)
        if unknown:
            raise ValueError(f"DexNetPolicy: unknown or fixed-by-checkpoint settings {sorted(unknown)}; "
                             f"adjustable: {SEARCH_FIELDS}")
        self.workspace = None if workspace is None else check_workspace(workspace, "DexNetPolicy")
        self.checkpoint = Path(checkpoint) if checkpoint is not None else DEFAULT_CHECKPOINT
        self.model, self.metadata = load_checkpoint(self.checkpoint)
        # Crop and network fields come from the checkpoint; search fields from today's defaults, then overrides.
        defaults = DexNetConfig()
        self.config: DexNetConfig = dataclasses.replace(
            self.model.config, **{**{name: getattr(defaults, name) for name in SEARCH_FIELDS}, **search})
        self._rng = np.random.default_rng(seed)

    def reset(self, seed: int | None = None) -> None:
        """Reseed the CEM sampler for a reproducible episode; ``None`` keeps the current stream."""
        if seed is not None:
            self._rng = np.random.default_rng(seed)

    def eligible(self, depth: np.ndarray, points: np.ndarray, normals: np.ndarray, K: np.ndarray,
                 T: np.ndarray) -> EligibleSet:
        """Cloud points (inside the workspace, if any) seen by the depth image with an approach within the
        allowed angle of vertical."""
        if self.workspace is not None:
            inside = in_box(points, *self.workspace)
            points, normals = points[inside], normals[inside]
        keep, uv, z, unit = eligible_points(depth, points, normals, K, T, self.config.min_vertical_cos,
                                            self.config.visibility_tolerance)
        return EligibleSet(points=points[keep], normals=unit, uv=uv, depth=z, extrinsics=T)

    def score(self, mosaic: DepthMosaic, cand: EligibleSet, idx: np.ndarray, K: np.ndarray) -> np.ndarray:
        image_angle, tilt = approach_angles(cand.normals[idx], cand.extrinsics)
        crops = mosaic.crops(cand.uv[idx], cand.depth[idx], image_angle, K[0, 0], K[1, 1], self.config)
        q = self.model.quality(crops, torch.as_tensor(cand.depth[idx], dtype=torch.float32),
                               torch.as_tensor(tilt, dtype=torch.float32))
        return q.numpy().astype(np.float64)

    def search(self, depth: np.ndarray, cand: EligibleSet, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cross-entropy method over candidate pixels: (indices into ``cand``, quality) of every scored one."""
        cfg, rng = self.config, self._rng
        mosaic = DepthMosaic(depth)
        width = float(depth.shape[1])
        feature = cand.uv / width  # GMM space: pixels / image width
        tree = cKDTree(feature, balanced_tree=False, compact_nodes=False)  # quicker to build, same answers
        population = rng.choice(len(cand), size=min(cfg.num_seeds, len(cand)), replace=False)
        quality = np.full(len(cand), np.nan)
        quality[population] = self.score(mosaic, cand, population, K)
        for _ in range(cfg.cem_iterations):
            num_elite = max(1, math.ceil(cfg.elite_fraction * len(population)))
            elite = population[np.argsort(-quality[population], kind="stable")[:num_elite]]
            gmm = fit_gmm(feature[elite], max(1, math.ceil(cfg.gmm_component_fraction * num_elite)), rng,
                          iterations=cfg.gmm_em_iterations, reg_covar=cfg.gmm_reg_covar)
            distance, nearest = tree.query(gmm.sample(cfg.num_gmm_samples, rng))
            population = np.unique(nearest[distance <= cfg.max_snap_distance])
            if len(population) == 0:
                break
            new = population[np.isnan(quality[population])]
            if len(new):
                quality[new] = self.score(mosaic, cand, new, K)
        scored = np.flatnonzero(~np.isnan(quality))
        return scored, quality[scored]

    def predict(self, obs: Mapping[str, np.ndarray], info: Mapping[str, Any] | None = None,
                top_k: int = 50) -> Candidates:
        """Ranked candidates; empty when no observed surface can be approached within the allowed angle."""
        if top_k < 1:
            raise ValueError(f"top_k must be >= 1, got {top_k}")
        depth, points, normals, K, T = _observation(obs, info)
        cand = self.eligible(depth, points, normals, K, T)
        if len(cand) == 0:
            empty = np.zeros((0, 3), np.float32)
            return Candidates(points=empty, normals=empty.copy(), scores=np.zeros(0, np.float32))
        idx, quality = self.search(depth, cand, K)
        return select_candidates(cand.points[idx], cand.normals[idx], quality, top_k=top_k,
                                 nms_radius=self.config.nms_radius)
