"""The ParcelPick-v0 Gymnasium environment, its configuration, the physical pick and replays."""

from parcelpick_env.envs.config import EnvConfig, GraspConfig
from parcelpick_env.envs.grasp import CONDITIONS, OUTCOMES

__all__ = ["EnvConfig", "GraspConfig", "CONDITIONS", "OUTCOMES"]
