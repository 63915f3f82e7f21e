"""Policy registry: names -> Policy classes, imported lazily so a missing optional policy never breaks the others."""

from __future__ import annotations

import importlib
from typing import Any, Callable, TypeVar

from policies.base import Policy

# name -> "module.path:ClassName"; import happens only in make_policy
_LAZY: dict[str, str] = {
    "diffusion": "policies.diffusion.policy:DiffusionSuctionPolicy",
    "diffusion_vote": "policies.diffusion.vote_policy:DiffusionCentreVotePolicy",  # + centre votes (not in the paper)
    "diffusion_hold": "policies.hold.policy:DiffusionHoldPolicy",  # + the learnt hold check (not in the paper)
    "diffusion_vote_hold": "policies.hold.vote_policy:DiffusionVoteHoldPolicy",  # + both (not in the paper)
    "normal_std": "policies.normal_std:NormalStdPolicy",
    "dexnet": "policies.dexnet.policy:DexNetPolicy",
    "cao": "policies.cao.policy:CaoPolicy",
    "random": "policies.random_policy:RandomPolicy",
    "sb3": "policies.sb3.policy:SB3Policy",
    "oracle": "policies.oracle:OraclePolicy",  # privileged upper bound (reads obs_mode='state_dict')
}
# The only policies allowed to declare a privileged obs_mode (ground truth): a ceiling, not a method.
PRIVILEGED_POLICIES: tuple[str, ...] = ("oracle",)
_CLASSES: dict[str, type[Policy]] = {}

P = TypeVar("P", bound=type[Policy])


def register_policy(name: str) -> Callable[[P], P]:
    """Class decorator: ``@register_policy("mine") class Mine(Policy): ...``."""
    if not name or not isinstance(name, str):
        raise ValueError(f"policy name must be a non-empty string, got {name!r}")

    def wrap(cls: P) -> P:
        if not (isinstance(cls, type) and issubclass(cls, Policy)):
            raise TypeError(f"{cls!r} is not a Policy subclass")
        _check_obs_mode(name, cls)
        _CLASSES[name] = cls
        return cls

    return wrap


def obs_mode_of(policy: Policy | type[Policy]) -> str:
    """The env ``obs_mode`` a policy needs: its ``obs_mode`` attribute, ``"pointcloud"`` when it declares none."""
    return str(getattr(policy, "obs_mode", "pointcloud"))


def _check_obs_mode(name: str, cls: type[Policy]) -> None:
    """Only PRIVILEGED_POLICIES may read the privileged channel; every policy must name a real mode."""
    from parcelpick_env.envs.config import OBS_MODES
    from parcelpick_env.envs.observation import PRIVILEGED_MODES

    mode = obs_mode_of(cls)
    if mode not in OBS_MODES:
        raise ValueError(f"policy {name!r} declares obs_mode {mode!r}; choose one of {OBS_MODES}")
    if mode in PRIVILEGED_MODES and name not in PRIVILEGED_POLICIES:
        raise ValueError(f"policy {name!r} declares the privileged obs_mode {mode!r}, which only "
                         f"{PRIVILEGED_POLICIES} may read (ground truth is not a policy input)")


def register_lazy(name: str, target: str) -> None:
    """Register ``"module.path:ClassName"`` under ``name`` without importing it."""
    if ":" not in target:
        raise ValueError(f"target must look like 'module.path:ClassName', got {target!r}")
    _LAZY[name] = target


def available_policies() -> list[str]:
    return sorted(set(_LAZY) | set(_CLASSES))


def _resolve(name: str) -> type[Policy]:
    if name in _CLASSES:
        return _CLASSES[name]
    if name not in _LAZY:
        raise ValueError(f"unknown policy {name!r}; choose one of {available_policies()}")
    module_name, _, attr = _LAZY[name].partition(":")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as e:
        if e.name and (module_name == e.name or module_name.startswith(e.name + ".")):
            raise NotImplementedError(f"policy {name!r} is not implemented yet (module {module_name} not found)") from e
        raise ImportError(f"policy {name!r}: importing {module_name} failed: {e}") from e
    cls = getattr(module, attr, None)
    if cls is None:
        raise NotImplementedError(f"policy {name!r} is not implemented yet ({module_name} has no {attr})")
    if not (isinstance(cls, type) and issubclass(cls, Policy)):
        raise TypeError(f"policy {name!r}: {module_name}:{attr} is not a Policy subclass")
    _check_obs_mode(name, cls)
    _CLASSES[name] = cls
    return cls


def policy_class(name: str) -> type[Policy]:
    """The class registered as ``name`` (imported now), without making a policy: ValueError if unknown."""
    return _resolve(name)


def make_policy(name: str, **kwargs: Any) -> Policy:
    """Instantiate a registered policy by name, e.g. ``make_policy("diffusion", checkpoint="runs/x/best.pt")``."""
    return _resolve(name)(**kwargs)
