"""The GraspNet/SuctionNet layout: ParcelPick scenes written in it read back to the same record; its files
follow GraspNet's conventions; labels come from SuctionNet's label files; malformed trees fail naming the file.

Two tiny generated scenes (160x120, 2-4 parcels, 512 points) are written once per module; tests that damage
a tree work on their own copy.
"""

from __future__ import annotations

import shutil
import xml.etree.ElementTree as ET

import numpy as np
import pytest
from generated_records import generate_records
import scipy.io
from scipy.spatial.transform import Rotation

from dataset.storage import open_dataset
from dataset.suctionnet.convert import import_views, split_views
from dataset.suctionnet.layout import DEPTH_FACTOR, LABEL_OFFSET, Layout, SuctionNetLayoutError, read_png
from dataset.suctionnet.models import is_suctionnet_record, world_meshes
from dataset.suctionnet.reader import ASSET_PREFIX, ReaderConfig, read_view
from dataset.suctionnet.writer import WriterConfig, write_records

CAMERA = "realsense"
POINTS = 512
TINY = dict(width=160, height=120, min_parcels=2, max_parcels=4, annotation_points=POINTS, object_set="mixed",
            scenes=2, split="test")


@pytest.fixture(scope="module")
def native(tmp_path_factory):
    out = tmp_path_factory.mktemp("native")
    records = generate_records(out, **TINY)
    return out, records


@pytest.fixture(scope="module")
def tree(native, tmp_path_factory):
    root = tmp_path_factory.mktemp("suctionnet") / "graspnet"
    written = write_records(native[1], root, scenes=[100, 101], config=WriterConfig(camera=CAMERA))
    return root, written


@pytest.fixture()
def copy(tree, tmp_path):
    """A private copy of the written tree, to damage."""
    return shutil.copytree(tree[0], tmp_path / "graspnet")


def _read(root, scene=100, **overrides):
    return read_view(root, scene, CAMERA, 0, ReaderConfig(**{"num_points": POINTS, **overrides}))


def _rotations(poses):
    return Rotation.from_quat(np.asarray(poses)[:, 3:]).as_matrix()


def test_written_scenes_read_back_to_the_same_record(native, tree):
    for scene, record in zip((100, 101), native[1]):
        back = _read(tree[0], scene)
        # points: back-projected from a 1 mm depth PNG, so each moves at most half a unit along its ray
        K, T = record["intrinsics"], record["extrinsics"]
        cam = (record["points"].astype(np.float64) - T[:3, 3]) @ T[:3, :3]
        bound = 0.5 / DEPTH_FACTOR * np.linalg.norm(cam, axis=1) / cam[:, 2] + 1e-6
        assert np.all(np.linalg.norm(back["points"] - record["points"], axis=1) <= bound)
        assert np.any(back["points"] != record["points"])  # really re-derived from the quantised depth
        np.testing.assert_array_equal(back["object_ids"], record["object_ids"])
        np.testing.assert_array_equal(back["point_pixels"], record["point_pixels"])
        np.testing.assert_allclose(back["normals"], record["normals"], atol=1e-6)
        on = record["object_ids"] >= 0
        assert on.sum() > 10
        np.testing.assert_allclose(back["labels"][on], record["labels"][on], atol=1e-7)
        np.testing.assert_array_equal(back["labels"][~on], 0.0)  # SuctionNet labels object surfaces only
        np.testing.assert_allclose(back["score"][on], record["labels"][on].prod(axis=1), atol=1e-7)
        np.testing.assert_allclose(back["object_poses"][:, :3], record["object_poses"][:, :3], atol=1e-7)
        np.testing.assert_allclose(_rotations(back["object_poses"]), _rotations(record["object_poses"]), atol=1e-7)
        np.testing.assert_array_equal(back["intrinsics"], K)
        np.testing.assert_allclose(back["extrinsics"], T, atol=1e-12)
        np.testing.assert_array_equal(back["rgb"], record["rgb"])
        np.testing.assert_array_equal(back["segmentation"], record["segmentation"])
        assert np.abs(back["depth"] - record["depth"]).max() <= 0.5 / DEPTH_FACTOR + 1e-6
        for key in ("object_asset_ids", "object_visibility", "bin_spec", "library_seed", "object_mass"):
            np.testing.assert_array_equal(back[key], record[key])
        np.testing.assert_allclose(back["object_com_world"], record["object_com_world"], atol=1e-7)


def test_files_follow_graspnet_conventions(native, tree):
    """Checked on the raw files, the way graspnet-baseline and suctionnetAPI read them, not through the reader."""
    root, written = tree
    record, layout, ids = native[1][0], Layout(root), np.array(written[100])
    depth = read_png(layout.view_file(100, CAMERA, "depth", 0), "depth")
    assert depth.dtype == np.uint16
    np.testing.assert_array_equal(depth, np.rint(record["depth"].astype(np.float64) * DEPTH_FACTOR))
    label = read_png(layout.view_file(100, CAMERA, "label", 0), "label")
    seg = record["segmentation"]
    np.testing.assert_array_equal(label[seg >= 0], ids[seg[seg >= 0]] + LABEL_OFFSET)
    assert np.all(label[seg < 0] == 0)
    meta = scipy.io.loadmat(layout.view_file(100, CAMERA, "meta", 0))
    assert float(meta["factor_depth"].reshape(-1)[0]) == DEPTH_FACTOR
    np.testing.assert_array_equal(meta["cls_indexes"].reshape(-1), ids + LABEL_OFFSET)
    cam_dir = layout.camera_dir(100, CAMERA)
    to_table = np.load(cam_dir / "cam0_wrt_table.npy") @ np.load(cam_dir / "camera_poses.npy")[0]
    np.testing.assert_allclose(to_table, record["extrinsics"], atol=1e-12)
    np.testing.assert_array_equal(np.load(cam_dir / "camK.npy"), meta["intrinsic_matrix"])
    # a pixel back-projected as suctionnetAPI does (depth / s, (u - cx) / fx * z), carried to the table frame
    K = meta["intrinsic_matrix"]
    r, c = record["point_pixels"][0]
    z = depth[r, c] / DEPTH_FACTOR
    p = to_table @ np.array([(c - K[0, 2]) / K[0, 0] * z, (r - K[1, 2]) / K[1, 1] * z, z, 1.0])
    assert np.linalg.norm(p[:3] - record["points"][0]) < 1e-3
    # the XML's pose (position, quaternion w x y z) equals meta['poses'] and the record's pose seen from the camera
    top = ET.parse(layout.view_file(100, CAMERA, "annotations", 0)).getroot()
    assert [int(o.findtext("obj_id")) for o in top] == ids.tolist()
    obj = top[0]
    pos = np.array(obj.findtext("pos_in_world").split(), float)
    w, x, y, zq = np.array(obj.findtext("ori_in_world").split(), float)
    np.testing.assert_allclose(Rotation.from_quat([x, y, zq, w]).as_matrix(), meta["poses"][:, :3, 0], atol=1e-7)
    np.testing.assert_allclose(pos, meta["poses"][:, 3, 0], atol=1e-7)
    world = np.eye(4)
    world[:3, :3] = _rotations(record["object_poses"][:1])[0]
    world[:3, 3] = record["object_poses"][0, :3]
    np.testing.assert_allclose(np.linalg.inv(record["extrinsics"]) @ world,
                               np.vstack([meta["poses"][..., 0], [0, 0, 0, 1]]), atol=1e-7)
    assert layout.model_mesh(int(ids[0])).is_file() and layout.dense_points(int(ids[0])).is_file()
    wrench = np.load(layout.wrench_label(100))
    assert sorted(wrench.files) == [f"arr_{i}" for i in range(len(ids))]


def test_a_later_view_is_placed_by_cam0_wrt_table_times_its_camera_pose(native, copy):
    """View 1 of a moving camera: table <- camera 0 <- camera 1, composed in that order (they do not commute)."""
    layout, record = Layout(copy), native[1][0]
    rng = np.random.default_rng(3)
    move = np.eye(4)
    move[:3, :3] = Rotation.from_rotvec(rng.normal(size=3) * 0.3).as_matrix()
    move[:3, 3] = rng.normal(size=3) * 0.2  # camera 1 in camera 0's frame
    cam_dir = layout.camera_dir(100, CAMERA)
    np.save(cam_dir / "camera_poses.npy", np.stack([np.eye(4), move]))
    np.save(cam_dir / "cam0_wrt_table.npy", record["extrinsics"] @ np.linalg.inv(move))
    for kind in ("rgb", "depth", "label", "meta", "annotations", "parcelpick"):
        src = layout.view_file(100, CAMERA, kind, 0)
        shutil.copy(src, layout.view_file(100, CAMERA, kind, 1))
    back = read_view(copy, 100, CAMERA, 1, ReaderConfig(num_points=POINTS))
    np.testing.assert_allclose(back["extrinsics"], record["extrinsics"], atol=1e-9)
    np.testing.assert_allclose(back["points"], record["points"], atol=1e-3)
    np.testing.assert_allclose(back["object_poses"][:, :3], record["object_poses"][:, :3], atol=1e-7)
    on = record["object_ids"] >= 0
    np.testing.assert_allclose(back["labels"][on], record["labels"][on], atol=1e-7)


def test_labels_come_from_the_suctionnet_label_files(native, copy):
    record, layout = native[1][0], Layout(copy)
    on0 = record["object_ids"] == 0
    model = _first_model(copy)
    seal = dict(np.load(layout.seal_label(model)))
    seal["scores"] = np.full_like(seal["scores"], 0.25)
    np.savez(layout.seal_label(model), **seal)
    collision = dict(np.load(layout.collision_label(100)))
    collision["arr_0"] = ~collision["arr_0"]
    np.savez(layout.collision_label(100), *[collision[f"arr_{i}"] for i in range(len(collision))])
    back = _read(copy)
    np.testing.assert_array_equal(back["labels"][on0, 0], 0.25)
    np.testing.assert_array_equal(back["labels"][on0, 2], 1.0 - record["labels"][on0, 2])
    others = record["object_ids"] > 0
    np.testing.assert_allclose(back["labels"][others], record["labels"][others], atol=1e-7)


def test_a_sample_facing_away_from_the_camera_labels_no_point(native, copy):
    """A back-face sample (a thin object's other side) at a point's very position must not take its label."""
    record, layout = native[1][0], Layout(copy)
    model, k = _first_model(copy), int(np.flatnonzero(native[1][0]["object_ids"] == 0)[0])
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = _rotations(record["object_poses"][:1])[0], record["object_poses"][0, :3]
    seal = dict(np.load(layout.seal_label(model)))
    seen = _read(copy)["points"][k].astype(np.float64)  # the sample goes exactly there, nearer than the point's own
    back_point = (seen - pose[:3, 3]) @ pose[:3, :3]
    back_normal = -(record["normals"][k] @ pose[:3, :3])
    seal = {"points": np.vstack([seal["points"], back_point]), "normals": np.vstack([seal["normals"], back_normal]),
            "scores": np.append(seal["scores"], 0.123), "collision": np.append(seal["collision"], False)}
    np.savez(layout.seal_label(model), **seal)
    for path, extra in ((layout.wrench_label(100), 0.5), (layout.collision_label(100), True)):
        arrays = dict(np.load(path))
        arrays["arr_0"] = np.append(arrays["arr_0"], extra)
        np.savez(path, *[arrays[f"arr_{i}"] for i in range(len(arrays))])
    back = _read(copy)
    np.testing.assert_allclose(back["labels"][k], record["labels"][k], atol=1e-7)


def test_a_tree_without_the_parcelpick_sidecar_reads_as_suctionnet_data(native, copy):
    """Real SuctionNet data has no sidecar: points are sampled and normals estimated here, models are named."""
    (Layout(copy).view_file(100, CAMERA, "parcelpick", 0)).unlink()
    back = _read(copy, num_points=300)
    assert back["points"].shape == (300, 3) and back["labels"].shape == (300, 4)
    assert is_suctionnet_record(back) and all(a.startswith(ASSET_PREFIX) for a in back["object_asset_ids"])
    assert str(back["split"]) == "test_seen" and int(back["suctionnet_scene"]) == 100
    np.testing.assert_allclose(np.linalg.norm(back["normals"], axis=1), 1.0, atol=1e-5)
    cam = back["extrinsics"][:3, 3]
    assert np.all(np.sum((cam - back["points"]) * back["normals"], axis=1) >= -1e-6)  # normals face the camera
    on = back["object_ids"] >= 0
    np.testing.assert_array_equal(back["labels"][on, 3], 1.0)  # SuctionNet has no visibility label
    from dataset.scene_record import bin_from_record

    table = bin_from_record(back).floor_meshes()[0].bounds  # suctionnetAPI's table: 1 m square, top at z = 0
    assert table[1, 2] == pytest.approx(0.0) and np.all(table[0, :2] <= -0.5) and np.all(table[1, :2] >= 0.5)
    # the record's models, posed, are the native parcels' true surfaces
    for mesh, truth in zip(world_meshes(back), _native_meshes(native[1][0]), strict=True):
        np.testing.assert_allclose(mesh.vertices, truth.vertices, atol=1e-6)


def _native_meshes(record):
    from dataset.scene_record import scene_from_record

    return scene_from_record(record).world_meshes()


def test_imported_views_serve_the_torch_dataset_and_the_ap_evaluator(native, tree, tmp_path):
    from dataset.torch_dataset import ParcelSuctionDataset
    from eval.ap import evaluate_ap

    views = split_views(tree[0], CAMERA, "test_seen")
    assert views == [(100, 0), (101, 0)]
    out = tmp_path / "imported"
    import_views(tree[0], out, CAMERA, views, split="test_seen", config=ReaderConfig(num_points=POINTS))
    item = ParcelSuctionDataset(out, split="test_seen", num_points=128)[1]
    assert item["points"].shape == (128, 3) and item["labels"].shape == (128, 4)
    ours, theirs = evaluate_ap("normal_std", native[0]), evaluate_ap("normal_std", out)
    assert [s["AP"] for s in theirs["scenes"]] == pytest.approx([s["AP"] for s in ours["scenes"]], abs=1e-9)


def _first_model(root):
    meta = scipy.io.loadmat(Layout(root).view_file(100, CAMERA, "meta", 0))
    return int(meta["cls_indexes"].reshape(-1)[0]) - LABEL_OFFSET


def _remove(path):
    path.unlink()
    return path


def _save(path, array):
    np.save(path, array)
    return path


def _rewrite_meta(root, **fields):
    path = Layout(root).view_file(100, CAMERA, "meta", 0)
    meta = {k: v for k, v in scipy.io.loadmat(path).items() if not k.startswith("__")}
    scipy.io.savemat(path, {**meta, **fields})
    return path


def _rewrite_xml_id(root, new_id):
    path = Layout(root).view_file(100, CAMERA, "annotations", 0)
    top = ET.parse(path)
    top.getroot()[0].find("obj_id").text = str(new_id)
    top.write(path)
    return path


@pytest.mark.parametrize("damage, message", [
    (lambda root: _remove(Layout(root).view_file(100, CAMERA, "meta", 0)), "meta file is missing"),
    (lambda root: _rewrite_meta(root, factor_depth=np.array([[100.0]])), "wrong depth factor"),
    (lambda root: _rewrite_meta(root, factor_depth=np.array([[0.0]])), "factor_depth must be a positive number"),
    (lambda root: _rewrite_xml_id(root, 77), "unknown object id 77"),
    (lambda root: _rewrite_meta(root, cls_indexes=np.array([[60.0]])), "cls_indexes name objects [59]"),
    (lambda root: _save(Layout(root).camera_file(100, CAMERA, "camK.npy"), 2 * np.eye(3)), "intrinsics differ"),
    (lambda root: _remove(Layout(root).seal_label(_first_model(root))), "seal label of object"),
    (lambda root: _remove(Layout(root).camera_file(100, CAMERA, "cam0_wrt_table.npy")), "transform is missing"),
])
def test_a_malformed_tree_fails_with_one_error_naming_the_file(copy, damage, message):
    path = damage(copy)
    with pytest.raises(SuctionNetLayoutError) as info:
        _read(copy)
    assert str(path) in str(info.value) and message in str(info.value)


def test_label_pixels_of_an_unannotated_object_name_the_label_image(copy):
    layout = Layout(copy)
    path = layout.view_file(100, CAMERA, "label", 0)
    label = read_png(path, "label")
    label[0, 0] = 200
    from dataset.suctionnet.layout import write_png

    write_png(path, label)
    with pytest.raises(SuctionNetLayoutError, match=r"label/0000\.png: unknown object id\(s\) \[199\]"):
        _read(copy)


def test_writer_refuses_records_without_images_and_existing_trees(native, tree):
    record = {k: v for k, v in native[1][0].items() if k != "depth"}
    with pytest.raises(ValueError, match="lacks \\['depth'\\]"):
        write_records([record], tree[0] / "unused")
    with pytest.raises(FileExistsError, match="is not empty"):  # its model ids would collide with the tree's
        write_records([native[1][0]], tree[0], scenes=[102])


def test_missing_view_and_empty_split_are_clear(tree):
    with pytest.raises(SuctionNetLayoutError, match="scene_0107/realsense: no such"):
        read_view(tree[0], 107, CAMERA, 0)
    with pytest.raises(SuctionNetLayoutError, match="no realsense views of split test_novel"):
        split_views(tree[0], CAMERA, "test_novel")


def test_the_two_commands_export_and_import(native, tmp_path):
    from dataset.suctionnet.__main__ import main

    root, out = tmp_path / "sn", tmp_path / "imported"
    assert main(["export", "--data", str(native[0]), "--out", str(root), "--first-scene", "160"]) == 0
    assert (root / "scenes" / "scene_0161" / CAMERA / "meta" / "0000.mat").is_file()
    assert main(["import", "--graspnet-root", str(root), "--camera", CAMERA, "--split", "test_novel",
                 "--out", str(out), "--points", "64", "--no-images"]) == 0
    store = open_dataset(out)
    assert len(store) == 2 and store.config["split"] == "test_novel" and store.config["views"] == [[160, 0], [161, 0]]
    assert "depth" not in store.scene(0) and store.scene(0)["points"].shape == (POINTS, 3)  # sidecar pixels win
    store.close()


def test_a_suctionnet_view_is_scored_on_its_own_models(native, copy):
    """Without the sidecar the asset library cannot name the objects: the evaluator rebuilds the scene from the
    view's models, and a pick's suctionnet quality there equals the same pick's on the native parcels."""
    from dataset.scene_record import scene_from_record
    from parcelpick_env.suction.quality import definition_scorer, score_definition

    (Layout(copy).view_file(100, CAMERA, "parcelpick", 0)).unlink()
    back = _read(copy, num_points=300)
    scene = scene_from_record(back)
    assert [p.asset.asset_id for p in scene.parcels] == list(back["object_asset_ids"])
    record = native[1][0]
    on = np.flatnonzero(record["object_ids"] >= 0)[:64]
    points, normals = record["points"][on].astype(np.float64), record["normals"][on].astype(np.float64)
    theirs = score_definition("suctionnet", definition_scorer("suctionnet", scene), points, normals,
                              record["object_ids"][on])
    ours = score_definition("suctionnet", definition_scorer("suctionnet", scene_from_record(record)), points, normals,
                            record["object_ids"][on])
    # the stored models and poses round the geometry, which moves a rim ray's hit: up to 8e-5 of the seal, measured
    np.testing.assert_allclose(theirs.seal, ours.seal, atol=2e-4)
    np.testing.assert_allclose(theirs.wrench, ours.wrench, atol=1e-5)  # the surface centroid, whatever the mass
    assert np.any(ours.quality > 0)
