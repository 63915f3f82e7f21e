"""Rerun replays of ParcelPick episodes: one ``.rrd`` file per episode, written offline.

Entities (world frame, metres):

- ``camera`` (pinhole + pose), ``camera/rgb``, ``camera/depth``: the observation images;
- ``world/cloud``: the observed point cloud (subsampled to ``max_points``);
- ``world/parcels/<k>``: each parcel's true mesh (static) and pose (per attempt);
- ``world/action/point``, ``world/action/normal``: the commanded suction point and outward normal;
- ``world/contact``: where the cup axis met the parcel, with the actual axis;
- ``world/arm``: the arm's link chain and ``world/arm/tip`` the cup lip, on the ``sim_time`` timeline;
- ``world/held``: the carried parcel's pose while held;
- ``outcome``: one text line per attempt (outcome, cause, seal); ``metrics/*`` scalars.

Timelines: ``attempt`` (sequence) for per-attempt data, ``sim_time`` (seconds) for motion.
Only the SDK's file sink is used (``RecordingStream.save``): no viewer is spawned and nothing is sent
over the network; the rerun CLI's own analytics are off when ``CI=true`` (set by the project's CI).
Read a file back with ``rerun.chunk.RrdReader(path).store()``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Callable

import numpy as np

from parcelpick_env.camera.frame import CameraFrame
from parcelpick_env.scene.scene import Scene


class EpisodeRecorder:
    """Writes one episode to ``path`` (``.rrd``)."""

    def __init__(self, path: str | Path, episode_id: str = "episode", max_points: int = 4096) -> None:
        import rerun as rr

        self.rr = rr
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.max_points = int(max_points)
        self.rec = rr.RecordingStream("parcelpick", recording_id=episode_id)
        self.rec.save(str(self.path))
        self.rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        self._meshes_logged: set[str] = set()

    # ----------------------------------------------------------------------------------- per attempt
    def log_observation(self, attempt: int, frame: CameraFrame, scene: Scene) -> None:
        rr, rec = self.rr, self.rec
        rec.set_time("attempt", sequence=attempt)
        K, T = frame.intrinsics, frame.extrinsics
        rec.log("camera", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
        rec.log("camera", rr.Pinhole(image_from_camera=K, width=frame.width, height=frame.height,
                                     camera_xyz=rr.ViewCoordinates.RDF))
        rec.log("camera/rgb", rr.Image(frame.rgb))
        rec.log("camera/depth", rr.DepthImage(frame.depth, meter=1.0))
        points = frame.points
        if len(points) > self.max_points:
            step = int(np.ceil(len(points) / self.max_points))
            points = points[::step]
        rec.log("world/cloud", rr.Points3D(points, radii=0.002))
        self.log_parcels(scene)

    def log_parcels(self, scene: Scene) -> None:
        rr, rec = self.rr, self.rec
        for ps in scene.parcels:
            key = f"world/parcels/{ps.asset.asset_id}-{ps.body_id}"
            if key not in self._meshes_logged:
                mesh = ps.asset.mesh
                rec.log(key + "/mesh", rr.Mesh3D(vertex_positions=mesh.vertices, triangle_indices=mesh.faces,
                                                 albedo_factor=ps.asset.rgba), static=True)
                self._meshes_logged.add(key)
            rec.log(key, rr.Transform3D(translation=ps.position, quaternion=rr.Quaternion(xyzw=ps.orientation)))

    def log_action(self, attempt: int, point: np.ndarray | None, normal: np.ndarray | None) -> None:
        rr, rec = self.rr, self.rec
        rec.set_time("attempt", sequence=attempt)
        if point is None or normal is None:
            return
        rec.log("world/action/point", rr.Points3D([point], radii=0.006, colors=[[255, 0, 255]]))
        rec.log("world/action/normal", rr.Arrows3D(origins=[point], vectors=[0.08 * np.asarray(normal)],
                                                    colors=[[255, 0, 255]]))

    def log_result(self, attempt: int, result: Any, link_chain: Callable[[np.ndarray], np.ndarray] | None = None,
                   metrics: dict[str, float] | None = None) -> None:
        """The attempt's motion trace on ``sim_time``, its contact and its outcome."""
        rr, rec = self.rr, self.rec
        for entry in getattr(result, "trace", []) or []:
            rec.set_time("sim_time", duration=float(entry["t"]))
            if link_chain is not None:
                rec.log("world/arm", rr.LineStrips3D([link_chain(entry["q"])], radii=0.02,
                                                     colors=[[90, 90, 110]]))
            rec.log("world/arm/tip", rr.Points3D([entry["tip"]], radii=0.01, colors=[[255, 140, 0]]))
            if "held_pose" in entry:
                pos, orn = entry["held_pose"]
                rec.log("world/held", rr.Transform3D(translation=pos, quaternion=rr.Quaternion(xyzw=orn)))
        rec.set_time("attempt", sequence=attempt)
        if result.contact_point is not None and result.contact_axis is not None:
            rec.log("world/contact", rr.Arrows3D(origins=[result.contact_point],
                                                 vectors=[-0.08 * np.asarray(result.contact_axis)],
                                                 colors=[[0, 200, 0] if result.outcome == "success" else [220, 0, 0]]))
        seal = "" if result.seal is None else f" seal={result.seal:.3f}"
        cause = "" if not result.failure_cause else f" cause={result.failure_cause}"
        level = rr.TextLogLevel.INFO if result.outcome == "success" else rr.TextLogLevel.WARN
        rec.log("outcome", rr.TextLog(f"attempt {attempt}: {result.outcome}{cause}{seal}", level=level))
        for name, value in (metrics or {}).items():
            rec.log(f"metrics/{name}", rr.Scalars(float(value)))

    def log_denoising(self, points: np.ndarray, maps: np.ndarray) -> None:
        """Optional policy extra: score maps (steps, M, C) over ``points`` (M, 3) after each denoising step
        (Diffusion-Suction's DDIM run: noise first, scores last). Each step is the cloud coloured by its
        channel mean, rescaled per step, on the ``denoise_step`` timeline."""
        rr, rec = self.rr, self.rec
        points = np.asarray(points, dtype=np.float32).reshape(-1, 3)
        maps = np.asarray(maps, dtype=np.float32)
        if maps.ndim != 3 or maps.shape[1] != len(points):
            raise ValueError(f"denoising maps must be (steps, {len(points)}, C), got {maps.shape}")
        for k, step in enumerate(maps):
            score = step.mean(axis=1)
            score = (score - score.min()) / max(float(np.ptp(score)), 1e-6)
            colours = np.stack([1.0 - score, score, 0.2 * np.ones_like(score)], axis=1)
            rec.set_time("denoise_step", sequence=k)
            rec.log("policy/denoising", rr.Points3D(points, colors=(colours * 255).astype(np.uint8), radii=0.003))

    def close(self) -> None:
        self.rec.flush()
        self.rec.disconnect()
