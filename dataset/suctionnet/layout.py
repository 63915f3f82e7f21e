"""Where GraspNet-1Billion / SuctionNet-1Billion keep each file, and safe loaders for them.

The one place that names the layout (docs/suctionnet_layout.md describes it, with sources). Every
loader here refuses code-carrying formats: ``.npy``/``.npz`` load with ``allow_pickle=False``, ``.mat``
through ``scipy.io.loadmat`` (MATLAB v5 data, no code), XML through the standard library's
``xml.etree`` (no external entities or DTD fetches), PNG through Open3D. Any failure is one
``SuctionNetLayoutError`` that names the file.
"""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import numpy as np

CAMERAS = ("kinect", "realsense")  # SuctionNet's two cameras; suctionnetAPI accepts no others
VIEWS_PER_SCENE = 256  # annotation ids 0..255 per scene and camera in the real data
NUM_MODELS = 88  # objects 000..087 in the real data
# Scene-id ranges of the public splits (suctionnetAPI's SuctionNet.__init__).
SPLITS: dict[str, range] = {
    "train": range(0, 100),
    "test": range(100, 190),
    "test_seen": range(100, 130),
    "test_similar": range(130, 160),
    "test_novel": range(160, 190),
}
DEPTH_FACTOR = 1000.0  # depth PNG units per metre in GraspNet (meta.mat 'factor_depth')
LABEL_OFFSET = 1  # label PNG value = object id + 1; 0 is background (graspnet-baseline's loader)


# Table I's names for the three test splits (the paper's "seen / similar / novel"), in its column order.
TEST_SPLITS: dict[str, str] = {"seen": "test_seen", "similar": "test_similar", "novel": "test_novel"}
LABEL_DIRS = ("seal_label", "wrench_label", "suction_collision_label|collision_label")  # what training needs


class SuctionNetLayoutError(ValueError):
    """A file of a GraspNet/SuctionNet tree is missing, unreadable or inconsistent; the message names it."""


def split_of_scene(scene: int) -> str:
    """The narrowest public split holding ``scene`` ('train', 'test_seen', 'test_similar', 'test_novel')."""
    for name in ("train", "test_seen", "test_similar", "test_novel"):
        if scene in SPLITS[name]:
            return name
    return "custom"


def is_suctionnet_root(path: str | os.PathLike) -> bool:
    """Whether ``path`` is laid out as GraspNet/SuctionNet (a ``scenes/`` folder) rather than a ParcelPick dataset
    directory (a ``manifest.json``)."""
    root = Path(path)
    return (root / "scenes").is_dir() and not (root / "manifest.json").exists()


def check_label_dirs(path: str | os.PathLike) -> None:
    """One clear error if a GraspNet tree lacks SuctionNet's label folders (GraspNet-1Billion alone has none)."""
    root = Path(path)
    missing = [name for name in LABEL_DIRS if not any((root / alt).is_dir() for alt in name.split("|"))]
    if missing:
        raise SuctionNetLayoutError(f"{root}: a GraspNet tree without SuctionNet-1Billion's labels "
                                    f"(no {', '.join(m.replace('|', ' or ') + '/' for m in missing)}); "
                                    "add SuctionNet's label folders to this root")


class Layout:
    """Paths of one GraspNet/SuctionNet root; nothing is read or created by constructing it."""

    def __init__(self, root: str | os.PathLike) -> None:
        self.root = Path(root)

    def scene_dir(self, scene: int) -> Path:
        return self.root / "scenes" / f"scene_{int(scene):04d}"

    def camera_dir(self, scene: int, camera: str) -> Path:
        return self.scene_dir(scene) / camera

    def view_file(self, scene: int, camera: str, kind: str, ann_id: int) -> Path:
        """``kind`` is rgb, depth, label (PNG), meta (.mat), annotations (.xml) or parcelpick (.npz)."""
        ext = {"rgb": "png", "depth": "png", "label": "png", "meta": "mat", "annotations": "xml",
               "parcelpick": "npz"}[kind]
        return self.camera_dir(scene, camera) / kind / f"{int(ann_id):04d}.{ext}"

    def camera_file(self, scene: int, camera: str, name: str) -> Path:
        """camK.npy, camera_poses.npy or cam0_wrt_table.npy."""
        return self.camera_dir(scene, camera) / name

    def object_id_list(self, scene: int) -> Path:
        return self.scene_dir(scene) / "object_id_list.txt"

    def model_mesh(self, obj_id: int) -> Path:
        return self.root / "models" / f"{int(obj_id):03d}" / "nontextured.ply"

    def dense_points(self, obj_id: int) -> Path:
        return self.root / "dense_point_clouds" / f"{int(obj_id):03d}.npz"

    def seal_label(self, obj_id: int) -> Path:
        return self.root / "seal_label" / f"{int(obj_id):03d}_seal.npz"

    def wrench_label(self, scene: int) -> Path:
        return self.root / "wrench_label" / f"{int(scene):04d}_wrench.npz"

    def collision_label(self, scene: int) -> Path:
        """suctionnetAPI's viewers and the baselines read ``suction_collision_label``; its
        ``loadCollisionLabels`` reads ``collision_label``. The first that exists wins."""
        primary = self.root / "suction_collision_label" / f"{int(scene):04d}_collision.npz"
        fallback = self.root / "collision_label" / f"{int(scene):04d}_collision.npz"
        return fallback if not primary.exists() and fallback.exists() else primary


def _require_file(path: Path, what: str) -> None:
    if not path.is_file():
        raise SuctionNetLayoutError(f"{path}: {what} is missing")


def load_npy(path: Path, what: str) -> np.ndarray:
    _require_file(path, what)
    try:
        return np.asarray(np.load(path, allow_pickle=False))
    except (ValueError, OSError) as exc:
        raise SuctionNetLayoutError(f"{path}: {what} is not a plain .npy array ({exc})") from exc


def load_npz(path: Path, what: str, keys: tuple[str, ...] = ()) -> dict[str, np.ndarray]:
    """Every array of an .npz (``arr_0``, ``arr_1`` ... when saved positionally); ``keys`` must be present."""
    _require_file(path, what)
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {key: np.asarray(data[key]) for key in data.files}
    except (ValueError, OSError, KeyError) as exc:
        raise SuctionNetLayoutError(f"{path}: {what} is not a plain .npz archive ({exc})") from exc
    missing = [key for key in keys if key not in arrays]
    if missing:
        raise SuctionNetLayoutError(f"{path}: {what} lacks {missing} (has {sorted(arrays)})")
    return arrays


def positional(arrays: dict[str, np.ndarray], count: int, path: Path, what: str) -> list[np.ndarray]:
    """``arr_0 .. arr_{count-1}`` of an ``np.savez(*arrays)`` file, one per scene object."""
    names = [f"arr_{i}" for i in range(count)]
    missing = [n for n in names if n not in arrays]
    if missing or len(arrays) != count:
        raise SuctionNetLayoutError(f"{path}: {what} has {len(arrays)} arrays, the scene has {count} objects")
    return [arrays[n] for n in names]


def load_mat(path: Path, what: str, keys: tuple[str, ...]) -> dict[str, np.ndarray]:
    _require_file(path, what)
    import scipy.io

    try:
        data = scipy.io.loadmat(str(path))
    except (ValueError, OSError, NotImplementedError, TypeError) as exc:  # v7.3 (HDF5) .mat: NotImplementedError
        raise SuctionNetLayoutError(f"{path}: {what} is not a readable MATLAB v5 file ({exc})") from exc
    missing = [key for key in keys if key not in data]
    if missing:
        raise SuctionNetLayoutError(f"{path}: {what} lacks {missing}")
    return {key: np.asarray(value) for key, value in data.items() if not key.startswith("__")}


def read_png(path: Path, what: str) -> np.ndarray:
    _require_file(path, what)
    import open3d as o3d

    image = np.asarray(o3d.io.read_image(path))
    if image.size == 0:
        raise SuctionNetLayoutError(f"{path}: {what} is not a readable PNG")
    return image


def write_png(path: Path, image: np.ndarray) -> None:
    import open3d as o3d

    path.parent.mkdir(parents=True, exist_ok=True)
    buffer: Any = np.ascontiguousarray(image)
    if not o3d.io.write_image(path, o3d.geometry.Image(buffer)):
        raise OSError(f"could not write {path}")


def read_annotation(path: Path) -> list[tuple[int, str, np.ndarray, np.ndarray]]:
    """(obj_id, obj_name, translation (3,), quaternion wxyz (4,)) per ``<obj>`` of an annotations XML.

    The fields are found by tag (``obj_id``, ``obj_name``, ``pos_in_world``, ``ori_in_world``), where
    graspnetAPI's xmlReader takes them by position; the files it writes have this order.
    """
    _require_file(path, "annotation XML")
    try:
        top = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise SuctionNetLayoutError(f"{path}: annotation XML does not parse ({exc})") from exc
    objects = []
    for k, obj in enumerate(top.findall("obj")):
        try:
            obj_id = int(obj.findtext("obj_id", ""))
            name = obj.findtext("obj_name", "") or ""
            pos = np.array([float(x) for x in (obj.findtext("pos_in_world") or "").split()])
            quat = np.array([float(x) for x in (obj.findtext("ori_in_world") or "").split()])
        except ValueError as exc:
            raise SuctionNetLayoutError(f"{path}: object {k} has a malformed field ({exc})") from exc
        if pos.shape != (3,) or quat.shape != (4,) or not np.all(np.isfinite(np.r_[pos, quat])) \
                or np.linalg.norm(quat) < 1e-6:
            raise SuctionNetLayoutError(f"{path}: object {k} needs 3 finite pos_in_world and 4 ori_in_world values")
        objects.append((obj_id, name, pos, quat / np.linalg.norm(quat)))
    return objects


def write_annotation(path: Path, objects: list[tuple[int, str, str, np.ndarray, np.ndarray]]) -> None:
    """(obj_id, obj_name, obj_path, translation, quaternion wxyz) per object, in graspnetAPI's tag order.

    Values get 9 significant digits where graspnetAPI's xmlWriter writes 4 decimals; its reader parses both.
    """
    top = ET.Element("scene")
    for obj_id, name, obj_path, pos, quat in objects:
        entry = ET.SubElement(top, "obj")
        ET.SubElement(entry, "obj_id").text = str(int(obj_id))
        ET.SubElement(entry, "obj_name").text = name
        ET.SubElement(entry, "obj_path").text = obj_path
        ET.SubElement(entry, "pos_in_world").text = " ".join(f"{v:.9g}" for v in pos)
        ET.SubElement(entry, "ori_in_world").text = " ".join(f"{v:.9g}" for v in quat)
    ET.indent(top, space="    ")
    path.parent.mkdir(parents=True, exist_ok=True)
    ET.ElementTree(top).write(path, encoding="utf-8", xml_declaration=True)


def scalar(value: Any) -> float:
    """A MATLAB scalar (stored as a 1x1 array) as a float."""
    array = np.asarray(value, dtype=np.float64).reshape(-1)
    if array.size != 1:
        raise ValueError(f"expected a scalar, got shape {np.shape(value)}")
    return float(array[0])
