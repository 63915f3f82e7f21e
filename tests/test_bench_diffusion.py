"""benchmarks/bench_diffusion.py's GPU table, run on the CPU so that it cannot rot between lent GPUs."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import bench_diffusion  # noqa: E402

from policies.diffusion.checkpoint import save_checkpoint  # noqa: E402
from policies.diffusion.config import DiffusionConfig  # noqa: E402
from policies.diffusion.model import build_model  # noqa: E402


@pytest.mark.parametrize("trained", [False, True])
def test_the_device_table_times_each_stage_and_sums_them(trained, tmp_path):
    config = DiffusionConfig.tiny(inference_steps=3)
    checkpoint = None
    if trained:
        checkpoint = str(save_checkpoint(tmp_path / "m.pt", build_model(DiffusionConfig.tiny(inference_steps=2))))
    rows = bench_diffusion.bench_cuda(config, 1, 64, checkpoint, torch.device("cpu"))
    steps = 2 if trained else 3  # a checkpoint is timed with its own config
    assert [r["precision"] for r in rows] == ["float32", "bfloat16"]
    for r in rows:
        assert r["config"] == ("trained" if trained else "paper (w=1.0)") and r["device"] == "cpu"
        assert r["total (decode N)"] == pytest.approx(r["precompute (CPU)"] + r["encoder"] + r[f"decoder x{steps} (N)"])
        assert r["total (decode 64)"] == pytest.approx(r["precompute (CPU)"] + r["encoder"]
                                                       + r[f"decoder x{steps} (64 pts)"])
        assert min(v for k, v in r.items() if isinstance(v, float)) > 0
