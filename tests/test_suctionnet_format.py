"""SuctionNet-1Billion's per-view N x 7 dump: written in its layout and camera frame, read back, scored the same."""

from __future__ import annotations

import numpy as np
import pytest

from dataset.storage import shard_name, write_manifest, write_shard
from eval.ap import APConfig, evaluate_ap, main
from eval.suctionnet_format import (
    COLUMNS,
    from_suctionnet,
    read_view,
    to_suctionnet,
    view_path,
    write_view,
)
from policies.base import Candidates


def _pose(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    T = np.eye(4)
    T[:3, :3] = q * np.sign(np.linalg.det(q))
    T[:3, 3] = rng.normal(size=3)
    return T


def _candidates(n: int, seed: int = 0) -> Candidates:
    rng = np.random.default_rng(seed)
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    scores = np.sort(rng.random(n))[::-1]
    return Candidates(rng.normal(size=(n, 3)).astype(np.float32), normals.astype(np.float32),
                      scores.astype(np.float32))


def test_dump_round_trips_through_the_suctionnet_file(tmp_path):
    cands, T = _candidates(40), _pose(1)
    path = write_view(view_path(tmp_path, 7, "test"), to_suctionnet(cands, T))
    assert path == tmp_path / "test" / "scene_0007" / "parcelpick" / "suction" / "0000.npz"
    raw = np.load(path)["arr_0"]  # what suctionnetAPI's SuctionGroup.from_npy reads
    assert raw.shape == (40, len(COLUMNS)) and raw.dtype == np.float32
    back = from_suctionnet(read_view(path), T)
    np.testing.assert_allclose(back.points, cands.points, atol=1e-5)
    np.testing.assert_allclose(back.normals, cands.normals, atol=1e-5)
    np.testing.assert_array_equal(back.scores, cands.scores)


def test_columns_are_score_normal_point_in_the_camera_frame():
    T = np.eye(4)
    T[:3, :3] = np.diag([1.0, -1.0, -1.0])  # a camera 1 m above the floor looking down, as the env's
    T[:3, 3] = (0.0, 0.0, 1.0)
    cands = Candidates(np.array([[0.1, 0.2, 0.0]], np.float32), np.array([[0, 0, 1.0]], np.float32),
                       np.array([0.9], np.float32))
    row = to_suctionnet(cands, T)[0]
    np.testing.assert_allclose(row, [0.9, 0, 0, -1, 0.1, -0.2, 1.0], atol=1e-6)  # normal faces the camera (-z)


def test_read_sorts_by_score_and_rejects_malformed_files(tmp_path):
    cands, T = _candidates(5), np.eye(4)
    shuffled = to_suctionnet(cands, T)[::-1]
    assert np.all(np.diff(from_suctionnet(shuffled, T).scores) <= 0)
    np.save(tmp_path / "six.npy", np.zeros((3, 6)))
    with pytest.raises(ValueError, match=r"six.npy: expected an \(N, 7\)"):
        read_view(tmp_path / "six.npy")
    with pytest.raises(FileNotFoundError, match="no SuctionNet predictions"):
        read_view(tmp_path / "none.npz")
    with pytest.raises(ValueError, match="zero normal"):
        from_suctionnet(np.zeros((2, 7)), T)


def test_a_dumped_policy_scores_the_same_when_read_back(tmp_path):
    from test_ap import _FixedPolicy, _record, _tops_over

    record = _record()
    pick = np.random.default_rng(0).choice(len(record["points"]), 30, replace=False)
    policy = _FixedPolicy(np.r_[_tops_over(record), record["points"][pick]],
                          np.r_[np.tile([0, 0, 1.0], (2, 1)), record["normals"][pick]])  # 2 good picks, 30 others
    data = tmp_path / "data"
    data.mkdir()
    write_manifest(data, {"split": "test"}, [write_shard(data / shard_name(0), 0, {0: record}, range(1))],
                   complete=True)
    config = APConfig(candidates=200)
    direct = evaluate_ap(policy, data, config=config, dump_dir=tmp_path / "dump")
    assert (tmp_path / "dump" / "test" / "scene_0000" / "parcelpick" / "suction" / "0000.npz").is_file()
    scored = evaluate_ap(None, data, config=config, predictions_dir=tmp_path / "dump")
    assert scored["policy"].startswith("predictions:")
    assert scored["AP"] == pytest.approx(direct["AP"], abs=1e-6) and direct["AP"] > 0
    assert scored["per_scene"]["AP"] == pytest.approx(direct["per_scene"]["AP"], abs=1e-6)
    assert main(["--predictions", str(tmp_path / "dump"), "--data", str(data), "--quiet"]) == 0
    with pytest.raises(SystemExit):
        main(["--predictions", str(tmp_path / "dump"), "--policy", "random", "--data", str(data)])
