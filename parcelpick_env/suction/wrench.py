"""Wrench score: can the cup's material resist gravity's torque? Three published definitions.

docs/labels.md, 'Wrench'. Every model takes the torque of gravity on a unit mass at a body centre ``c``
about the contact ``p`` and compares its bending part with ``tau_thr = r * k * pi``:

- ``"paper"`` (the paper's corrected label): ``(1 - min(1, |tau_e| / tau_thr)) * (1 - a / pi)``, with ``tau_e``
  the components orthogonal to the cup axis, ``c`` the centre of mass, and ``a`` the angle between the approach
  ``-n`` and gravity.
- ``"suctionnet"`` (SuctionNet-1Billion's evaluator, ``get_wrench_score``): ``1 - min(1, max(|tau_y|, |tau_z|) /
  tau_thr)`` in SuctionNet's approach frame (x along ``n``, y horizontal, z = x cross y), ``c`` the centroid of
  the object's surface, no angle factor.
- ``"suctionnet_label"`` (SuctionNet's label-time wrench): ``1 - min(1, |(tau_x, tau_y)| / (sqrt(2) tau_thr))``
  in the same frame: the twist and one bending axis, at a threshold sqrt(2) higher. Far more lenient.
"""

from __future__ import annotations

import numpy as np

from parcelpick_env.suction.config import SuctionConfig


def suctionnet_frames(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """SuctionNet's approach frame per unit normal (``viewpoint_params_to_matrix`` at angle 0): x along ``n``,
    y = (-n_y, n_x, 0) normalised (world y where ``n`` is vertical), z = x cross y."""
    x = np.asarray(normals, dtype=np.float64)
    y = np.stack([-x[:, 1], x[:, 0], np.zeros(len(x))], axis=1)
    norm = np.linalg.norm(y, axis=1, keepdims=True)
    y = np.where(norm > 0, y / np.where(norm > 0, norm, 1.0), np.array([0.0, 1.0, 0.0]))
    return x, y, np.cross(x, y)


def wrench_scores(points: np.ndarray, normals: np.ndarray, centres: np.ndarray,
                  config: SuctionConfig) -> np.ndarray:
    """(N,) wrench score for contacts ``points`` with outward ``normals`` on bodies centred at ``centres``
    (the COM for ``"paper"``, the surface centroid for the SuctionNet models; the scorer chooses)."""
    torque = np.cross(centres - points, _unit_weight(config))
    a, b = _frame_axes(normals, config)
    return _scores(np.sum(torque * a, axis=1), np.sum(torque * b, axis=1), normals, config)


def expected_wrench_scores(points: np.ndarray, normals: np.ndarray, centres: np.ndarray, spread: np.ndarray,
                           draws: np.ndarray, config: SuctionConfig) -> np.ndarray:
    """(N,) mean of ``wrench_scores`` over centres moved horizontally by ``spread * draws[k]``: the score expected
    when each centre is known to within ``spread`` (N,) metres an axis, ``draws`` (K, 2) being samples of the unit
    error. A centre's shift adds its own cross product with the weight to the torque, so each torque component the
    score reads is the unshifted one plus ``spread`` times a (K, N) product: no K calls, no (K, N, 3) torques."""
    weight = _unit_weight(config)
    torque = np.cross(centres - points, weight)
    shifts = np.cross(np.column_stack([draws, np.zeros(len(draws))]), weight)  # (K, 3): torque of a unit shift
    spread = np.asarray(spread, dtype=np.float64)

    def component(axis: np.ndarray) -> np.ndarray:
        # the shifts' torques are horizontal (a horizontal lever times a vertical weight): two outer products,
        # in place from here (fresh (K, N) temporaries cost more than the arithmetic; a BLAS matmul this thin
        # waits on its threads when the cores are busy)
        out = np.multiply.outer(shifts[:, 0], axis[:, 0])
        out += np.multiply.outer(shifts[:, 1], axis[:, 1])
        out *= spread
        out += np.sum(torque * axis, axis=1)
        return out
    a, b = _frame_axes(normals, config)
    return _scores(component(a), component(b), normals, config).mean(axis=0, dtype=np.float64).astype(np.float32)


def _unit_weight(config: SuctionConfig) -> np.ndarray:
    return np.array([0.0, 0.0, -config.unit_mass * config.gravity])


def _frame_axes(normals: np.ndarray, config: SuctionConfig) -> tuple[np.ndarray, np.ndarray]:
    """The two axes of each contact's SuctionNet frame whose torque components ``config``'s score reads: (x, y)
    for the label-time wrench, the bending axes (y, z) for the others (x is the normal, so the torque's part
    orthogonal to it, which ``"paper"`` bends by, is (t_y, t_z))."""
    x, y, z = suctionnet_frames(normals)
    return (x, y) if config.wrench_model == "suctionnet_label" else (y, z)


def _scores(t_a: np.ndarray, t_b: np.ndarray, normals: np.ndarray, config: SuctionConfig) -> np.ndarray:
    """(..., N) float32 scores of gravity's torque from its (..., N) components on ``_frame_axes``."""
    if config.wrench_model == "paper":
        torque_ratio = np.minimum(1.0, np.hypot(t_a, t_b) / config.torque_threshold)
        # -n . (0, 0, -1) = n_z
        angle = np.arccos(np.clip(normals[:, 2], -1.0, 1.0))
        return ((1.0 - torque_ratio) * (1.0 - angle / np.pi)).astype(np.float32)
    if config.wrench_model == "suctionnet":
        load = np.maximum(np.abs(t_a), np.abs(t_b)) / config.torque_threshold
    else:  # suctionnet_label: (t_x, t_y)
        load = np.hypot(t_a, t_b) / (np.sqrt(2.0) * config.torque_threshold)
    return (1.0 - np.minimum(1.0, load)).astype(np.float32)
