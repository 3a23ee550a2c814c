"""Kinematics and IK of the arm's tool frame: FK against PyBullet, FK(IK(x)) = x, limits, unreachable targets."""

import time

import numpy as np
import pinocchio as pin
import pybullet as pb
import pytest

from controllers.ik import IKConfig, IKSolver
from controllers.kinematics import ArmKinematics
from robotdemo.assets import ARM_JOINTS, GRIPPER_JOINTS, ROBOT_URDF, TOOL_FRAME, urdf_path

HOME_Q = np.array([0.0, -0.35, 1.9, 0.0, 1.15, 0.0])
STROKE_GRIPPER = dict(zip(GRIPPER_JOINTS, (0.0, 0.0, -0.6, -0.8, -0.6, -0.8)))


@pytest.fixture(scope="module")
def kin() -> ArmKinematics:
    return ArmKinematics(urdf_path(ROBOT_URDF), TOOL_FRAME, ARM_JOINTS, STROKE_GRIPPER)


@pytest.fixture(scope="module")
def ik(kin) -> IKSolver:
    return IKSolver(kin, IKConfig(seed=0))


def rotation_error_rad(R_a: np.ndarray, R_b: np.ndarray) -> float:
    return float(np.linalg.norm(pin.log3(R_a.T @ R_b)))


def test_limits_read_from_urdf(kin):
    assert kin.joint_names == ARM_JOINTS
    np.testing.assert_allclose(kin.upper_limits_rad, np.radians([178, 130, 135, 178, 128, 360]), atol=1e-8)
    np.testing.assert_allclose(kin.lower_limits_rad, -kin.upper_limits_rad)
    np.testing.assert_allclose(kin.velocity_limits_radps, np.radians([180, 180, 225, 225, 225, 225]), atol=1e-8)


def test_fk_matches_pybullet(kin):
    client = pb.connect(pb.DIRECT)
    try:
        body = pb.loadURDF(str(urdf_path(ROBOT_URDF)), useFixedBase=True, physicsClientId=client)
        infos = [pb.getJointInfo(body, j, physicsClientId=client)
                 for j in range(pb.getNumJoints(body, physicsClientId=client))]
        index = {i[1].decode(): i[0] for i in infos}
        tool = next(i[0] for i in infos if i[12].decode() == TOOL_FRAME)
        rng = np.random.default_rng(3)
        for _ in range(5):
            q = kin.random_configuration(rng)
            for name, value in list(zip(ARM_JOINTS, q)) + list(STROKE_GRIPPER.items()):
                pb.resetJointState(body, index[name], value, physicsClientId=client)
            state = pb.getLinkState(body, tool, computeForwardKinematics=True, physicsClientId=client)
            pose = kin.fk(q)
            np.testing.assert_allclose(pose.position_m, state[4], atol=1e-6)
            R_pb = np.array(pb.getMatrixFromQuaternion(state[5])).reshape(3, 3)
            assert rotation_error_rad(pose.rotation, R_pb) < 1e-6
    finally:
        pb.disconnect(client)


def test_jacobian_matches_finite_differences(kin):
    q = np.array([0.3, -0.2, 1.2, 0.4, 0.9, -0.5])
    J = kin.jacobian(q)  # LOCAL_WORLD_ALIGNED: [v; omega] in base axes
    eps = 1e-6
    p0, R0 = kin.fk(q).position_m, kin.fk(q).rotation
    for j in range(6):
        dq = np.zeros(6)
        dq[j] = eps
        pose = kin.fk(q + dq)
        np.testing.assert_allclose((pose.position_m - p0) / eps, J[:3, j], atol=1e-5)
        np.testing.assert_allclose(pin.log3(pose.rotation @ R0.T) / eps, J[3:, j], atol=1e-5)


def test_locked_gripper_values_move_the_tool_frame(kin):
    bent = ArmKinematics(urdf_path(ROBOT_URDF), TOOL_FRAME, ARM_JOINTS, {**STROKE_GRIPPER, "finger0_joint1": 0.5})
    assert np.linalg.norm(bent.fk(HOME_Q).position_m - kin.fk(HOME_Q).position_m) > 0.01
    with pytest.raises(ValueError, match="finger0_joint1"):
        ArmKinematics(urdf_path(ROBOT_URDF), TOOL_FRAME, ARM_JOINTS, {"finger0_joint1": 3.0})
    with pytest.raises(ValueError, match="no frame"):
        ArmKinematics(urdf_path(ROBOT_URDF), "nope", ARM_JOINTS)


def test_ik_round_trip_on_random_reachable_poses(kin, ik):
    rng = np.random.default_rng(0)
    n, solved = 100, 0
    for _ in range(n):
        oMdes = kin.fk_se3(kin.random_configuration(rng))
        result = ik.solve(oMdes, HOME_Q)
        assert kin.within_limits(result.q)
        oMf = kin.fk_se3(result.q)
        position_error = np.linalg.norm(oMf.translation - oMdes.translation)
        orientation_error = rotation_error_rad(oMf.rotation, oMdes.rotation)
        assert result.position_error_m == pytest.approx(position_error, abs=1e-9)
        if result.success:
            solved += 1
            assert position_error <= 1e-4 and orientation_error <= np.radians(0.1)
    assert solved >= 99


def test_ik_prefers_the_current_configuration(kin, ik):
    rng = np.random.default_rng(1)
    for _ in range(20):
        q_true = rng.uniform(kin.lower_limits_rad * 0.8, kin.upper_limits_rad * 0.8)
        q_near = q_true + rng.normal(0.0, 0.05, 6)
        result = ik.solve(kin.fk_se3(q_true), q_near)
        assert result.success and result.attempts == 1
        assert np.max(np.abs(result.q - q_true)) < 1e-3


def test_unreachable_targets_fail_fast_without_raising(kin, ik):
    far = pin.SE3(np.eye(3), np.array([1.2, 0.0, 0.3]))
    t0 = time.perf_counter()
    result = ik.solve(far, HOME_Q)
    assert time.perf_counter() - t0 < 0.05
    assert not result.success and not result.reachable_bound and result.attempts == 1
    assert result.position_error_m > 0.3 and kin.within_limits(result.q)

    # Within the reach bound but not reachable (the base's own position): bounded restarts, still no exception.
    inside = pin.SE3(np.eye(3), np.array([0.0, 0.0, 0.0]))
    t0 = time.perf_counter()
    result = ik.solve(inside, HOME_Q)
    assert time.perf_counter() - t0 < 0.5
    assert not result.success and result.attempts == ik.config.max_restarts + 1
    assert np.isfinite(result.position_error_m) and kin.within_limits(result.q)


def test_ik_config_is_validated():
    with pytest.raises(ValueError, match="tolerances"):
        IKConfig(position_tolerance_m=0.0)
    with pytest.raises(ValueError, match="solutions_to_compare"):
        IKConfig(solutions_to_compare=0)
