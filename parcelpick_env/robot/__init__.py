"""The Kinova Gen3 7-DoF arm with a suction tool: URDF from Kinova's figures, IK and motion."""

from parcelpick_env.robot.arm import ArmConfig, Gen3Arm, reachability
from parcelpick_env.robot.gen3 import URDF_PATH, SuctionToolSpec, gen3_suction_urdf

__all__ = ["ArmConfig", "Gen3Arm", "reachability", "URDF_PATH", "SuctionToolSpec", "gen3_suction_urdf"]
