"""Dex-Net 3.0 style baseline: crops, CEM, training CLI and the policy on synthetic depth scenes.

The synthetic scenes are axis-aligned boxes on a floor seen by an overhead pinhole camera, rendered
analytically; their labels come from simple geometry (seal needs the cup inside the top face, wrench
falls with the distance to the box centre). They exist only to exercise this package quickly.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from policies.dexnet.cem import fit_gmm
from policies.dexnet.config import DexNetConfig, TrainConfig
from policies.dexnet.crops import DepthMosaic, extract_crops
from policies.dexnet.network import SuctionQualityNet, load_checkpoint, save_checkpoint
from policies.dexnet.projection import approach_angles, project

CAMERA_HEIGHT = 1.0
CUP_RADIUS = 0.01
TORQUE_THRESHOLD = CUP_RADIUS * 15.6 * math.pi
MASS = 0.3  # kg: the wrench score reaches 0 at a 17 cm lever
SMALL = DexNetConfig(crop_size=32, crop_metric_size=0.16, conv_channels=(8, 16), fc_width=16,
                     num_seeds=40, num_gmm_samples=20)


def overhead_camera(width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    f = width / (2 * math.tan(math.radians(30)))
    K = np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1.0]])
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])  # OpenCV camera looking straight down: x right, y down, z forward
    T[:3, 3] = [0, 0, CAMERA_HEIGHT]
    return K, T


def synthetic_scene(seed: int, width: int = 64, height: int = 48, boxes: int = 3) -> dict[str, np.ndarray]:
    """A dataset-like record: depth image, camera, every pixel as an annotation point with labels."""
    rng = np.random.default_rng(seed)
    K, T = overhead_camera(width, height)
    centres = rng.uniform(-0.2, 0.2, size=(boxes, 2))
    half = rng.uniform(0.04, 0.10, size=(boxes, 2))
    tops = rng.uniform(0.05, 0.2, size=boxes)
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]], -1)  # camera x, y per unit z
    # World xy of the ray at height h: camera x -> world x, camera y -> world -y.
    surface = np.full((height, width), 0.0)
    owner = np.full((height, width), -1)
    for i in np.argsort(tops):  # higher boxes drawn last, so they win
        z = CAMERA_HEIGHT - tops[i]
        xy = np.stack([rays[..., 0] * z, -rays[..., 1] * z], -1)
        inside = np.all(np.abs(xy - centres[i]) <= half[i], axis=-1)
        surface[inside], owner[inside] = tops[i], i
    depth = (CAMERA_HEIGHT - surface).astype(np.float32)
    xy = np.stack([rays[..., 0] * depth, -rays[..., 1] * depth], -1)
    points = np.concatenate([xy, surface[..., None]], -1).reshape(-1, 3)
    own = owner.reshape(-1)
    margin = np.min(half[own] - np.abs(points[:, :2] - centres[own]), axis=1)
    lever = np.linalg.norm(points[:, :2] - centres[own], axis=1)
    seal = np.where((own >= 0) & (margin > CUP_RADIUS), 1.0, 0.0)
    wrench = np.where(own >= 0, 1 - np.minimum(1, MASS * 9.8 * lever / TORQUE_THRESHOLD), 0.0)
    labels = np.stack([seal, wrench, np.ones_like(seal), (own >= 0).astype(float)], 1)
    return {"depth": depth, "intrinsics": K, "extrinsics": T, "points": points.astype(np.float32),
            "normals": np.tile(np.float32([0, 0, 1]), (len(points), 1)), "labels": labels.astype(np.float32)}


def write_dataset(root, records) -> None:
    from dataset.storage import shard_name, write_manifest, write_shard

    entry = write_shard(root / shard_name(0), 0, dict(enumerate(records)), range(len(records)))
    write_manifest(root, {"source": "tests/test_dexnet.py synthetic boxes"}, [entry], complete=True)


def observation(record):
    obs = {"depth": record["depth"][..., None], "points": record["points"], "normals": record["normals"],
           "rgb": np.zeros(record["depth"].shape + (3,), np.uint8)}
    return obs, {"intrinsics": record["intrinsics"], "extrinsics": record["extrinsics"]}


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    """The default network trained briefly through the CLI on a tiny synthetic dataset (shared by the policy tests)."""
    from policies.dexnet.train import main

    root = tmp_path_factory.mktemp("dexnet")
    data = root / "data"
    data.mkdir()
    write_dataset(data, [synthetic_scene(s) for s in range(5)])
    out = root / "tiny.pt"
    history = main(["--data", str(data), "--out", str(out), "--epochs", "3", "--seed", "0", "--batch-size", "64",
                    "--samples-per-epoch", "256", "--max-points-per-scene", "300", "--no-progress"])
    return out, history


# ------------------------------------------------------------------------------------------------ crops

def test_crop_centre_value_and_orientation_follow_the_approach_axis():
    K, _ = overhead_camera(64, 48)
    slope = 0.002  # metres of depth per pixel to the right
    v, u = np.mgrid[0:48, 0:64].astype(np.float32)
    depth = 1.0 + slope * u
    config = DexNetConfig(crop_size=32, crop_metric_size=0.08)
    centre = np.array([[30.0, 20.0]])
    z = np.array([1.0 + slope * 30.0])
    aligned, turned = extract_crops(depth, np.repeat(centre, 2, 0), np.repeat(z, 2), np.array([0.0, np.pi / 2]),
                                    K[0, 0], K[1, 1], config)
    assert aligned.shape == (2, 32, 32) and torch.all(aligned[1] == 1)
    # Crop pixel centres sit at +-half a crop pixel around the candidate: the centre 2x2 averages to 0.
    assert abs(float(aligned[0, 15:17, 15:17].mean())) < 1e-4
    # Angle 0: depth grows along crop columns by exactly the metric offset in pixels times the slope.
    px_per_crop_px = (config.crop_metric_size / 32) * K[0, 0] / z[0]
    expected = slope * px_per_crop_px * (np.arange(32) - 15.5) / config.depth_scale
    np.testing.assert_allclose(aligned[0, 10].numpy(), expected, atol=1e-4)
    assert float(aligned[0, :, 0].std()) < 1e-5  # constant down a column
    # Angle pi/2: crop +x points down the image, so image +u runs towards the crop's top rows.
    np.testing.assert_allclose(turned[0, :, 10].numpy(), expected[::-1], atol=1e-4)


def test_crops_mark_missing_depth_and_image_edges_invalid_and_keep_images_apart():
    K, _ = overhead_camera(64, 48)
    near = np.full((48, 64), 0.8, np.float32)
    near[:, 40:] = 0.0  # no return on the right
    far = np.full((48, 64), 1.5, np.float32)
    config = DexNetConfig(crop_size=32, crop_metric_size=0.2)
    crops = DepthMosaic(np.stack([near, far])).crops(
        np.array([[40.0, 47.0], [32.0, 24.0]]), np.array([0.8, 1.5]), np.zeros(2), K[0, 0], K[1, 1], config,
        image_index=np.array([0, 1]))
    first, second = crops[0], crops[1]
    assert torch.all(first[1, :16, :14] == 1) and torch.all(first[1, :, 16:] == 0)  # missing columns are invalid
    assert torch.all(first[1, 18:, :] == 0)  # below the image's last row: invalid, never the next image
    assert torch.all(first[0][first[1] == 0] == 0)
    assert torch.all(second[1] == 1) and torch.allclose(second[0], torch.zeros(32, 32), atol=1e-4)


def test_projection_and_approach_angles_for_the_overhead_camera():
    K, T = overhead_camera(64, 48)
    uv, z = project(np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.5]]), K, T)
    np.testing.assert_allclose(uv[0], [K[0, 2], K[1, 2]])
    assert z[0] == pytest.approx(1.0) and z[1] == pytest.approx(0.5)
    assert uv[1, 0] == pytest.approx(K[0, 2] + K[0, 0] * 0.1 / 0.5)
    # A normal tilted towards +x world: approach -n points to -x world = -x camera (angle pi), tilt 20 deg.
    tilt = math.radians(20)
    angle, tilt_out = approach_angles(np.array([[math.sin(tilt), 0, math.cos(tilt)]]), T)
    assert abs(abs(angle[0]) - math.pi) < 1e-9 and tilt_out[0] == pytest.approx(tilt)


# ------------------------------------------------------------------------------------------ GMM and net

def test_gmm_recovers_two_clusters():
    rng = np.random.default_rng(0)
    x = np.concatenate([rng.normal([0, 0], 0.01, (200, 2)), rng.normal([1, 1], 0.01, (100, 2))])
    gmm = fit_gmm(x, 2, np.random.default_rng(1), iterations=20, reg_covar=1e-6)
    order = np.argsort(gmm.means[:, 0])
    np.testing.assert_allclose(gmm.means[order], [[0, 0], [1, 1]], atol=0.01)
    np.testing.assert_allclose(gmm.weights[order], [2 / 3, 1 / 3], atol=0.01)
    samples = gmm.sample(1000, np.random.default_rng(2))
    assert 0.55 < np.mean(samples[:, 0] < 0.5) < 0.78


def test_checkpoint_round_trip_and_clear_errors(tmp_path):
    model = SuctionQualityNet(SMALL)
    path = tmp_path / "net.pt"
    save_checkpoint(path, model, {"seed": 3})
    loaded, meta = load_checkpoint(path)
    assert meta == {"seed": 3} and loaded.config == SMALL
    crops = torch.randn(3, 2, 32, 32)
    q = loaded.quality(crops, torch.ones(3), torch.zeros(3))
    assert q.shape == (3,) and torch.all((q >= 0) & (q <= 1))
    with pytest.raises(FileNotFoundError, match="missing.pt"):
        load_checkpoint(tmp_path / "missing.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="junk.pt"):
        load_checkpoint(tmp_path / "junk.pt")


def test_config_rejects_bad_values():
    with pytest.raises(ValueError, match="elite_fraction"):
        DexNetConfig(elite_fraction=0)
    with pytest.raises(ValueError, match="crop_metric_size"):
        DexNetConfig(crop_metric_size=-0.1)
    with pytest.raises(ValueError, match="max_approach_angle_deg"):
        DexNetConfig(max_approach_angle_deg=120)
    with pytest.raises(ValueError, match="epochs"):
        TrainConfig(epochs=0)


# ----------------------------------------------------------------------------------- training and policy

def test_training_cli_runs_end_to_end_and_lowers_the_loss(checkpoint):
    path, history = checkpoint
    assert path.is_file()
    assert history["train_positives"] > 0 and history["val_samples"] > 0
    assert history["final_loss"] < history["initial_loss"]
    _, meta = load_checkpoint(path)
    assert meta["train_config"]["seed"] == 0 and "--epochs 3" in meta["command"]


def test_policy_returns_ranked_vertical_candidates_and_a_valid_action(checkpoint):
    from policies.dexnet.policy import DexNetPolicy

    policy = DexNetPolicy(checkpoint=checkpoint[0])
    record = synthetic_scene(100)
    # Tilt a third of the normals by 45 degrees: those may never be proposed.
    normals = record["normals"].copy()
    normals[::3] = [math.sqrt(0.5), 0.0, math.sqrt(0.5)]
    record["normals"] = normals
    obs, info = observation(record)
    cands = policy.predict(obs, info, top_k=10)
    assert 1 <= len(cands) <= 10
    assert np.all(np.diff(cands.scores) <= 0) and np.all((cands.scores >= 0) & (cands.scores <= 1))
    np.testing.assert_allclose(np.linalg.norm(cands.normals, axis=1), 1, atol=1e-5)
    assert np.all(cands.normals[:, 2] >= math.cos(math.radians(30)) - 1e-6)
    # Every candidate is an observed point, and candidates are at least the NMS radius apart.
    dist = np.linalg.norm(record["points"][None] - cands.points[:, None], axis=-1)
    assert np.all(dist.min(axis=1) < 1e-6)
    pair = np.linalg.norm(cands.points[:, None] - cands.points[None], axis=-1)[np.triu_indices(len(cands), 1)]
    assert np.all(pair > 0.02)
    action = policy.act(obs, info)
    assert action.shape == (6,) and np.all(np.isfinite(action))
    assert np.linalg.norm(action[3:]) == pytest.approx(1, abs=1e-5) and action[5] >= math.cos(math.radians(30))
    # A workspace box keeps every candidate inside it.
    box = ((-0.1, -0.1, -0.01), (0.1, 0.1, 0.5))
    boxed = DexNetPolicy(checkpoint=checkpoint[0], workspace=box, num_seeds=60, num_gmm_samples=20)
    inside = boxed.predict(obs, info, top_k=10)
    assert len(inside) >= 1 and np.all((inside.points >= box[0]) & (inside.points <= box[1]))
    # Reproducible under reset(seed) (a smaller search keeps this quick).
    small = DexNetPolicy(checkpoint=checkpoint[0], num_seeds=60, num_gmm_samples=20)
    small.reset(7)
    first = small.predict(obs, info, top_k=5)
    small.reset(7)
    np.testing.assert_array_equal(first.points, small.predict(obs, info, top_k=5).points)


def test_policy_rejects_bad_observations_and_missing_checkpoints(checkpoint, tmp_path):
    from policies.dexnet.policy import DexNetPolicy

    with pytest.raises(FileNotFoundError, match="nowhere.pt"):
        DexNetPolicy(checkpoint=tmp_path / "nowhere.pt")
    with pytest.raises(ValueError, match="crop_size"):
        DexNetPolicy(checkpoint=checkpoint[0], crop_size=64)
    with pytest.raises(ValueError, match="workspace"):
        DexNetPolicy(checkpoint=checkpoint[0], workspace=((0, 0, 0), (0, 1, 1)))
    policy = DexNetPolicy(checkpoint=checkpoint[0])
    obs, info = observation(synthetic_scene(5))
    nan_depth = dict(obs, depth=np.where(obs["depth"] > 0.9, np.nan, obs["depth"]))
    with pytest.raises(ValueError, match="NaN"):
        policy.predict(nan_depth, info)
    with pytest.raises(ValueError, match="empty"):
        policy.predict(dict(obs, depth=np.zeros_like(obs["depth"])), info)
    with pytest.raises(ValueError, match="empty"):
        policy.predict(dict(obs, points=np.zeros((0, 3)), normals=np.zeros((0, 3))), info)
    bad_points = obs["points"].copy()
    bad_points[0, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        policy.predict(dict(obs, points=bad_points), info)
    with pytest.raises(ValueError, match="intrinsics"):
        policy.predict(obs, None)


def test_shipped_checkpoint_loads_through_the_registry_and_records_its_provenance():
    from policies.dexnet.policy import DEFAULT_CHECKPOINT, DexNetPolicy
    from policies.registry import make_policy

    policy = make_policy("dexnet")
    assert policy.checkpoint == DEFAULT_CHECKPOINT and DEFAULT_CHECKPOINT.stat().st_size < 2_000_000
    assert policy.config == DexNetConfig()  # shipped with the default crops and network
    assert DexNetPolicy(num_seeds=100).config.num_seeds == 100
    meta = policy.metadata
    assert meta["command"].startswith("python -m policies.dexnet.train") and "seed" in meta["train_config"]
    assert meta["history"]["final_loss"] < meta["history"]["initial_loss"]
