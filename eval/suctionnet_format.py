"""Predictions in SuctionNet-1Billion's per-view dump format, written and read back.

suctionnetAPI's evaluator (``SuctionNetEval.eval_scene`` loading ``SuctionGroup().from_npy``) reads, per
view, ``<dump>/<split>/scene_XXXX/<camera>/suction/YYYY.npz`` holding one ``(N, 7)`` array under
``arr_0`` (``np.savez``'s default name). Its columns are ``score, normal (3), point (3)``
(``SuctionGroup.scores()``, ``.directions()`` = columns 1-3, ``.translations()`` = columns 4-6), in the
camera frame, with normals pointing out of the surface, towards the camera, as its baselines estimate them.

ParcelPick's candidates are in the world frame; ``extrinsics`` (camera to world, as in every stored
capture) converts them both ways, so a dump made here can be scored by SuctionNet's tooling and a dump
made by another code base can be scored by ``eval/ap.py --predictions``.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from policies.base import Candidates

COLUMNS: tuple[str, ...] = ("score", "nx", "ny", "nz", "x", "y", "z")  # suctionnetAPI's SuctionGroup layout
CAMERA = "parcelpick"  # SuctionNet names its cameras 'realsense' and 'kinect'; ours is one simulated camera
VIEW = 0  # ParcelPick stores one view per scene: SuctionNet's annotation id 0


def view_path(dump_dir: str | os.PathLike, scene: int, split: str = "test", camera: str = CAMERA,
              view: int = VIEW) -> Path:
    """Where suctionnetAPI looks for one view's predictions."""
    return Path(dump_dir) / split / f"scene_{int(scene):04d}" / camera / "suction" / f"{int(view):04d}.npz"


def _check_extrinsics(extrinsics: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    T = np.asarray(extrinsics, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"extrinsics must be a finite 4x4 camera-to-world transform, got shape {T.shape}")
    return T[:3, :3], T[:3, 3]


def to_suctionnet(candidates: Candidates, extrinsics: np.ndarray) -> np.ndarray:
    """The ``(N, 7)`` float32 array of world-frame candidates, in the camera frame of ``extrinsics``."""
    R, t = _check_extrinsics(extrinsics)
    points = (np.asarray(candidates.points, dtype=np.float64) - t) @ R  # R^T (p - t), row-wise
    normals = np.asarray(candidates.normals, dtype=np.float64) @ R
    scores = np.asarray(candidates.scores, dtype=np.float64).reshape(-1, 1)
    return np.concatenate([scores, normals, points], axis=1).astype(np.float32)


def from_suctionnet(array: np.ndarray, extrinsics: np.ndarray, where: str = "predictions") -> Candidates:
    """World-frame candidates, sorted by descending score, from a SuctionNet ``(N, 7)`` array."""
    a = np.asarray(array, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != len(COLUMNS):
        raise ValueError(f"{where}: expected an (N, {len(COLUMNS)}) array {COLUMNS}, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{where}: contains NaN or inf")
    R, t = _check_extrinsics(extrinsics)
    normals = a[:, 1:4]
    norms = np.linalg.norm(normals, axis=1)
    if np.any(norms < 1e-6):
        raise ValueError(f"{where}: {int(np.sum(norms < 1e-6))} rows have a zero normal")
    order = np.argsort(-a[:, 0], kind="stable")
    return Candidates(points=(a[order, 4:7] @ R.T + t).astype(np.float32),
                      normals=((normals / norms[:, None])[order] @ R.T).astype(np.float32),
                      scores=a[order, 0].astype(np.float32))


def write_view(path: str | os.PathLike, array: np.ndarray) -> Path:
    """``np.savez`` as SuctionNet's baselines do (the array lands under ``arr_0``), atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.stem + ".tmp.npz")
    np.savez(tmp, np.asarray(array, dtype=np.float32))
    os.replace(tmp, path)
    return path


def read_view(path: str | os.PathLike) -> np.ndarray:
    """One view's ``(N, 7)`` array from a ``.npz`` (``arr_0``) or ``.npy`` file, as ``SuctionGroup.from_npy``."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no SuctionNet predictions at {path}")
    try:
        loaded = np.load(path, allow_pickle=False)
        array = loaded["arr_0"] if path.suffix == ".npz" else loaded
    except (KeyError, ValueError, OSError) as exc:
        raise ValueError(f"{path} is not a SuctionNet prediction file: {exc}") from exc
    array = np.asarray(array)
    if array.ndim != 2 or array.shape[1] != len(COLUMNS):
        raise ValueError(f"{path}: expected an (N, {len(COLUMNS)}) array {COLUMNS}, got shape {array.shape}")
    return array
