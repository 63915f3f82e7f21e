"""Hostile inputs: no code runs from a model file, no corrupt byte reaches a result, every CLI error is one early line.

The dataset cases use one tiny dataset made by the real pipeline (3 scenes, 160x120, 2 cartons, 256 points)
and damage copies of it in place, as a bad disk or a hostile user would: 8 bytes of an uncompressed array, or
8 bytes inside a gzip chunk, XOR-ed with 0xFF at the offset HDF5 reports for that array's data.
"""

from __future__ import annotations

import base64
import json
import os
import pickle
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import gymnasium as gym
import h5py
import numpy as np
import pytest

from dataset.config import GenerationConfig
from dataset.generate import generate
from dataset.storage import MANIFEST, CorruptShardError, open_dataset, shard_name
from parcelpick_env.cli import run_cli

REPO = Path(__file__).resolve().parents[1]
os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")


# ------------------------------------------------------------------------------------------- SB3 model files

class _WriteMarker:
    """Unpickling this opens (creates) the marker file: the stand-in for an attacker's payload."""

    def __init__(self, marker: Path) -> None:
        self.marker = str(marker)

    def __reduce__(self):
        return open, (self.marker, "w")


def _malicious_sb3_zip(path: Path, marker: Path) -> bytes:
    """An SB3-style model zip whose ``data`` entry carries a pickled payload under ``policy_class``."""
    payload = pickle.dumps(_WriteMarker(marker))
    data = {"policy_class": {":type:": "<class 'abc.ABCMeta'>", ":serialized:": base64.b64encode(payload).decode()},
            "observation_space": {":type:": "<class 'gymnasium.spaces.box.Box'>",
                                  ":serialized:": base64.b64encode(payload).decode()}}
    with zipfile.ZipFile(path, "w") as archive:
        archive.writestr("data", json.dumps(data))
        archive.writestr("_stable_baselines3_version", "2.9.2")
    return payload


def test_crafted_sb3_zip_is_refused_and_its_payload_never_runs(tmp_path):
    from policies.registry import make_policy

    marker, model = tmp_path / "pwned", tmp_path / "ppo_pixel.zip"
    payload = _malicious_sb3_zip(model, marker)
    with pytest.raises(ValueError, match=f"{model}.*refused"):
        make_policy("sb3", checkpoint=model)
    assert not marker.exists()
    pickle.loads(payload)  # control: the payload is live, so the absence above means it never ran
    assert marker.exists()


def _ppo_policy(obs_dim: int = 12 * 16):
    import gymnasium as gym
    from stable_baselines3.common.policies import ActorCriticPolicy

    return ActorCriticPolicy(gym.spaces.Box(0.0, 1.0, (obs_dim,), np.float32),
                             gym.spaces.Box(-1.0, 1.0, (2,), np.float32), lr_schedule=lambda _: 0.0)


def test_model_file_round_trips_and_every_misfit_is_refused_naming_the_file(tmp_path):
    import torch
    from safetensors.torch import save_file

    from policies.sb3.model_io import FORMAT, load_model, save_model
    from policies.sb3.policy import SB3Policy

    policy = _ppo_policy()
    good = save_model(policy, tmp_path / "good.safetensors")
    loaded, spec = load_model(good, "train")
    obs = np.random.default_rng(0).uniform(0, 1, (8, 192)).astype(np.float32)
    np.testing.assert_array_equal(policy.predict(obs, deterministic=True)[0], loaded.predict(obs, deterministic=True)[0])
    assert spec.observation_shape == (192,) and spec.activation == "tanh"

    tensors = {k: v.contiguous() for k, v in policy.state_dict().items()}
    spec_json = json.dumps({**json.loads(json.dumps(spec.__dict__)), "observation_shape": [192]})
    cases = {
        "no_metadata.safetensors": (tensors, None, "format tag"),
        "bad_spec.safetensors": (tensors, {"format": FORMAT, "spec": spec_json.replace('"tanh"', '"os.system"')},
                                 "activation"),
        "unknown_key.safetensors": (tensors, {"format": FORMAT, "spec": spec_json[:-1] + ', "exec": 1}'},
                                    "unknown keys"),
        "wrong_weights.safetensors": ({**tensors, "action_net.bias": torch.zeros(3)}, {"format": FORMAT,
                                      "spec": spec_json}, "do not match"),
    }
    for name, (weights, metadata, reason) in cases.items():
        save_file(weights, str(tmp_path / name), metadata=metadata)
        with pytest.raises(ValueError, match=f"{name}.*{reason}|{reason}.*{name}"):
            SB3Policy(checkpoint=tmp_path / name)
    (tmp_path / "garbage.safetensors").write_bytes(b"\x00" * 64)
    with pytest.raises(ValueError, match="garbage.safetensors.*not a"):
        SB3Policy(checkpoint=tmp_path / "garbage.safetensors")
    other = save_model(_ppo_policy(obs_dim=10), tmp_path / "other.safetensors")
    with pytest.raises(ValueError, match="other.safetensors maps observations"):
        SB3Policy(checkpoint=other)
    with pytest.raises(FileNotFoundError, match="missing.safetensors"):
        SB3Policy(checkpoint=tmp_path / "missing.safetensors")


class _SpacesOnly(gym.Env):
    """The PPO baseline's spaces and nothing else: enough to build and save an SB3 model (it never steps)."""

    observation_space = gym.spaces.Box(0.0, 1.0, (12 * 16,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)

    def reset(self, *, seed=None, options=None):
        return np.zeros(192, np.float32), {}

    def step(self, action):
        return np.zeros(192, np.float32), 0.0, True, False, {}


def test_converter_turns_a_trusted_zip_into_a_model_with_identical_actions(tmp_path, capsys):
    from stable_baselines3 import PPO

    from policies.sb3.convert import main
    from policies.sb3.policy import SB3Policy

    trusted = tmp_path / "mine.zip"
    model = PPO("MlpPolicy", _SpacesOnly(), n_steps=16, batch_size=16, seed=3, device="cpu")
    model.save(trusted)
    assert run_cli(main, [str(trusted)]) == 0
    converted = SB3Policy(checkpoint=tmp_path / "mine.safetensors").model
    obs = np.random.default_rng(1).uniform(0, 1, (32, 192)).astype(np.float32)
    np.testing.assert_array_equal(model.predict(obs, deterministic=True)[0], converted.predict(obs, deterministic=True)[0])
    assert "actions identical" in capsys.readouterr().out
    with pytest.raises(ValueError, match="mine.zip is a stable-baselines3 .zip"):
        SB3Policy(checkpoint=trusted)  # the policy itself still never unpickles a zip, even a trusted one


# ------------------------------------------------------------------------------------------- corrupt datasets

@pytest.fixture(scope="module")
def real_data(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("hostile") / "data"
    config = GenerationConfig(scenes=3, split="test", seed=1, min_parcels=2, max_parcels=2, width=160, height=120,
                              annotation_points=256, scenes_per_shard=3, object_set="rectangular")
    generate(root, config, progress=False)
    return root


def _flip(root: Path, key: str, scene: int = 0) -> None:
    """XOR 8 bytes in the middle of ``key``'s stored data (its contiguous block, or its one gzip chunk)."""
    path = root / shard_name(0)
    with h5py.File(path, "r") as handle:
        dataset = handle[f"scene_{scene:08d}/{key}"]
        if dataset.chunks is None:
            offset, size = dataset.id.get_offset(), dataset.id.get_storage_size()
        else:
            info = dataset.id.get_chunk_info(0)
            offset, size = info.byte_offset, info.size
    assert size >= 16
    with open(path, "r+b") as raw:
        raw.seek(offset + size // 2 - 4)
        block = raw.read(8)
        raw.seek(offset + size // 2 - 4)
        raw.write(bytes(b ^ 0xFF for b in block))


@pytest.fixture(params=["object_poses", "points"], ids=["uncompressed", "gzip-chunk"])
def damaged(request, real_data, tmp_path) -> Path:
    root = tmp_path / "damaged"
    shutil.copytree(real_data, root)
    _flip(root, request.param)
    return root


def _assert_named(text: str) -> None:
    assert shard_name(0) in text and "scene 0" in text and "dataset.generate" in text, text


def test_flip_fails_open_read_and_the_generator_rebuilds_it(damaged, real_data):
    store = open_dataset(damaged)  # structure is intact: the damage is found when the scene is read
    with pytest.raises(CorruptShardError) as error:
        store.scene(0, ("num_parcels",))  # even a read of an undamaged array of the scene fails
    _assert_named(str(error.value))
    assert "\n" not in str(error.value)
    assert open_dataset(damaged).scene(1)["points"].shape == (256, 3)  # other scenes stay readable
    config = GenerationConfig.from_dict(json.loads((damaged / MANIFEST).read_text())["config"])
    report = generate(damaged, config, progress=False)
    assert report.shards_replaced == [0]
    clean, rebuilt = open_dataset(real_data).scene(0), open_dataset(damaged).scene(0)
    assert all(np.array_equal(clean[k], rebuilt[k]) for k in clean)


def test_no_verify_is_an_explicit_opt_out(real_data, tmp_path):
    root = tmp_path / "damaged"
    shutil.copytree(real_data, root)
    _flip(root, "object_poses")
    poses = open_dataset(root, verify=False).scene(0, ("object_poses",))["object_poses"]
    assert not np.array_equal(poses, open_dataset(real_data).scene(0)["object_poses"])


def test_legacy_shard_without_array_digests_is_checksummed_whole(real_data, tmp_path):
    root = tmp_path / "legacy"
    shutil.copytree(real_data, root)
    with h5py.File(root / shard_name(0), "r+") as handle:
        for group in handle.values():
            for dataset in group.values():
                del dataset.attrs["sha256"]
    manifest = json.loads((root / MANIFEST).read_text())
    manifest["shards"][0]["bytes"] = (root / shard_name(0)).stat().st_size
    (root / MANIFEST).write_text(json.dumps(manifest))
    assert open_dataset(root).scene(2)["points"].shape == (256, 3)
    _flip(root, "object_poses")
    with pytest.raises(CorruptShardError, match=f"{shard_name(0)} fails its checksum.*dataset.generate"):
        open_dataset(root).scene(2)


def _cli(module: str, argv: list[str], capsys) -> str:
    """Run a CLI's ``main`` through ``run_cli`` in-process; return its stderr after asserting a non-zero exit."""
    main = __import__(module, fromlist=["main"]).main
    code = run_cli(main, argv)
    err = capsys.readouterr().err.strip()
    assert code != 0, err
    return err


def test_flip_fails_ap_stats_and_every_trainer_in_one_line(damaged, tmp_path, capsys):
    runs = {
        "eval.ap": ["--policy", "random", "--data", str(damaged), "--quiet"],
        "dataset.stats": [str(damaged), "--out", str(tmp_path / "stats.png")],
        "policies.cao.train": ["--data", str(damaged), "--out", str(tmp_path / "cao.pt"), "--epochs", "1",
                               "--input-height", "48", "--input-width", "64", "--widths", "4", "8", "--quiet"],
        "policies.dexnet.train": ["--data", str(damaged), "--out", str(tmp_path / "dexnet.pt"), "--epochs", "1",
                                  "--samples-per-epoch", "32", "--batch-size", "16", "--no-progress"],
        "policies.diffusion.train": ["--data", str(damaged), "--out", str(tmp_path / "diffusion"), "--preset", "tiny",
                                     "--num-points", "128", "--steps", "1", "--batch-size", "3",
                                     "--val-fraction", "0.34", "--no-progress", "--threads", "1", "--workers", "1"],
    }
    for module, argv in runs.items():
        err = _cli(module, argv, capsys)
        lines = [line for line in err.splitlines() if "warn" not in line.lower()]
        assert len(lines) == 1, (module, err)
        _assert_named(lines[0])


# ------------------------------------------------------------------------------------------- fail early, one line

UNWRITABLE = "/proc/parcelpick_x"  # /proc refuses new entries even to root, which passes os.access everywhere


def _one_line(err: str, *needles: str) -> None:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and all(n in lines[0] for n in needles), err


@pytest.fixture
def no_work(monkeypatch):
    """Make the expensive part of each CLI explode, so a passing check provably ran before any of it."""
    import dataset.generate
    import eval.clearance

    def boom(*_args, **_kwargs):
        raise AssertionError("expensive work started before the arguments were checked")

    monkeypatch.setattr(eval.clearance, "evaluate_clearance", boom)
    monkeypatch.setattr(dataset.generate, "generate", boom)


def test_clearance_checks_record_dir_and_checkpoint_before_any_pile(no_work, tmp_path, capsys):
    from eval.clearance import main

    assert run_cli(main, ["--policy", "random", "--record", UNWRITABLE]) == 2
    _one_line(capsys.readouterr().err, "--record", UNWRITABLE)
    missing = tmp_path / "missing.pt"
    assert run_cli(main, ["--policy", "dexnet", "--checkpoint", str(missing)]) == 2
    _one_line(capsys.readouterr().err, "--checkpoint", str(missing), "does not exist")
    dexnet_checkpoint = REPO / "policies" / "dexnet" / "checkpoint.pt"
    assert run_cli(main, ["--policy", "cao", "--checkpoint", str(dexnet_checkpoint)]) == 2
    _one_line(capsys.readouterr().err, str(dexnet_checkpoint), "not a Cao checkpoint")
    assert run_cli(main, ["--policy", "nope", "--out", str(tmp_path / "summary.json")]) == 2
    _one_line(capsys.readouterr().err, "unknown policy 'nope'")


def test_cao_given_dexnets_checkpoint_names_the_file():
    from policies.registry import make_policy

    path = REPO / "policies" / "dexnet" / "checkpoint.pt"
    with pytest.raises(ValueError, match=f"{path} is not a Cao checkpoint"):
        make_policy("cao", checkpoint=path)


def test_ap_checks_policy_checkpoint_and_output_first(real_data, tmp_path, capsys):
    from eval.ap import main

    for argv, needles in (
        (["--policy", "dexnet", "--checkpoint", str(tmp_path / "missing.pt")], ("--checkpoint", "missing.pt")),
        (["--policy", "random", "--out", f"{UNWRITABLE}/ap.json"], ("--out", UNWRITABLE)),
        (["--policy", "sb3", "--checkpoint", str(REPO / "policies" / "cao" / "checkpoint.pt")],
         ("--checkpoint", "checkpoint.pt", "not a parcelpick-sb3-ppo/1")),
    ):
        with pytest.raises(SystemExit) as exit_:
            main([*argv, "--data", str(real_data)])
        assert exit_.value.code == 2
        _one_line(capsys.readouterr().err, *needles)


def test_generate_stats_and_trainers_refuse_unwritable_outputs(no_work, real_data, capsys):
    runs = {
        "dataset.generate": ["--out", UNWRITABLE, "--scenes", "1"],
        "dataset.stats": [str(real_data), "--out", f"{UNWRITABLE}/stats.png"],
        "policies.cao.train": ["--data", str(real_data), "--out", f"{UNWRITABLE}/cao.pt"],
        "policies.dexnet.train": ["--data", str(real_data), "--out", f"{UNWRITABLE}/dexnet.pt"],
        "policies.diffusion.train": ["--data", str(real_data), "--out", UNWRITABLE],
        "policies.sb3.train": ["--out", f"{UNWRITABLE}/ppo.safetensors"],
    }
    for module, argv in runs.items():
        _one_line(_cli(module, argv, capsys), "--out", UNWRITABLE)
    _one_line(_cli("policies.cao.train", ["--data", "/nonexistent_data", "--out", "x.pt"], capsys),
              "--data", "/nonexistent_data")


def test_debug_flag_restores_the_traceback(capsys):
    from parcelpick_env.cli import UsageError, check_output_path

    def main(argv: list[str]) -> int:
        assert "--debug" not in argv  # run_cli consumes it
        check_output_path(UNWRITABLE, "--record", directory=True)
        return 0

    assert run_cli(main, []) == 2
    _one_line(capsys.readouterr().err, "--record")
    with pytest.raises(UsageError, match="--record"):
        run_cli(main, ["--debug"])


def test_argparse_errors_are_one_line_too(capsys):
    """An unknown flag or a value argparse refuses: its one error line, not the usage block."""
    from dataset.generate import main as generate_main

    for argv in (["--out", "x", "--bogus"], ["--out", "x", "--scenes", "many"]):
        with pytest.raises(SystemExit) as exit_info:
            run_cli(generate_main, argv)
        assert exit_info.value.code == 2
        _one_line(capsys.readouterr().err, argv[-1])


def test_clearance_script_prints_one_line_and_exits_nonzero():
    run = subprocess.run([sys.executable, "-m", "eval.clearance", "--policy", "dexnet", "--checkpoint", "missing.pt"],
                         cwd=REPO, capture_output=True, text=True, timeout=120, check=False)
    assert run.returncode == 2 and run.stdout == ""
    _one_line("\n".join(line for line in run.stderr.splitlines() if not line.startswith("pybullet build")),
              "missing.pt")


def test_pool_workers_leave_no_simulator_temp_dirs(tmp_path, monkeypatch):
    """``--workers 2``: each spawned worker's cached simulator removes its OBJ directory when the worker exits."""
    scratch = tmp_path / "tmp"
    scratch.mkdir()
    monkeypatch.setenv("TMPDIR", str(scratch))  # read afresh by each spawned worker's tempfile module
    config = GenerationConfig(scenes=2, split="test", seed=3, min_parcels=2, max_parcels=2, width=160, height=120,
                              annotation_points=128, scenes_per_shard=1, object_set="rectangular")
    report = generate(tmp_path / "data", config, workers=2, progress=False)
    assert report.scenes_generated == 2
    assert not list(scratch.glob("parcelpick_sim_*"))


# ------------------------------------------------------------------------------------------- env and configs

def _box_env(**kwargs):
    from parcelpick_env.camera.config import CameraConfig
    from parcelpick_env.envs.custom_scene import BoxScene, PlacedBox
    from parcelpick_env.envs.parcel_pick import ParcelPickEnv

    return ParcelPickEnv(scene_factory=BoxScene([PlacedBox((0.30, 0.20, 0.10), 0.5)]),
                         camera=CameraConfig(width=160, height=120), num_points=256, **kwargs)


def test_coerced_actions_are_invalid_and_step_after_close_is_a_clear_error():
    env = _box_env(max_consecutive_failures=10)
    try:
        env.reset(seed=0)
        top = [0.0, 0.0, 0.1, 0.0, 0.0, 1.0]  # above the box, pointing up: a real pick if executed
        for action in (["0.0", "0.0", "0.1", "0", "0", "1"], np.array(top, dtype=complex),
                       [False, False, True, False, False, True], np.array(top, dtype=bool),
                       (0.0, 0.0, 0.1, 0.0, 0.0, True), np.array(top, dtype=object).astype(str), "0.1"):
            _, reward, _, _, info = env.step(action)
            assert info["outcome"] == "invalid_action" and "not numeric" in info["invalid_reason"], action
            assert reward == 0.0
        _, _, _, _, info = env.step([0, 0, 0.1, 0, 0, 1])  # plain ints are numbers: executed as a pick
        assert info["outcome"] != "invalid_action"
    finally:
        env.close()
    with pytest.raises(RuntimeError, match="env is closed: step\\(\\) after close\\(\\)"):
        env.step(np.array(top, np.float32))


def test_configs_refuse_inf_strings_huge_cameras_and_bad_record_dirs():
    from parcelpick_env.camera.config import CameraConfig
    from parcelpick_env.envs.config import EnvConfig
    from parcelpick_env.suction.config import SuctionConfig

    for kwargs, match in (({"cup_radius": float("inf")}, "SuctionConfig: cup_radius"),
                          ({"cup_radius": "a"}, "SuctionConfig: cup_radius .* got 'a'"),
                          ({"tool_far": float("nan")}, "SuctionConfig: tool_far")):
        with pytest.raises(ValueError, match=match):
            SuctionConfig(**kwargs)
    with pytest.raises(ValueError, match="CameraConfig: width must be an int in \\[8, 4096\\], got 100000"):
        CameraConfig(width=100000, height=100000)
    with pytest.raises(ValueError, match="CameraConfig: height"):
        CameraConfig(height=100000)
    with pytest.raises(ValueError, match="EnvConfig: record_dir .* got 123"):
        EnvConfig(record_dir=123)
    assert EnvConfig(record_dir=Path("/tmp/replays")).record_dir == Path("/tmp/replays")
