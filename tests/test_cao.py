"""Cao et al. (SuctionNet baseline) heatmap policy: targets, training, inference and errors.

Scenes here are synthetic (boxes on a floor under an overhead pinhole camera), written with the
dataset's own shard storage, so the tests exercise the real reading path without running pybullet.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from dataset.config import GenerationConfig
from dataset.storage import shard_name, write_manifest, write_shard
from policies.base import Candidates
from policies.cao.config import CaoConfig
from policies.cao.policy import DEFAULT_CHECKPOINT, CaoPolicy, load_checkpoint
from policies.cao.targets import centre_target, frame_from_record, frame_targets, project_points
from policies.heatmap import grid_topk, pixels_to_candidates
from policies.cao.train import main as train_main
from policies.cao.train import train

H, W = 48, 64
CAMERA_HEIGHT = 1.0
K = np.array([[80.0, 0.0, (W - 1) / 2], [0.0, 80.0, (H - 1) / 2], [0.0, 0.0, 1.0]])
T = np.eye(4)
T[:3, :3] = np.diag([1.0, -1.0, -1.0])  # OpenCV camera looking straight down: x right, y down, z forward
T[2, 3] = CAMERA_HEIGHT
SMALL = CaoConfig(input_height=H, input_width=W, widths=(8, 16), epochs=6, batch_size=4, learning_rate=1e-2,
                  val_fraction=0.2)


def synthetic_record(seed: int, num_points: int = 256) -> dict[str, np.ndarray]:
    """Boxes on a floor: seal 1 on box tops away from their edges, 0 elsewhere; object centres at box centres."""
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0:H, 0:W]
    depth = np.full((H, W), CAMERA_HEIGHT, dtype=np.float32)
    segmentation = np.full((H, W), -1, dtype=np.int16)
    rgb = np.full((H, W, 3), 90, dtype=np.uint8)
    seal = np.zeros((H, W), dtype=np.float32)
    centres = []
    for obj in range(3):
        h0, w0 = rng.integers(8, 16, size=2)
        r0, c0 = rng.integers(0, H - h0), rng.integers(0, W - w0)
        height = rng.uniform(0.05, 0.2)
        inside = (rows >= r0) & (rows < r0 + h0) & (cols >= c0) & (cols < c0 + w0)
        depth[inside] = CAMERA_HEIGHT - height
        segmentation[inside] = obj
        rgb[inside] = rng.integers(120, 255, size=3)
        seal[inside] = 0.0
        interior = (rows >= r0 + 2) & (rows < r0 + h0 - 2) & (cols >= c0 + 2) & (cols < c0 + w0 - 2)
        seal[interior] = 1.0
        centre_px = np.array([r0 + (h0 - 1) / 2, c0 + (w0 - 1) / 2])
        centres.append(unproject(centre_px[None], np.array([CAMERA_HEIGHT - height / 2]))[0])
    pick = rng.choice(H * W, size=num_points, replace=False)
    pr, pc = np.unravel_index(pick, (H, W))
    points = unproject(np.stack([pr, pc], 1).astype(float), depth[pr, pc].astype(float))
    on_object = (segmentation[pr, pc] >= 0).astype(np.float32)
    labels = np.stack([seal[pr, pc], on_object, on_object, on_object], axis=1)
    return {"rgb": rgb, "depth": depth, "segmentation": segmentation, "intrinsics": K, "extrinsics": T,
            "points": points.astype(np.float32), "labels": labels.astype(np.float32),
            "object_ids": segmentation[pr, pc].astype(np.int32), "point_pixels": np.stack([pr, pc], 1).astype(np.int32),
            "object_com_world": np.array(centres)}


def unproject(pixels_rc: np.ndarray, z: np.ndarray) -> np.ndarray:
    cam = np.stack([(pixels_rc[:, 1] - K[0, 2]) * z / K[0, 0], (pixels_rc[:, 0] - K[1, 2]) * z / K[1, 1], z], 1)
    return cam @ T[:3, :3].T + T[:3, 3]


def observation(record: dict[str, np.ndarray]) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    depth = record["depth"]
    rr, cc = np.nonzero(depth > 0)
    points = unproject(np.stack([rr, cc], 1).astype(float), depth[rr, cc].astype(float)).astype(np.float32)
    normals = np.tile(np.array([0.0, 0.0, 1.0], dtype=np.float32), (len(points), 1))
    obs = {"rgb": record["rgb"], "depth": depth[..., None], "points": points, "normals": normals}
    return obs, {"intrinsics": K, "extrinsics": T}


@pytest.fixture(scope="module")
def tiny_dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("cao_data")
    scenes = 10
    records = {i: synthetic_record(i) for i in range(scenes)}
    gen = GenerationConfig(scenes=scenes, width=W, height=H, annotation_points=256, scenes_per_shard=scenes)
    entry = write_shard(root / shard_name(0), 0, records, range(scenes), compression="lzf")
    write_manifest(root, gen.to_dict(), [entry], complete=True)
    return root


@pytest.fixture(scope="module")
def trained(tiny_dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("cao_ckpt") / "checkpoint.pt"
    meta = train(tiny_dataset, out, SMALL, seed=0, threads=1, progress=False)
    return out, meta


def test_seal_gaussian_peaks_at_labelled_point_pixel():
    record = synthetic_record(0, num_points=1)
    record["labels"][:] = [0.7, 1.0, 1.0, 1.0]
    frame = frame_from_record(record)
    config = dataclasses.replace(SMALL, input_height=H // 2, input_width=W // 2)  # targets live at network size
    seal = frame_targets(frame, config)[0]
    expected_rc = np.array([record["point_pixels"][0, 0] + 0.5, record["point_pixels"][0, 1] + 0.5]) / 2 - 0.5
    peak = np.unravel_index(np.argmax(seal), seal.shape)
    assert np.all(np.abs(np.array(peak) - expected_rc) <= 0.5)
    offset2 = np.sum((np.array(peak) - expected_rc) ** 2)
    assert seal.max() == pytest.approx(0.7 * np.exp(-offset2 / (2 * config.seal_sigma_px**2)), rel=1e-4)
    rr, cc = np.mgrid[0:seal.shape[0], 0:seal.shape[1]]
    far = np.hypot(rr - expected_rc[0], cc - expected_rc[1]) > 5 * config.seal_sigma_px
    assert far.any() and np.all(seal[far] == 0.0)  # a local Gaussian, not a flood


def test_centre_gaussian_peaks_at_object_centre_pixel():
    record = synthetic_record(3)
    frame = frame_from_record(record)
    centre = frame_targets(frame, SMALL)[1]
    centres_rc, _ = project_points(record["object_com_world"], K, T)
    for obj, rc in enumerate(centres_rc):
        mask = record["segmentation"] == obj
        if not mask.any():
            continue
        masked = np.where(mask, centre, -1.0)
        peak = np.array(np.unravel_index(np.argmax(masked), masked.shape))
        assert np.all(np.abs(peak - rc) <= 0.5 + 1e-9), (obj, peak, rc)
    assert np.all(centre[record["segmentation"] < 0] == 0.0)  # masked to each object's own pixels
    assert 0.0 <= centre.min() and centre.max() <= 1.0


def test_centre_target_without_segmentation_peaks_at_each_centre():
    centres = np.array([[10.0, 12.0], [30.0, 50.0]])
    centre = centre_target(centres, np.array([2.0, 4.0]), (H, W))
    assert centre[10, 12] == pytest.approx(1.0) and centre[30, 50] == pytest.approx(1.0)
    assert centre[10, 12 + 2] == pytest.approx(np.exp(-0.5), rel=1e-5)  # one sigma away
    assert centre[45, 5] < 1e-6


def test_grid_topk_takes_the_best_pixel_per_cell_best_first():
    rng = np.random.default_rng(0)
    heat = rng.random((25, 32))
    heat[:5, :5] = -np.inf  # a cell with no valid pixel yields nothing
    rows, cols, scores = grid_topk(heat, cell=5, top_k=1000)
    assert len(rows) == 5 * 7 - 1  # 5 x 7 cells (the last column of cells is partial), one empty
    assert np.all(np.diff(scores) <= 0) and np.array_equal(scores, heat[rows, cols])
    for r, c in zip(rows, cols):
        r0, c0 = r // 5 * 5, c // 5 * 5
        assert heat[r, c] == heat[r0:r0 + 5, c0:c0 + 5].max()
    top = grid_topk(heat, cell=5, top_k=3)
    assert np.array_equal(top[2], scores[:3])


def tilted_plane_depth(slope: float = 0.3, offset: float = 0.1) -> np.ndarray:
    """Z-depth of the world plane z = slope * x + offset seen by the test camera (exact ray casting)."""
    rows, cols = np.mgrid[0:H, 0:W]
    ray = np.stack([(cols - K[0, 2]) / K[0, 0], (rows - K[1, 2]) / K[1, 1], np.ones((H, W))], -1) @ T[:3, :3].T
    t = (slope * T[0, 3] + offset - T[2, 3]) / (ray[..., 2] - slope * ray[..., 0])
    return t.astype(np.float32)  # z-depth equals t: the camera-frame ray has unit z


def test_candidate_normals_from_depth_or_a_nearby_cloud():
    slope = 0.3
    depth = tilted_plane_depth(slope)
    rows, cols = np.array([10, 20, 30]), np.array([15, 30, 45])
    scores = np.array([0.9, 0.8, 0.7])
    truth = np.array([-slope, 0.0, 1.0]) / np.hypot(slope, 1.0)
    from_depth = pixels_to_candidates(rows, cols, scores, depth, K, T, nms_radius=0.0, top_k=3)
    assert len(from_depth) == 3 and np.allclose(from_depth.normals, truth, atol=1e-3)
    assert np.allclose(from_depth.points[:, 2], slope * from_depth.points[:, 0] + 0.1, atol=1e-5)
    up = np.tile([0.0, 0.0, 1.0], (3, 1))
    near = pixels_to_candidates(rows, cols, scores, depth, K, T, cloud_points=from_depth.points + 0.001,
                                cloud_normals=up, nms_radius=0.0, top_k=3)
    assert np.allclose(near.normals, up, atol=1e-6)  # the cloud's own estimates win when they are close
    far = pixels_to_candidates(rows, cols, scores, depth, K, T, cloud_points=from_depth.points + 0.05,
                               cloud_normals=up, nms_radius=0.0, top_k=3)
    assert np.allclose(far.normals, truth, atol=1e-3)  # a distant cloud point is another surface


def test_labelled_frame_rejects_mismatched_shapes():
    record = synthetic_record(1)
    record["rgb"] = record["rgb"][:-1]
    with pytest.raises(ValueError, match="rgb"):
        frame_from_record(record)
    record = synthetic_record(1)
    del record["segmentation"]
    with pytest.raises(ValueError, match="store_images"):
        frame_from_record(record)


def test_config_validation():
    with pytest.raises(ValueError, match="divide"):
        CaoConfig(input_height=50, input_width=64, widths=(8, 16, 32))
    with pytest.raises(ValueError, match="seal_channels"):
        CaoConfig(seal_channels=("grip",))
    assert CaoConfig.from_dict(SMALL.to_dict()) == SMALL


def test_training_loss_decreases_and_checkpoint_loads(trained):
    path, meta = trained
    history = meta["history"]
    assert len(history) == SMALL.epochs
    assert history[-1]["train_loss"] < 0.8 * history[0]["train_loss"]
    assert np.isfinite(history[-1]["val_loss"]) and meta["val_scenes"] == 2
    net, checkpoint = load_checkpoint(path)
    assert CaoConfig.from_dict(checkpoint["config"]) == SMALL and checkpoint["meta"]["seed"] == 0
    assert path.stat().st_size < 2_000_000


def test_training_is_reproducible_under_a_seed(tiny_dataset, tmp_path):
    config = dataclasses.replace(SMALL, epochs=1, widths=(4, 8))
    weights = []
    for name in ("a.pt", "b.pt", "c.pt"):
        train(tiny_dataset, tmp_path / name, config, seed=0 if name != "c.pt" else 1, threads=1, progress=False)
        weights.append(torch.load(tmp_path / name, weights_only=True)["state_dict"])
    assert all(torch.equal(weights[0][k], weights[1][k]) for k in weights[0])
    assert not all(torch.equal(weights[0][k], weights[2][k]) for k in weights[0])


def test_training_cli_runs_end_to_end(tiny_dataset, tmp_path, capsys):
    out = tmp_path / "cli.pt"
    code = train_main(["--data", str(tiny_dataset), "--out", str(out), "--epochs", "1", "--seed", "1",
                       "--input-height", str(H), "--input-width", str(W), "--widths", "4", "8", "--threads", "1",
                       "--quiet"])
    assert code == 0 and out.is_file()
    assert "trained on" in capsys.readouterr().out
    assert torch.load(out, weights_only=True)["config"]["colour"] is True
    assert train_main(["--data", str(tiny_dataset), "--out", str(out), "--epochs", "1", "--input-height", str(H),
                       "--input-width", str(W), "--widths", "4", "8", "--threads", "1", "--quiet", "--no-colour"]) == 0
    assert torch.load(out, weights_only=True)["config"]["colour"] is False
    assert train_main(["--data", str(tmp_path / "nowhere"), "--out", str(out)]) == 2


def test_depth_only_network_reads_relief_alone_and_ignores_colour(tiny_dataset, trained, tmp_path):
    """The ablation without colour: one input plane, the relief one, so recolouring the scene changes nothing."""
    from policies.cao.network import prepare_input

    record = synthetic_record(3)
    depth_only = dataclasses.replace(SMALL, colour=False)
    assert depth_only.input_channels == 1 and SMALL.input_channels == 4
    both, relief = prepare_input(record["rgb"], record["depth"], SMALL), prepare_input(record["rgb"], record["depth"],
                                                                                        depth_only)
    assert both.shape == (4, H, W) and relief.shape == (1, H, W) and np.array_equal(relief[0], both[3])
    assert CaoConfig.from_dict(depth_only.to_dict()) == depth_only
    with pytest.raises(ValueError, match="colour"):
        CaoConfig(colour="no")
    out = tmp_path / "depth.pt"
    train(tiny_dataset, out, dataclasses.replace(depth_only, epochs=1, widths=(4, 8)), seed=0, threads=1,
          progress=False)
    policy = CaoPolicy(checkpoint=out, threads=1)
    assert policy.net.in_channels == 1
    obs, info = observation(record)
    recoloured = {**obs, "rgb": (255 - obs["rgb"]).astype(np.uint8)}
    assert np.array_equal(policy.heatmaps(obs, info), policy.heatmaps(recoloured, info))
    grey = {k: v for k, v in obs.items() if k != "rgb"}  # nor needs it
    assert np.array_equal(policy.heatmaps(grey, info), policy.heatmaps(obs, info))
    colour = CaoPolicy(checkpoint=trained[0], threads=1)  # the RGB-D network does read it, and needs it
    assert not np.array_equal(colour.heatmaps(obs, info), colour.heatmaps(recoloured, info))
    with pytest.raises(ValueError, match="rgb"):
        colour.heatmaps(grey, info)
    with pytest.raises(ValueError, match="colour"):
        prepare_input(None, record["depth"], SMALL)


def test_policy_returns_ranked_candidates_and_valid_action(trained):
    path, _ = trained
    policy = CaoPolicy(checkpoint=path, threads=1)
    record = synthetic_record(42)
    obs, info = observation(record)
    threads = torch.get_num_threads()
    heat = policy.heatmaps(obs, info)
    assert torch.get_num_threads() == threads  # the policy's own thread count does not leak out
    assert heat.shape == (2, H, W) and heat.min() >= 0.0 and heat.max() <= 1.0
    candidates = policy.predict(obs, info, top_k=10)
    assert isinstance(candidates, Candidates) and 1 <= len(candidates) <= 10
    assert np.all(np.diff(candidates.scores) <= 0)
    assert np.allclose(np.linalg.norm(candidates.normals, axis=1), 1.0, atol=1e-5)
    # every candidate lies on the observed surface: it re-projects onto a pixel with the same depth
    rc, z = project_points(candidates.points, K, T)
    pix = np.rint(rc).astype(int)
    assert np.allclose(record["depth"][pix[:, 0], pix[:, 1]], z, atol=1e-4)
    action = policy.act(obs, info)
    assert action.shape == (6,) and action.dtype == np.float32 and np.all(np.isfinite(action))
    assert np.allclose(action[:3], candidates.points[0]) and action[5] > 0.99  # normals face up, to the camera


def test_policy_keeps_candidates_inside_the_workspace(trained):
    """Pixels outside info['workspace'] (bin walls, rim, the floor around the bin) never become candidates."""
    path, _ = trained
    policy = CaoPolicy(checkpoint=path, threads=1)
    obs, info = observation(synthetic_record(42))
    everywhere = policy.predict(obs, info, top_k=50).points
    cut = float(np.median(everywhere[:, 0]))  # a box holding about half of the unrestricted candidates
    box = np.array([[cut, -10.0, -10.0], [10.0, 10.0, 10.0]])
    inside = policy.predict(obs, {**info, "workspace": box}, top_k=50)
    assert len(inside) >= 1 and np.all(inside.points[:, 0] >= cut - 1e-9)
    assert np.any(everywhere[:, 0] < cut)  # the restriction removed something
    with pytest.raises(ValueError, match="workspace"):  # an empty box is a malformed observation, not 0 candidates
        policy.predict(obs, {**info, "workspace": [[0.0, 0.0, 0.0], [0.0, 1.0, 1.0]]})


def test_trained_heatmaps_separate_parcels_from_floor(trained):
    """A few epochs on boxes already light up parcels: an untrained net's maps are flat (~0.43 vs ~0.43)."""
    path, _ = trained
    policy = CaoPolicy(checkpoint=path, threads=1)
    for seed in (100, 101):
        record = synthetic_record(seed)
        seal, centre = policy.heatmaps(*observation(record))
        on = record["segmentation"] >= 0
        assert centre[on].mean() > centre[~on].mean() + 0.1
        assert seal[on].mean() > seal[~on].mean()


def test_policy_depth_normals_without_cloud(trained):
    path, _ = trained
    obs, info = observation(synthetic_record(5))
    del obs["points"], obs["normals"]
    candidates = CaoPolicy(checkpoint=path, threads=1).predict(obs, info, top_k=5)
    assert len(candidates) >= 1 and np.all(candidates.normals[:, 2] > 0.9)  # flat tops and floor face up


def test_policy_bad_observation_raises_clear_errors(trained):
    path, _ = trained
    policy = CaoPolicy(checkpoint=path, threads=1)
    obs, info = observation(synthetic_record(6))
    with pytest.raises(ValueError, match="rgb"):
        policy.predict({"depth": obs["depth"]}, info)
    with pytest.raises(ValueError, match="match the depth"):
        policy.predict({**obs, "rgb": obs["rgb"][:-1]}, info)
    bad_depth = obs["depth"].copy()
    bad_depth[0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        policy.predict({**obs, "depth": bad_depth}, info)
    with pytest.raises(ValueError, match="intrinsics"):
        policy.predict(obs, None)
    with pytest.raises(ValueError, match="focal"):
        policy.predict(obs, {"intrinsics": np.zeros((3, 3)), "extrinsics": T})
    with pytest.raises(ValueError, match="top_k"):
        policy.predict(obs, info, top_k=0)


def test_missing_or_corrupt_checkpoint_raises(tmp_path):
    with pytest.raises(FileNotFoundError, match="policies.cao.train"):
        CaoPolicy(checkpoint=tmp_path / "missing.pt")
    corrupt = tmp_path / "corrupt.pt"
    corrupt.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="corrupt"):
        CaoPolicy(checkpoint=corrupt)
    torch.save({"weights": 1}, tmp_path / "foreign.pt")
    with pytest.raises(ValueError, match="config"):
        CaoPolicy(checkpoint=tmp_path / "foreign.pt")


def test_policy_without_any_depth_returns_no_candidates(trained):
    path, _ = trained
    obs, info = observation(synthetic_record(7))
    obs = {"rgb": obs["rgb"], "depth": np.zeros_like(obs["depth"])}
    policy = CaoPolicy(checkpoint=path, threads=1)
    assert len(policy.predict(obs, info)) == 0
    with pytest.raises(ValueError, match="no candidates"):
        policy.act(obs, info)


@pytest.mark.skipif(not DEFAULT_CHECKPOINT.is_file(), reason="no shipped Cao checkpoint")
def test_shipped_checkpoint_is_small_and_loads_through_the_registry():
    from policies.registry import make_policy

    assert DEFAULT_CHECKPOINT.stat().st_size < 2_000_000
    policy = make_policy("cao")
    assert isinstance(policy, CaoPolicy) and policy.meta.get("seed") is not None
    action = policy.act(*observation(synthetic_record(8)))
    assert action.shape == (6,) and np.all(np.isfinite(action))


@pytest.mark.skipif(not DEFAULT_CHECKPOINT.is_file(), reason="no shipped Cao checkpoint")
def test_shipped_policy_picks_a_parcel_in_a_real_capture(small_scene):
    """On the shared simulated pile, the shipped model's best suction lies on a parcel's visible surface."""
    frame = small_scene.frame
    obs = {"rgb": frame.rgb, "depth": frame.depth[..., None], "points": frame.points, "normals": frame.normals}
    info = {"intrinsics": frame.intrinsics, "extrinsics": frame.extrinsics}
    candidates = CaoPolicy().predict(obs, info, top_k=5)
    assert 1 <= len(candidates) <= 5
    rc, z = project_points(candidates.points, frame.intrinsics, frame.extrinsics)
    pix = np.rint(rc).astype(int)
    assert np.allclose(frame.depth[pix[:, 0], pix[:, 1]], z, atol=1e-3)  # on the observed surface
    assert frame.segmentation[pix[0, 0], pix[0, 1]] >= 0  # the best one on a parcel, not the bin
    to_camera = frame.extrinsics[:3, 3] - candidates.points
    assert np.all(np.einsum("ij,ij->i", candidates.normals, to_camera) > 0)  # normals face the camera
