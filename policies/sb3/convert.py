"""Convert a TRUSTED stable-baselines3 PPO ``.zip`` into the data-only model file the ``sb3`` policy loads.

    python -m policies.sb3.convert policies/sb3/ppo_pixel.zip            # -> policies/sb3/ppo_pixel.safetensors

The shipped model was converted this way from the zip that commit bbaf400 shipped; the zip is no longer in
the tree (nothing loads it), and ``git show bbaf400:policies/sb3/ppo_pixel.zip > ppo_pixel.zip`` restores it.

This is the one place that calls ``PPO.load``, which unpickles the zip's ``data`` entry and so runs any
code it holds: run it only on a file you made or otherwise trust. The output is checked by reloading it
through the safe loader and comparing actions with the original model on random observations.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

from parcelpick_env.cli import check_output_path, run_cli
from policies.sb3.model_io import load_model, save_model


def convert(src: str | Path, dst: str | Path, *, checks: int = 64, seed: int = 0) -> Path:
    """Load ``src`` with SB3 (trusted input only), write ``dst``, and verify the two give identical actions."""
    from stable_baselines3 import PPO

    src, dst = Path(src), Path(dst)
    model = PPO.load(src, device="cpu")
    save_model(model.policy, dst, extra={"converted_from": src.name})
    policy, _ = load_model(dst, f"python -m policies.sb3.convert {src}")
    low = np.broadcast_to(model.observation_space.low, model.observation_space.shape)
    high = np.broadcast_to(model.observation_space.high, model.observation_space.shape)
    obs = np.random.default_rng(seed).uniform(low, high, (checks, *low.shape)).astype(np.float32)
    with torch.no_grad():
        before, _ = model.predict(obs, deterministic=True)
        after, _ = policy.predict(obs, deterministic=True)
    if not np.array_equal(before, after):
        dst.unlink()
        raise ValueError(f"{dst} does not reproduce {src}'s actions (max diff {np.abs(before - after).max()})")
    return dst


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m policies.sb3.convert", description=__doc__.split("\n\n")[0])
    parser.add_argument("src", type=Path, help="trusted SB3 PPO .zip")
    parser.add_argument("--out", type=Path, default=None, help="output .safetensors (default: SRC with that suffix)")
    args = parser.parse_args(argv)
    if not args.src.is_file():
        parser.error(f"src {args.src} is not a file")
    out = check_output_path(args.out or args.src.with_suffix(".safetensors"), "--out")
    convert(args.src, out)
    print(f"wrote {out} ({out.stat().st_size / 1e3:.0f} kB); actions identical to {args.src}")
    return 0


if __name__ == "__main__":
    sys.exit(run_cli(main))
