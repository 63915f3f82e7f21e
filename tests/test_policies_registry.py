"""The policy registry: names resolve lazily, unknown names and unimplemented policies fail clearly."""

from __future__ import annotations

import pytest

from policies import registry
from policies.base import Candidates, Policy


def test_all_paper_policies_are_listed():
    assert {"diffusion", "normal_std", "dexnet", "cao", "random", "sb3"} <= set(registry.available_policies())


def test_diffusion_resolves_to_its_class():
    from policies.diffusion.policy import DiffusionSuctionPolicy

    assert registry._resolve("diffusion") is DiffusionSuctionPolicy


def test_unknown_name_lists_choices():
    with pytest.raises(ValueError, match="unknown policy 'nope'.*diffusion"):
        registry.make_policy("nope")


def test_diffusion_without_checkpoint_file_is_a_clear_error(tmp_path):
    with pytest.raises(FileNotFoundError, match="absent.pt"):
        registry.make_policy("diffusion", checkpoint=tmp_path / "absent.pt")


def test_missing_module_is_not_implemented(monkeypatch):
    monkeypatch.setitem(registry._LAZY, "ghost", "policies.ghost_policy_xyz:GhostPolicy")
    with pytest.raises(NotImplementedError, match="ghost"):
        registry.make_policy("ghost")
    monkeypatch.setitem(registry._LAZY, "ghost2", "policies.base:NoSuchClass")
    with pytest.raises(NotImplementedError, match="NoSuchClass"):
        registry.make_policy("ghost2")


def test_register_policy_decorator(monkeypatch):
    monkeypatch.setattr(registry, "_CLASSES", dict(registry._CLASSES))

    @registry.register_policy("constant")
    class Constant(Policy):
        def __init__(self, value: float = 1.0):
            self.value = value

        def predict(self, obs, info=None, top_k=50):
            import numpy as np
            return Candidates(np.zeros((1, 3), np.float32), np.array([[0, 0, 1]], np.float32),
                              np.array([self.value], np.float32))

    p = registry.make_policy("constant", value=0.5)
    assert isinstance(p, Constant) and p.value == 0.5 and "constant" in registry.available_policies()
    with pytest.raises(TypeError):
        registry.register_policy("bad")(int)
