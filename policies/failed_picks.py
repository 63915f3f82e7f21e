"""Where a cell's picks failed, read from the env's ``info``: the memory that keeps a deterministic policy from
taking again a pick the cell could not do (a failed pick mostly leaves the pile as it was, so the same geometry
gives the same pick).

One memory, two rules, for its two users:

- the deployment tool check (``policies/tool_check.py``) remembers where the cup touched (``info['contact_point']``,
  else the pick it offered) and forgets everything on a success, since a cleared parcel changes the pile;
- the oracle (``policies/oracle.py``) remembers the approach it offered, point and normal, for the whole
  episode, so the last parcel left is tried another way rather than the same way again; it tags each failure with
  the parcel it aimed at (privileged: which parcel, from its ``state_dict``), so that parcel goes behind the others.
"""

from __future__ import annotations

import math
from typing import Any, Mapping

import numpy as np


class FailedPicks:
    """The picks that failed in this episode (since its last success, with ``forget_on_success``), learnt from the
    env's ``info`` once per attempt: ``points`` (K, 3), the approach ``normals`` (K, 3; NaN where not given) and
    the caller's ``tags`` (K; None where not given)."""

    def __init__(self, *, forget_on_success: bool = True, at_contact: bool = True) -> None:
        self.forget_on_success = forget_on_success
        self.at_contact = at_contact
        self.clear()

    def clear(self) -> None:
        """Forget every failure (a new episode)."""
        self.points, self.normals = np.zeros((0, 3)), np.zeros((0, 3))
        self.tags: list[Any] = []
        self._seen = 0

    def note(self, info: Mapping[str, Any] | None, offered: np.ndarray | None,
             offered_normal: np.ndarray | None = None, tag: Any = None) -> bool:
        """Read the last attempt's outcome from ``info`` (nothing if none, or if its attempt was read already):
        a failure adds ``offered`` (the pick this policy offered; with ``at_contact``, where the cup touched if it
        did) and ``tag``, a success forgets every failure with ``forget_on_success``. True where a failure was
        added."""
        attempts = int((info or {}).get("attempts", 0))
        if info is None or "outcome" not in info or attempts <= self._seen:
            return False
        self._seen = attempts
        if info["outcome"] == "success":
            if self.forget_on_success:
                self.points, self.normals, self.tags = np.zeros((0, 3)), np.zeros((0, 3)), []
            return False
        where = np.asarray(info["contact_point"], dtype=np.float64) if self.at_contact and info.get("contacted") \
            else offered
        if where is None:
            return False
        normal = np.full(3, np.nan) if offered_normal is None else np.asarray(offered_normal, dtype=np.float64)
        self.points = np.vstack([self.points, np.asarray(where, dtype=np.float64).reshape(1, 3)])
        self.normals = np.vstack([self.normals, normal.reshape(1, 3)])
        self.tags.append(tag)
        return True

    def count_near(self, points: np.ndarray, radius: float, normals: np.ndarray | None = None,
                   max_angle_deg: float | None = None) -> np.ndarray:
        """(K,) int: how many failures each of ``points`` lies within ``radius`` of (and, given ``normals`` and
        ``max_angle_deg``, whose approach it is within that angle of: the same approach again)."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if len(self.points) == 0 or radius <= 0:
            return np.zeros(len(points), dtype=np.int64)
        near = np.linalg.norm(points[:, None] - self.points[None], axis=-1) <= radius
        if normals is not None and max_angle_deg is not None:
            # a failure offered without a normal matches no approach (NaN compares false)
            near &= np.asarray(normals, dtype=np.float64) @ self.normals.T >= math.cos(math.radians(max_angle_deg))
        return near.sum(axis=1)

    def near(self, points: np.ndarray, radius: float) -> np.ndarray:
        """(K,) bool: within ``radius`` of a failed pick."""
        return self.count_near(points, radius) > 0
