"""Diffusion-Suction (Huang et al.): a PointNet++ encoder run once per scene, and a light PCDB decoder that
denoises per-point [seal, wrench, collision, visibility] scores over a few DDIM steps.

- ``config.DiffusionConfig``: every hyper-parameter and ablation switch (``.cpu()`` for 2-core training).
- ``model.DiffusionSuction``: ``encode`` / ``sample`` / ``forward_train``.
- ``policy.DiffusionSuctionPolicy``: the ``Policy`` (registry name ``diffusion``).
- ``train``: ``python -m policies.diffusion.train --data DIR --out runs/diffusion --preset cpu --steps 5000``.
- ``checkpoint``: versioned save/load; the shipped weights live at ``checkpoints/diffusion_suction.pt``.
"""

from policies.diffusion.config import DiffusionConfig

__all__ = ["DiffusionConfig"]
