"""A Kinova Gen3 7-DoF URDF with a suction tool, written from Kinova's published figures.

No registry ships a bare Gen3 URDF, so the kinematics come from Kinova's GEN3_URDF_V12 (the figures
below; the cell's moves: docs/cell.md) and every link is a capsule along the segment to the next joint.
The tool is a flange, a rod and a cup; ``tool_tip`` sits at the cup lip, centred on the cup axis, with
+z pointing out of the cup (the approach direction), so a suction candidate (p, n) is reached with the
tip at p and z = -n.

``python -m parcelpick_env.robot.gen3`` regenerates the committed ``gen3_suction.urdf``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from parcelpick_env.suction.config import CELL_CUP_RADIUS

URDF_PATH = Path(__file__).with_name("gen3_suction.urdf")

PI = math.pi
# (name, parent->child xyz, roll, type, lower, upper, effort N m); velocity limit is shared.
# Continuous joints get +-2 pi: unlimited on the robot, finite here so IK and interpolation stay sane.
TWO_PI = 2 * math.pi
JOINTS: tuple[tuple[str, tuple[float, float, float], float, str, float, float, float], ...] = (
    ("joint_1", (0.0, 0.0, 0.15643), PI, "continuous", -TWO_PI, TWO_PI, 39.0),
    ("joint_2", (0.0, 0.005375, -0.12838), PI / 2, "revolute", -2.41, 2.41, 39.0),
    ("joint_3", (0.0, -0.21038, -0.006375), -PI / 2, "continuous", -TWO_PI, TWO_PI, 39.0),
    ("joint_4", (0.0, 0.006375, -0.21038), PI / 2, "revolute", -2.66, 2.66, 39.0),
    ("joint_5", (0.0, -0.20843, -0.006375), -PI / 2, "continuous", -TWO_PI, TWO_PI, 9.0),
    ("joint_6", (0.0, 0.00017505, -0.10593), PI / 2, "revolute", -2.23, 2.23, 9.0),
    ("joint_7", (0.0, -0.10593, -0.00017505), -PI / 2, "continuous", -TWO_PI, TWO_PI, 9.0),
)
# rad: the table's joint limits as arrays (read only), for the kinematics' own IK without a pybullet arm
JOINT_LOWER, JOINT_UPPER = (np.array([j[k] for j in JOINTS]) for k in (4, 5))
JOINT_LOWER.flags.writeable = JOINT_UPPER.flags.writeable = False
EE_OFFSET = (0.0, 0.0, -0.061525)  # bracelet -> end effector, roll pi
LINKS = ("base_link", "shoulder_link", "half_arm_1_link", "half_arm_2_link", "forearm_link",
         "spherical_wrist_1_link", "spherical_wrist_2_link", "bracelet_link")
MASSES = (1.697, 1.3773, 1.1636, 1.1636, 0.9302, 0.6781, 0.6781, 0.5006)
RADII = (0.055, 0.048, 0.045, 0.045, 0.042, 0.038, 0.038, 0.035)
VELOCITY_LIMIT = 0.8727  # rad/s, every joint (V12)


@dataclass(frozen=True)
class SuctionToolSpec:
    """The tool on the flange. The cup radius matches the env's default cup (EnvConfig.suction)."""

    flange_radius: float = 0.035
    flange_length: float = 0.012
    rod_radius: float = 0.008
    rod_length: float = 0.14
    cup_radius: float = CELL_CUP_RADIUS
    cup_length: float = 0.015
    mass: float = 0.25

    def __post_init__(self) -> None:
        for name in ("flange_radius", "flange_length", "rod_radius", "rod_length", "cup_radius",
                     "cup_length", "mass"):
            if not getattr(self, name) > 0:
                raise ValueError(f"SuctionToolSpec.{name} must be > 0")

    @property
    def length(self) -> float:
        """End-effector frame to cup lip along the tool axis."""
        return self.flange_length + self.rod_length + self.cup_length


def _f(v: float) -> str:
    return f"{v:.6g}"


def _inertial(mass: float, radius: float, length: float, xyz, rpy) -> str:
    """A solid cylinder's inertia about its centre; close enough for capsule links."""
    ixx = mass * (3 * radius**2 + length**2) / 12.0
    izz = mass * radius**2 / 2.0
    return (f'    <inertial><origin xyz="{" ".join(map(_f, xyz))}" rpy="{" ".join(map(_f, rpy))}"/>'
            f'<mass value="{_f(mass)}"/>'
            f'<inertia ixx="{_f(ixx)}" ixy="0" ixz="0" iyy="{_f(ixx)}" iyz="0" izz="{_f(izz)}"/></inertial>\n')


def _capsule_link(name: str, mass: float, radius: float, segment: np.ndarray, rgba: str) -> str:
    """A capsule from the link origin to ``segment`` (the next joint origin, in this link's frame)."""
    length = float(np.linalg.norm(segment))
    centre = segment / 2.0
    direction = segment / max(length, 1e-9)
    rot, _ = Rotation.align_vectors([direction], [[0.0, 0.0, 1.0]])
    rpy = rot.as_euler("xyz")  # URDF rpy: fixed-axis roll, pitch, yaw
    xyz = " ".join(map(_f, centre))
    rpy_s = " ".join(map(_f, rpy))
    body = max(length - radius, 0.02)  # capsule cylinder part; the caps round off the joints
    geom = f'<capsule radius="{_f(radius)}" length="{_f(body)}"/>'
    return (f'  <link name="{name}">\n'
            + _inertial(mass, radius, length, centre, rpy)
            + f'    <visual><origin xyz="{xyz}" rpy="{rpy_s}"/><geometry>{geom}</geometry>'
            f'<material name="{name}_mat"><color rgba="{rgba}"/></material></visual>\n'
            f'    <collision><origin xyz="{xyz}" rpy="{rpy_s}"/><geometry>{geom}</geometry></collision>\n'
            '  </link>\n')


def _cylinder_link(name: str, mass: float, radius: float, length: float, z0: float, rgba: str) -> str:
    """A cylinder along +z from z0 to z0 + length in the link frame."""
    xyz = f"0 0 {_f(z0 + length / 2)}"
    geom = f'<cylinder radius="{_f(radius)}" length="{_f(length)}"/>'
    return (f'  <link name="{name}">\n'
            + _inertial(mass, radius, length, (0, 0, z0 + length / 2), (0, 0, 0))
            + f'    <visual><origin xyz="{xyz}"/><geometry>{geom}</geometry>'
            f'<material name="{name}_mat"><color rgba="{rgba}"/></material></visual>\n'
            f'    <collision><origin xyz="{xyz}"/><geometry>{geom}</geometry></collision>\n'
            '  </link>\n')


def _frame_link(name: str) -> str:
    """A massless-in-effect frame (pybullet would give an inertia-less link 1 kg)."""
    return (f'  <link name="{name}"><inertial><mass value="0.001"/>'
            '<inertia ixx="1e-7" ixy="0" ixz="0" iyy="1e-7" iyz="0" izz="1e-7"/></inertial></link>\n')


def _joint(name: str, jtype: str, parent: str, child: str, xyz, rpy, limits=None) -> str:
    s = (f'  <joint name="{name}" type="{"revolute" if jtype == "continuous" else jtype}">\n'
         f'    <parent link="{parent}"/><child link="{child}"/>\n'
         f'    <origin xyz="{" ".join(map(_f, xyz))}" rpy="{" ".join(map(_f, rpy))}"/>\n')
    if jtype != "fixed":
        lower, upper, effort = limits
        s += (f'    <axis xyz="0 0 1"/>\n'
              f'    <limit lower="{_f(lower)}" upper="{_f(upper)}" effort="{_f(effort)}" '
              f'velocity="{_f(VELOCITY_LIMIT)}"/>\n'
              '    <dynamics damping="0.1" friction="0.0"/>\n')
    return s + "  </joint>\n"


def gen3_suction_urdf(tool: SuctionToolSpec = SuctionToolSpec()) -> str:
    """The URDF text. Continuous joints are written as revolute +-2 pi so IK respects a finite range."""
    grey, dark, black = "0.75 0.75 0.78 1", "0.25 0.25 0.28 1", "0.1 0.1 0.1 1"
    parts = ['<?xml version="1.0"?>\n<robot name="kinova_gen3_suction">\n']
    offsets = [np.array(j[1]) for j in JOINTS] + [np.array(EE_OFFSET)]
    for i, link in enumerate(LINKS):
        parts.append(_capsule_link(link, MASSES[i], RADII[i], offsets[i], grey if i % 2 else dark))
    for i, (name, xyz, roll, jtype, lower, upper, effort) in enumerate(JOINTS):
        parts.append(_joint(name, jtype, LINKS[i], LINKS[i + 1], xyz, (roll, 0, 0), (lower, upper, effort)))
    # end effector frame (bracelet -> EE, roll pi), then flange, rod and cup stacked along its +z
    parts.append(_frame_link("end_effector_link"))
    parts.append(_joint("end_effector", "fixed", LINKS[-1], "end_effector_link", EE_OFFSET, (PI, 0, 0)))
    m = tool.mass
    parts.append(_cylinder_link("tool_flange", 0.6 * m, tool.flange_radius, tool.flange_length, 0.0, black))
    parts.append(_joint("tool_flange_joint", "fixed", "end_effector_link", "tool_flange", (0, 0, 0), (0, 0, 0)))
    parts.append(_cylinder_link("tool_rod", 0.3 * m, tool.rod_radius, tool.rod_length, 0.0, grey))
    parts.append(_joint("tool_rod_joint", "fixed", "tool_flange", "tool_rod", (0, 0, tool.flange_length), (0, 0, 0)))
    parts.append(_cylinder_link("suction_cup", 0.1 * m, tool.cup_radius, tool.cup_length, 0.0, "0.9 0.5 0.1 1"))
    parts.append(_joint("suction_cup_joint", "fixed", "tool_rod", "suction_cup", (0, 0, tool.rod_length), (0, 0, 0)))
    parts.append(_frame_link("tool_tip"))
    parts.append(_joint("tool_tip_joint", "fixed", "suction_cup", "tool_tip", (0, 0, tool.cup_length), (0, 0, 0)))
    parts.append("</robot>\n")
    return "".join(parts)


def write_urdf(path: Path | str = URDF_PATH, tool: SuctionToolSpec = SuctionToolSpec()) -> Path:
    path = Path(path)
    path.write_text(gen3_suction_urdf(tool))
    return path


if __name__ == "__main__":
    print(write_urdf())
