"""HDF5 shards: atomic, checksummed, resumable storage of annotated scenes.

A dataset directory holds ``manifest.json`` and ``shard-XXXXX.h5`` files. Shard ``k`` always holds the
scene indices ``config.shard_range(k)``, so an interrupted run resumes by skipping shards that verify,
and can never write a scene twice. Each shard is written to ``shard-XXXXX.h5.tmp``, fsynced and then
renamed, so a reader never sees a half-written shard under its final name. The ``complete`` attribute
and a SHA-256 over every stored array catch truncated or corrupted files.

Every read is verified by default: each stored array carries its own SHA-256 (attribute ``sha256``), and
``ShardedDataset`` recomputes it for every array it returns, so a flipped byte anywhere in the data
(compressed or not) fails with an error naming the shard, the scene and the array, however little of the
dataset a caller reads. Shards written before per-array digests are verified whole, once per process, on
first use. ``open_dataset(..., verify=False)`` skips this, for speed, when the data is known good.

Why HDF5 rather than zarr: one file per shard (thousands of scenes) keeps file counts low on cluster
file systems, h5py ships in the base environment, files open lazily per DataLoader worker and read
only the requested scene, and the single-file shard makes the write-tmp-then-rename commit atomic.
Zarr's directory-of-chunks layout would need its own commit protocol for the same guarantee.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np

FORMAT_VERSION = 1
MANIFEST = "manifest.json"
SCENE_GROUP = "scene_{:08d}"
# Arrays smaller than this are stored contiguous: compressing a few bytes only adds chunk overhead.
_COMPRESS_MIN_BYTES = 1024

Record = dict[str, np.ndarray]


class CorruptShardError(OSError):
    """A shard file is missing, truncated, incomplete or fails its checksum."""


def rebuild_hint(root: Path) -> str:
    """What to do about a corrupt shard: the generator re-verifies every shard on a re-run and rebuilds bad ones."""
    return (f"re-run `python -m dataset.generate --out {root}` with the arguments that made it "
            f"(its {MANIFEST} holds them) to rebuild the shard")


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


def shard_name(shard: int) -> str:
    return f"shard-{shard:05d}.h5"


def _is_string(array: np.ndarray) -> bool:
    return array.dtype.kind in ("U", "S", "O")


def _hash_array(digest: Any, key: str, array: np.ndarray) -> None:
    """Feed one array into the digest in a form that survives an HDF5 round trip."""
    digest.update(key.encode())
    digest.update(repr(tuple(array.shape)).encode())
    if _is_string(array):
        items = [x.decode() if isinstance(x, bytes) else str(x) for x in array.reshape(-1).tolist()]
        digest.update(b"str")
        digest.update("\x00".join(items).encode())
    else:
        contiguous = np.ascontiguousarray(array)
        digest.update(contiguous.dtype.str.encode())
        digest.update(contiguous.tobytes())


def array_checksum(key: str, array: np.ndarray) -> str:
    """SHA-256 of one named array, as stored beside it (attribute ``sha256``) and checked on every read."""
    digest = hashlib.sha256()
    _hash_array(digest, key, np.asarray(array))
    return digest.hexdigest()


def records_checksum(records: Mapping[int, Mapping[str, np.ndarray]]) -> str:
    """SHA-256 over every scene's arrays, keyed by scene index and array name (order independent)."""
    digest = hashlib.sha256()
    for index in sorted(records):
        digest.update(SCENE_GROUP.format(index).encode())
        for key in sorted(records[index]):
            _hash_array(digest, key, np.asarray(records[index][key]))
    return digest.hexdigest()


def _fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:  # some platforms cannot open directories
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` so that ``path`` holds either the old or the new content, never a mix."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as handle:
        handle.write(data)
        handle.flush()
        os.fsync(handle.fileno())
    os.replace(tmp, path)
    _fsync_dir(path.parent)


def _validate_record(index: int, record: Mapping[str, np.ndarray]) -> None:
    if not record:
        raise ValueError(f"scene {index}: empty record")
    for key, value in record.items():
        if not isinstance(key, str) or not key or "/" in key:
            raise ValueError(f"scene {index}: bad array name {key!r}")
        array = np.asarray(value)
        if array.dtype.kind == "f" and not np.all(np.isfinite(array)):
            raise ValueError(f"scene {index}: array {key!r} contains NaN or inf")
        if array.dtype.kind not in "biufUSO":
            raise ValueError(f"scene {index}: array {key!r} has unsupported dtype {array.dtype}")


def write_shard(
    path: Path,
    shard: int,
    records: Mapping[int, Mapping[str, np.ndarray]],
    scene_range: range,
    *,
    compression: str = "gzip",
    compression_level: int = 4,
) -> dict[str, Any]:
    """Atomically write one shard holding exactly the scenes in ``scene_range``; return its manifest entry."""
    path = Path(path)
    if sorted(records) != list(scene_range):
        raise ValueError(f"{path.name}: records {sorted(records)[:5]}... do not match scenes {scene_range}")
    for index, record in records.items():
        _validate_record(index, record)
    checksum = records_checksum(records)
    tmp = path.with_name(path.name + ".tmp")
    options = {"compression": compression}
    if compression == "gzip":
        options["compression_opts"] = compression_level
    with h5py.File(tmp, "w", track_order=True) as handle:
        for index in scene_range:
            group = handle.create_group(SCENE_GROUP.format(index), track_order=True)
            group.attrs["scene_index"] = index
            for key, value in records[index].items():
                array = np.asarray(value)
                if _is_string(array):
                    data = np.array([x.decode() if isinstance(x, bytes) else str(x) for x in array.reshape(-1)],
                                    dtype=h5py.string_dtype("utf-8")).reshape(array.shape)
                    dataset = group.create_dataset(key, data=data, track_times=False)
                elif array.ndim == 0 or array.nbytes < _COMPRESS_MIN_BYTES:
                    dataset = group.create_dataset(key, data=array, track_times=False)
                else:
                    # One chunk per array: readers always load whole arrays of one scene.
                    dataset = group.create_dataset(key, data=array, chunks=array.shape, shuffle=True,
                                                   track_times=False, **options)
                dataset.attrs["sha256"] = array_checksum(key, array)
        handle.attrs["format_version"] = FORMAT_VERSION
        handle.attrs["shard"] = shard
        handle.attrs["scene_start"] = scene_range.start
        handle.attrs["scene_stop"] = scene_range.stop
        handle.attrs["num_scenes"] = len(scene_range)
        handle.attrs["sha256"] = checksum
        handle.attrs["complete"] = True  # set last: a file cut short before this point is detectably incomplete
    with open(tmp, "rb+") as raw:
        os.fsync(raw.fileno())
    os.replace(tmp, path)
    _fsync_dir(path.parent)
    return {"file": path.name, "shard": shard, "scene_start": scene_range.start, "scene_stop": scene_range.stop,
            "sha256": checksum, "bytes": path.stat().st_size}


def _where(group: h5py.Group) -> str:
    return f"shard {group.file.filename}, scene {group.attrs.get('scene_index', '?')} ({group.name.lstrip('/')})"


def read_array(group: h5py.Group, key: str, *, verify: bool = True) -> np.ndarray:
    """One array of a scene group (strings as numpy unicode), checked against its stored SHA-256 when
    ``verify`` and the shard has one; ``CorruptShardError`` naming shard, scene and array otherwise."""
    try:
        dataset = group[key]
        if h5py.check_string_dtype(dataset.dtype) is not None:
            array = np.asarray(dataset.asstr()[()], dtype=str)
        else:
            array = dataset[()]
        expected = dataset.attrs.get("sha256") if verify else None
    except (OSError, RuntimeError, ValueError) as exc:  # h5py: a damaged chunk fails to decompress
        raise CorruptShardError(f"{_where(group)}: array {key!r} is unreadable ({_one_line(exc)}); "
                                f"{rebuild_hint(Path(group.file.filename).parent)}") from exc
    if expected is not None and array_checksum(key, array) != str(expected):
        raise CorruptShardError(f"{_where(group)}: array {key!r} fails its checksum (the file is corrupt); "
                                f"{rebuild_hint(Path(group.file.filename).parent)}")
    return array


def has_array_checksums(handle: h5py.File) -> bool:
    """Whether this shard stores per-array digests (written since they were added); checked on its first array."""
    for group in handle.values():
        for dataset in group.values():
            return "sha256" in dataset.attrs
    return False


def read_group(group: h5py.Group, *, verify: bool = True) -> Record:
    """Load every array of one scene group (see ``read_array``)."""
    return {key: read_array(group, key, verify=verify) for key in group}


def _open_checked(path: Path) -> h5py.File:
    if not path.exists():
        raise CorruptShardError(f"shard file {path} is missing")
    try:
        return h5py.File(path, "r")
    except OSError as exc:  # h5py reports truncation and garbage headers as OSError
        raise CorruptShardError(f"shard file {path} is corrupt or truncated and cannot be opened: {exc}") from exc


@dataclass(frozen=True)
class ShardInfo:
    path: Path
    shard: int
    scene_start: int
    scene_stop: int
    sha256: str

    @property
    def scene_range(self) -> range:
        return range(self.scene_start, self.scene_stop)


def verify_shard(path: str | os.PathLike, *, checksum: bool = True, expected: range | None = None) -> ShardInfo:
    """Check that a shard is complete and intact; raise ``CorruptShardError`` naming the file if not.

    ``checksum=False`` checks structure only (attributes, scene groups), which is cheap enough to run on
    every open; the full check re-reads every array and compares SHA-256.
    """
    path = Path(path)
    handle = _open_checked(path)
    try:
        attrs = handle.attrs
        try:
            if not bool(attrs.get("complete", False)):
                raise CorruptShardError(f"shard file {path} is incomplete (no 'complete' flag)")
            start, stop = int(attrs["scene_start"]), int(attrs["scene_stop"])
            info = ShardInfo(path, int(attrs["shard"]), start, stop, str(attrs["sha256"]))
        except KeyError as exc:
            raise CorruptShardError(f"shard file {path} lacks attribute {exc}") from exc
        if expected is not None and info.scene_range != expected:
            raise CorruptShardError(f"shard file {path} holds scenes {info.scene_range}, expected {expected}")
        names = [SCENE_GROUP.format(i) for i in info.scene_range]
        missing = [name for name in names if name not in handle]
        if missing or len(handle) != len(names):
            raise CorruptShardError(f"shard file {path} has scene groups {list(handle)[:4]}..., "
                                    f"expected {names[:4]}...")
        if checksum:
            try:
                records = {i: read_group(handle[SCENE_GROUP.format(i)]) for i in info.scene_range}
            except CorruptShardError:
                raise
            except (OSError, RuntimeError, KeyError, ValueError) as exc:
                raise CorruptShardError(f"shard file {path} has unreadable data: {_one_line(exc)}; "
                                        f"{rebuild_hint(path.parent)}") from exc
            actual = records_checksum(records)
            if actual != info.sha256:
                raise CorruptShardError(f"shard file {path} fails its checksum ({actual[:12]} != {info.sha256[:12]}); "
                                        f"{rebuild_hint(path.parent)}")
        return info
    finally:
        handle.close()


def write_manifest(root: Path, config: Mapping[str, Any], shards: Iterable[Mapping[str, Any]], *,
                   complete: bool) -> dict[str, Any]:
    manifest = {
        "format_version": FORMAT_VERSION,
        "complete": complete,
        "config": dict(config),
        "shards": sorted((dict(s) for s in shards), key=lambda s: s["shard"]),
    }
    manifest["num_scenes"] = sum(s["scene_stop"] - s["scene_start"] for s in manifest["shards"])
    atomic_write_bytes(Path(root) / MANIFEST, json.dumps(manifest, indent=2, sort_keys=True).encode())
    return manifest


def read_manifest(root: str | os.PathLike) -> dict[str, Any]:
    path = Path(root) / MANIFEST
    if not path.exists():
        raise FileNotFoundError(f"{path} not found: {root} is not a dataset directory (or generation never started)")
    try:
        manifest = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise CorruptShardError(f"manifest {path} is not valid JSON: {exc}") from exc
    if manifest.get("format_version") != FORMAT_VERSION:
        raise ValueError(f"manifest {path} has format_version {manifest.get('format_version')}, "
                         f"this code reads {FORMAT_VERSION}")
    return manifest


class ShardedDataset:
    """Read access to a verified dataset directory, one scene at a time.

    HDF5 handles are opened lazily and per process, so an instance can be handed to DataLoader
    workers (forked or spawned) and each opens its own files. With ``verify`` every array read is
    checked against its stored digest (a legacy shard without digests is checksummed whole on first use).
    """

    def __init__(self, root: str | os.PathLike, manifest: dict[str, Any], verify: bool = True) -> None:
        self.root = Path(root)
        self.manifest = manifest
        self.verify = bool(verify)
        self.config: dict[str, Any] = manifest["config"]
        self._locations: list[tuple[str, str]] = []
        self.scene_indices: list[int] = []
        for entry in manifest["shards"]:
            for index in range(entry["scene_start"], entry["scene_stop"]):
                self._locations.append((entry["file"], SCENE_GROUP.format(index)))
                self.scene_indices.append(index)
        self._handles: dict[str, h5py.File] = {}
        self._verified: set[int] = set()  # scenes whose every array this process has checked
        self._pid = os.getpid()

    def __len__(self) -> int:
        return len(self._locations)

    def _file(self, name: str) -> h5py.File:
        if self._pid != os.getpid():  # inherited through fork: never share HDF5 handles across processes
            self._handles, self._pid = {}, os.getpid()
        handle = self._handles.get(name)
        if handle is None:
            handle = _open_checked(self.root / name)
            if self.verify and not has_array_checksums(handle):
                verify_shard(self.root / name, checksum=True)  # legacy shard: whole-file SHA-256, once
            self._handles[name] = handle
        return handle

    def scene(self, i: int, keys: Iterable[str] | None = None) -> Record:
        """Arrays of the ``i``-th stored scene (all of them, or only ``keys``), each checked when ``verify``.

        The first read of a scene in a process checks every array of it, not just the requested ones, so a
        damaged array fails every consumer whichever keys it reads; later reads check what they return.
        """
        if not -len(self) <= i < len(self):
            raise IndexError(f"scene {i} out of range for {len(self)} scenes")
        i %= len(self)
        name, group_name = self._locations[i]
        group = self._file(name)[group_name]
        keys = None if keys is None else list(keys)
        for key in keys or ():
            if key not in group:
                raise KeyError(f"{self.root / name}:{group_name} has no array {key!r}")
        if self.verify and i not in self._verified:
            record = read_group(group, verify=True)
            self._verified.add(i)
            return record if keys is None else {key: record[key] for key in keys}
        if keys is None:
            return read_group(group, verify=self.verify)
        return {key: read_array(group, key, verify=self.verify) for key in keys}

    def close(self) -> None:
        for handle in self._handles.values():
            handle.close()
        self._handles = {}

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        state["_handles"] = {}
        return state

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # interpreter shutdown
            pass


def open_dataset(root: str | os.PathLike, *, verify: bool = True, checksum: bool = False,
                 allow_incomplete: bool = False) -> ShardedDataset:
    """Open a dataset directory after checking every shard's structure; errors name the offending file.

    ``verify`` (default) checks every array read against its digest; ``verify=False`` skips that, for speed.
    ``checksum`` additionally re-reads and checksums every shard now (what the generator does on resume).
    A dataset whose generation has not finished is refused unless ``allow_incomplete``; then only its
    finished shards are read.
    """
    root = Path(root)
    manifest = read_manifest(root)
    if not manifest["complete"] and not allow_incomplete:
        raise CorruptShardError(f"dataset {root} is incomplete ({len(manifest['shards'])} shards written); "
                                f"resume generation or pass allow_incomplete=True")
    for entry in manifest["shards"]:
        path = root / entry["file"]
        if path.exists() and path.stat().st_size != entry["bytes"]:
            raise CorruptShardError(f"shard file {path} has {path.stat().st_size} bytes, manifest says "
                                    f"{entry['bytes']} (truncated or replaced)")
        info = verify_shard(path, checksum=checksum, expected=range(entry["scene_start"], entry["scene_stop"]))
        if info.sha256 != entry["sha256"]:
            raise CorruptShardError(f"shard file {path} does not match the manifest's checksum; {rebuild_hint(root)}")
    return ShardedDataset(root, manifest, verify=verify)
