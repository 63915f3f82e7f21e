"""The Kinova Gen3 7-DoF arm with a suction tool: URDF from Kinova's figures, kinematics and IK,
jerk-limited timing (ruckig), collision-free planning (OMPL) and driven execution."""

from parcelpick_env.robot.arm import ArmConfig, Gen3Arm, reachability
from parcelpick_env.robot.gen3 import URDF_PATH, SuctionToolSpec, gen3_suction_urdf
from parcelpick_env.robot.planning import (
           Attachment,
           Collision,
           MotionPlanner,
           PlannerConfig,
)
from parcelpick_env.robot.timing import (
           GEN3_LIMITS,
           JointLimits,
           Trajectory,
           joint_trajectory,
           path_trajectory,
)

__all__ = ["GEN3_LIMITS", "URDF_PATH", "ArmConfig", "Attachment", "Collision", "Gen3Arm", "JointLimits",
           "MotionPlanner", "PlannerConfig", "SuctionToolSpec", "Trajectory", "gen3_suction_urdf",
           "joint_trajectory", "path_trajectory", "reachability"]
