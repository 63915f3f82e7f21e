"""The centre bound (eval/centre_bound.py): its centres on known answers, the re-ranking by the evaluator's wrench, and
the whole analysis on two generated scenes."""

from __future__ import annotations

import numpy as np
import pytest

from generated_records import generate_tiny

from eval.centre_bound import (CentreBoundConfig, _centred, _ChannelCapture, centre_bound, jittered_centres, main,
                               visible_top_centres)
from parcelpick_env.suction.quality import definition_config

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return generate_tiny(tmp_path_factory.mktemp("centre_bound") / "data", split="test", seed=5)


def test_a_parcels_error_moves_its_centre_horizontally_once_and_reproducibly():
    centres = np.array([[0.1, 0.2, 0.3], [-0.1, 0.0, 0.05]])
    np.testing.assert_array_equal(jittered_centres(centres, 0.0, np.random.default_rng(0)), centres)
    moved = jittered_centres(centres, 0.01, np.random.default_rng(7))
    np.testing.assert_array_equal(moved[:, 2], centres[:, 2])  # height untouched
    assert np.all(np.abs(moved[:, :2] - centres[:, :2]) > 0)
    np.testing.assert_array_equal(moved, jittered_centres(centres, 0.01, np.random.default_rng(7)))
    many = jittered_centres(np.zeros((20000, 3)), 0.02, np.random.default_rng(1))
    assert abs(float(many[:, :2].std()) - 0.02) < 5e-4


def test_a_parcel_is_centred_on_its_observed_top_else_on_all_it_shows():
    config = CentreBoundConfig(min_top_points=3)
    up, side = np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])
    # parcel 0: three top points about (0.1, 0.0) and two side points far off; parcel 1: two top points (too few)
    # and a side point; a point 1 cm off parcel 0 is no observation of it; parcel 2 shows nothing
    points = np.array([[0.09, 0.0, 0.1], [0.11, 0.01, 0.1], [0.10, -0.01, 0.1], [0.3, 0.0, 0.05], [0.3, 0.1, 0.05],
                       [-0.2, 0.0, 0.2], [-0.2, 0.02, 0.2], [-0.26, 0.01, 0.14], [0.5, 0.5, 0.5]])
    normals = np.array([up, up, up, side, side, up, up, side, up])
    owner = np.array([0, 0, 0, 0, 0, 1, 1, 1, 0])
    distance = np.array([0.0, 0.001, 0.0, 0.002, 0.0, 0.0, 0.0, 0.0, 0.01])
    centres = visible_top_centres(points, normals, owner, distance, 3, config)
    np.testing.assert_allclose(centres[0], [0.1, 0.0, 0.1])
    np.testing.assert_allclose(centres[1], points[5:8].mean(axis=0))
    assert np.all(np.isnan(centres[2]))


def test_the_wrench_channel_is_replaced_by_the_evaluators_about_the_given_centres():
    policy = _ChannelCapture.__new__(_ChannelCapture)  # the re-ranking alone: no model needed
    policy.nms_radius = 0.0
    points = np.array([[0.0, 0.0, 0.1], [0.2, 0.0, 0.1], [0.4, 0.0, 0.1]], dtype=np.float32)
    normals = np.tile(np.array([0.0, 0.0, 1.0], dtype=np.float32), (3, 1))
    channels = np.array([[0.9, 1.0, 0.9], [1.0, 0.0, 1.0], [0.5, 1.0, 0.5]], dtype=np.float32)  # seal, wrench, coll.
    policy.captured = (points, normals, channels)
    config = definition_config("suctionnet")
    lever = 0.003
    centres = np.array([[0.0, 0.0, 0.05], [0.2 + lever, 0.0, 0.05], [np.nan] * 3])  # the last: no centre, lever 0
    picks = _centred(policy, centres, top_k=3)
    expected = {0.0: 0.81, 0.2: 1.0 - config.unit_mass * config.gravity * lever / config.torque_threshold, 0.4: 0.25}
    assert len(picks) == 3
    for point, score in zip(picks.points, picks.scores):
        assert score == pytest.approx(expected[round(float(point[0]), 1)], rel=1e-5)
    assert picks.points[0][0] == pytest.approx(0.2)  # its own wrench channel was 0: replaced, it now ranks first


def test_the_true_centre_bounds_a_centre_ten_centimetres_off(data):
    result = centre_bound(data, config=CentreBoundConfig(sigmas=(0.0, 0.1)), progress=False)
    rows = result["rows"]
    assert list(rows) == ["label oracle", "model", "true", "sigma=0", "sigma=0.1", "visible_top"]
    assert rows["label oracle"]["share_of_label_oracle"] == pytest.approx(1.0)
    assert rows["true"]["AP"] == pytest.approx(rows["sigma=0"]["AP"])  # no error: the same centres, the same AP
    assert rows["true"]["median_error_m"] == 0.0 and rows["sigma=0.1"]["median_error_m"] > 0.05
    assert rows["true"]["AP"] > rows["sigma=0.1"]["AP"]
    for row in rows.values():
        assert row["low"] <= row["AP"] <= row["high"]


@pytest.mark.parametrize("args, message", [(["--sigmas", "-0.01"], "sigmas"), (["--scenes", "0"], "--scenes"),
                                           (["--checkpoint", "nowhere.pt"], "--checkpoint")])
def test_bad_arguments_end_in_one_line(data, capsys, args, message):
    with pytest.raises(SystemExit) as stop:
        main(["--data", str(data), "--quiet", *args])
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err
