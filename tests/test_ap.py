"""The offline AP evaluator on a hand-built stored scene: two library parcels resting on the bin floor.

The scene record is written with the dataset's own storage functions and holds what
``dataset/annotate.py`` stores; the capture is ray-cast from the true meshes, so the evaluator's
re-scoring on rebuilt meshes can be checked against policies whose answers are known.
"""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest

from dataset.storage import shard_name, write_manifest, write_shard
from dataset.scene_record import scene_from_record
from eval.ap import APConfig, evaluate_ap, main, observation_from_record
from parcelpick_env.assets.library import AssetLibrary
from parcelpick_env.scene.scene import BinSpec
from policies.base import Candidates, Policy
from policies.normal_std import NormalStdPolicy
from policies.random_policy import RandomPolicy

REPO = Path(__file__).resolve().parents[1]
ASSETS = ("test-rectangular-000", "test-planar-001")
POSITIONS = ((-0.15, 0.0), (0.17, 0.05))


def _record() -> dict:
    library = AssetLibrary.default(0)
    poses, meshes = [], []
    for asset_id, (x, y) in zip(ASSETS, POSITIONS):
        mesh = library.get(asset_id).mesh
        pose = np.array([x, y, -mesh.bounds[0, 2], 0, 0, 0, 1.0])
        poses.append(pose)
        meshes.append(mesh.copy().apply_translation(pose[:3]))
    bin_spec = BinSpec()
    width, height, focal = 160, 120, 120.0
    K = np.array([[focal, 0, width / 2 - 0.5], [0, focal, height / 2 - 0.5], [0, 0, 1.0]])
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])
    T[:3, 3] = (0.0, 0.0, 1.0)
    scene = o3d.t.geometry.RaycastingScene()
    for m in meshes + bin_spec.meshes():
        scene.add_triangles(o3d.core.Tensor(np.asarray(m.vertices, np.float32)),
                            o3d.core.Tensor(np.asarray(m.faces, np.uint32)))
    rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(o3d.core.Tensor(K), o3d.core.Tensor(np.linalg.inv(T)),
                                                              width, height)
    t_hit = scene.cast_rays(rays)["t_hit"].numpy()
    depth = np.where(np.isfinite(t_hit), t_hit * (rays.numpy()[..., 3:] @ T[:3, :3])[..., 2], 0).astype(np.float32)
    rows, cols = np.nonzero(depth > 0)
    z = depth[rows, cols]
    cam = np.stack([(cols - K[0, 2]) * z / focal, (rows - K[1, 2]) * z / focal, z], -1)
    points = cam @ T[:3, :3].T + T[:3, 3]
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
    cloud.orient_normals_towards_camera_location(T[:3, 3])
    return {
        "points": points.astype(np.float32), "normals": np.asarray(cloud.normals, np.float32),
        "rgb": np.zeros((height, width, 3), np.uint8), "depth": depth,
        "intrinsics": K, "extrinsics": T,
        "object_asset_ids": np.array(ASSETS), "object_categories": np.array(["rectangular", "planar"]),
        "object_poses": np.array(poses), "object_visibility": np.ones(2),
        "bin_spec": np.array(json.dumps({"inner_size": list(bin_spec.inner_size), "wall_height": 0.25,
                                         "wall_thickness": 0.02, "center_xy": [0.0, 0.0], "floor_z": 0.0})),
        "library_seed": np.array(0, dtype=np.int64),
    }


@pytest.fixture(scope="module")
def dataset_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("ap_data")
    entry = write_shard(root / shard_name(0), 0, {0: _record()}, range(0, 1))
    write_manifest(root, {"split": "test"}, [entry], complete=True)
    return root


class _FixedPolicy(Policy):
    """Proposes fixed suction poses, best first."""

    def __init__(self, points, normals):
        self.points = np.asarray(points, np.float32)
        self.normals = np.asarray(normals, np.float32)

    def predict(self, obs, info=None, top_k=50):
        scores = np.linspace(1.0, 0.5, len(self.points)).astype(np.float32)
        return Candidates(self.points[:top_k], self.normals[:top_k], scores[:top_k])


def _tops_over(record, centres: str = "surface"):
    """The top-surface point straight above each parcel's surface centroid (SuctionNet's wrench centre) or its
    centre of mass (``"com"``, where the env's physics wants the cup): a near-perfect pick under that definition."""
    scene = scene_from_record(record)
    points = (scene.world_coms() if centres == "com" else
              np.array([(m.triangles_center * m.area_faces[:, None]).sum(0) / m.area for m in scene.world_meshes()]))
    tops = []
    for mesh, centre in zip(scene.world_meshes(), points):
        hit = mesh.ray.intersects_location([[centre[0], centre[1], 1.0]], [[0, 0, -1.0]])[0]
        tops.append(hit[np.argmax(hit[:, 2])])
    return np.array(tops)


def test_oracle_scores_what_the_protocol_allows_and_bad_picks_score_zero(dataset_dir):
    tops = _tops_over(_record())
    up = np.tile([0, 0, 1.0], (2, 1))
    oracle = evaluate_ap(_FixedPolicy(tops, up), dataset_dir)
    assert oracle["scenes"][0]["num_scored"] == 2
    assert oracle["top1_AP0.8"] == pytest.approx(100.0)
    # Two perfect picks and nothing else: P@k = min(2, k) / k at every θ, averaged over k = 1..50.
    expected = 100 * (2 + sum(2 / k for k in range(3, 51))) / 50
    assert oracle["AP0.8"] == pytest.approx(expected, rel=1e-6)
    assert oracle["per_category"]["planar"]["top1_AP"] == pytest.approx(100.0)
    # Picks on the bin floor and picks with a sideways cup axis have quality 0.
    floor = np.array([[0.3, -0.2, 0.0], [-0.3, 0.2, 0.0], [0.0, -0.2, 0.0]])
    assert evaluate_ap(_FixedPolicy(floor, np.tile([0, 0, 1.0], (3, 1))), dataset_dir)["AP"] == 0.0
    assert evaluate_ap(_FixedPolicy(tops, np.tile([1.0, 0, 0], (2, 1))), dataset_dir)["AP"] == 0.0
    # The q = 1 ceiling of 2 parcels is 10 perfect slots each: P@k = min(k, 20) / k.
    assert oracle["ceiling"]["AP"] == pytest.approx(100 * (20 + sum(20 / k for k in range(21, 51))) / 50, rel=1e-6)


def test_distance_cutoff_scores_a_hovering_prediction_zero(dataset_dir):
    """5 cm above a carton's top the suctionnet seal and wrench are perfect (they only see the surface below), but
    no cup is there: the assignment's cutoff scores it 0. 3 mm above (depth noise) still counts."""
    top = _tops_over(_record())[:1]
    up = np.array([[0, 0, 1.0]])
    hovering = evaluate_ap(_FixedPolicy(top + [0, 0, 0.05], up), dataset_dir)
    assert hovering["top1_AP"] == 0.0 and hovering["scenes"][0]["num_off_surface"] == 1
    close = evaluate_ap(_FixedPolicy(top + [0, 0, 0.003], up), dataset_dir)
    assert close["top1_AP"] == pytest.approx(100.0)
    loose = evaluate_ap(_FixedPolicy(top + [0, 0, 0.05], up), dataset_dir, config=APConfig(max_distance=0.1))
    assert loose["top1_AP"] == pytest.approx(100.0)  # what the evaluator scored before the cutoff


def test_physical_quality_rewards_the_pick_over_the_centre_of_mass(dataset_dir):
    """The env's cup at the real COM holds both parcels; under `physical` AP+vis equals AP (visibility 1 here)."""
    result = evaluate_ap(_FixedPolicy(_tops_over(_record(), "com"), np.tile([0, 0, 1.0], (2, 1))), dataset_dir,
                         config=APConfig(quality="physical"))
    assert result["quality"] == "physical" and result["top1_AP0.4"] == pytest.approx(100.0)
    assert result["AP+vis"] == pytest.approx(result["AP"])
    assert set(result["channel_cost"]) == {"seal", "wrench", "collision"}


def test_policies_see_the_bin_as_their_workspace_like_in_the_env():
    record = _record()
    obs, info = observation_from_record(record, 100, np.random.default_rng(0))
    assert obs["points"].shape == (100, 3)
    np.testing.assert_allclose(info["workspace"], scene_from_record(record).bin.workspace())
    assert "object_poses" not in info  # the pile itself stays hidden
    del record["bin_spec"]
    with pytest.raises(ValueError, match="bin_spec"):
        observation_from_record(record, None, np.random.default_rng(0))


@pytest.mark.parametrize("policy", [RandomPolicy(seed=0), NormalStdPolicy()], ids=["random", "normal_std"])
def test_baselines_end_to_end(dataset_dir, tmp_path, policy):
    result = evaluate_ap(policy, dataset_dir, config=APConfig(candidates=200))
    for key in ("AP", "AP0.4", "AP0.8", "top1_AP", "top1_AP0.4", "top1_AP0.8"):
        assert 0.0 <= result[key] <= 100.0
    assert set(result["per_category"]) == {"rectangular", "planar"}
    assert result["num_scenes"] == 1 and result["policy"] == policy.name
    json.dumps(result)  # the CLI writes exactly this


def test_cli_errors_in_process(dataset_dir, tmp_path, capsys):
    with pytest.raises(SystemExit) as missing:
        main(["--policy", "random", "--data", str(tmp_path / "nope")])
    assert missing.value.code != 0 and "does not exist" in capsys.readouterr().err
    with pytest.raises(SystemExit) as unknown:
        main(["--policy", "no_such_policy", "--data", str(dataset_dir)])
    assert unknown.value.code != 0 and "no_such_policy" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main(["--policy", "random", "--data", str(tmp_path / "empty")]) != 0
    assert "manifest.json" in capsys.readouterr().err


def test_cli_as_script_writes_json(dataset_dir, tmp_path):
    out = tmp_path / "random.json"
    ok = subprocess.run([sys.executable, "eval/ap.py", "--policy", "random", "--data", str(dataset_dir),
                         "--out", str(out), "--quiet", "--candidates", "100"], cwd=REPO, capture_output=True, text=True)
    assert ok.returncode == 0, ok.stderr
    assert "| overall |" in ok.stdout and "| planar |" in ok.stdout
    assert 0 <= json.loads(out.read_text())["AP"] <= 100


def test_generated_dataset_end_to_end(tmp_path):
    """A 1-scene dataset made by the real pipeline (pile, camera, labels), evaluated with both baselines."""
    from dataset.config import GenerationConfig
    from dataset.generate import generate
    from dataset.storage import open_dataset
    from parcelpick_env.suction.scorer import SuctionScorer

    config = GenerationConfig(scenes=1, split="test", seed=1, min_parcels=2, max_parcels=3, width=160, height=120,
                              annotation_points=1024, scenes_per_shard=1)
    generate(tmp_path / "data", config, workers=1, progress=False)
    record = open_dataset(tmp_path / "data").scene(0)

    # The meshes rebuilt from asset ids and poses reproduce the stored labels exactly.
    on_parcel = record["object_ids"] >= 0
    rescored = SuctionScorer.from_scene(scene_from_record(record)).score(
        record["points"][on_parcel].astype(np.float64), record["normals"][on_parcel].astype(np.float64),
        record["object_ids"][on_parcel], visibility=record["object_visibility"])
    np.testing.assert_allclose(rescored.as_array(), record["labels"][on_parcel], atol=1e-6)

    # The registered oracle, given the stored labels (the AP's privileged channel), submits the best-labelled
    # points; its Top-1 is the suctionnet quality of the best stored point.
    from parcelpick_env.suction.quality import definition_scorer, score_definition
    from policies.registry import make_policy

    results = {"oracle": evaluate_ap(make_policy("oracle"), tmp_path / "data")}
    best = int(np.argmax(record["score"]))
    scorer = definition_scorer("suctionnet", scene_from_record(record))
    q_best = float(score_definition("suctionnet", scorer, record["points"][best:best + 1].astype(np.float64),
                                    record["normals"][best:best + 1].astype(np.float64),
                                    record["object_ids"][best:best + 1]).quality[0])
    for policy in (RandomPolicy(seed=0), NormalStdPolicy()):
        result = evaluate_ap(policy, tmp_path / "data", scenes=1, config=APConfig(candidates=300))
        for key in ("AP", "AP0.4", "AP0.8", "top1_AP", "top1_AP0.4", "top1_AP0.8"):
            assert 0.0 <= result[key] <= 100.0
        scene = result["scenes"][0]
        assert 2 <= scene["num_objects"] <= 3
        assert 0 < scene["num_scored"] <= 10 * scene["num_objects"]
        assert result["per_category"] and set(result["per_category"]) <= {"rectangular", "planar", "cylindrical"}
        results[policy.name] = result
    assert results["oracle"]["top1_AP"] == pytest.approx(100 * np.mean(q_best >= np.array([0.2, 0.4, 0.6, 0.8])))
    assert results["oracle"]["AP"] >= results["random"]["AP"]


def test_policy_args_reach_the_policy_and_the_json(dataset_dir, tmp_path, capsys):
    from parcelpick_env.cli import UsageError, parse_policy_args

    assert parse_policy_args(["draws=4", "precision=bfloat16", "seed=null", "nms_radius=0.03", "flag=true",
                              'name="x=y"']) == {"draws": 4, "precision": "bfloat16", "seed": None,
                                                 "nms_radius": 0.03, "flag": True, "name": "x=y"}
    for bad, why in (("draws", "KEY=VALUE"), ("=4", "KEY=VALUE"), ("checkpoint=a.pt", "--checkpoint"),
                     ("2x=1", "KEY=VALUE")):
        with pytest.raises(UsageError, match=why):
            parse_policy_args([bad])
    with pytest.raises(UsageError, match="twice"):
        parse_policy_args(["seed=1", "seed=2"])
    out = tmp_path / "r.json"
    assert main(["--policy", "random", "--data", str(dataset_dir), "--policy-arg", "seed=3", "--out", str(out),
                 "--quiet"]) == 0
    assert json.loads(out.read_text())["policy_kwargs"] == {"seed": 3}
    with pytest.raises(SystemExit) as bad_kwarg:  # one line naming the flag and the policy's complaint
        main(["--policy", "random", "--data", str(dataset_dir), "--policy-arg", "bogus=1"])
    err = capsys.readouterr().err
    assert bad_kwarg.value.code == 2 and "--policy-arg bogus=1" in err and "unexpected keyword" in err
