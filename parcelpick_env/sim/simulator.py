"""One headless pybullet world: bin, parcels, stepping and settling.

Parcels collide as the convex hull of their true mesh (reduced to a few dozen vertices, which is
what keeps 30-parcel piles fast) and render as the true mesh with its per-face colours, so the
camera's RGB and segmentation show exactly the surface the suction scorer ray-casts. Collision
shapes are created from vertex arrays; visuals are written once per asset as one OBJ per colour
(pybullet's EGL renderer only draws meshes loaded from files) into a per-simulator temporary
directory that ``close()`` removes.

The pybullet client is connected at first use, not in the constructor, and EGL clients come from the
process's one owner (``sim/egl.py``), which keeps them valid whatever other simulators close and refuses
EGL in a fork of a process that had already started it.

pybullet reports a body's pose as its inertial (centre-of-mass) frame. Everything public here
speaks the parcel's mesh frame instead: ``body_pose``/``set_body_pose`` convert.
"""

from __future__ import annotations

import io
import logging
import shutil
import tempfile
import weakref
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Sequence

import numpy as np
import pybullet as pb
import trimesh

from parcelpick_env.assets.parcel import ParcelAsset
from parcelpick_env.farthest_points import farthest_point_indices
from parcelpick_env.scene.scene import BinSpec
from parcelpick_env.sim.config import SimConfig
from parcelpick_env.sim.egl import EGL_OWNER, connect_plain

log = logging.getLogger(__name__)

BIN_RGBA = (0.45, 0.47, 0.50, 1.0)
GROUND_RGBA = (0.30, 0.30, 0.30, 1.0)
# m: the floor and the ground collide as slabs this thick, so their mid-planes lie 10 cm below the surface, deeper
# than anything sinks in one step (a parcel at 5 m/s moves 8 cm per carry step)
SOLID_DEPTH = 0.2

# Geometry derived from an asset once per process (the asset is immutable).
_GEOMETRY_CACHE: "weakref.WeakKeyDictionary[ParcelAsset, dict]" = weakref.WeakKeyDictionary()


def _obj_rows(fmt: str, rows: np.ndarray) -> str:
    """The text ``np.savetxt(rows, fmt=fmt)`` writes (``fmt % row``, a line each), in one formatting call:
    savetxt's Python loop over rows was half of what a parcel's first use in a process cost."""
    rows = np.asarray(rows)
    return ((fmt + "\n") * len(rows)) % tuple(rows.ravel().tolist())


def _asset_geometry(asset: ParcelAsset, max_hull_vertices: int) -> dict:
    """Hull vertices for collision, and one triangle soup per face colour for rendering.

    Colours are per-part ``rgbaColors`` rather than a texture: after ``resetSimulation`` the EGL
    renderer binds stale texture handles, which made RGB depend on what a simulator drew before.
    """
    key = ("geometry", max_hull_vertices)
    cached = _GEOMETRY_CACHE.setdefault(asset, {})
    if key in cached:
        return cached[key]
    mesh: trimesh.Trimesh = asset.mesh
    hull = mesh.convex_hull.vertices
    if len(hull) > max_hull_vertices:
        # FPS from the vertex farthest from the centroid: the kept vertices span the hull evenly
        start = int(np.argmax(((hull - hull.mean(0)) ** 2).sum(1)))
        hull = hull[farthest_point_indices(hull, max_hull_vertices, start)]
    visual: Any = mesh.visual  # ColorVisuals: assets carry per-face colours, never textures
    face_colours = np.asarray(visual.face_colors, dtype=np.uint8)[:, :3]
    palette, face_palette = np.unique(face_colours, axis=0, return_inverse=True)
    face_palette = face_palette.reshape(-1)
    parts = []
    for colour_index, colour in enumerate(palette):
        faces = np.flatnonzero(face_palette == colour_index)
        obj = io.StringIO()
        obj.write("# ParcelPick parcel part (one colour)\n")
        obj.write(_obj_rows("v %.6f %.6f %.6f", mesh.vertices))
        obj.write(_obj_rows("vn %.6f %.6f %.6f", mesh.face_normals[faces]))
        f = mesh.faces[faces] + 1
        nrm = np.repeat(np.arange(1, len(faces) + 1)[:, None], 3, axis=1)
        obj.write(_obj_rows("f %d//%d %d//%d %d//%d", np.stack([f, nrm], axis=2).reshape(len(faces), 6)))
        parts.append((obj.getvalue(), (*(colour / 255.0), 1.0)))
    geometry = {"hull": np.ascontiguousarray(hull, dtype=np.float64), "parts": parts}
    cached[key] = geometry
    return geometry


class Simulator:
    """Owns one pybullet DIRECT client. Use as a context manager or call ``close()``."""

    def __init__(self, config: SimConfig | None = None) -> None:
        self.config = config or SimConfig()
        self._client: int | None = None  # connected at first use (see ``client``)
        self._closed = False
        self.egl_plugin = -1
        self._tmpdir = Path(tempfile.mkdtemp(prefix="parcelpick_sim_"))
        # Removed by close(), or when garbage-collected, or at exit of a process (a pool worker) that never closes.
        self._remove_tmpdir = weakref.finalize(self, shutil.rmtree, self._tmpdir, ignore_errors=True)
        self._com: dict[int, np.ndarray] = {}  # body id -> COM in the body (mesh) frame
        self._files: dict[int, tuple[ParcelAsset, list[str]]] = {}  # id(asset) -> (asset, OBJ paths)
        self.steps_taken = 0

    @property
    def client(self) -> int:
        """The pybullet client id, connected (with EGL when configured) at first use, so that constructing a
        simulator, or an env, starts no renderer (``sim/egl.py``: EGL does not survive fork)."""
        if self._client is None:
            self._require_open()
            if self.config.egl_rendering:
                self._client, self.egl_plugin = EGL_OWNER.acquire()
            else:
                self._client = connect_plain()
            self._configure()
        elif self.egl_plugin >= 0:
            EGL_OWNER.activate(self._client)  # every pybullet call on this client may touch its GL context
        return self._client

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def egl_enabled(self) -> bool:
        """True when OpenGL (EGL) rendering is available to cameras on this client."""
        if self._closed:
            return False
        _ = self.client  # connects: the plugin is loaded with the client
        return self.egl_plugin >= 0

    @property
    def egl_current(self) -> bool:
        """True while this simulator's EGL client is live in the process's owner (``sim/egl.py``), which
        keeps every EGL client's renderer valid whatever other simulators close; False once closed."""
        return self.egl_enabled and EGL_OWNER.is_live(self._client)

    # ----------------------------------------------------------------- world
    def _configure(self) -> None:
        cfg = self.config
        pb.setGravity(0, 0, -cfg.gravity, physicsClientId=self.client)
        pb.setPhysicsEngineParameter(
            fixedTimeStep=cfg.timestep, numSolverIterations=cfg.solver_iterations,
            deterministicOverlappingPairs=1, physicsClientId=self.client,
        )

    def reset(self) -> None:
        """Empty the world (bodies, shapes) and re-apply the configuration."""
        self._require_open()
        pb.resetSimulation(physicsClientId=self.client)
        self._com.clear()
        self.steps_taken = 0
        self._configure()

    def close(self) -> None:
        """Release the client: an EGL client goes back to the process's owner (emptied, for reuse; closing
        it would blank every other EGL client's renders), a plain one disconnects. Idempotent."""
        client, self._client, self._closed = self._client, None, True
        if client is not None:
            try:
                if self.egl_plugin >= 0:
                    EGL_OWNER.release(client)
                else:
                    pb.disconnect(physicsClientId=client)
            except pb.error:  # already disconnected
                pass
            self.egl_plugin = -1
        self._remove_tmpdir()

    def __enter__(self) -> "Simulator":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self) -> None:  # best effort; close() is the contract
        try:
            self.close()
        except Exception:
            pass

    def _require_open(self) -> None:
        if self._closed:
            raise RuntimeError("Simulator is closed")

    # ----------------------------------------------------------------- time
    def step(self, n: int = 1) -> None:
        self._require_open()
        if int(n) < 0:
            raise ValueError(f"cannot step a negative number of times ({n})")
        for _ in range(int(n)):
            pb.stepSimulation(physicsClientId=self.client)
        self.steps_taken += int(n)

    def _slower_than(self, body_id: int, lin_tol: float, ang_tol: float) -> bool:
        """Whether the body moves slower than both ``lin_tol`` (m/s) and ``ang_tol`` (rad/s) now."""
        lin, ang = pb.getBaseVelocity(body_id, physicsClientId=self.client)
        return (lin[0] ** 2 + lin[1] ** 2 + lin[2] ** 2 <= lin_tol ** 2
                and ang[0] ** 2 + ang[1] ** 2 + ang[2] ** 2 <= ang_tol ** 2)

    @contextmanager
    def asleep(self, body_ids: Iterable[int]) -> Iterator[list[int]]:
        """Deactivate, for the block, the bodies of ``body_ids`` that are as good as still; yields their ids.

        Bullet neither integrates sleeping bodies nor collides them with each other: a resting 30-parcel
        pile costs 3-5 ms a step at the carry's settings awake, 0.2-0.5 ms asleep (docs/cell.md). Sleep
        zeroes a body's velocity, so only bodies below ``SimConfig.sleep_linear_velocity`` and
        ``sleep_angular_velocity`` sleep (a coarse step's jitter, not a fall); one awake body keeps its whole
        island of touching bodies awake, at the full cost but with the physics intact. A contact
        with an awake body (the carried parcel, the arm) wakes the sleeper's island. Their own solver jitter
        cannot wake them (wake-up on motion is off), and a woken body falls asleep again only after Bullet's
        2 s below ``SimConfig.sleep_motion``. On exit every one is awake, and sleeps by itself never again:
        pybullet's default, which Bullet's own threshold would break (v^2 + w^2 < 0.05 for 2 s froze a
        parcel sliding at 1 cm/s).
        """
        with self.sleep_scope() as doze:
            yield doze(body_ids)

    @contextmanager
    def sleep_scope(self) -> Iterator[Callable[[Iterable[int]], list[int]]]:
        """``asleep`` for a block that decides during it when bodies may sleep: yields ``doze(body_ids)``,
        which deactivates those of ``body_ids`` that are as good as still at that moment and returns their
        ids; it may be called any number of times. On exit every body dozed in the block is awake."""
        c = self.client
        cfg = self.config
        dozed: dict[int, None] = {}  # insertion-ordered set: woken in the order they slept
        # one flag per call: pybullet applies only some of the flags of a combined call (a combined wake-up
        # and disable-sleeping left the body able to sleep, measured)
        entry = (pb.ACTIVATION_STATE_ENABLE_SLEEPING, pb.ACTIVATION_STATE_DISABLE_WAKEUP, pb.ACTIVATION_STATE_SLEEP)
        leave = (pb.ACTIVATION_STATE_ENABLE_WAKEUP, pb.ACTIVATION_STATE_WAKE_UP, pb.ACTIVATION_STATE_DISABLE_SLEEPING)

        def doze(body_ids: Iterable[int]) -> list[int]:
            slept = [b for b in body_ids if self.has_body(b)
                     and self._slower_than(b, cfg.sleep_linear_velocity, cfg.sleep_angular_velocity)]
            for b in slept:
                pb.changeDynamics(b, -1, sleepThreshold=cfg.sleep_motion, physicsClientId=c)
                for flag in entry:
                    pb.changeDynamics(b, -1, activationState=flag, physicsClientId=c)
                dozed[b] = None
            return slept

        try:
            yield doze
        finally:
            for b in dozed:
                if self.has_body(b):
                    for flag in leave:
                        pb.changeDynamics(b, -1, activationState=flag, physicsClientId=c)

    @property
    def timestep(self) -> float:
        """The engine's step now, s (``SimConfig.timestep`` outside a ``physics_overrides`` block)."""
        return float(pb.getPhysicsEngineParameters(physicsClientId=self.client)["fixedTimeStep"])

    def com_poses(self, body_ids: Sequence[int]) -> tuple[np.ndarray, np.ndarray]:
        """World centre-of-mass positions (n, 3) and orientations (n, 4, xyzw): pybullet's own base frame."""
        poses = [pb.getBasePositionAndOrientation(b, physicsClientId=self.client) for b in body_ids]
        return (np.array([q[0] for q in poses], dtype=np.float64).reshape(-1, 3),
                np.array([q[1] for q in poses], dtype=np.float64).reshape(-1, 4))

    def rest_steps(self, dt: float | None = None) -> int:
        """Steps of ``dt`` (the engine's step by default) in one ``SimConfig.rest_window``."""
        return max(1, int(round(self.config.rest_window / (self.timestep if dt is None else dt))))

    def still(self, before: tuple[np.ndarray, np.ndarray], after: tuple[np.ndarray, np.ndarray],
              seconds: float) -> np.ndarray:
        """Per body, whether its net motion between two ``com_poses`` taken ``seconds`` apart is within the
        velocity tolerances times ``seconds``: the one test of rest (pile building and every settle). Solver
        jitter that goes nowhere (thin mailers on hulls) passes, sliding and toppling do not."""
        cfg = self.config
        turned = 2 * np.arccos(np.clip(np.abs(np.sum(after[1] * before[1], axis=1)), 0.0, 1.0))
        return ((np.linalg.norm(after[0] - before[0], axis=1) < cfg.linear_velocity_tol * seconds)
                & (turned < cfg.angular_velocity_tol * seconds))

    def settle(self, body_ids: Sequence[int], max_steps: int | None = None) -> int:
        """Step at the engine's current step until the bodies of ``body_ids`` are at rest (``still`` over one
        ``SimConfig.rest_window``); returns the number of steps taken, capped at ``max_steps`` (config default).
        """
        self._require_open()
        cap = self.config.max_settle_steps if max_steps is None else int(max_steps)
        ids = list(body_ids)
        missing = [b for b in ids if not self.has_body(b)]
        if missing:
            raise ValueError(f"cannot settle bodies that are not in the simulator: {missing}")
        dt = self.timestep
        window = self.rest_steps(dt)
        steps, before = 0, self.com_poses(ids)
        while steps < cap:
            n = min(window, cap - steps)
            self.step(n)
            steps += n
            after = self.com_poses(ids)
            if self.still(before, after, window * dt).all():
                break
            before = after
        return steps

    # ----------------------------------------------------------------- bodies
    def add_bin(self, spec: BinSpec) -> list[int]:
        """Static bin (floor + four walls, one compound body) on a ground slab; returns [bin, ground]."""
        self._require_open()
        boxes = spec.meshes()
        half = [list(m.extents / 2) for m in boxes]
        centres = [list(m.bounds.mean(axis=0)) for m in boxes]
        # The floor collides as a slab SOLID_DEPTH thick below its top (its visual keeps the wall thickness): a
        # box penetrated past its mid-plane pushes the intruder out of its far side, and a thin mailer falling
        # 1 m/s moves 17 mm per carry step, most of the 2 cm floor (docs/cell.md, 'Tunnelling').
        # The walls' collision boxes reach down through that slab: standing on its top face, they left a seam where
        # a thin envelope could wedge under a wall and be pressed into the floor (results/ORACLE.md, seventeenth session).
        col_half, col_centres = [list(h) for h in half], [list(c) for c in centres]
        bottom = spec.floor_z - SOLID_DEPTH
        for i in range(len(boxes)):
            top = col_centres[i][2] + col_half[i][2] if i else spec.floor_z
            col_half[i][2] = (top - bottom) / 2
            col_centres[i][2] = (top + bottom) / 2
        col = pb.createCollisionShapeArray([pb.GEOM_BOX] * len(boxes), halfExtents=col_half,
                                           collisionFramePositions=col_centres, physicsClientId=self.client)
        vis = pb.createVisualShapeArray([pb.GEOM_BOX] * len(boxes), halfExtents=half,
                                        visualFramePositions=centres, rgbaColors=[BIN_RGBA] * len(boxes),
                                        physicsClientId=self.client)
        bin_id = pb.createMultiBody(0.0, col, vis, physicsClientId=self.client)
        ground_half = [3.0, 3.0, SOLID_DEPTH / 2]
        gz = spec.floor_z - spec.wall_thickness - ground_half[2]
        gcol = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=ground_half, physicsClientId=self.client)
        gvis = pb.createVisualShape(pb.GEOM_BOX, halfExtents=ground_half, rgbaColor=GROUND_RGBA,
                                    physicsClientId=self.client)
        ground_id = pb.createMultiBody(0.0, gcol, gvis, basePosition=[*spec.center_xy, gz],
                                       physicsClientId=self.client)
        for b in (bin_id, ground_id):
            pb.changeDynamics(b, -1, lateralFriction=0.6, restitution=0.0, physicsClientId=self.client)
        return [bin_id, ground_id]

    def _visual_files(self, asset: ParcelAsset, geo: dict) -> list[str]:
        """One OBJ per colour part of ``asset``, written once per simulator (EGL only draws files)."""
        key = id(asset)
        if key not in self._files or self._files[key][0] is not asset:
            stem = f"parcel_{len(self._files):05d}"
            paths = []
            for i, (obj, _) in enumerate(geo["parts"]):
                path = self._tmpdir / f"{stem}_{i}.obj"
                path.write_text(obj)
                paths.append(str(path))
            self._files[key] = (asset, paths)
        return self._files[key][1]

    def _parcel_shapes(self, asset: ParcelAsset) -> tuple[int, int]:
        geo = _asset_geometry(asset, self.config.max_hull_vertices)
        paths = self._visual_files(asset, geo)
        col = pb.createCollisionShape(pb.GEOM_MESH, vertices=geo["hull"].tolist(), physicsClientId=self.client)
        vis = pb.createVisualShapeArray([pb.GEOM_MESH] * len(paths), fileNames=paths,
                                        rgbaColors=[list(rgba) for _, rgba in geo["parts"]],
                                        physicsClientId=self.client)
        if col < 0 or vis < 0:
            raise RuntimeError(f"pybullet could not create shapes for asset {asset.asset_id}")
        return col, vis

    def add_parcel(self, asset: ParcelAsset, position: Sequence[float], orientation: Sequence[float],
                   friction: float) -> int:
        """Add a dynamic parcel with its mesh frame at ``position``/``orientation`` (xyzw)."""
        self._require_open()
        pos = np.asarray(position, dtype=np.float64)
        orn = np.asarray(orientation, dtype=np.float64)
        if pos.shape != (3,) or orn.shape != (4,):
            raise ValueError(f"position must be (3,) and orientation (4,) xyzw, got {pos.shape}, {orn.shape}")
        if not (np.isfinite(pos).all() and np.isfinite(orn).all()):
            raise ValueError("parcel pose must be finite")
        norm = np.linalg.norm(orn)
        if norm < 1e-9:
            raise ValueError("orientation quaternion has zero norm")
        if not (np.isfinite(friction) and friction >= 0):
            raise ValueError(f"friction must be a finite non-negative number, got {friction!r}")
        col, vis = self._parcel_shapes(asset)
        com = np.asarray(asset.com, dtype=np.float64)
        body = pb.createMultiBody(
            baseMass=float(asset.mass), baseCollisionShapeIndex=col, baseVisualShapeIndex=vis,
            basePosition=pos.tolist(), baseOrientation=(orn / norm).tolist(),
            baseInertialFramePosition=com.tolist(), physicsClientId=self.client,
        )
        if body < 0:
            raise RuntimeError(f"pybullet could not create a body for asset {asset.asset_id}")
        pb.changeDynamics(
            body, -1, lateralFriction=float(friction), spinningFriction=0.01, rollingFriction=0.01,
            restitution=0.0, collisionMargin=self.config.collision_margin, physicsClientId=self.client,
        )
        self._com[body] = com
        return body

    def remove(self, body_id: int) -> None:
        """Remove any body of this world (parcels, or bodies others loaded into ``client``)."""
        self._require_open()
        if not self.has_body(body_id):
            raise ValueError(f"body {body_id} is not in this simulator")
        pb.removeBody(body_id, physicsClientId=self.client)
        self._com.pop(body_id, None)

    def has_body(self, body_id: int) -> bool:
        """Whether ``body_id`` exists in the world now (however it was added or removed)."""
        self._require_open()
        try:
            pb.getBodyInfo(int(body_id), physicsClientId=self.client)
            return True
        except pb.error:
            return False

    def aabb(self, body_id: int) -> tuple[np.ndarray, np.ndarray]:
        """World axis-aligned bounds (lo, hi) of a body's collision shape."""
        self._require_open()
        lo, hi = pb.getAABB(body_id, physicsClientId=self.client)
        return np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)

    @contextmanager
    def physics_overrides(self, timestep: float | None = None, solver_iterations: int | None = None) -> Iterator[None]:
        """Temporarily use another timestep and/or solver iteration count (e.g. a cheap drop phase)."""
        self._require_open()
        cfg = self.config
        if timestep is not None and not 0 < timestep <= 0.05:
            raise ValueError(f"timestep must be in (0, 0.05], got {timestep}")
        if solver_iterations is not None and solver_iterations < 1:
            raise ValueError(f"solver_iterations must be >= 1, got {solver_iterations}")
        pb.setPhysicsEngineParameter(fixedTimeStep=timestep or cfg.timestep,
                                     numSolverIterations=int(solver_iterations or cfg.solver_iterations),
                                     physicsClientId=self.client)
        try:
            yield
        finally:
            pb.setPhysicsEngineParameter(fixedTimeStep=cfg.timestep, numSolverIterations=cfg.solver_iterations,
                                         physicsClientId=self.client)

    # ----------------------------------------------------------------- poses
    def body_pose(self, body_id: int) -> tuple[np.ndarray, np.ndarray]:
        """Mesh-frame (position, orientation xyzw) of a body; pybullet itself reports the COM frame."""
        self._require_open()
        pos, orn = pb.getBasePositionAndOrientation(body_id, physicsClientId=self.client)
        pos, orn = np.asarray(pos, dtype=np.float64), np.asarray(orn, dtype=np.float64)
        com = self._com.get(body_id)
        if com is not None:
            R = np.asarray(pb.getMatrixFromQuaternion(orn.tolist()), dtype=np.float64).reshape(3, 3)
            pos = pos - R @ com
        return pos, orn

    def set_body_pose(self, body_id: int, position: Sequence[float], orientation: Sequence[float]) -> None:
        """Teleport a body so its mesh frame is at ``position``/``orientation`` (xyzw); zeroes velocity."""
        self._require_open()
        pos = np.asarray(position, dtype=np.float64)
        orn = np.asarray(orientation, dtype=np.float64)
        orn = orn / np.linalg.norm(orn)
        com = self._com.get(body_id)
        if com is not None:
            R = np.asarray(pb.getMatrixFromQuaternion(orn.tolist()), dtype=np.float64).reshape(3, 3)
            pos = pos + R @ com
        pb.resetBasePositionAndOrientation(body_id, pos.tolist(), orn.tolist(), physicsClientId=self.client)
        pb.resetBaseVelocity(body_id, [0, 0, 0], [0, 0, 0], physicsClientId=self.client)
