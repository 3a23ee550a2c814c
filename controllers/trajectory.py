"""Jerk-limited joint-space moves (Ruckig) and Cartesian straight lines tracked through IK.

Joint moves: Ruckig's community edition plans one time-optimal, time-synchronised, jerk-limited segment from a
state to a state. A path through several configurations is a chain of such segments; at an interior waypoint a
joint that keeps moving in the same direction passes through with a non-zero velocity (chosen below), the others
stop there. Every segment starts and ends with zero acceleration.

Cartesian lines: the tool origin follows a straight line with the orientation held, its arc length following a
1-D jerk-limited Ruckig profile; the profile is sampled at the control rate and every sample is solved by IK seeded
with the previous sample's solution (no restarts, so the arm never jumps to another branch mid-line).

Acceleration and jerk limits (the RM65-B publishes none): by default a joint reaches its URDF velocity limit in
``ACCELERATION_TIME_S`` = 0.6 s and its acceleration limit in ``JERK_TIME_S`` = 0.1 s, i.e. 5.2 rad/s^2 and
52 rad/s^3 for J1-J2, 6.5 rad/s^2 and 65 rad/s^3 for J3-J6. Reasoning: J2 carries the most; stretched out
horizontally (about 0.68 m to the gripper) with a 0.5 kg block, gravity takes about 26 of its 60 N m and the
arm's inertia about J2 is about 1 kg m^2, so the torque left allows roughly 30 rad/s^2; we use a sixth of that,
which also keeps PyBullet's effort-limited position motors tracking closely. J3 (30 N m, about 0.35 m to the tip)
and the wrist (10 N m, about 0.15 m, 0.1 kg m^2 or less) have a similar or larger margin. A 0.1 s jerk ramp is a
common smoothness choice that keeps the acceleration ramps well above the 240 Hz control period.
"""

from __future__ import annotations

import bisect
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import pinocchio as pin
import ruckig

from controllers.ik import IKSolver

ACCELERATION_TIME_S = 0.6
"""Default time for a joint to reach its velocity limit from rest: acceleration limit = velocity / this."""
JERK_TIME_S = 0.1
"""Default time to reach the acceleration limit: jerk limit = acceleration / this."""

_RUCKIG_OK = (ruckig.Result.Working, ruckig.Result.Finished)


class TrajectoryError(ValueError):
    """A move cannot be planned (invalid input, or a state outside the limits)."""


@dataclass(frozen=True)
class JointMotionLimits:
    """Kinematic limits of the joints, one entry per joint.

    Attributes:
        lower_rad, upper_rad: position limits, rad.
        velocity_radps: velocity limits, rad/s.
        acceleration_radps2: acceleration limits, rad/s^2.
        jerk_radps3: jerk limits, rad/s^3.
    """

    lower_rad: tuple[float, ...]
    upper_rad: tuple[float, ...]
    velocity_radps: tuple[float, ...]
    acceleration_radps2: tuple[float, ...]
    jerk_radps3: tuple[float, ...]

    def __post_init__(self) -> None:
        n = len(self.lower_rad)
        for name in ("upper_rad", "velocity_radps", "acceleration_radps2", "jerk_radps3"):
            values = getattr(self, name)
            if len(values) != n:
                raise ValueError(f"JointMotionLimits.{name} has {len(values)} entries, expected {n}")
            if name != "upper_rad" and not all(v > 0 and np.isfinite(v) for v in values):
                raise ValueError(f"JointMotionLimits.{name} must be positive and finite: {values}")
        if any(lo > hi for lo, hi in zip(self.lower_rad, self.upper_rad)):
            raise ValueError("JointMotionLimits: a lower limit exceeds its upper limit")

    @property
    def dof(self) -> int:
        return len(self.lower_rad)

    @staticmethod
    def from_urdf_limits(lower_rad: Sequence[float], upper_rad: Sequence[float], velocity_radps: Sequence[float],
                         velocity_scale: float = 1.0, acceleration_time_s: float = ACCELERATION_TIME_S,
                         jerk_time_s: float = JERK_TIME_S) -> "JointMotionLimits":
        """Limits from the URDF's position and velocity limits, with the documented acceleration and jerk rule.

        Args:
            lower_rad, upper_rad, velocity_radps: the URDF's limits (e.g. ``ArmKinematics.lower_limits_rad``...).
            velocity_scale: fraction (0, 1] of the URDF velocity to plan with; acceleration and jerk scale with it.
            acceleration_time_s: time from rest to the velocity limit, s.
            jerk_time_s: time from zero to the acceleration limit, s.
        """
        if not 0.0 < velocity_scale <= 1.0:
            raise ValueError(f"velocity_scale must be in (0, 1], got {velocity_scale}")
        v = np.asarray(velocity_radps, dtype=float) * velocity_scale
        a = v / acceleration_time_s
        return JointMotionLimits(tuple(map(float, lower_rad)), tuple(map(float, upper_rad)), tuple(v.tolist()),
                                 tuple(a.tolist()), tuple((a / jerk_time_s).tolist()))


class JointState(NamedTuple):
    """Joint position (rad), velocity (rad/s) and acceleration (rad/s^2) at one instant."""

    q_rad: np.ndarray
    qd_radps: np.ndarray
    qdd_radps2: np.ndarray


@dataclass(frozen=True)
class SampledJointTrajectory:
    """A trajectory sampled at a fixed rate, the last sample at the exact end time.

    Attributes:
        t_s: (N,) sample times from 0, s.
        q_rad, qd_radps, qdd_radps2: (N, dof) positions, velocities, accelerations.
    """

    t_s: np.ndarray
    q_rad: np.ndarray
    qd_radps: np.ndarray
    qdd_radps2: np.ndarray


@dataclass(frozen=True)
class JointTrajectory:
    """A chain of Ruckig segments through ``waypoints_rad``.

    Attributes:
        segments: the Ruckig trajectories, one per pair of consecutive waypoints.
        start_times_s: start time of each segment, s (the first is 0).
        waypoints_rad: (M, dof) the configurations passed through, first = start, last = goal.
        waypoint_velocities_radps: (M, dof) velocity at each waypoint (zero at the last; at the first too unless
            the move started moving).
        duration_s: total duration, s.
    """

    segments: tuple[ruckig.Trajectory, ...]
    start_times_s: tuple[float, ...]
    waypoints_rad: np.ndarray
    waypoint_velocities_radps: np.ndarray
    duration_s: float

    @property
    def waypoint_times_s(self) -> tuple[float, ...]:
        """Time at which each waypoint is passed, s."""
        return (*self.start_times_s, self.duration_s)

    def sample(self, t_s: float) -> JointState:
        """State at time ``t_s`` (clamped to [0, duration_s])."""
        t = min(max(float(t_s), 0.0), self.duration_s)
        i = max(bisect.bisect_right(self.start_times_s, t) - 1, 0)
        segment = self.segments[i]
        local = min(t - self.start_times_s[i], segment.duration)
        q, qd, qdd = segment.at_time(local)
        return JointState(np.array(q), np.array(qd), np.array(qdd))

    def sampled(self, rate_hz: float) -> SampledJointTrajectory:
        """The trajectory sampled every ``1 / rate_hz`` s, plus the exact end."""
        if rate_hz <= 0:
            raise ValueError(f"rate_hz must be positive, got {rate_hz}")
        n = int(np.floor(self.duration_s * rate_hz + 1e-9)) + 1
        t = np.arange(n) / rate_hz
        if t[-1] < self.duration_s - 1e-12:
            t = np.append(t, self.duration_s)
        states = [self.sample(ti) for ti in t]
        return SampledJointTrajectory(t, np.array([s.q_rad for s in states]), np.array([s.qd_radps for s in states]),
                                      np.array([s.qdd_radps2 for s in states]))


def _ruckig_input(limits: JointMotionLimits, q0: np.ndarray, v0: np.ndarray,
                  a0: np.ndarray | None = None) -> ruckig.InputParameter:
    """Ruckig's input from a start state (at zero acceleration unless ``a0``) under ``limits``, ending at zero
    acceleration; the caller sets the target."""
    inp = ruckig.InputParameter(limits.dof)
    inp.current_position = q0.tolist()
    inp.current_velocity = v0.tolist()
    inp.current_acceleration = [0.0] * limits.dof if a0 is None else a0.tolist()
    inp.target_acceleration = [0.0] * limits.dof
    inp.max_velocity = list(limits.velocity_radps)
    inp.max_acceleration = list(limits.acceleration_radps2)
    inp.max_jerk = list(limits.jerk_radps3)
    return inp


def _ruckig_calculate(limits: JointMotionLimits, inp: ruckig.InputParameter
                      ) -> tuple[ruckig.Result, ruckig.Trajectory]:
    traj = ruckig.Trajectory(limits.dof)
    try:
        return ruckig.Ruckig(limits.dof).calculate(inp, traj), traj
    except RuntimeError:  # Ruckig raises on invalid input in some builds
        return ruckig.Result.ErrorInvalidInput, traj


def _ruckig_segment(limits: JointMotionLimits, q0: np.ndarray, v0: np.ndarray, q1: np.ndarray,
                    v1: np.ndarray, a0: np.ndarray | None = None) -> tuple[ruckig.Result, ruckig.Trajectory]:
    inp = _ruckig_input(limits, q0, v0, a0)
    inp.target_position = q1.tolist()
    inp.target_velocity = v1.tolist()
    return _ruckig_calculate(limits, inp)


def _stopping_distance_rad(v: np.ndarray, a_max: np.ndarray, j_max: np.ndarray) -> np.ndarray:
    """Distance to brake from speed ``|v|`` (zero acceleration) to rest under acceleration and jerk limits."""
    v = np.abs(v)
    short = v < a_max * a_max / j_max  # the acceleration limit is never reached
    return np.where(short, v * np.sqrt(v / j_max), v * v / (2 * a_max) + v * a_max / (2 * j_max))


def _pass_through_velocities(waypoints: np.ndarray, limits: JointMotionLimits) -> np.ndarray:
    """Velocity at each waypoint: zero at the ends and where a joint turns or rests, else a safe cruise value.

    For a joint moving the same way on both sides of a waypoint, the velocity is the smaller of the two adjacent
    segments' mean speeds (from stop-to-stop plans, so the other joints' synchronisation is accounted for),
    capped so that braking from it takes at most half of the shorter adjacent distance (no overshoot past the
    next waypoint, hence none past a joint limit).
    """
    m = len(waypoints)
    velocities = np.zeros_like(waypoints)
    if m < 3:
        return velocities
    a_max, j_max = np.asarray(limits.acceleration_radps2), np.asarray(limits.jerk_radps3)
    v_max = np.asarray(limits.velocity_radps)
    durations = []
    zero = np.zeros(limits.dof)
    for i in range(m - 1):
        result, traj = _ruckig_segment(limits, waypoints[i], zero, waypoints[i + 1], zero)
        if result not in _RUCKIG_OK:
            raise TrajectoryError(f"segment {i} -> {i + 1} cannot be planned (Ruckig: {result})")
        durations.append(max(traj.duration, 1e-9))
    for i in range(1, m - 1):
        d_prev, d_next = waypoints[i] - waypoints[i - 1], waypoints[i + 1] - waypoints[i]
        same_way = (np.sign(d_prev) == np.sign(d_next)) & (np.abs(d_prev) > 1e-9) & (np.abs(d_next) > 1e-9)
        speed = np.minimum(np.abs(d_prev) / durations[i - 1], np.abs(d_next) / durations[i])
        speed = np.minimum(speed, 0.95 * v_max)
        room = 0.5 * np.minimum(np.abs(d_prev), np.abs(d_next))
        for _ in range(60):  # shrink until braking fits in the room (monotone in speed)
            too_far = _stopping_distance_rad(speed, a_max, j_max) > room
            if not np.any(too_far & same_way):
                break
            speed = np.where(too_far, 0.8 * speed, speed)
        velocities[i] = np.where(same_way, np.sign(d_next) * speed, 0.0)
    return velocities


def plan_joint_path(waypoints_rad: Sequence[Sequence[float]] | np.ndarray, limits: JointMotionLimits,
                    pass_through: bool = True, start_velocity_radps: Sequence[float] | None = None,
                    start_acceleration_radps2: Sequence[float] | None = None) -> JointTrajectory:
    """Jerk-limited, time-optimal move from rest (or from a moving start) through every waypoint to rest at the
    last one.

    Args:
        waypoints_rad: (M >= 2, dof) configurations; the first is the start state.
        limits: the joints' limits; every waypoint must lie within the position limits.
        pass_through: keep moving through interior waypoints where a joint does not turn (else stop at each).
        start_velocity_radps, start_acceleration_radps2: (dof,) the start state's velocity and acceleration
            (default: at rest), e.g. a move taken over from one that was cut short: the new one brakes and
            turns within the jerk and acceleration limits instead of starting with a step.

    Returns:
        The :class:`JointTrajectory`; its position stays within the limits (a segment whose braking would leave
        them is replanned with a stop at its waypoints).

    Raises:
        TrajectoryError: fewer than two waypoints, a wrong size, a waypoint outside the limits, or Ruckig failing.
    """
    waypoints = np.atleast_2d(np.asarray(waypoints_rad, dtype=float))
    if waypoints.shape[0] < 2 or waypoints.shape[1] != limits.dof:
        raise TrajectoryError(f"need (M >= 2, {limits.dof}) waypoints, got shape {waypoints.shape}")
    lower, upper = np.asarray(limits.lower_rad), np.asarray(limits.upper_rad)
    for i, q in enumerate(waypoints):
        if not np.all(np.isfinite(q)) or np.any(q < lower - 1e-9) or np.any(q > upper + 1e-9):
            raise TrajectoryError(f"waypoint {i} {np.round(q, 4).tolist()} is outside the joint limits")
    velocities = _pass_through_velocities(waypoints, limits) if pass_through else np.zeros_like(waypoints)
    a0 = None
    if start_velocity_radps is not None or start_acceleration_radps2 is not None:
        v0 = np.zeros(limits.dof) if start_velocity_radps is None else np.asarray(start_velocity_radps, dtype=float)
        a0 = np.zeros(limits.dof) if start_acceleration_radps2 is None else np.asarray(start_acceleration_radps2,
                                                                                       dtype=float)
        if v0.shape != (limits.dof,) or a0.shape != (limits.dof,) or not np.all(np.isfinite(v0) & np.isfinite(a0)):
            raise TrajectoryError(f"the start velocity and acceleration must be {limits.dof} finite numbers each")
        velocities[0] = v0
    segments: list[ruckig.Trajectory] = []
    start_times: list[float] = []
    t = 0.0
    i = 0
    while i < len(waypoints) - 1:
        result, traj = _ruckig_segment(limits, waypoints[i], velocities[i], waypoints[i + 1], velocities[i + 1],
                                       a0 if i == 0 else None)
        ok = result in _RUCKIG_OK and all(lower[j] - 1e-9 <= e.min and e.max <= upper[j] + 1e-9
                                          for j, e in enumerate(traj.position_extrema))
        if not ok:
            if np.any(velocities[i + 1]) and i + 1 < len(waypoints) - 1:
                velocities[i + 1] = 0.0  # stop at the next waypoint instead, then retry this segment
                continue
            if np.any(velocities[i]) and i > 0:
                velocities[i] = 0.0  # arrive at rest: replan the previous segment too
                segments.pop()
                t = start_times.pop()
                i -= 1
                continue
            raise TrajectoryError(f"segment {i} -> {i + 1} cannot be planned within the limits (Ruckig: {result})")
        segments.append(traj)
        start_times.append(t)
        t += traj.duration
        i += 1
    return JointTrajectory(tuple(segments), tuple(start_times), waypoints, velocities, t)


def plan_joint_stop(q_rad: Sequence[float], qd_radps: Sequence[float], qdd_radps2: Sequence[float],
                    limits: JointMotionLimits) -> JointTrajectory:
    """The quickest jerk-limited stop from a moving state: every joint brought to rest within the acceleration
    and jerk limits (Ruckig's velocity interface, target velocity 0), wherever that leaves it.

    Raises:
        TrajectoryError: a wrong size, a non-finite state, Ruckig failing, or a stop that would cross a position
            limit.
    """
    q, qd, qdd = (np.asarray(x, dtype=float) for x in (q_rad, qd_radps, qdd_radps2))
    if any(x.shape != (limits.dof,) or not np.all(np.isfinite(x)) for x in (q, qd, qdd)):
        raise TrajectoryError(f"a stop needs {limits.dof} finite positions, velocities and accelerations")
    inp = _ruckig_input(limits, q, qd, qdd)
    inp.control_interface = ruckig.ControlInterface.Velocity
    inp.target_velocity = [0.0] * limits.dof
    result, traj = _ruckig_calculate(limits, inp)
    lower, upper = np.asarray(limits.lower_rad), np.asarray(limits.upper_rad)
    if result not in _RUCKIG_OK or not all(lower[j] - 1e-9 <= e.min and e.max <= upper[j] + 1e-9
                                           for j, e in enumerate(traj.position_extrema)):
        raise TrajectoryError(f"no stop within the limits from {np.round(q, 4).tolist()} rad (Ruckig: {result})")
    end = np.array(traj.at_time(traj.duration)[0])
    return JointTrajectory((traj,), (0.0,), np.stack([q, end]), np.stack([qd, np.zeros(limits.dof)]),
                           traj.duration)


def plan_joint_move(q_start_rad: Sequence[float], q_goal_rad: Sequence[float],
                    limits: JointMotionLimits) -> JointTrajectory:
    """Jerk-limited, time-optimal move from rest at ``q_start_rad`` to rest at ``q_goal_rad`` (one segment)."""
    return plan_joint_path([q_start_rad, q_goal_rad], limits, pass_through=False)


# --------------------------------------------------------------------------------------------------------------
# Cartesian straight lines


@dataclass(frozen=True)
class CartesianLimits:
    """Limits along a Cartesian path's arc length.

    Attributes:
        speed_mps: largest tool speed, m/s.
        acceleration_mps2: largest tool acceleration along the path, m/s^2.
        jerk_mps3: largest tool jerk along the path, m/s^3.
    """

    speed_mps: float = 0.05
    acceleration_mps2: float = 0.25
    jerk_mps3: float = 2.5

    def __post_init__(self) -> None:
        for name in ("speed_mps", "acceleration_mps2", "jerk_mps3"):
            value = getattr(self, name)
            if not (value > 0 and np.isfinite(value)):
                raise ValueError(f"CartesianLimits.{name} must be positive and finite, got {value}")


@dataclass(frozen=True)
class PathProfile:
    """A 1-D jerk-limited profile of arc length: ``s(t)`` from 0 to ``length_m``, at rest at both ends."""

    trajectory: ruckig.Trajectory
    length_m: float

    @property
    def duration_s(self) -> float:
        return float(self.trajectory.duration)

    def at(self, t_s: float) -> tuple[float, float, float]:
        """Arc length (m), speed (m/s) and acceleration (m/s^2) at ``t_s`` (clamped to the profile)."""
        if self.length_m == 0.0:
            return 0.0, 0.0, 0.0
        s, v, a = self.trajectory.at_time(min(max(float(t_s), 0.0), self.duration_s))
        return float(s[0]), float(v[0]), float(a[0])


def plan_path_profile(length_m: float, limits: CartesianLimits) -> PathProfile:
    """Time-optimal jerk-limited rest-to-rest profile along a path of ``length_m`` (m)."""
    if not (length_m >= 0 and np.isfinite(length_m)):
        raise TrajectoryError(f"path length must be finite and >= 0, got {length_m}")
    traj = ruckig.Trajectory(1)
    if length_m > 0:
        inp = ruckig.InputParameter(1)
        inp.current_position, inp.target_position = [0.0], [float(length_m)]
        inp.max_velocity, inp.max_acceleration = [limits.speed_mps], [limits.acceleration_mps2]
        inp.max_jerk = [limits.jerk_mps3]
        result = ruckig.Ruckig(1).calculate(inp, traj)
        if result not in _RUCKIG_OK:
            raise TrajectoryError(f"path profile of {length_m} m cannot be planned (Ruckig: {result})")
    return PathProfile(traj, float(length_m))


@dataclass(frozen=True)
class SpeedRamp:
    """A 1-D jerk-limited change of speed along a path, held at ``target_speed_mps`` once reached.

    Attributes:
        trajectory: Ruckig's velocity-interface trajectory from the start state to the target speed.
        target_speed_mps: the speed held after the ramp, m/s.
    """

    trajectory: ruckig.Trajectory
    target_speed_mps: float

    @property
    def duration_s(self) -> float:
        return float(self.trajectory.duration)

    def at(self, t_s: float) -> tuple[float, float, float]:
        """Distance from the start (m), speed (m/s) and acceleration (m/s^2) at ``t_s`` >= 0."""
        t = max(float(t_s), 0.0)
        s, v, a = self.trajectory.at_time(min(t, self.duration_s))
        extra = max(t - self.duration_s, 0.0)
        if extra > 0.0:
            return float(s[0]) + self.target_speed_mps * extra, self.target_speed_mps, 0.0
        return float(s[0]), float(v[0]), float(a[0])


def plan_speed_ramp(speed_mps: float, acceleration_mps2: float, target_speed_mps: float,
                    limits: CartesianLimits) -> SpeedRamp:
    """The quickest jerk-limited change from (``speed_mps``, ``acceleration_mps2``) to ``target_speed_mps``
    within ``limits`` (Ruckig's velocity interface); for motions whose end is not known in advance, such as a
    descent that stops when contact is felt.

    Raises:
        TrajectoryError: a non-finite state or target, or Ruckig failing.
    """
    state = (speed_mps, acceleration_mps2, target_speed_mps)
    if not all(np.isfinite(x) for x in state):
        raise TrajectoryError(f"speed ramp needs finite speeds and acceleration, got {state}")
    inp = ruckig.InputParameter(1)
    inp.control_interface = ruckig.ControlInterface.Velocity
    inp.current_position, inp.current_velocity = [0.0], [float(speed_mps)]
    inp.current_acceleration, inp.target_velocity = [float(acceleration_mps2)], [float(target_speed_mps)]
    inp.max_velocity = [max(limits.speed_mps, abs(float(speed_mps)), abs(float(target_speed_mps)))]
    inp.max_acceleration, inp.max_jerk = [limits.acceleration_mps2], [limits.jerk_mps3]
    traj = ruckig.Trajectory(1)
    result = ruckig.Ruckig(1).calculate(inp, traj)
    if result not in _RUCKIG_OK:
        raise TrajectoryError(f"speed ramp {speed_mps} -> {target_speed_mps} m/s cannot be planned (Ruckig: {result})")
    return SpeedRamp(traj, float(target_speed_mps))


@dataclass(frozen=True)
class CartesianPath:
    """A straight tool-frame line sampled at the control rate and solved by IK.

    Attributes:
        success: every sample was solved within tolerance and the joint steps stayed within the velocity limits.
        message: empty on success, else what failed and at which sample.
        failed_sample: index of the first failing sample, or None.
        t_s: (N,) sample times, s.
        positions_m: (N, 3) desired tool origins in the base frame, m.
        rotation: (3, 3) the held tool orientation in the base frame.
        q_rad: (K, nq) joint solutions of the samples solved (K = N on success, else the samples before the
            failing one).
        position_errors_m: (K,) IK position error per solved sample, m.
        orientation_errors_rad: (K,) IK orientation error per solved sample, rad.
    """

    success: bool
    message: str
    failed_sample: int | None
    t_s: np.ndarray
    positions_m: np.ndarray
    rotation: np.ndarray
    q_rad: np.ndarray
    position_errors_m: np.ndarray
    orientation_errors_rad: np.ndarray

    @property
    def duration_s(self) -> float:
        return float(self.t_s[-1]) if len(self.t_s) else 0.0


def plan_cartesian_line(ik: IKSolver, q_start_rad: Sequence[float], goal_position_m: Sequence[float],
                        limits: CartesianLimits, rate_hz: float,
                        joint_velocity_margin: float = 1.0) -> CartesianPath:
    """Tool frame from its placement at ``q_start_rad`` straight to ``goal_position_m``, orientation held.

    Args:
        ik: the IK solver of the arm (its tool frame moves along the line).
        q_start_rad: (nq,) start configuration; its tool placement is the line's start and the held orientation.
        goal_position_m: (3,) end of the line in the base frame, m.
        limits: speed, acceleration and jerk along the line.
        rate_hz: control rate at which the line is sampled, Hz.
        joint_velocity_margin: a sample fails if a joint moves faster than this times its URDF velocity limit
            between consecutive samples (a sign of a singularity or a branch change).

    Returns:
        A :class:`CartesianPath`; ``success`` False (with the failing sample named) when a sample is unreachable.
    """
    if rate_hz <= 0:
        raise ValueError(f"rate_hz must be positive, got {rate_hz}")
    kin = ik.kinematics
    q_prev = np.asarray(q_start_rad, dtype=float)
    oMstart = kin.fk_se3(q_prev, kin.new_data())
    start = np.array(oMstart.translation)
    rotation = np.array(oMstart.rotation)
    goal = np.asarray(goal_position_m, dtype=float)
    length = float(np.linalg.norm(goal - start))
    direction = (goal - start) / length if length > 0 else np.zeros(3)
    profile = plan_path_profile(length, limits)
    n = int(np.floor(profile.duration_s * rate_hz + 1e-9)) + 1
    t = np.arange(n) / rate_hz
    if t[-1] < profile.duration_s - 1e-12:
        t = np.append(t, profile.duration_s)
    positions = np.array([start + profile.at(ti)[0] * direction for ti in t])
    max_step = kin.velocity_limits_radps * joint_velocity_margin
    solutions, pos_errors, rot_errors = [], [], []
    message, failed = "", None
    for k, (tk, p) in enumerate(zip(t, positions)):
        result = ik.solve_local(pin.SE3(rotation, p), q_prev)
        if not result.success:
            message = (f"sample {k} (t = {tk:.3f} s, p = {np.round(p, 4).tolist()} m) unreachable: IK residual "
                       f"{result.position_error_m * 1e3:.3f} mm, {np.degrees(result.orientation_error_rad):.3f} deg")
            failed = k
            break
        if k > 0:
            dt = tk - t[k - 1]
            speed_ratio = np.abs(result.q - q_prev) / (max_step * max(dt, 1e-12))
            if np.any(speed_ratio > 1.0):
                j = int(np.argmax(speed_ratio))
                message = (f"sample {k} (t = {tk:.3f} s): joint {kin.joint_names[j]} would move at "
                           f"{speed_ratio[j] * joint_velocity_margin:.2f} x its velocity limit (singularity?)")
                failed = k
                break
        solutions.append(result.q)
        pos_errors.append(result.position_error_m)
        rot_errors.append(result.orientation_error_rad)
        q_prev = result.q
    q = np.array(solutions) if solutions else np.zeros((0, kin.nq))
    return CartesianPath(failed is None, message, failed, t, positions, rotation, q, np.array(pos_errors),
                         np.array(rot_errors))
