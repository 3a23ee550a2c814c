"""Arm motion in the simulator: IK in world coordinates and trajectories executed one control tick at a time.

The controllers work in the arm's base frame; this module turns world poses into base-frame targets, plans
with :mod:`controllers.trajectory` (Ruckig) and feeds the joint motors one control tick per :meth:`step`, so a
state machine can advance the whole robot tick by tick.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pinocchio as pin

from controllers.ik import IKConfig, IKResult, IKSolver
from controllers.kinematics import ArmKinematics
from controllers.trajectory import (CartesianLimits, JointMotionLimits, JointTrajectory, TrajectoryError,
                                    plan_cartesian_line, plan_joint_path, plan_joint_stop)
from robotdemo.assets import ARM_JOINTS, GRIPPER_JOINTS, TOOL_FRAME
from robotdemo.errors import RobotDemoError
from robotdemo.robot import GripperPosture, Robot

GRASP_FRAME = "gripper_base"
DOWN = np.diag([1.0, -1.0, -1.0])
"""A tool orientation with its z axis pointing down (world), x along world x."""


class UnreachableError(RobotDemoError):
    """A target pose is outside what the arm can reach."""


MOVING_RADPS = 1e-6
"""A commanded joint speed (rad/s) above which :meth:`ArmMotion.plan_path` counts the arm as still moving."""


@dataclass(frozen=True)
class MotionConfig:
    """Control-loop settings.

    Attributes:
        control_period_s: one control tick (IK + motor targets); a multiple of every physics step mode
            (see :class:`robotdemo.sim.SimConfig`).
        velocity_scale: fraction of the URDF joint speeds used by joint-space moves.
    """

    control_period_s: float = 0.004
    velocity_scale: float = 0.5


class ArmMotion:
    """IK for the pad (stroke posture) and the hand (grasping) in world coordinates, and move planning."""

    def __init__(self, robot: Robot, config: MotionConfig = MotionConfig()) -> None:
        self.robot = robot
        self.config = config
        sim_dt = robot.sim.config.time_step_s
        self.substeps = max(1, int(round(config.control_period_s / sim_dt)))
        """Fine physics steps per control tick (a stroke steps them one by one to record each)."""
        stroke_lock = dict(zip(GRIPPER_JOINTS, GripperPosture.stroke().q))
        self.pad_kin = ArmKinematics(robot.urdf, TOOL_FRAME, ARM_JOINTS, stroke_lock)
        self.hand_kin = ArmKinematics(robot.urdf, GRASP_FRAME, ARM_JOINTS)
        self.pad_ik = IKSolver(self.pad_kin, IKConfig())
        self.force_ik = IKSolver(self.pad_kin, IKConfig(position_tolerance_m=1e-7, orientation_tolerance_rad=1e-6))
        """Pad IK for force control: converged to 0.1 um. At the default 10 um tolerance a small change of the
        target returned the previous joints unchanged, so the pad moved in 10 um steps, which on a stiff
        object (1e5 N/m and more) are force steps of 1 N and more: the force loop chattered and never settled."""
        self.hand_ik = IKSolver(self.hand_kin, IKConfig())
        self.limits = JointMotionLimits.from_urdf_limits(self.pad_kin.lower_limits_rad, self.pad_kin.upper_limits_rad,
                                                         self.pad_kin.velocity_limits_radps, config.velocity_scale)
        self.last_move: JointMove | None = None
        """The planned move that gave the arm its last command (None before any)."""

    # -- frames -----------------------------------------------------------------------------------------------
    def to_base(self, position_w: np.ndarray, rotation_w: np.ndarray) -> pin.SE3:
        """World pose -> pose in the arm's base frame."""
        rb = self.robot.base_rotation
        return pin.SE3(rb.T @ rotation_w, rb.T @ (np.asarray(position_w, dtype=float) - self.robot.base_position_m))

    def to_world(self, oMf: pin.SE3) -> tuple[np.ndarray, np.ndarray]:
        rb = self.robot.base_rotation
        return rb @ oMf.translation + self.robot.base_position_m, rb @ oMf.rotation

    def pad_pose_world(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return self.to_world(self.pad_kin.fk_se3(q))

    # -- IK ---------------------------------------------------------------------------------------------------
    def solve_pad(self, position_w: np.ndarray, rotation_w: np.ndarray = DOWN, q: np.ndarray | None = None) -> IKResult:
        return self.pad_ik.solve(self.to_base(position_w, rotation_w), self.robot.arm_q() if q is None else q)

    def solve_hand(self, position_w: np.ndarray, rotation_w: np.ndarray = DOWN, q: np.ndarray | None = None) -> IKResult:
        return self.hand_ik.solve(self.to_base(position_w, rotation_w), self.robot.arm_q() if q is None else q)

    # -- planning ---------------------------------------------------------------------------------------------
    def plan_path(self, waypoints: list[np.ndarray]) -> "JointMove":
        """A Ruckig move from the current configuration through ``waypoints`` (rad), ending at rest.

        It starts at rest from the measured joints, unless the previous tick commanded a planned move still
        under way (one cut short by a fault, a slip or a retried grasp, or the stop braking it). Then it starts
        from that command, its velocity and acceleration, so the arm brakes and turns within the jerk and
        acceleration limits instead of being told to stop within one tick.
        """
        robot = self.robot
        moving = self.moving_last_tick()
        q0 = robot.arm_target if moving else robot.arm_q()
        start = np.clip(q0, self.limits.lower_rad, self.limits.upper_rad)
        return JointMove(self, plan_joint_path(
            [start, *waypoints], self.limits, start_velocity_radps=robot.arm_target_velocity_radps if moving else None,
            start_acceleration_radps2=robot.arm_target_acceleration_radps2 if moving else None))

    def moving_last_tick(self) -> bool:
        """Whether the previous control tick commanded the arm a planned velocity (a move under way, not at its
        end: a finished move ends at about 1e-14 rad/s)."""
        robot = self.robot
        qd = robot.arm_target_velocity_radps
        return (qd is not None and float(np.max(np.abs(qd))) > MOVING_RADPS
                and robot.sim.time_s - robot.arm_command_time_s <= 1.5 * self.config.control_period_s)

    def stop_if_moving(self) -> "JointMove | None":
        """A move that brings the arm to rest within the jerk and acceleration limits from the last command, if
        the previous tick commanded it to move (a move was cut short and nothing took over); else None, and
        also None if no such stop stays within the joint limits (the motors then hold their targets)."""
        if not self.moving_last_tick():
            return None
        robot = self.robot
        qdd = robot.arm_target_acceleration_radps2
        try:
            stop = plan_joint_stop(robot.arm_target, robot.arm_target_velocity_radps,
                                   np.zeros(self.limits.dof) if qdd is None else qdd, self.limits)
        except TrajectoryError:
            return None
        return JointMove(self, stop)

    def plan_pad_line(self, goal_w: np.ndarray, speed_mps: float, q_start: np.ndarray) -> "SampledMove":
        """The pad's centre in a straight line to ``goal_w`` (world), orientation held, tracked by IK."""
        goal_b = self.robot.base_rotation.T @ (np.asarray(goal_w, dtype=float) - self.robot.base_position_m)
        limits = CartesianLimits(speed_mps=speed_mps, acceleration_mps2=max(0.2, 4 * speed_mps),
                                 jerk_mps3=max(2.0, 40 * speed_mps))
        path = plan_cartesian_line(self.pad_ik, q_start, goal_b, limits, 1.0 / self.config.control_period_s)
        if not path.success:
            raise UnreachableError(f"pad line to {np.round(goal_w, 3).tolist()} m: {path.message}")
        return SampledMove(self, path.q_rad)


class JointMove:
    """A planned joint trajectory fed to the arm motors, one control tick per :meth:`step`."""

    def __init__(self, motion: ArmMotion, trajectory: JointTrajectory) -> None:
        self.motion = motion
        self.trajectory = trajectory
        self.t_s = 0.0
        self.tracking_errors_rad: list[float] = []

    @property
    def done(self) -> bool:
        return self.t_s >= self.trajectory.duration_s

    def step(self) -> bool:
        """Command the next sample and advance the physics one control tick. Returns True once finished."""
        m = self.motion
        self.t_s = min(self.t_s + m.config.control_period_s, self.trajectory.duration_s)
        q, qd, qdd = self.trajectory.sample(self.t_s)
        m.robot.command_arm(q, qd, qdd)
        m.last_move = self
        m.robot.sim.advance(m.config.control_period_s)
        self.tracking_errors_rad.append(float(np.max(np.abs(m.robot.arm_q() - q))))
        return self.done


class SampledMove:
    """Joint samples at the control rate (e.g. a Cartesian line solved by IK) fed one per :meth:`step`."""

    def __init__(self, motion: ArmMotion, q_samples: np.ndarray) -> None:
        self.motion = motion
        self.q_samples = q_samples
        self.index = 0

    @property
    def done(self) -> bool:
        return self.index >= len(self.q_samples)

    def step(self) -> bool:
        m = self.motion
        q = self.q_samples[min(self.index, len(self.q_samples) - 1)]
        m.robot.command_arm(q)
        m.robot.sim.advance(m.config.control_period_s)
        self.index += 1
        return self.done


def run_to_completion(move: JointMove | SampledMove, max_ticks: int = 100_000) -> None:
    """Step ``move`` until it finishes (tests and scripts; the state machine steps it itself)."""
    for _ in range(max_ticks):
        if move.step():
            return
    raise RobotDemoError(f"move did not finish within {max_ticks} ticks")


def hold(robot: Robot, seconds: float, control_period_s: float = 0.004) -> None:
    """Keep the current motor targets for ``seconds`` of simulated time."""
    robot.sim.advance(seconds)
