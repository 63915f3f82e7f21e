"""Wrench score: can the cup's material resist gravity's torque, and how far from vertical is it?

docs/labels.md, 'Wrench' (the paper's corrected material condition):
``S = (1 - min(1, |tau_e| / tau_thr)) * (1 - a / pi)``, with ``tau_e`` the torque of a unit mass
at the centre of mass about the contact, in the components orthogonal to the cup axis, and ``a``
the angle between the approach ``-n`` and gravity.
"""

from __future__ import annotations

import numpy as np

from parcelpick_env.suction.config import SuctionConfig


def wrench_scores(points: np.ndarray, normals: np.ndarray, coms: np.ndarray,
                  config: SuctionConfig) -> np.ndarray:
    """(N,) wrench score for contacts ``points`` with outward ``normals`` on bodies with ``coms``."""
    force = np.array([0.0, 0.0, -config.unit_mass * config.gravity])
    torque = np.cross(coms - points, force)
    torque -= np.sum(torque * normals, axis=1, keepdims=True) * normals
    torque_ratio = np.minimum(1.0, np.linalg.norm(torque, axis=1) / config.torque_threshold)
    # -n . (0, 0, -1) = n_z
    angle = np.arccos(np.clip(normals[:, 2], -1.0, 1.0))
    return ((1.0 - torque_ratio) * (1.0 - angle / np.pi)).astype(np.float32)
