"""benchmarks/bench_diffusion.py's GPU table, run on the CPU so that it cannot rot between lent GPUs, and its table on
the env's own clouds, run on tiny ones."""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

import numpy as np
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


def test_the_env_cloud_table_times_both_precisions_on_every_cloud():
    clouds = bench_diffusion.env_clouds(2, points=512)
    assert [c["points"].shape for c in clouds] == [(512, 3), (512, 3)]
    assert not np.array_equal(clouds[0]["points"], clouds[1]["points"])  # two piles, not one twice
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # bfloat16 is emulated on some CPUs: slow, not wrong
        rows = bench_diffusion.bench_env_clouds(clouds, 3, 64, DiffusionConfig.tiny(inference_steps=2))
    assert [r["precision"] for r in rows] == ["float32", "bfloat16"]
    for r in rows:
        assert r["clouds"] == 2 and r["calls"] == 6
        assert 0 < r["p10 (ms)"] <= r["predict median (ms)"] <= r["p90 (ms)"]
        fast, calls = map(int, r["calls <= 200 ms"].split("/"))
        assert calls == 6 and 0 <= fast <= 6
