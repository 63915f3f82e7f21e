"""PointNet++ MSG encoder (4 SA + 4 FP) that only gathers by precomputed indices, plus the PointNet ablation.

Tensors are channel-last, (B, N, C), so every shared MLP is a plain matmul over the last axis.
"""

from __future__ import annotations

import copy
from typing import Mapping, Sequence

import torch
from torch import nn

from policies.diffusion.config import DiffusionConfig
from policies.diffusion.segment_inputs import segment_channels, segment_features


# Grouped rows (centres x neighbours) an inference pass of a set abstraction takes at once: a few MB per layer, so
# its intermediates stay in cache (4k-16k rows tie on the 2-core host; 32k is already 40% slower, benchmarks/RESULTS.md).
INFERENCE_GROUP_ROWS = 16384


def gather(values: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """values (B, N, C), index (B, ...) -> (B, ..., C).

    Rows are picked with ``index_select`` on the flattened batch: unlike ``Tensor.gather`` it copies whole
    channel rows, not one expanded index per element."""
    b, n, c = values.shape
    flat = index.reshape(b, -1)
    if b > 1:
        flat = flat + n * torch.arange(b, device=index.device).unsqueeze(1)
    return values.reshape(b * n, c).index_select(0, flat.reshape(-1)).reshape(*index.shape, c)


class SharedMLP(nn.Sequential):
    """Linear + BatchNorm + ReLU per layer on the last axis of any-rank input."""

    def __init__(self, channels: Sequence[int], last_act: bool = True):
        layers: list[nn.Module] = []
        for i, (c_in, c_out) in enumerate(zip(channels[:-1], channels[1:])):
            is_last = i == len(channels) - 2
            layers.append(nn.Linear(c_in, c_out, bias=is_last and not last_act))
            if not is_last or last_act:
                layers += [_ChannelLastBatchNorm(c_out), nn.ReLU(inplace=True)]
        super().__init__(*layers)


class _ChannelLastBatchNorm(nn.BatchNorm1d):
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        shape = x.shape
        return super().forward(x.reshape(-1, shape[-1])).reshape(shape)


class SetAbstractionMSG(nn.Module):
    """Group neighbours at several radii, shared MLP on [offset / radius, features], max-pool per group.

    The first layer is linear, so it runs once per *input point* and is gathered afterwards:
    W [(p - c) / r, f] = (W_p p / r + W_f f) - W_p c / r. Same model, 5-10x fewer first-layer products.
    Out of training (where BatchNorm uses running statistics, so each row is independent) the centres go through
    in chunks of :data:`INFERENCE_GROUP_ROWS` grouped rows.
    """

    def __init__(self, in_channels: int, radii: Sequence[float], mlp: Sequence[int]):
        super().__init__()
        self.radii = tuple(float(r) for r in radii)
        self.first = nn.ModuleList(nn.Linear(in_channels + 3, mlp[0], bias=False) for _ in radii)
        self.rest = nn.ModuleList(
            nn.Sequential(_ChannelLastBatchNorm(mlp[0]), nn.ReLU(inplace=True), SharedMLP(mlp)) if len(mlp) > 1
            else nn.Sequential(_ChannelLastBatchNorm(mlp[0]), nn.ReLU(inplace=True)) for _ in radii)
        self.out_channels = mlp[-1] * len(radii)

    def forward(self, xyz: torch.Tensor, feats: torch.Tensor | None, centres: torch.Tensor,
                groups: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        new_xyz = gather(xyz, centres)  # (B, M, 3)
        outs = []
        for s, (radius, first, rest) in enumerate(zip(self.radii, self.first, self.rest)):
            w_p, w_f = first.weight[:, :3] / radius, first.weight[:, 3:]  # metres -> O(1) offsets
            per_point = xyz @ w_p.T if feats is None else xyz @ w_p.T + feats @ w_f.T  # (B, N, C1)
            if first.bias is not None:  # only after fold_batchnorm
                per_point = per_point + first.bias
            centre_term = (new_xyz @ w_p.T).unsqueeze(2)  # (B, M, 1, C1)
            m = centres.shape[1]
            step = m if self.training else max(1, INFERENCE_GROUP_ROWS // groups.shape[-1])
            pooled = [rest(gather(per_point, groups[:, a:a + step, s]) - centre_term[:, a:a + step]).amax(dim=2)
                      for a in range(0, m, step)]  # (B, M, K, C1) -> (B, M, C)
            outs.append(pooled[0] if len(pooled) == 1 else torch.cat(pooled, dim=1))
        return new_xyz, torch.cat(outs, dim=-1)


class FeaturePropagation(nn.Module):
    """Inverse-distance 3-NN interpolation from the coarse level, concatenated with the skip features, then MLP.

    Interpolation is linear, so the first layer's coarse half runs on the coarse points (4x fewer) and is
    interpolated afterwards: W [sum_k w_k c_k, s] = sum_k w_k (W_c c_k) + W_s s. Same model, no concatenation."""

    def __init__(self, channels: Sequence[int]):
        super().__init__()
        self.mlp = SharedMLP(channels)

    def forward(self, skip: torch.Tensor | None, coarse: torch.Tensor, index: torch.Tensor,
                weight: torch.Tensor) -> torch.Tensor:
        first: nn.Linear = self.mlp[0]
        c = coarse.shape[-1]
        projected = coarse @ first.weight[:, :c].T  # (B, M, C1)
        up = gather(projected, index[..., 0]) * weight[..., :1]  # (B, N, C1), one neighbour at a time: no (B, N, 3, C1)
        for k in range(1, index.shape[-1]):
            up = up.addcmul_(gather(projected, index[..., k]), weight[..., k:k + 1])
        if skip is not None:
            up = up + skip @ first.weight[:, c:].T
        if first.bias is not None:  # only after fold_batchnorm
            up = up + first.bias
        for layer in list(self.mlp)[1:]:  # (slicing would rebuild a SharedMLP from its modules)
            up = layer(up)
        return up


def _w(c: int, width: float) -> int:
    return max(4, int(round(c * width)))


def point_feature_channels(config: DiffusionConfig) -> int:
    """Per-point input channels beside xyz: the normals, and the segment features under ``levers_in_encoder``."""
    return (3 if config.use_normals else 0) + segment_channels(config, "encoder")


def point_features(batch: Mapping[str, torch.Tensor], config: DiffusionConfig) -> torch.Tensor | None:
    """(B, N, point_feature_channels) or None when there are none (xyz only)."""
    parts = ([batch["normals"]] if config.use_normals else []) + segment_features(
        batch, config, "encoder", batch["points"].dtype)
    return torch.cat(parts, dim=-1) if parts else None


class PointNet2Encoder(nn.Module):
    """The public code's Pointnet2MSGBackbone: SA 64/128/256/512 x 3 scales, FP back to ``feature_dim`` per point."""

    def __init__(self, config: DiffusionConfig):
        super().__init__()
        self.levels = len(config.sa_npoints)
        w = config.width
        in_feat = point_feature_channels(config)
        self.config = config
        base = [(32, 32, 64), (64, 64, 128), (128, 128, 256), (256, 256, 512)]
        while len(base) < self.levels:
            base.append(tuple(2 * c for c in base[-1]))
        self.sa = nn.ModuleList()
        skip_channels = [in_feat]
        c_in = in_feat
        for l in range(self.levels):
            sa = SetAbstractionMSG(c_in, config.sa_radii[l], [_w(c, w) for c in base[l]])
            self.sa.append(sa)
            c_in = sa.out_channels
            skip_channels.append(c_in)
        # FP, coarse to fine: (coarse + skip) -> hidden -> out; the finest ends at feature_dim
        fp_out = [(_w(128, w), config.feature_dim), (_w(256, w), _w(128, w)), (_w(256, w), _w(256, w)),
                  (_w(512, w), _w(512, w))]
        while len(fp_out) < self.levels:
            fp_out.append(fp_out[-1])
        self.fp = nn.ModuleList()
        coarse = skip_channels[-1]
        for l in range(self.levels, 0, -1):  # propagate level l -> l-1
            hidden, out = fp_out[l - 1]
            self.fp.append(FeaturePropagation([coarse + skip_channels[l - 1], hidden, out]))
            coarse = out
        self.out_channels = config.feature_dim

    def forward(self, batch: Mapping[str, torch.Tensor], rows: torch.Tensor | None = None) -> torch.Tensor:
        """(B, N, feature_dim), or (B, M, feature_dim) at ``rows`` (B, M): the finest feature propagation is
        per point, so it then runs only where the decoder reads (8x fewer rows at 2,048 of 16,384 points). The
        batch's ``fp1_index`` / ``fp1_weight`` may hold every point's (N rows) or the rows' alone (M < N rows,
        ``model_inputs(..., rows=...)``)."""
        xyz = batch["points"]
        feats = point_features(batch, self.config)
        xyzs, featss = [xyz], [feats]
        for l, sa in enumerate(self.sa, start=1):
            xyz, feats = sa(xyz, feats, batch[f"sa{l}_centres"], batch[f"sa{l}_groups"])
            xyzs.append(xyz)
            featss.append(feats)
        coarse = featss[-1]
        for fp, l in zip(self.fp, range(self.levels, 0, -1)):
            skip, index, weight = featss[l - 1], batch[f"fp{l}_index"], batch[f"fp{l}_weight"]
            if l == 1 and rows is not None:
                skip = None if skip is None else gather(skip, rows)
                if index.shape[1] == xyzs[0].shape[1]:  # given at every point: take the rows'
                    index, weight = gather(index, rows), gather(weight, rows)
            coarse = fp(skip, coarse, index, weight)
        return coarse  # (B, N or M, feature_dim)


class PointNetEncoder(nn.Module):
    """Ablation: per-point MLP + global max-pool (no local neighbourhoods)."""

    def __init__(self, config: DiffusionConfig):
        super().__init__()
        w = config.width
        self.config = config
        c_in = 3 + point_feature_channels(config)
        self.local = SharedMLP([c_in, _w(64, w), _w(64, w)])
        self.glob = SharedMLP([_w(64, w), _w(128, w), _w(1024, w)])
        self.head = SharedMLP([_w(64, w) + _w(1024, w), _w(256, w), config.feature_dim])
        self.out_channels = config.feature_dim

    def forward(self, batch: Mapping[str, torch.Tensor], rows: torch.Tensor | None = None) -> torch.Tensor:
        xyz = batch["points"]
        x = xyz - xyz.mean(dim=1, keepdim=True)
        feats = point_features(batch, self.config)
        if feats is not None:
            x = torch.cat([x, feats], dim=-1)
        local = self.local(x)
        g = self.glob(local).amax(dim=1, keepdim=True)
        if rows is not None:  # the global feature needs every point; the head only the rows read
            local = gather(local, rows)
        return self.head(torch.cat([local, g.expand(-1, local.shape[1], -1)], dim=-1))


def build_encoder(config: DiffusionConfig) -> nn.Module:
    return PointNet2Encoder(config) if config.encoder == "pointnet2" else PointNetEncoder(config)


def _bn_affine(bn: nn.BatchNorm1d) -> tuple[torch.Tensor, torch.Tensor]:
    scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)
    return scale, bn.bias - bn.running_mean * scale


@torch.no_grad()
def fold_batchnorm(module: nn.Module) -> nn.Module:
    """Inference copy with each eval-mode BatchNorm folded into the Linear before it (one memory pass less each).
    Folding a folded module changes nothing. The fused layers keep the device and dtype of the ones they replace."""
    module = copy.deepcopy(module).eval()
    for m in list(module.modules()):
        if isinstance(m, SetAbstractionMSG):
            for s, (first, rest) in enumerate(zip(m.first, m.rest)):
                if not isinstance(rest[0], _ChannelLastBatchNorm):  # folded already
                    continue
                scale, shift = _bn_affine(rest[0])
                fused = nn.Linear(first.in_features, first.out_features, bias=True, device=first.weight.device,
                                  dtype=first.weight.dtype)
                fused.weight.copy_(first.weight * scale[:, None])
                fused.bias.copy_(shift)
                m.first[s] = fused
                rest[0] = nn.Identity()
        elif isinstance(m, nn.Sequential):
            for i in range(len(m) - 1):
                if isinstance(m[i], nn.Linear) and isinstance(m[i + 1], _ChannelLastBatchNorm):
                    scale, shift = _bn_affine(m[i + 1])
                    lin = m[i]
                    fused = nn.Linear(lin.in_features, lin.out_features, bias=True, device=lin.weight.device,
                                      dtype=lin.weight.dtype)
                    fused.weight.copy_(lin.weight * scale[:, None])
                    fused.bias.copy_(shift if lin.bias is None else lin.bias * scale + shift)
                    m[i], m[i + 1] = fused, nn.Identity()
    return module
