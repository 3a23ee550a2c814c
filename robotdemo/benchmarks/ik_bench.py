"""Side-by-side IK benchmark: our :class:`controllers.ik.IKSolver` against PyBullet's calculateInverseKinematics.

All solve the same seeded random reachable targets (the tool frame's placement at random in-limit arm
configurations, gripper in the stroke posture) starting from the same current configuration (the robot's home
posture, also PyBullet's rest pose). Both answers are scored by the same forward kinematics (Pinocchio, gripper
joints at the posture's values), against 0.1 mm and 0.1 deg; only the solver call itself is timed.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Sequence

import numpy as np
import pinocchio as pin
import pybullet as pb
from tqdm import tqdm

from controllers.ik import IKConfig, IKSolver
from controllers.kinematics import ArmKinematics
from robotdemo.assets import ARM_JOINTS, GRIPPER_JOINTS, ROBOT_URDF, TOOL_FRAME, urdf_path
from robotdemo.robot import HOME_ARM_Q, GripperPosture

SUCCESS_POSITION_M = 1e-4
SUCCESS_ORIENTATION_RAD = float(np.deg2rad(0.1))
LOOSE_POSITION_M = 1e-3
LOOSE_ORIENTATION_RAD = float(np.deg2rad(0.6))


def _pose_errors(kin: ArmKinematics, q: np.ndarray, oMdes: pin.SE3) -> tuple[float, float]:
    oMf = kin.fk_se3(q)
    position_error_m = float(np.linalg.norm(oMf.translation - oMdes.translation))
    orientation_error_rad = float(np.linalg.norm(pin.log3(oMf.rotation.T @ oMdes.rotation)))
    return position_error_m, orientation_error_rad


def _summary(times_s: list[float], errors: list[tuple[float, float]], in_limits: list[bool]) -> dict:
    t_ms = np.asarray(times_s) * 1e3
    err = np.asarray(errors)
    ok = (err[:, 0] <= SUCCESS_POSITION_M) & (err[:, 1] <= SUCCESS_ORIENTATION_RAD)
    loose = (err[:, 0] <= LOOSE_POSITION_M) & (err[:, 1] <= LOOSE_ORIENTATION_RAD)
    return {
        "success_rate": float(np.mean(ok & np.asarray(in_limits))),
        "success_rate_1mm_0.6deg": float(np.mean(loose & np.asarray(in_limits))),
        "within_joint_limits_rate": float(np.mean(in_limits)),
        "median_ms": float(np.median(t_ms)),
        "p95_ms": float(np.percentile(t_ms, 95)),
        "max_ms": float(np.max(t_ms)),
        "median_position_error_m": float(np.median(err[:, 0])),
        "median_orientation_error_rad": float(np.median(err[:, 1])),
    }


def _record(rows: tuple[list, list, list], kin: ArmKinematics, dt_s: float, q: np.ndarray, oMdes: pin.SE3) -> None:
    rows[0].append(dt_s)
    rows[1].append(_pose_errors(kin, q, oMdes))
    rows[2].append(kin.within_limits(q))


class _PyBulletIK:
    """PyBullet DIRECT with the same URDF; IK on the tool link, every call starting from the seed state.

    Two set-ups, both with ``maxNumIterations=100`` and ``residualThreshold=1e-6``:

    * ``limited`` (as a user would call it for a robot with limits): lower/upper limits and ranges of every movable
      joint from the URDF, rest poses = the seed configuration with the gripper posture. PyBullet then uses its
      null-space solver, which treats limits as soft and moves the thumb (its joints carry the tool frame).
      Pinning the gripper joints with lower = upper (or +-0.01 rad) was tried and is worse still.
    * ``damped``: no limits; a joint damping of 1e4 on the gripper joints (0.1 on the arm's) keeps the gripper
      still, which is PyBullet's most accurate set-up here, but joint limits are not enforced.
    """

    def __init__(self, gripper_q: Sequence[float], seed_q: np.ndarray) -> None:
        self.client = pb.connect(pb.DIRECT)
        self.body = pb.loadURDF(str(urdf_path(ROBOT_URDF)), useFixedBase=True, physicsClientId=self.client)
        infos = [pb.getJointInfo(self.body, j, physicsClientId=self.client)
                 for j in range(pb.getNumJoints(self.body, physicsClientId=self.client))]
        self.tool_link = next(i[0] for i in infos if i[12].decode() == TOOL_FRAME)
        movable = [i for i in infos if i[2] != pb.JOINT_FIXED]
        names = [i[1].decode() for i in movable]
        state = dict(zip(ARM_JOINTS, seed_q)) | dict(zip(GRIPPER_JOINTS, gripper_q))
        self.joint_indices = [i[0] for i in movable]
        self.rest = [float(state[n]) for n in names]
        self.lower = [float(i[8]) for i in movable]
        self.upper = [float(i[9]) for i in movable]
        self.ranges = [u - l for l, u in zip(self.lower, self.upper)]
        self.damping = [0.1 if n in ARM_JOINTS else 1e4 for n in names]
        self.arm_slots = [names.index(n) for n in ARM_JOINTS]
        self.gripper_slots = [names.index(n) for n in GRIPPER_JOINTS]
        self.gripper_q = np.asarray(gripper_q, dtype=float)

    def reset(self) -> None:
        for j, value in zip(self.joint_indices, self.rest):
            pb.resetJointState(self.body, j, value, physicsClientId=self.client)

    def solve(self, oMdes: pin.SE3, mode: str) -> tuple[np.ndarray, float]:
        """Arm configuration (rad) and the largest gripper-joint deviation from its posture (rad)."""
        x, y, z, w = pin.Quaternion(oMdes.rotation).coeffs()
        extra = (dict(lowerLimits=self.lower, upperLimits=self.upper, jointRanges=self.ranges, restPoses=self.rest)
                 if mode == "limited" else dict(jointDamping=self.damping))
        q = pb.calculateInverseKinematics(self.body, self.tool_link, oMdes.translation.tolist(), [x, y, z, w],
                                          maxNumIterations=100, residualThreshold=1e-6, physicsClientId=self.client,
                                          **extra)
        gripper_dev = float(np.max(np.abs(np.array([q[s] for s in self.gripper_slots]) - self.gripper_q)))
        return np.array([q[s] for s in self.arm_slots]), gripper_dev

    def close(self) -> None:
        pb.disconnect(self.client)


def run_ik_benchmark(n_poses: int = 1000, seed: int = 0, progress: bool = True,
                     ik_config: IKConfig = IKConfig(), seed_q_rad: Sequence[float] | None = None) -> dict:
    """Runs both IK solvers on the same ``n_poses`` seeded random reachable targets.

    Args:
        n_poses: number of targets.
        seed: seed of the random arm configurations whose tool placements are the targets.
        progress: show a tqdm bar on stderr.
        ik_config: settings of our solver.
        seed_q_rad: (6,) current configuration both solvers start from (default: the robot's home posture).

    Returns:
        A JSON-ready dict: ``ours``, ``pybullet`` (limits, ranges and rest poses set) and ``pybullet_damped``
        (gripper held by joint damping, no limits; see :class:`_PyBulletIK`), each with the success rate at
        0.1 mm and 0.1 deg within the joint limits, the same at 1 mm / 0.6 deg, the within-limits rate, median,
        p95 and max solve time ms, median position error m and orientation error rad (PyBullet's also the median
        gripper-joint deviation rad); ``median_time_ratio_ours_over_pybullet`` (and ``..._damped``); the set-up.
    """
    gripper_q = GripperPosture.stroke().q
    kin = ArmKinematics(urdf_path(ROBOT_URDF), TOOL_FRAME, ARM_JOINTS, dict(zip(GRIPPER_JOINTS, gripper_q)))
    solver = IKSolver(kin, ik_config)
    q_seed = np.asarray(HOME_ARM_Q if seed_q_rad is None else seed_q_rad, dtype=float)
    # a child stream: with default_rng(seed) itself the targets were the solver's own restart configurations
    # (IKConfig.seed draws them from default_rng(0)), so at seed 0 restart k started at pose k's answer
    rng = np.random.default_rng(np.random.SeedSequence(seed).spawn(1)[0])
    targets = [kin.fk_se3(kin.random_configuration(rng)) for _ in range(n_poses)]
    bullet = _PyBulletIK(gripper_q, q_seed)
    results = {name: ([], [], []) for name in ("ours", "pybullet", "pybullet_damped")}
    gripper_dev = {"pybullet": [], "pybullet_damped": []}
    try:
        for oMdes in tqdm(targets, desc="ik bench", file=sys.stderr, disable=not progress):
            t0 = time.perf_counter()
            ours = solver.solve(oMdes, q_seed)
            dt = time.perf_counter() - t0
            _record(results["ours"], kin, dt, ours.q, oMdes)
            for name, mode in (("pybullet", "limited"), ("pybullet_damped", "damped")):
                bullet.reset()
                t0 = time.perf_counter()
                q_pb, dev = bullet.solve(oMdes, mode)
                dt = time.perf_counter() - t0
                _record(results[name], kin, dt, q_pb, oMdes)
                gripper_dev[name].append(dev)
    finally:
        bullet.close()
    summary = {name: _summary(*rows) for name, rows in results.items()}
    for name, devs in gripper_dev.items():
        summary[name]["median_gripper_joint_deviation_rad"] = float(np.median(devs))
    return {
        "n_poses": n_poses,
        "seed": seed,
        "success_position_m": SUCCESS_POSITION_M,
        "success_orientation_rad": SUCCESS_ORIENTATION_RAD,
        "start_configuration_rad": q_seed.tolist(),
        **summary,
        "median_time_ratio_ours_over_pybullet": summary["ours"]["median_ms"] / summary["pybullet"]["median_ms"],
        "median_time_ratio_ours_over_pybullet_damped":
            summary["ours"]["median_ms"] / summary["pybullet_damped"]["median_ms"],
    }
