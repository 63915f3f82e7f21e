"""Which parcel a pick took, and whether other parcels rested on it: the evaluator's privileged reading of a pick.

On stacked piles most lift drops are of parcels that others rest on (their drag about the cup's axis breaks the
20 mm lip's torsion capacity; docs/cell.md), and a policy that picks such a parcel while free ones remain loses
attempts the oracle would not. The audit says so per attempt, from the true scene just before the pick, with the
oracle's own geometry (``policies/oracle.py``: ``pinned_parcels``, another hull lies on it or hangs over it;
``leaned_on``, one touches it above its centre of mass). It only reads: the pick, the physics and the policy's
input are unchanged, and nothing here is shown to a policy. ``eval/clearance.py --audit-picks`` records it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import trimesh

from parcelpick_env.assets.library import AssetLibrary
from policies.oracle import GroundTruth, ground_truth, hull_contacts, leaned_on, pinned_parcels

NO_PARCEL = -1  # the pick point is farther than ``max_distance`` from every parcel (a wall, the floor)


@dataclass(frozen=True)
class PickAudit:
    """One pick read against the true scene just before it."""

    parcel: int  # row of the parcel whose true surface is nearest the pick point, or NO_PARCEL
    covered: bool | None  # another parcel rests or leans on it (None without a parcel)
    off_com_mm: float | None  # horizontal distance from the pick point to that parcel's centre of mass
    to_surface_mm: float | None  # from the pick point to the nearest true parcel surface (None: no parcel left)
    free_parcels: int  # parcels in the bin that no other rests or leans on: could it have taken one?

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def covered_parcels(truth: GroundTruth) -> np.ndarray:
    """(P,) bool: parcels another parcel rests on or leans on (the oracle defers them)."""
    contacts = hull_contacts(truth)
    return pinned_parcels(truth, contacts) | leaned_on(truth, contacts)


def audit_truth(truth: GroundTruth, point: np.ndarray, max_distance: float = 0.02) -> PickAudit:
    """The audit of a pick at ``point`` (3,) on the true scene ``truth``."""
    point = np.asarray(point, dtype=np.float64).reshape(3)
    covered = covered_parcels(truth)
    free = int((~covered).sum())
    if not truth.meshes:
        return PickAudit(NO_PARCEL, None, None, None, free)
    scene = trimesh.util.concatenate(truth.meshes)
    owner = np.repeat(np.arange(len(truth.meshes)), [len(m.faces) for m in truth.meshes])
    _, distance, triangle = trimesh.proximity.closest_point(scene, point[None])
    k, d = int(owner[triangle[0]]), float(distance[0])
    if d > max_distance:
        return PickAudit(NO_PARCEL, None, None, 1e3 * d, free)
    return PickAudit(k, bool(covered[k]), 1e3 * float(np.linalg.norm((point - truth.coms[k])[:2])), 1e3 * d, free)


def audit_pick(env: Any, action: np.ndarray) -> PickAudit:
    """The audit of a ``pose`` action (point, normal) about to be taken in ``env`` (a ``ParcelPickEnv``)."""
    action = np.asarray(action, dtype=np.float64).reshape(-1)
    if action.shape != (6,) or not np.all(np.isfinite(action)):
        raise ValueError(f"audit_pick needs a finite 'pose' action (point, normal), got {action!r}")
    truth = ground_truth(env.privileged_state(), AssetLibrary.default(env.config.asset_seed))
    return audit_truth(truth, action[:3])


def cover_rates(attempt_logs: list[list[dict[str, Any]]]) -> dict[str, dict[str, int]] | None:
    """Attempts and successes on free and on covered parcels (and on none), over episodes' audited attempt
    logs; None when no attempt was audited."""
    out: dict[str, dict[str, int]] = {}
    for log in attempt_logs:
        for attempt in log:
            audit = attempt.get("audit")
            if audit is None:
                continue
            kind = "none" if audit["parcel"] == NO_PARCEL else ("covered" if audit["covered"] else "free")
            row = out.setdefault(kind, {"attempts": 0, "successes": 0, "while_free_left": 0})
            row["attempts"] += 1
            row["successes"] += attempt["outcome"] == "success"
            row["while_free_left"] += kind == "covered" and audit["free_parcels"] > 0
    return out or None
