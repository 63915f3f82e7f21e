"""ParcelPick: suction bin-picking of parcels in pybullet. Importing registers ``ParcelPick-v0``.

Kept light: only gymnasium's registry is touched here; the env and pybullet load on ``gym.make``.
"""

from gymnasium.envs.registration import register, registry

ENV_ID = "ParcelPick-v0"

if ENV_ID not in registry:
    register(id=ENV_ID, entry_point="parcelpick_env.envs.parcel_pick:ParcelPickEnv")

__all__ = ["ENV_ID"]
