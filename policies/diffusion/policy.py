"""Diffusion-Suction as a ParcelPick policy: observation cloud -> denoised per-point scores -> NMS -> top-k."""

from __future__ import annotations

import copy
import os
import warnings
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np
import torch

from policies.base import Candidates, Policy
from policies.diffusion.checkpoint import DEFAULT_CHECKPOINT, load_model
from policies.diffusion.model import DiffusionSuction, check_draws
from policies.diffusion.pointnet2 import fold_batchnorm
from policies.diffusion.candidates import depth_candidates, has_depth_view
from policies.diffusion.neighbourhood import grid_sample, model_inputs, model_inputs_at, sample_indices
from policies.observation import point_cloud
from policies.postprocess import NMS_RADIUS, select_candidates

MIN_POINTS = 16  # below this a cloud cannot hold a suction candidate worth ranking: empty Candidates
# Inference precisions of the encoder: bfloat16 runs its matmuls under torch.autocast (CPUs with AVX512-BF16 or AMX do
# them at up to twice the float32 rate: the paper preset's encoder 218 -> 153 ms on 2 cores); float32 keeps the trained
# numerics exactly. The decoder stays in float32: its matmuls are small, and in bfloat16 it was slower (35 -> 48 ms).
PRECISIONS: dict[str, torch.dtype] = {"float32": torch.float32, "bfloat16": torch.bfloat16}


def cpu_runs_bfloat16_natively() -> bool:
    """Whether oneDNN has bfloat16 matmul instructions here (AVX512-BF16 or AMX). Without them it emulates them:
    on an AVX2-only host the paper preset's encoder took 2,485 ms in bfloat16 against 267 ms in float32."""
    return bool(torch.ops.mkldnn._is_mkldnn_bf16_supported())


@dataclass
class Trajectory:
    """The last denoising run, for replays: the denoised points and the score maps after each DDIM step."""

    points: np.ndarray  # (M, 3)
    maps: np.ndarray  # (steps + 1, M, C), noise first, final scores last


def _empty() -> Candidates:
    z = np.zeros((0, 3), dtype=np.float32)
    return Candidates(points=z, normals=z.copy(), scores=np.zeros(0, dtype=np.float32))


class DiffusionSuctionPolicy(Policy):
    name = "diffusion"

    def __init__(self, checkpoint: str | os.PathLike | None = None, device: str = "cpu", seed: int = 0,
                 num_threads: int | None = None, inference_steps: int | None = None, decode_points: int | None = None,
                 nms_radius: float = NMS_RADIUS, record_trajectory: bool = True, model: DiffusionSuction | None = None,
                 precision: str = "float32", draws: int = 1, candidate_points: int | None = None):
        """Loads ``checkpoint`` (default: the shipped one); ``model`` instead uses an in-memory model (tests).

        ``candidate_points`` > 0 decodes at up to that many of the depth image's points in the bin, where the
        observation carries them (``DiffusionConfig.candidate_points``, its default); 0 at the encoded points.
        ``decode_points`` > 0 denoises a uniform subset of that many of those points (faster).
        ``precision`` ('float32' | 'bfloat16') is the encoder's arithmetic at inference (see ``PRECISIONS``).
        ``draws`` > 1 ranks by the mean score map of that many noise draws (``DiffusionSuction.sample``).
        """
        self.draws = check_draws(draws)  # refused here, before a checkpoint is read
        if precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {sorted(PRECISIONS)}, got {precision!r}")
        self.precision = precision
        if precision == "bfloat16" and torch.device(device).type == "cpu" and not cpu_runs_bfloat16_natively():
            warnings.warn("precision='bfloat16' on a CPU without AVX512-BF16 or AMX: its matmuls are emulated, "
                          "about 10x slower than float32; use precision='float32' here")
        if num_threads is not None:
            torch.set_num_threads(int(num_threads))
        self.device = torch.device(device)
        if model is None:
            model, _ = load_model(checkpoint or DEFAULT_CHECKPOINT, map_location=self.device)
        else:
            model = copy.deepcopy(model)  # the encoder gets folded below; leave the caller's model alone
        self.model = model.to(self.device).eval()
        self.model.encoder = fold_batchnorm(self.model.encoder)  # inference-only speed-up, same outputs
        self.config = self.model.config
        self.inference_steps = inference_steps or self.config.inference_steps
        if self.inference_steps != self.config.inference_steps:
            warnings.warn(f"sampling with {self.inference_steps} DDIM steps, trained with "
                          f"{self.config.inference_steps}: the paper finds mismatched step counts lose most AP")
        self.decode_points = self.config.decode_points if decode_points is None else int(decode_points)
        self.candidate_points = self.config.candidate_points if candidate_points is None else int(candidate_points)
        if self.decode_points < 0 or self.candidate_points < 0:
            raise ValueError(f"decode_points and candidate_points must be >= 0, got {self.decode_points}, "
                             f"{self.candidate_points}")
        if self.config.encoder != "pointnet2":
            self.candidate_points = 0  # the PointNet ablation's global feature cannot leave the queries out
        self.nms_radius = nms_radius
        self.record_trajectory = record_trajectory
        self.last_trajectory: Trajectory | None = None
        self.reset(seed)

    def reset(self, seed: int | None = None) -> None:
        """Reseed the sampler's noise; ``None`` keeps the current noise stream going."""
        if seed is not None or not hasattr(self, "_generator"):
            self._generator = torch.Generator(device=self.device).manual_seed(0 if seed is None else int(seed))

    def predict(self, obs: Mapping[str, np.ndarray], info: Mapping[str, Any] | None = None,
                top_k: int = 50) -> Candidates:
        points, normals = point_cloud(obs, "Diffusion-Suction", drop_invalid=True, dtype=np.float32)
        if len(points) < MIN_POINTS:
            self.last_trajectory = None
            return _empty()
        cfg = self.config
        if len(points) > cfg.num_points:
            keep = sample_indices(points, cfg.num_points, cfg.sampler)
            points, normals = points[keep], normals[keep]
        subset = None
        if self.candidate_points > 0 and info is not None and has_depth_view(obs, info):
            queries, query_normals = depth_candidates(obs, info, self.candidate_points)
            if len(queries) == 0:
                self.last_trajectory = None
                return _empty()
            if 0 < self.decode_points < len(queries):
                keep = np.sort(grid_sample(queries, self.decode_points))
                queries, query_normals = queries[keep], query_normals[keep]
            features = self.encode_at(points, normals, queries, query_normals)
            points, normals = queries, query_normals
        else:
            if 0 < self.decode_points < len(points):
                subset = np.sort(grid_sample(points, self.decode_points))
            features = self.encode_cloud(points, normals, subset)  # (1, M, F), at the decoded points only
        with torch.inference_mode():
            out = self.model.sample(features, self.inference_steps, self._generator,
                                    return_trajectory=self.record_trajectory, draws=self.draws)
        scores, trajectory = out if self.record_trajectory else (out, None)
        if subset is not None:
            points, normals = points[subset], normals[subset]
        channel_scores = scores[0].float().cpu().numpy()
        if trajectory is not None:
            self.last_trajectory = Trajectory(points=points, maps=trajectory[:, 0].float().cpu().numpy())
        quality = self.quality(points, normals, features[0], channel_scores, info)
        return select_candidates(points, normals, quality, top_k=top_k, nms_radius=self.nms_radius)

    def encode_cloud(self, points: np.ndarray, normals: np.ndarray, subset: np.ndarray | None = None) -> torch.Tensor:
        """The encoder's per-point condition features (1, M, F) of one cloud, at the ``subset`` rows (all: None)."""
        batch = {"points": points, "normals": normals,  # the finest interpolation only where the decoder reads
                 **model_inputs(points, normals, self.config, workers=torch.get_num_threads(), rows=subset)}
        rows = None if subset is None else torch.from_numpy(subset).unsqueeze(0).to(self.device)
        return self._encode(batch, rows)

    def encode_at(self, points: np.ndarray, normals: np.ndarray, queries: np.ndarray, query_normals: np.ndarray
                  ) -> torch.Tensor:
        """The encoder's condition features (1, M, F) at ``queries`` (M, 3), of the cloud ``points`` (its levels
        sample ``points`` alone: ``neighbourhood.model_inputs_at``)."""
        batch = model_inputs_at(points, normals, queries, query_normals, self.config, workers=torch.get_num_threads())
        rows = torch.arange(len(points), len(points) + len(queries), device=self.device).unsqueeze(0)
        return self._encode(batch, rows)

    def _encode(self, batch: Mapping[str, np.ndarray], rows: torch.Tensor | None) -> torch.Tensor:
        tensors = {k: torch.from_numpy(np.ascontiguousarray(v)).unsqueeze(0).to(self.device) for k, v in batch.items()}
        low = self.precision != "float32"
        with torch.inference_mode():
            with torch.autocast(self.device.type, dtype=PRECISIONS[self.precision], enabled=low):
                return self.model.encode(tensors, rows).float()

    def quality(self, points: np.ndarray, normals: np.ndarray, features: torch.Tensor, channel_scores: np.ndarray,
                info: Mapping[str, Any] | None = None) -> np.ndarray:
        """(M,) ranking score of the decoded points: the product of the sampled channels (seal, wrench, collision
        (, visibility)). ``features`` (M, F) are the encoder's and ``info`` the observation's, for variants that read
        more from them."""
        return channel_scores.prod(axis=1)
