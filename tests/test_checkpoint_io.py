"""The checkpoint I/O every learned policy shares: atomic saves and clear errors for bad files."""

import pytest
import torch
from torch import nn

from policies.checkpoint_io import load_weights, read_checkpoint, save_atomic


def test_save_is_atomic_and_reads_back(tmp_path):
    path = save_atomic({"format": "x", "state_dict": nn.Linear(2, 3).state_dict()}, tmp_path / "sub" / "m.pt")
    assert path.is_file() and not list(path.parent.glob("*.tmp"))
    payload = read_checkpoint(path, "Test", "make it", format_tag="x", required=("state_dict",))
    assert load_weights(nn.Linear(2, 3), payload["state_dict"], path, "Test").weight.shape == (3, 2)


def test_every_kind_of_bad_file_names_itself(tmp_path):
    with pytest.raises(FileNotFoundError, match="gone.pt.*train me"):
        read_checkpoint(tmp_path / "gone.pt", "Test", "train me")
    (tmp_path / "junk.pt").write_bytes(b"\x00garbage")
    with pytest.raises(ValueError, match="junk.pt is corrupt"):
        read_checkpoint(tmp_path / "junk.pt", "Test", "-")
    torch.save([1, 2], tmp_path / "list.pt")
    with pytest.raises(ValueError, match="list.pt.*not a dict"):
        read_checkpoint(tmp_path / "list.pt", "Test", "-")
    torch.save({"format": "other"}, tmp_path / "foreign.pt")
    with pytest.raises(ValueError, match="not a Test checkpoint"):
        read_checkpoint(tmp_path / "foreign.pt", "Test", "-", format_tag="mine")
    with pytest.raises(ValueError, match=r"lacks \['config'\]"):
        read_checkpoint(tmp_path / "foreign.pt", "Test", "-", required=("format", "config"))
    with pytest.raises(ValueError, match="m.pt: weights do not match"):
        load_weights(nn.Linear(2, 4), nn.Linear(2, 3).state_dict(), tmp_path / "m.pt", "Test")
    with pytest.raises(ValueError, match="missing"):
        load_weights(nn.Linear(2, 3), {"weight": torch.zeros(3, 2)}, tmp_path / "m.pt", "Test")
