"""The PPO baseline's model file: safetensors weights plus a declared, data-only JSON spec. Nothing is unpickled.

stable-baselines3's own ``.zip`` stores the policy class, spaces and schedules as cloudpickle, so ``PPO.load``
runs whatever code a crafted file carries. Here the file is one ``.safetensors``: its tensors are the
``ActorCriticPolicy`` state dict, and its string metadata holds ``format`` and ``spec`` (``PPOSpec`` as JSON).
Loading parses that JSON into the dataclass (unknown keys and bad values refused), builds the policy
from it with SB3's own classes, and loads the tensors strictly, so a file that does not fit is refused with
an error naming it. A trusted SB3 zip is turned into this format once with ``python -m policies.sb3.convert``.
"""

from __future__ import annotations

import json
import math
import os
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from torch import nn

from parcelpick_env.config_checks import (
    config_from_dict,
    config_to_dict,
    require,
    require_choice,
    require_int,
)
from policies.checkpoint_io import load_weights

FORMAT = "parcelpick-sb3-ppo/1"
CONVERT_COMMAND = "python -m policies.sb3.convert"
# The only activations a spec may name: a name maps to a class here, never to an import.
ACTIVATIONS: dict[str, type[nn.Module]] = {"tanh": nn.Tanh, "relu": nn.ReLU, "elu": nn.ELU,
                                           "leaky_relu": nn.LeakyReLU}


@dataclass(frozen=True)
class PPOSpec:
    """Everything needed to rebuild an SB3 ``MlpPolicy`` (``ActorCriticPolicy``) for Box -> Box, as plain data."""

    observation_shape: tuple[int, ...]
    observation_low: float
    observation_high: float
    action_shape: tuple[int, ...]
    action_low: float
    action_high: float
    net_arch_pi: tuple[int, ...] = (64, 64)
    net_arch_vf: tuple[int, ...] = (64, 64)
    activation: str = "tanh"
    log_std_init: float = 0.0
    ortho_init: bool = True

    def __post_init__(self) -> None:
        owner = type(self).__name__
        for name in ("observation_shape", "action_shape", "net_arch_pi", "net_arch_vf"):
            value = getattr(self, name)
            require(isinstance(value, tuple) and len(value) >= (0 if name.startswith("net") else 1), owner,
                    f"{name} must be a list of ints, got {value!r}")
            for size in value:
                require_int(owner, name, size, lo=1, hi=1 << 20)
        for name in ("observation_low", "observation_high", "action_low", "action_high", "log_std_init"):
            value = getattr(self, name)
            require(isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value),
                    owner, f"{name} must be a finite number, got {value!r}")
        require(self.observation_low < self.observation_high and self.action_low < self.action_high, owner,
                "observation_low/action_low must be below observation_high/action_high")
        require_choice(owner, "activation", self.activation, tuple(ACTIVATIONS))
        require(isinstance(self.ortho_init, bool), owner, f"ortho_init must be a bool, got {self.ortho_init!r}")


def _uniform_bound(values: np.ndarray, what: str) -> float:
    if not np.all(values == values.flat[0]):
        raise ValueError(f"{what} must be the same for every element to be stored in a PPOSpec")
    return float(values.flat[0])


def spec_from_policy(policy: Any) -> PPOSpec:
    """The spec of a live SB3 policy; ValueError for anything this format does not describe (SDE, custom parts)."""
    from gymnasium import spaces
    from stable_baselines3.common.policies import ActorCriticPolicy
    from stable_baselines3.common.torch_layers import FlattenExtractor

    params = policy._get_constructor_parameters()
    obs, act = policy.observation_space, policy.action_space
    activation = {cls: name for name, cls in ACTIVATIONS.items()}.get(params["activation_fn"])
    net_arch = params["net_arch"]
    if isinstance(net_arch, list):  # SB3's shorthand: the same layers for policy and value
        net_arch = {"pi": net_arch, "vf": net_arch}
    problems = [text for bad, text in (
        (type(policy) is not ActorCriticPolicy, f"policy class {type(policy).__name__} (need ActorCriticPolicy)"),
        (not (isinstance(obs, spaces.Box) and isinstance(act, spaces.Box)), "non-Box spaces"),
        (params.get("use_sde", False), "gSDE exploration"),
        (params["features_extractor_class"] is not FlattenExtractor or params["features_extractor_kwargs"],
         "a custom features extractor"),
        (not policy.share_features_extractor, "separate policy/value feature extractors"),
        (activation is None, f"activation {params['activation_fn']}"),
    ) if bad]
    if problems:
        raise ValueError(f"this SB3 policy cannot be stored as a {FORMAT} model: {', '.join(problems)}")
    assert activation is not None  # listed among the problems otherwise
    return PPOSpec(
        observation_shape=tuple(int(s) for s in obs.shape),
        observation_low=_uniform_bound(obs.low, "observation_space.low"),
        observation_high=_uniform_bound(obs.high, "observation_space.high"),
        action_shape=tuple(int(s) for s in act.shape),
        action_low=_uniform_bound(act.low, "action_space.low"),
        action_high=_uniform_bound(act.high, "action_space.high"),
        net_arch_pi=tuple(int(n) for n in net_arch["pi"]), net_arch_vf=tuple(int(n) for n in net_arch["vf"]),
        activation=activation, log_std_init=float(params["log_std_init"]), ortho_init=bool(params["ortho_init"]))


def build_policy(spec: PPOSpec) -> Any:
    """A fresh SB3 ``ActorCriticPolicy`` with the spec's spaces and layers (random weights), on the CPU."""
    from gymnasium import spaces
    from stable_baselines3.common.policies import ActorCriticPolicy

    obs = spaces.Box(spec.observation_low, spec.observation_high, spec.observation_shape, np.float32)
    act = spaces.Box(spec.action_low, spec.action_high, spec.action_shape, np.float32)
    return ActorCriticPolicy(obs, act, lr_schedule=lambda _: 0.0,
                             net_arch={"pi": list(spec.net_arch_pi), "vf": list(spec.net_arch_vf)},
                             activation_fn=ACTIVATIONS[spec.activation], log_std_init=spec.log_std_init,
                             ortho_init=spec.ortho_init)


def save_model(policy: Any, path: str | os.PathLike, extra: dict[str, str] | None = None) -> Path:
    """Write ``policy`` (an SB3 ActorCriticPolicy) as ``path`` (.safetensors), atomically."""
    from safetensors.torch import save_file

    path = Path(path)
    spec = spec_from_policy(policy)
    tensors = {k: v.detach().cpu().contiguous() for k, v in policy.state_dict().items()}
    metadata = {**(extra or {}), "format": FORMAT, "spec": json.dumps(config_to_dict(spec), sort_keys=True)}
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    save_file(tensors, str(tmp), metadata=metadata)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)  # safetensors creates 0600 files; a model is as readable as any other output
    os.replace(tmp, path)
    return path


def load_model(path: str | os.PathLike, train_command: str) -> tuple[Any, PPOSpec]:
    """The policy stored at ``path`` and its spec. FileNotFoundError (naming ``train_command``) when missing;
    ValueError naming the file when it is an SB3 zip (pickled, refused unread), not safetensors, lacks
    or has a bad spec, or holds weights that do not fit the spec."""
    from safetensors import safe_open

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no PPO model at {path}; train one with `{train_command}`")
    if zipfile.is_zipfile(path):  # reading the member names unpickles nothing
        with zipfile.ZipFile(path) as archive:
            names = archive.namelist()
        if "data" in names:
            raise ValueError(f"{path} is a stable-baselines3 .zip, whose loader unpickles (runs) code from it: "
                             f"refused. If you trust it, convert it once with `{CONVERT_COMMAND} {path}`")
        raise ValueError(f"{path} is a zip archive (a torch checkpoint?), not a {FORMAT} safetensors model")
    try:
        with safe_open(str(path), framework="pt", device="cpu") as handle:
            metadata = handle.metadata() or {}
            tensors = {key: handle.get_tensor(key) for key in handle.keys()}  # noqa: SIM118  (safe_open is not a Mapping)
    except Exception as exc:  # safetensors raises its own error types for foreign or truncated files
        raise ValueError(f"{path} is not a {FORMAT} model (not a readable safetensors file: {exc})") from exc
    if metadata.get("format") != FORMAT:
        raise ValueError(f"{path} is not a {FORMAT} model (format tag {metadata.get('format')!r})")
    try:
        fields = json.loads(metadata["spec"])
        if not isinstance(fields, dict):
            raise TypeError(f"spec is a JSON {type(fields).__name__}, not an object")
        spec = config_from_dict(PPOSpec, fields)
    except (KeyError, TypeError, ValueError) as exc:  # JSONDecodeError is a ValueError
        raise ValueError(f"{path}: bad or missing PPO spec: {exc}") from exc
    policy = load_weights(build_policy(spec), tensors, path, "PPO")
    return policy.eval(), spec
