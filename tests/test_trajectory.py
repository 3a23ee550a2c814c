"""Ruckig joint moves (limits, exact ends, pass-through waypoints) and Cartesian lines tracked through IK."""

import numpy as np
import pinocchio as pin
import pytest

from controllers.ik import IKSolver
from controllers.kinematics import ArmKinematics
from controllers.trajectory import (CartesianLimits, JointMotionLimits, TrajectoryError, plan_cartesian_line,
                                    plan_joint_move, plan_joint_path, plan_joint_stop, plan_path_profile)
from robotdemo.assets import ARM_JOINTS, ROBOT_URDF, TOOL_FRAME, urdf_path

HOME_Q = np.array([0.0, -0.35, 1.9, 0.0, 1.15, 0.0])
RATE_HZ = 240.0


@pytest.fixture(scope="module")
def kin() -> ArmKinematics:
    return ArmKinematics(urdf_path(ROBOT_URDF), TOOL_FRAME, ARM_JOINTS)


@pytest.fixture(scope="module")
def limits(kin) -> JointMotionLimits:
    return JointMotionLimits.from_urdf_limits(kin.lower_limits_rad, kin.upper_limits_rad, kin.velocity_limits_radps)


def worst_relative_violation(traj, limits: JointMotionLimits, rate_hz: float = 1000.0) -> float:
    s = traj.sampled(rate_hz)
    jerk = np.diff(s.qdd_radps2, axis=0) / np.diff(s.t_s)[:, None]
    span = np.subtract(limits.upper_rad, limits.lower_rad)
    return float(max(np.max(np.abs(s.qd_radps) / limits.velocity_radps) - 1.0,
                     np.max(np.abs(s.qdd_radps2) / limits.acceleration_radps2) - 1.0,
                     np.max(np.abs(jerk) / limits.jerk_radps3) - 1.0,
                     np.max((s.q_rad - limits.upper_rad) / span),
                     np.max((np.array(limits.lower_rad) - s.q_rad) / span)))


def test_default_acceleration_and_jerk_follow_the_documented_rule(limits):
    np.testing.assert_allclose(limits.acceleration_radps2, np.array(limits.velocity_radps) / 0.6)
    np.testing.assert_allclose(limits.jerk_radps3, np.array(limits.acceleration_radps2) / 0.1)


def test_random_moves_respect_limits_and_hit_their_ends(kin, limits):
    rng = np.random.default_rng(0)
    for _ in range(60):
        waypoints = [kin.random_configuration(rng) for _ in range(int(rng.integers(2, 5)))]
        traj = plan_joint_path(waypoints, limits)
        assert worst_relative_violation(traj, limits) <= 1e-6
        start, end = traj.sample(0.0), traj.sample(traj.duration_s)
        np.testing.assert_allclose(start.q_rad, waypoints[0], atol=1e-12)
        np.testing.assert_allclose(end.q_rad, waypoints[-1], atol=1e-9)
        for state in (start, end):
            np.testing.assert_allclose(state.qd_radps, 0.0, atol=1e-9)
            np.testing.assert_allclose(state.qdd_radps2, 0.0, atol=1e-9)
        for q_wp, t_wp, v_wp in zip(waypoints, traj.waypoint_times_s, traj.waypoint_velocities_radps):
            state = traj.sample(t_wp)
            np.testing.assert_allclose(state.q_rad, q_wp, atol=1e-9)
            np.testing.assert_allclose(state.qd_radps, v_wp, atol=1e-9)


def test_pass_through_waypoints_keep_moving_and_save_time(limits):
    start, goal = np.array([-1.0, -0.5, 0.2, -1.0, -0.8, -2.0]), np.array([1.0, 0.8, 1.5, 1.2, 0.9, 2.0])
    waypoints = [start + f * (goal - start) for f in (0.0, 0.3, 0.65, 1.0)]
    through = plan_joint_path(waypoints, limits)
    stopping = plan_joint_path(waypoints, limits, pass_through=False)
    assert np.all(np.abs(through.waypoint_velocities_radps[1:-1]) > 0.1)
    np.testing.assert_allclose(through.waypoint_velocities_radps[[0, -1]], 0.0)
    assert through.duration_s < 0.85 * stopping.duration_s
    assert through.duration_s >= plan_joint_move(start, goal, limits).duration_s - 1e-9
    # A joint that turns back at a waypoint stops there.
    turn = plan_joint_path([np.zeros(6), np.full(6, 0.5), np.zeros(6)], limits)
    np.testing.assert_allclose(turn.waypoint_velocities_radps, 0.0)


def test_sampled_form_at_the_control_rate(limits):
    traj = plan_joint_move(np.zeros(6), np.array([0.5, -0.3, 0.2, 0.1, 0.0, 1.0]), limits)
    s = traj.sampled(RATE_HZ)
    assert s.t_s[0] == 0.0 and s.t_s[-1] == pytest.approx(traj.duration_s)
    assert np.all(np.diff(s.t_s)[:-1] == pytest.approx(1.0 / RATE_HZ))
    assert s.q_rad.shape == s.qd_radps.shape == s.qdd_radps2.shape == (len(s.t_s), 6)


def test_a_move_taken_over_while_moving_starts_from_that_state_and_respects_the_limits(kin, limits):
    """A move cut short is taken over by one that starts with its velocity and acceleration: no step in the
    command, and braking, turning and the rest within the limits."""
    rng = np.random.default_rng(4)
    speeds = []
    for _ in range(30):
        cut = plan_joint_path([kin.random_configuration(rng), kin.random_configuration(rng)], limits)
        state = cut.sample(float(rng.uniform(0.2, 0.8)) * cut.duration_s)  # where it was cut short
        speeds.append(float(np.max(np.abs(state.qd_radps))))
        goal = kin.random_configuration(rng)
        traj = plan_joint_path([state.q_rad, goal], limits, start_velocity_radps=state.qd_radps,
                               start_acceleration_radps2=state.qdd_radps2)
        start, end = traj.sample(0.0), traj.sample(traj.duration_s)
        np.testing.assert_allclose(start.q_rad, state.q_rad, atol=1e-12)
        np.testing.assert_allclose(start.qd_radps, state.qd_radps, atol=1e-9)
        np.testing.assert_allclose(start.qdd_radps2, state.qdd_radps2, atol=1e-9)
        np.testing.assert_allclose(end.q_rad, goal, atol=1e-9)
        np.testing.assert_allclose(end.qd_radps, 0.0, atol=1e-9)
        assert worst_relative_violation(traj, limits) <= 1e-6
    assert min(speeds) > 0.1  # every one was taken over at speed
    with pytest.raises(TrajectoryError, match="start velocity"):
        plan_joint_path([np.zeros(6), np.full(6, 0.1)], limits, start_velocity_radps=np.zeros(5))
    with pytest.raises(TrajectoryError, match="start velocity"):
        plan_joint_path([np.zeros(6), np.full(6, 0.1)], limits, start_velocity_radps=np.full(6, np.nan))


def test_a_stop_from_speed_respects_the_limits_and_ends_at_rest(kin, limits):
    rng = np.random.default_rng(5)
    for _ in range(20):
        move = plan_joint_path([kin.random_configuration(rng), kin.random_configuration(rng)], limits)
        state = move.sample(float(rng.uniform(0.2, 0.5)) * move.duration_s)
        stop = plan_joint_stop(state.q_rad, state.qd_radps, state.qdd_radps2, limits)
        start, end = stop.sample(0.0), stop.sample(stop.duration_s)
        np.testing.assert_allclose(start.qd_radps, state.qd_radps, atol=1e-9)
        np.testing.assert_allclose(end.qd_radps, 0.0, atol=1e-9)
        np.testing.assert_allclose(end.q_rad, stop.waypoints_rad[-1], atol=1e-9)
        assert worst_relative_violation(stop, limits) <= 1e-6
        assert stop.duration_s < move.duration_s  # braking is quicker than the move it cuts short
    near_limit = np.array(limits.upper_rad) - 1e-3
    with pytest.raises(TrajectoryError, match="no stop within the limits"):
        plan_joint_stop(near_limit, np.array(limits.velocity_radps), np.zeros(6), limits)
    with pytest.raises(TrajectoryError, match="finite"):
        plan_joint_stop(np.zeros(6), np.full(6, np.nan), np.zeros(6), limits)


def test_waypoints_outside_limits_are_rejected(limits):
    with pytest.raises(TrajectoryError, match="waypoint 1"):
        plan_joint_path([np.zeros(6), np.array([0, 0, 3.0, 0, 0, 0])], limits)
    with pytest.raises(TrajectoryError, match="M >= 2"):
        plan_joint_path([np.zeros(6)], limits)


def test_path_profile_is_jerk_limited():
    lim = CartesianLimits(speed_mps=0.05, acceleration_mps2=0.25, jerk_mps3=2.5)
    profile = plan_path_profile(0.1, lim)
    t = np.linspace(0.0, profile.duration_s, 2001)
    s, v, a = np.array([profile.at(ti) for ti in t]).T
    assert s[0] == 0.0 and s[-1] == pytest.approx(0.1)
    assert np.max(v) <= lim.speed_mps * (1 + 1e-9) and np.max(np.abs(a)) <= lim.acceleration_mps2 * (1 + 1e-9)
    assert np.max(np.abs(np.diff(a) / np.diff(t))) <= lim.jerk_mps3 * 1.01


def test_cartesian_line_holds_orientation_and_stays_on_the_line(kin):
    ik = IKSolver(kin)
    start = kin.fk(HOME_Q)
    goal = start.position_m + np.array([0.04, 0.03, -0.05])
    lim = CartesianLimits(speed_mps=0.05, acceleration_mps2=0.25, jerk_mps3=2.5)
    path = plan_cartesian_line(ik, HOME_Q, goal, lim, RATE_HZ)
    assert path.success, path.message
    assert path.failed_sample is None and len(path.q_rad) == len(path.t_s)
    direction = (goal - start.position_m) / np.linalg.norm(goal - start.position_m)
    for q, p_des in zip(path.q_rad, path.positions_m):
        pose = kin.fk(q)
        assert np.linalg.norm(pose.position_m - p_des) <= 1e-5
        offset = pose.position_m - start.position_m
        assert np.linalg.norm(offset - (offset @ direction) * direction) <= 1e-5  # on the line
        assert np.degrees(np.linalg.norm(pin.log3(pose.rotation.T @ start.rotation))) <= 0.01
        assert kin.within_limits(q)
    np.testing.assert_allclose(path.positions_m[-1], goal, atol=1e-12)
    speeds = np.linalg.norm(np.diff(path.positions_m, axis=0), axis=1) / np.diff(path.t_s)
    assert np.max(speeds) <= lim.speed_mps * (1 + 1e-6)
    joint_speeds = np.abs(np.diff(path.q_rad, axis=0)) / np.diff(path.t_s)[:, None]
    assert np.all(joint_speeds <= kin.velocity_limits_radps)


def test_cartesian_line_reports_the_unreachable_sample(kin):
    ik = IKSolver(kin)
    start = kin.fk(HOME_Q)
    goal = start.position_m + np.array([0.9, 0.0, 0.0])
    path = plan_cartesian_line(ik, HOME_Q, goal, CartesianLimits(speed_mps=0.3, acceleration_mps2=1.0, jerk_mps3=10.0),
                               RATE_HZ)
    assert not path.success
    assert path.failed_sample is not None and 0 < path.failed_sample < len(path.t_s)
    assert f"sample {path.failed_sample}" in path.message
    assert len(path.q_rad) == path.failed_sample
