"""The arm + gripper in the simulator: joint bookkeeping, joint-motor commands, gripper postures, pad contact.

All commands go through joint motors with the URDF's efforts (no teleporting after :meth:`Robot.reset_to`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from robotdemo.assets import ARM_JOINTS, GRIPPER_JOINTS, ROBOT_URDF, TOOL_FRAME, urdf_path
from robotdemo.errors import AssetError
from robotdemo.sim import ContactPoint, LinkState, Simulator

HOME_ARM_Q = np.array([0.0, -0.35, 1.9, 0.0, 1.15, 0.0])
"""A folded, collision-free start posture with the hand pointing down over the table (rad)."""


PROXIMAL_LENGTH_M = 0.05
PINCH_ZERO_WIDTH_M = 0.0239
"""Distance between the thumb's inner face and the other fingers' faces with the proximal joints at zero."""
GRASP_CENTER_IN_GRIPPER_M = np.array([0.00665, 0.0, 0.0])
"""Mid-point between the thumb's face and the fingers' faces, gripper_base frame (x, y); z depends on depth."""
PALM_HEIGHT_M = 0.05
DISTAL_AND_TIP_M = 0.07
"""Palm height, and distal segment + tip: with the proximal joint at a, the fingertip ends lie
PALM_HEIGHT_M + PROXIMAL_LENGTH_M cos(a) + DISTAL_AND_TIP_M from gripper_base along its z axis."""
MAX_GRASP_WIDTH_M = 0.088
"""Widest pinch: the proximal joints open to -0.7 rad (their limit), 23.9 mm + 100 mm x sin(0.7) = 88 mm."""
FINGER_OFFSET_M = 0.0266 * math.sin(math.radians(120.0))
"""The two fingers' centre lines stand this far (23 mm) either side of the thumb's: their bases sit on a
26.6 mm circle at 120 deg from the thumb's (urdf/generate.py)."""
FINGER_WIDTH_M = 0.02


def round_pinch_width(diameter_m: float) -> float:
    """Pinch width at first contact on an upright cylinder of ``diameter_m``, m.

    The thumb, on the pinch axis, touches the cylinder's side at the radius r; the two fingers, whose inner
    edges stand e = FINGER_OFFSET_M - FINGER_WIDTH_M / 2 (13 mm) off the axis, touch it at sqrt(r^2 - e^2). The
    pinch meets the cylinder at r + sqrt(r^2 - e^2), not 2 r: 46.4 mm for a 50 mm cylinder, 35.3 mm for 40 mm.
    """
    r = 0.5 * diameter_m
    e = FINGER_OFFSET_M - 0.5 * FINGER_WIDTH_M
    return r + math.sqrt(max(r * r - e * e, 0.0))


@dataclass(frozen=True)
class GripperPosture:
    """Joint targets of the three fingers (rad), in GRIPPER_JOINTS order: f0 j1, f0 j2, f1 j1, f1 j2, f2 j1, f2 j2."""

    q: tuple[float, ...]

    @staticmethod
    def stroke() -> "GripperPosture":
        """Thumb straight so its pad faces along the approach axis; the other two fingers folded up and away."""
        return GripperPosture((0.0, 0.0, -0.6, -0.8, -0.6, -0.8))

    @staticmethod
    def pinch_width(width_m: float) -> "GripperPosture":
        """Parallel pinch whose inner finger faces stand ``width_m`` apart (thumb face to the other two faces).

        Geometry (urdf/dg3f_lite/README.md): faces at x = 18.6 mm - L sin(a) (thumb) and -5.3 mm + L sin(a)
        (fingers) in the gripper frame with L = 50 mm the proximal length, so width = 23.9 mm - 2 L sin(a).
        """
        s = (PINCH_ZERO_WIDTH_M - width_m) / (2.0 * PROXIMAL_LENGTH_M)
        if not -1.0 <= s <= 1.0 or width_m > MAX_GRASP_WIDTH_M:
            raise ValueError(f"pinch width {width_m * 1000:.1f} mm is outside what the gripper can open to")
        return GripperPosture.pinch(float(np.arcsin(s)))

    @staticmethod
    def pinch(opening: float) -> "GripperPosture":
        """Parallel pinch: proximal joints at ``opening`` rad (negative opens), distal joints keep the tip segments
        parallel to the approach axis so the flat inner faces meet the object's sides."""
        return GripperPosture((opening, -opening) * 3)


@dataclass(frozen=True)
class RobotConfig:
    """Servo gains and the fingers' and pad's contact properties.

    Attributes:
        position_gain, velocity_gain, gripper_position_gain: PyBullet position-control gains.
        grasp_effort_nm: the gripper joints' torque limit while grasping, N m.
        pad_friction, finger_friction: Coulomb friction coefficients.
        finger_contact_stiffness_n_per_m: contact stiffness of the fingers and the pad (a silicone skin), N/m.
        finger_contact_damping: contact damping of the finger links, N s/m.
        pad_contact_damping: contact damping of the tactile pad, N s/m. PyBullet's contact force follows
            F = k pen + (c + k dt) v per point, so at the fingers' 200 N s/m the pad's touch-down speed, not the
            press, made most of the first contact's peak (8.8 N on a granite slab at a 0.66 N target, session 26).
            A silicone skin damps far less; 10 N s/m is within an estimated 10-50 N s/m for the whole pad.
    """

    position_gain: float = 0.3
    velocity_gain: float = 1.0
    gripper_position_gain: float = 0.05
    grasp_effort_nm: float = 1.5
    pad_friction: float = 1.0
    finger_friction: float = 1.2
    finger_contact_stiffness_n_per_m: float = 3.0e4
    finger_contact_damping: float = 200.0
    pad_contact_damping: float = 10.0


class Robot:
    """The RM65-B + DG-3F-lite model loaded in a :class:`Simulator`."""

    def __init__(self, sim: Simulator, base_position_m: Sequence[float] = (0, 0, 0), base_yaw_rad: float = 0.0,
                 config: RobotConfig = RobotConfig()) -> None:
        self.sim = sim
        self.config = config
        self.urdf = urdf_path(ROBOT_URDF)
        half = 0.5 * base_yaw_rad
        self.body = sim.load_urdf(self.urdf, position_m=base_position_m,
                                  orientation_xyzw=(0.0, 0.0, np.sin(half), np.cos(half)), fixed_base=True)
        self.joint_info = {j.name: j for j in sim.joints(self.body)}
        self.link_index = {j.link_name: j.index for j in self.joint_info.values()}
        missing = [n for n in ARM_JOINTS + GRIPPER_JOINTS if n not in self.joint_info]
        if missing or TOOL_FRAME not in self.link_index:
            raise AssetError(f"{self.urdf}: robot description lacks joints {missing} or frame {TOOL_FRAME!r}")
        self.arm_joints = [self.joint_info[n].index for n in ARM_JOINTS]
        self.gripper_joints = [self.joint_info[n].index for n in GRIPPER_JOINTS]
        self.arm_efforts = [self.joint_info[n].effort_nm for n in ARM_JOINTS]
        self.arm_speeds = [self.joint_info[n].velocity_radps for n in ARM_JOINTS]
        self.gripper_speeds = [self.joint_info[n].velocity_radps for n in GRIPPER_JOINTS]
        self.arm_lower = np.array([self.joint_info[n].lower_rad for n in ARM_JOINTS])
        self.arm_upper = np.array([self.joint_info[n].upper_rad for n in ARM_JOINTS])
        self.tool_link = self.link_index[TOOL_FRAME]
        self.pad_link = self.link_index["tactile_pad"]
        self.finger_links = [self.link_index[f"finger{f}_{s}"] for f in range(3) for s in ("proximal", "distal", "tip")]
        self.base_position_m = np.asarray(base_position_m, dtype=float)
        c, s_ = np.cos(base_yaw_rad), np.sin(base_yaw_rad)
        self.base_rotation = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]])
        """World orientation of the arm's base frame (a yaw about world z)."""
        for link in self.finger_links:
            sim.set_dynamics(self.body, link, lateralFriction=config.finger_friction,
                             contactStiffness=config.finger_contact_stiffness_n_per_m,
                             contactDamping=config.finger_contact_damping)
        sim.set_dynamics(self.body, self.pad_link, lateralFriction=config.pad_friction,
                         contactStiffness=config.finger_contact_stiffness_n_per_m,
                         contactDamping=config.pad_contact_damping)
        self.arm_target = HOME_ARM_Q.copy()
        self.arm_target_velocity_radps: np.ndarray | None = None
        """The last arm command's velocity (rad/s), ``None`` where the command gave none (an IK-tracked pose)."""
        self.arm_target_acceleration_radps2: np.ndarray | None = None
        """The last arm command's acceleration (rad/s^2) where the command gave one (a planned move)."""
        self.arm_command_time_s = sim.time_s
        """Simulated time at which the arm was last commanded, s."""
        self.gripper_target = np.array(GripperPosture.stroke().q)
        self.gripper_effort_nm = config.grasp_effort_nm
        self.reset_to(HOME_ARM_Q, GripperPosture.stroke())

    # -- state ------------------------------------------------------------------------------------------------
    def arm_q(self) -> np.ndarray:
        return self.sim.joint_positions(self.body, self.arm_joints)

    def arm_qd(self) -> np.ndarray:
        return self.sim.joint_velocities(self.body, self.arm_joints)

    def gripper_q(self) -> np.ndarray:
        return self.sim.joint_positions(self.body, self.gripper_joints)

    def tool_state(self) -> LinkState:
        return self.sim.link_state(self.body, self.tool_link)

    def pad_contacts(self, other: int | None = None) -> list[ContactPoint]:
        return self.sim.contact_points(self.body, other, link_a=self.pad_link)

    def finger_contacts(self, other: int) -> list[ContactPoint]:
        return [c for c in self.sim.contact_points(self.body, other) if c.link_a in self.finger_links]

    # -- commands ---------------------------------------------------------------------------------------------
    def reset_to(self, arm_q: Sequence[float], posture: GripperPosture) -> None:
        """Place the joints (initialisation only) and hold them there with the motors."""
        self.sim.reset_joints(self.body, self.arm_joints, arm_q)
        self.sim.reset_joints(self.body, self.gripper_joints, posture.q)
        self.command_arm(arm_q)
        self.command_gripper(posture)

    def command_arm(self, q: Sequence[float], qd: Sequence[float] | None = None,
                    qdd: Sequence[float] | None = None) -> None:
        """Joint-motor targets for the arm (rad, rad/s), clipped to the joint limits. ``qdd`` (rad/s^2), the
        planned acceleration at this sample, goes to no motor; it is kept with ``qd`` so that a move taking
        over from one cut short starts from where the command was heading (``ArmMotion.plan_path``)."""
        self.arm_target = np.clip(np.asarray(q, dtype=float), self.arm_lower, self.arm_upper)
        self.arm_target_velocity_radps = None if qd is None else np.asarray(qd, dtype=float)
        self.arm_target_acceleration_radps2 = None if qdd is None else np.asarray(qdd, dtype=float)
        self.arm_command_time_s = self.sim.time_s
        self.sim.position_control(self.body, self.arm_joints, self.arm_target, self.arm_efforts,
                                  self.arm_speeds, target_velocities=qd, position_gain=self.config.position_gain,
                                  velocity_gain=self.config.velocity_gain)

    def command_gripper(self, posture: GripperPosture, effort_nm: float | None = None) -> None:
        """Finger joint targets; ``effort_nm`` caps each finger's motors (the grasp force comes from this cap).

        The thumb opposes two fingers, so its motors get twice the cap: the squeeze is balanced and closing
        the hand does not drag the object towards one side.
        """
        self.gripper_target = np.asarray(posture.q, dtype=float)
        self.gripper_effort_nm = self.config.grasp_effort_nm if effort_nm is None else effort_nm
        caps = [2.0 * self.gripper_effort_nm] * 2 + [self.gripper_effort_nm] * 4
        self.sim.position_control(self.body, self.gripper_joints, self.gripper_target, caps, self.gripper_speeds,
                                  position_gain=self.config.gripper_position_gain, velocity_gain=1.0)


def hand_position_for_grasp(center_xy_m: Sequence[float], tip_height_m: float, opening_rad: float,
                            hand_rotation: np.ndarray) -> np.ndarray:
    """World position of ``gripper_base`` (hand pointing down) that puts the grasp centre over ``center_xy_m``
    with the fingertip ends at height ``tip_height_m`` (world z) for proximal joints at ``opening_rad``."""
    reach = PALM_HEIGHT_M + PROXIMAL_LENGTH_M * np.cos(opening_rad) + DISTAL_AND_TIP_M
    position = np.array([center_xy_m[0], center_xy_m[1], tip_height_m + reach])
    position[:2] -= (hand_rotation @ GRASP_CENTER_IN_GRIPPER_M)[:2]
    return position
