"""The PPO baseline's training command runs end to end and its model drives the sb3 policy."""

import json
import zipfile

import numpy as np
import pytest
from safetensors import safe_open

from policies.sb3.model_io import FORMAT
from policies.sb3.policy import DEFAULT_MODEL, SB3Policy
from policies.sb3.train import main


def test_training_command_writes_a_model_the_policy_loads_and_a_reward_log(tmp_path):
    out = tmp_path / "ppo.safetensors"
    main(["--timesteps", "16", "--n-steps", "8", "--parcels", "1", "--seed", "0", "--out", str(out)])
    log = json.loads(out.with_suffix(".json").read_text())
    assert log["timesteps"] == 16 and sum(log["episode_lengths"]) <= 16
    assert log["command_args"]["out"] == str(out)  # outside the repository: the path as given
    assert all(0 <= r <= 1 for r in log["episode_rewards"])  # one parcel: at most one delivery per episode
    assert not zipfile.is_zipfile(out)  # data-only safetensors, never SB3's pickled zip
    with safe_open(str(out), framework="pt") as handle:
        assert handle.metadata()["format"] == FORMAT
    assert SB3Policy(checkpoint=out).model.observation_space.shape == (12 * 16,)


def test_training_command_rejects_bad_arguments(tmp_path):
    with pytest.raises(SystemExit):
        main(["--timesteps", "0", "--out", str(tmp_path / "x.zip")])


@pytest.mark.skipif(not DEFAULT_MODEL.is_file(), reason="no shipped PPO model")
def test_shipped_model_is_small_and_has_its_training_log():
    assert DEFAULT_MODEL.stat().st_size < 1_000_000
    log = json.loads(DEFAULT_MODEL.with_suffix(".json").read_text())
    assert log["command_args"]["seed"] == 0 and log["timesteps"] >= 2000
    assert log["command_args"]["out"] == "policies/sb3/ppo_pixel.safetensors"  # inside it: the repository's path
    policy = SB3Policy()  # the shipped model loads through the data-only path and gives in-range pixels
    actions, _ = policy.model.predict(np.random.default_rng(0).uniform(0, 1, (16, 12 * 16)).astype(np.float32),
                                      deterministic=True)
    assert actions.shape == (16, 2) and np.all(np.abs(actions) <= 1.0)
