"""Where a checkpoint came from: git commit, exact command, seed, dataset manifest hash and wall time.

Every trainer stores ``training_provenance(...)`` in its checkpoint's metadata (``provenance``); the
report prints ``checkpoint_provenance(path)`` for each shipped model. Checkpoints shipped before this was
recorded carry a sidecar ``<file>.provenance.json`` holding what is known from the README's commands, and
``"not recorded"`` for the rest: nothing is reconstructed after the fact.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

FIELDS: tuple[str, ...] = ("git_commit", "command", "seed", "dataset_manifest_sha256", "wall_time_s")
NOT_RECORDED = "not recorded"
NO_DATASET = "no dataset"
SIDECAR_SUFFIX = ".provenance.json"
REPO = Path(__file__).resolve().parents[1]
# The checkpoints the policies load by default (policies/<name>/...), keyed by registry name.
SHIPPED: dict[str, tuple[str, ...]] = {
    "diffusion": ("policies/diffusion/checkpoints/diffusion_suction.pt",),
    "diffusion_vote": ("policies/diffusion/checkpoints/centre_vote.pt",),  # the head; the model is diffusion's
    "diffusion_hold": ("policies/hold/checkpoints/hold.pt",),  # the hold check; the model is diffusion's
    "diffusion_vote_hold": ("policies/hold/checkpoints/hold_vote.pt",),  # its hold check; the head is diffusion_vote's
    "cao": ("policies/cao/checkpoint.pt",),
    "dexnet": ("policies/dexnet/checkpoint.pt",),
    "sb3": ("policies/sb3/ppo_pixel.safetensors", "policies/sb3/ppo_pixel.zip"),  # the first that exists
}


COMMIT_ENV = "PARCELPICK_GIT_COMMIT"


def git_commit(root: str | os.PathLike = REPO) -> str:
    """The commit that the sender names in ``PARCELPICK_GIT_COMMIT`` where it is set (a copy of the tree sent to a
    lent machine: what git finds there can be an older HEAD, seen on 2026-12-04), else HEAD's hash with '+dirty'
    when tracked files differ from it, else NOT_RECORDED (outside a git checkout)."""
    if os.environ.get(COMMIT_ENV):
        return os.environ[COMMIT_ENV]
    try:
        head = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True,
                              timeout=10, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=10, check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return NOT_RECORDED
    return head + ("+dirty" if dirty else "")


def manifest_sha256(data_dir: str | os.PathLike | None) -> str:
    """SHA-256 of a dataset's ``manifest.json`` (which lists every shard); NO_DATASET for a run without one
    (online RL, synthetic scenes), NOT_RECORDED when the directory holds no manifest."""
    if data_dir is None:
        return NO_DATASET
    path = Path(data_dir) / "manifest.json"
    return hashlib.sha256(path.read_bytes()).hexdigest() if path.is_file() else NOT_RECORDED


def command_line(module: str, argv: Sequence[str] | None) -> str:
    """The command as typed: ``python -m <module> <args>`` (``argv`` None: this process's own arguments)."""
    args = sys.argv[1:] if argv is None else list(argv)
    return " ".join(["python -m", module, *args])


def training_provenance(command: str, seed: int, data_dir: str | os.PathLike | None,
                        started: float) -> dict[str, Any]:
    """The record a trainer stores beside its weights: ``command`` as ``command_line`` gives it, ``started``
    the ``time.perf_counter()`` at the run's start (so wall time covers data loading too)."""
    return {"git_commit": git_commit(), "command": command, "seed": int(seed),
            "dataset_manifest_sha256": manifest_sha256(data_dir), "wall_time_s": time.perf_counter() - started,
            "recorded_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}


PART_FIELDS: tuple[str, ...] = ("git_commit", "command", "wall_time_s", "recorded_at")


def chain_parts(record: dict[str, Any], earlier: Any) -> dict[str, Any]:
    """A resumed run's record: ``earlier`` is the provenance its start checkpoint carried (None for a fresh run).
    Each invocation's commit, command and wall time is kept in ``parts``, and ``wall_time_s`` is their sum, so a
    run stopped by ``--max-minutes`` and resumed still says what all of it cost."""
    if not isinstance(earlier, dict):
        return record
    parts = earlier.get("parts") or [{k: earlier.get(k, NOT_RECORDED) for k in PART_FIELDS}]
    chained = dict(record, parts=[*parts, {k: record.get(k, NOT_RECORDED) for k in PART_FIELDS}])
    times = [p["wall_time_s"] for p in chained["parts"]]
    chained["wall_time_s"] = sum(times) if all(isinstance(t, (int, float)) for t in times) else NOT_RECORDED
    return chained


def _embedded(path: Path) -> dict[str, Any] | None:
    """The provenance stored in the checkpoint itself (torch payload metadata, or the JSON log beside it)."""
    if path.suffix == ".pt":
        import torch

        try:
            payload = torch.load(path, map_location="cpu", weights_only=True)
        except Exception:  # noqa: BLE001  an unreadable file has no provenance; its loader reports why
            return None
        if not isinstance(payload, dict):
            return None
        for owner in (payload, payload.get("extra"), payload.get("meta"), payload.get("metadata")):
            if isinstance(owner, dict) and isinstance(owner.get("provenance"), dict):
                return owner["provenance"]
        return None
    log = path.with_suffix(".json")  # the sb3 trainer's log beside its model
    if log.is_file():
        try:
            found = json.loads(log.read_text()).get("provenance")
        except (ValueError, AttributeError):
            return None
        return found if isinstance(found, dict) else None
    return None


def checkpoint_provenance(path: str | os.PathLike) -> dict[str, Any]:
    """Every FIELDS entry for a checkpoint (NOT_RECORDED where unknown), plus ``source``: where it was read."""
    path = Path(path)
    found, source = _embedded(path), "checkpoint"
    sidecar = path.with_name(path.name + SIDECAR_SUFFIX)
    if found is None and sidecar.is_file():
        found, source = json.loads(sidecar.read_text()), str(sidecar.name)
    if found is None:
        found, source = {}, NOT_RECORDED
    record = {k: found.get(k, NOT_RECORDED) for k in FIELDS}
    record.update(source=source, checkpoint=str(path), note=found.get("note"))
    return record


def repo_path(path: str | os.PathLike, root: str | os.PathLike = REPO) -> str:
    """``path`` as the repository names it (relative to ``root``) where it lies inside, else as given: a record
    that names a shipped file must not name the checkout it was made in."""
    full, base = Path(os.path.abspath(path)), Path(os.path.abspath(root))
    return str(full.relative_to(base)) if full.is_relative_to(base) else str(path)


def shipped_provenance(root: str | os.PathLike = REPO) -> dict[str, dict[str, Any]]:
    """``checkpoint_provenance`` of every shipped checkpoint that exists, by policy name."""
    out = {}
    for name, candidates in SHIPPED.items():
        path = next((Path(root) / c for c in candidates if (Path(root) / c).is_file()), None)
        if path is not None:
            out[name] = checkpoint_provenance(path)
            out[name]["checkpoint"] = repo_path(path, root)
    return out
