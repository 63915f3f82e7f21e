"""Table I on a miniature SuctionNet-format tree: per split and camera, a scene is the mean of its views and the
intervals resample scenes; the figures are eval/ap.py's on the same records; absent data is one line, exit 0.

Four tiny generated test scenes (160x120, 2-4 parcels) are written once as scenes 100 and 101 (seen), 130
(similar) and 160 (novel) of a realsense tree; scene 100 gets a second view, a copy of its first.
"""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from generated_records import generate_records

from dataset.suctionnet.layout import SPLITS, TEST_SPLITS, Layout
from dataset.suctionnet.reader import ReaderConfig
from dataset.suctionnet.writer import WriterConfig, write_records
from eval.ap import APConfig, evaluate_ap
from eval.table_one import (
    TOPS,
    TableOneConfig,
    absent_line,
    format_markdown,
    main,
    plan_views,
    present_test_scenes,
    run_table_one,
)
from policies.registry import make_policy

CAMERA = "realsense"
SCENES = (100, 101, 130, 160)
POINTS = 512
TINY = dict(width=160, height=120, min_parcels=2, max_parcels=4, annotation_points=POINTS, object_set="mixed",
            scenes=len(SCENES), split="test")


def _second_view(root, scene):
    """View 1 of ``scene``: a copy of view 0 (same files, an identity camera pose), so its AP equals view 0's."""
    layout = Layout(root)
    for kind in ("rgb", "depth", "label", "meta", "annotations", "parcelpick"):
        src = layout.view_file(scene, CAMERA, kind, 0)
        if src.exists():
            shutil.copy(src, layout.view_file(scene, CAMERA, kind, 1))
    np.save(layout.camera_file(scene, CAMERA, "camera_poses.npy"), np.stack([np.eye(4)] * 2))


@pytest.fixture(scope="module")
def trees(tmp_path_factory):
    """(native dataset dir, tree with sidecars = the native records, tree without = as real SuctionNet data)."""
    native = tmp_path_factory.mktemp("native")
    records = generate_records(native, **TINY)
    base = tmp_path_factory.mktemp("sn")
    exact, bare = base / "exact", base / "bare"
    write_records(records, exact, scenes=list(SCENES), config=WriterConfig(camera=CAMERA))
    shutil.copytree(exact, bare)
    for scene in SCENES:
        Layout(bare).view_file(scene, CAMERA, "parcelpick", 0).unlink()
    for root in (exact, bare):
        _second_view(root, 100)
    return native, exact, bare


def _config(root, **overrides):
    return TableOneConfig(**{"graspnet_root": str(root), "cameras": (CAMERA,),
                             "reader": ReaderConfig(num_points=POINTS), **overrides})


def test_split_ranges_and_view_plans(trees, tmp_path):
    assert [SPLITS[TEST_SPLITS[s]] for s in ("seen", "similar", "novel")] == [range(100, 130), range(130, 160),
                                                                              range(160, 190)]
    _, exact, _ = trees
    assert plan_views(exact, CAMERA, "seen") == {100: [0, 1], 101: [0]}
    assert plan_views(exact, CAMERA, "seen", scenes=1, views=1) == {100: [0]}
    assert plan_views(exact, "kinect", "seen") == {}
    meta = tmp_path / "scenes" / "scene_0131" / "kinect" / "meta"  # 256 views: --views 4 spreads them out
    meta.mkdir(parents=True)
    for a in range(256):
        (meta / f"{a:04d}.mat").touch()
    assert plan_views(tmp_path, "kinect", "similar", views=4) == {131: [0, 85, 170, 255]}
    assert present_test_scenes(exact) == list(SCENES) and present_test_scenes(tmp_path / "nowhere") == []


def test_table_one_equals_eval_ap_on_the_same_records_scene_by_scene(trees):
    """With sidecars the tree reads back to the native records: each split's per-scene figures are eval/ap.py's on
    the native scenes (scene 100's two identical views average to its one), and intervals count scenes."""
    native, exact, _ = trees
    policy = make_policy("normal_std")
    result = run_table_one(_config(exact), {"normal_std": policy})
    theirs = evaluate_ap("normal_std", native)
    by_index = dict(zip(SCENES, range(len(SCENES))))
    cells = result["cells"][CAMERA]
    assert cells["seen"]["scenes"] == [100, 101] and cells["seen"]["views"] == 3
    for split, cell in cells.items():
        ours = cell["policies"]["normal_std"]
        assert ours["num_scenes"] == len(cell["scenes"]) == ours["intervals"]["AP"]["n"]
        for keys in TOPS.values():
            for key in keys:
                expected = [theirs["per_scene"][key][by_index[s]] for s in cell["scenes"]]
                assert ours["per_scene"][key] == pytest.approx(expected, abs=1e-9), (split, key)
                assert ours[key] == pytest.approx(np.mean(expected), abs=1e-9)
    assert any(cells[s]["policies"]["normal_std"]["AP"] > 0 for s in cells)


def test_a_tree_read_as_suctionnet_data_is_scored_on_its_own_models(trees):
    """Without sidecars the records name SuctionNet models (suctionnet:OOO); every policy's figures come out."""
    _, _, bare = trees
    policies = {"normal_std": make_policy("normal_std"), "cao": make_policy("cao")}
    result = run_table_one(_config(bare, splits=("seen", "novel"), scenes=1), policies)
    cells = result["cells"][CAMERA]
    assert set(cells) == {"seen", "novel"} and cells["seen"]["scenes"] == [100]
    for cell in cells.values():
        for figures in cell["policies"].values():
            assert all(0.0 <= figures[k] <= 100.0 for keys in TOPS.values() for k in keys)
            assert figures["intervals"]["AP"]["n"] == 1
    assert any(cells[s]["policies"][p]["AP"] > 0 for s in cells for p in policies)
    md = format_markdown(result)
    assert "**realsense, Top-50**" in md and "**realsense, Top-1**" in md and "| Cao et al. (paper) |" in md
    assert "seen 1 scenes / 2 views" in md
    # the paper's own RealSense cells (its Table I, after the slash), seen then novel, beside ours
    assert "| Cao et al. (paper) | 28.31 | 3.41 | 38.56 | 8.23 | 0.35 | 10.29 |" in md  # Top-50
    assert "| Normal-STD (paper) | 15.40 | 1.82 | 18.83 | 4.89 | 0.52 | 5.96 |" in md  # Top-1
    both = run_table_one(_config(bare, cameras=("kinect", CAMERA), splits=("novel",)), {"normal_std": policies[
        "normal_std"]})
    assert both["cells"]["kinect"]["novel"] == {"status": "no views", "scenes": [], "views": 0}
    assert "**kinect**: no test views in this tree." in format_markdown(both)


def test_the_command_writes_json_and_markdown(trees, tmp_path, capsys):
    _, _, bare = trees
    out, md = tmp_path / "t1.json", tmp_path / "T1.md"
    assert main(["--graspnet-root", str(bare), "--camera", CAMERA, "--policies", "normal_std", "--scenes", "1",
                 "--views", "1", "--points", str(POINTS), "--out", str(out), "--markdown", str(md), "--quiet"]) == 0
    result = json.loads(out.read_text())
    assert result["checkpoints"] == {"normal_std": "shipped"} and result["quality"] == "suctionnet"
    assert result["cells"][CAMERA]["seen"]["views"] == 1
    assert md.read_text().startswith("# Table I") and "Normal-STD" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main(["--graspnet-root", str(bare), "--policies", "normal_std", "--checkpoint", "cao=x.pt"])


def test_absent_data_is_one_line_and_exit_zero(trees, tmp_path, capsys):
    native, _, _ = trees
    train_only = tmp_path / "train_only"
    (train_only / "scenes" / "scene_0003" / CAMERA / "meta").mkdir(parents=True)
    for root in (tmp_path / "nowhere", native, train_only):
        assert main(["--graspnet-root", str(root)]) == 0
        assert capsys.readouterr().out.strip().splitlines() == [absent_line(root)]
    with pytest.raises(ValueError, match="no masses"):
        _config(native, ap=APConfig(quality="physical"))


def test_the_report_adds_table_one_or_the_one_line(trees, tmp_path):
    from eval.report.cli import build_parser
    from eval.report.config import ReportConfig
    from eval.report.markdown import table_one_lines
    from eval.report.orchestration import evaluate_table_one

    _, _, bare = trees
    assert build_parser().parse_args(["--test-data", "x", "--graspnet-root", str(bare)]).graspnet_root == str(bare)
    assert table_one_lines({"table_one": None}) == []
    absent = evaluate_table_one(ReportConfig(test_data=str(tmp_path), policies=("normal_std",),
                                             graspnet_root=str(tmp_path / "nowhere"), progress=False))
    assert table_one_lines({"table_one": absent})[2] == absent_line(tmp_path / "nowhere")
    root = shutil.copytree(bare, tmp_path / "graspnet")
    shutil.rmtree(root / "scenes" / "scene_0101")  # keep it quick: one view of 130 and 160, two of 100
    present = evaluate_table_one(ReportConfig(test_data=str(tmp_path), policies=("normal_std", "random", "sb3"),
                                              graspnet_root=str(root), progress=False))
    assert present["policies"] == ["normal_std"] and present["cells"][CAMERA]["seen"]["scenes"] == [100]
    lines = "\n".join(table_one_lines({"table_one": present}))
    assert "## SuctionNet-1Billion (paper Table I layout)" in lines and "| Normal-STD |" in lines
