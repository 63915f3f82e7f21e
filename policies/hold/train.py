"""Train the hold check on rehearsal-labelled picks (``policies.hold.collect``) and report it on held-out episodes.

    python -m policies.hold.train --data data/hold --out policies/hold/checkpoints/hold.pt --seed 0

Episodes are split, not picks: every ``--val-every``-th episode file of each folder (sorted by name) is held out. Printed on the
held-out states: the ROC-AUC of the predicted hold (and of the policy's own score), and how often the pick each
ranking takes first held on the twin: the policy's own first passing pick, the first by hold probability (what
``diffusion_hold`` takes), and by score x hold probability, paired over states with a bootstrap interval. That is
the offline counterpart of R_grasp.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from eval.label_physics import roc_auc
from eval.stats import bootstrap_mean, format_interval, paired_difference
from policies.hold.features import hold_features
from policies.hold.model import HoldNet, HoldNetConfig, save_hold
from policies.provenance import command_line, git_commit


@dataclass
class PickSet:
    """Rehearsed picks: features (P, F), twin verdicts (P,), and the state (P,) and in-state order (P,) of each."""

    features: np.ndarray
    held: np.ndarray
    state: np.ndarray
    order: np.ndarray


def load_picks(files: list[Path]) -> PickSet:
    """Every rehearsed candidate of every state in ``files`` (``collect`` output), with its features."""
    feats, held, state, order = [], [], [], []
    states = 0
    for path in files:
        with np.load(path, allow_pickle=False) as d:
            for s in range(len(d["twin_outcome"])):
                valid = d["twin_outcome"][s] != ""
                if not valid.any():
                    continue
                feats.append(hold_features(d["points"][s], d["normals"][s], d["cand_points"][s][valid],
                                           d["cand_normals"][s][valid], d["cand_scores"][s][valid], d["workspace"][s]))
                held.append(d["twin_outcome"][s][valid] == "success")
                state.append(np.full(int(valid.sum()), states))
                order.append(np.arange(int(valid.sum())))
                states += 1
    if not feats:
        raise ValueError(f"no rehearsed picks in {len(files)} files")
    return PickSet(np.concatenate(feats), np.concatenate(held), np.concatenate(state), np.concatenate(order))


def first_held(picks: PickSet, ranking: np.ndarray) -> np.ndarray:
    """(states,) 1.0 where the pick with the highest ``ranking`` in each state held on the twin (ties: the
    policy's order)."""
    out = []
    for s in np.unique(picks.state):
        rows = np.flatnonzero(picks.state == s)
        best = rows[np.lexsort((picks.order[rows], -ranking[rows]))[0]]
        out.append(float(picks.held[best]))
    return np.asarray(out)


def fit(picks: PickSet, config: HoldNetConfig, seed: int, steps: int, lr: float, weight_decay: float) -> HoldNet:
    """Full-batch AdamW on the binary cross-entropy; the picks are few (thousands), so no mini-batches."""
    torch.manual_seed(seed)
    net = HoldNet(config)
    net.fit_scaling(picks.features)
    x = torch.as_tensor(picks.features)
    y = torch.as_tensor(picks.held, dtype=torch.float32)
    opt = torch.optim.AdamW(net.parameters(), lr=lr, weight_decay=weight_decay)
    loss_fn = torch.nn.BCEWithLogitsLoss()
    for _ in range(steps):
        opt.zero_grad()
        loss = loss_fn(net(x), y)
        loss.backward()
        opt.step()
    return net.eval()


def data_sha256(files: list[Path]) -> str:
    """One hash over the episode files' names and bytes: which data a checkpoint was trained on."""
    h = hashlib.sha256()
    for path in files:
        h.update(f"{path.parent.name}/{path.name}".encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def report(val: PickSet, net: HoldNet) -> dict[str, object]:
    """The held-out figures the module docstring lists; intervals are bootstrap over states."""
    p = net.hold_probability(val.features)
    score = val.features[:, 0]
    policy_first = first_held(val, -val.order.astype(np.float64))
    reranked = first_held(val, score * p)
    by_hold = first_held(val, p)
    return {"val_picks": int(len(val.held)), "val_states": int(len(policy_first)), "val_held_share": float(val.held.mean()),
            "auc": roc_auc(p, val.held), "auc_score_only": roc_auc(score, val.held),
            "first_held_policy": bootstrap_mean(policy_first), "first_held_score_x_hold": bootstrap_mean(reranked),
            "first_held_by_hold": bootstrap_mean(by_hold),
            "by_hold_minus_policy": paired_difference(by_hold, policy_first),
            "score_x_hold_minus_policy": paired_difference(reranked, policy_first),
            "best_possible": bootstrap_mean(np.asarray([float(val.held[val.state == s].any()) for s in np.unique(val.state)]))}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--data", required=True, nargs="+", help="folders of collect's .npz episode files")
    p.add_argument("--out", default=None, help="checkpoint to write (none: report only)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--hidden", type=int, default=32)
    p.add_argument("--layers", type=int, default=HoldNetConfig.layers, help="hidden layers; 0 is logistic regression")
    p.add_argument("--steps", type=int, default=2000)
    p.add_argument("--lr", type=float, default=1e-2)
    p.add_argument("--weight-decay", type=float, default=1e-3)
    p.add_argument("--val-every", type=int, default=5, help="every k-th episode file is held out; 0: none")
    args = p.parse_args(argv)
    started = time.perf_counter()
    if args.val_every < 0 or args.steps < 1 or args.hidden < 1 or args.layers < 0:
        print("error: --val-every must be >= 0, --steps and --hidden >= 1, --layers >= 0", file=sys.stderr)
        return 2
    files, held_out = [], []
    for folder in args.data:
        found = sorted(Path(folder).glob("*.npz"))
        if not found:
            print(f"error: --data {folder} holds no .npz episode files (run python -m policies.hold.collect)",
                  file=sys.stderr)
            return 2
        files += found  # every k-th file of each folder held out, so each source is validated
        held_out += [f for i, f in enumerate(found) if args.val_every and i % args.val_every == args.val_every - 1]
    train_files = [f for f in files if f not in held_out]
    train = load_picks(train_files)
    config = HoldNetConfig(hidden=args.hidden, layers=args.layers)
    net = fit(train, config, args.seed, args.steps, args.lr, args.weight_decay)
    print(f"trained on {len(train.held)} picks in {len(np.unique(train.state))} states of {len(train_files)} "
          f"episodes ({train.held.mean():.1%} held on the twin)")
    summary: dict[str, object] = {}
    if held_out:
        summary = report(load_picks(held_out), net)
        for key, value in summary.items():
            print(f"  {key}: {format_interval(value) if not isinstance(value, (int, float)) else value}")
    if args.out:
        provenance = {"git_commit": git_commit(), "command": command_line("policies.hold.train", argv),
                      "seed": args.seed, "dataset_manifest_sha256": data_sha256(files),
                      "wall_time_s": time.perf_counter() - started,
                      "recorded_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
        metadata = {"provenance": provenance, "train_picks": int(len(train.held)),
                    "held_out_files": [f"{f.parent.name}/{f.name}" for f in held_out],
                    "validation": json.loads(json.dumps(summary, default=lambda v: getattr(v, "__dict__", str(v))))}
        save_hold(args.out, net, metadata)
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
