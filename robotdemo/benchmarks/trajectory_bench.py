"""Trajectory benchmark: Ruckig planning time for 6-DoF moves and the worst limit violation found by dense sampling.

Random in-limit start and goal configurations of the arm (and, separately, paths through two random interior
waypoints) are planned with the URDF's velocity limits and the documented acceleration and jerk limits
(:func:`controllers.trajectory.JointMotionLimits.from_urdf_limits`), then sampled at ``sample_rate_hz``; jerk is
the finite difference of the sampled acceleration. A violation is relative: ``|x| / limit - 1`` for velocity,
acceleration and jerk, and the distance outside the position range divided by the range.
"""

from __future__ import annotations

import sys
import time

import numpy as np
from tqdm import tqdm

from controllers.kinematics import ArmKinematics
from controllers.trajectory import JointMotionLimits, JointTrajectory, plan_joint_move, plan_joint_path
from robotdemo.assets import ARM_JOINTS, ROBOT_URDF, TOOL_FRAME, urdf_path


def _violations(traj: JointTrajectory, limits: JointMotionLimits, rate_hz: float) -> dict[str, float]:
    s = traj.sampled(rate_hz)
    jerk = np.diff(s.qdd_radps2, axis=0) / np.diff(s.t_s)[:, None]
    lower, upper = np.asarray(limits.lower_rad), np.asarray(limits.upper_rad)
    span = upper - lower
    return {
        "position": float(max(np.max((s.q_rad - upper) / span), np.max((lower - s.q_rad) / span))),
        "velocity": float(np.max(np.abs(s.qd_radps) / limits.velocity_radps) - 1.0),
        "acceleration": float(np.max(np.abs(s.qdd_radps2) / limits.acceleration_radps2) - 1.0),
        "jerk": float(np.max(np.abs(jerk) / limits.jerk_radps3) - 1.0),
    }


def _summary(times_s: list[float], durations_s: list[float], violations: list[dict[str, float]]) -> dict:
    worst = {k: max(v[k] for v in violations) for k in violations[0]}
    return {
        "n": len(times_s),
        "median_plan_ms": float(np.median(times_s) * 1e3),
        "p95_plan_ms": float(np.percentile(times_s, 95) * 1e3),
        "median_duration_s": float(np.median(durations_s)),
        "worst_relative_violation": {k: max(0.0, v) for k, v in worst.items()},
        "worst_relative_violation_overall": max(0.0, *worst.values()),
        "within_1_percent": bool(max(worst.values()) <= 0.01),
    }


def run_trajectory_benchmark(n_plans: int = 1000, seed: int = 0, progress: bool = True,
                             sample_rate_hz: float = 1000.0) -> dict:
    """Plans ``n_plans`` random single moves and ``n_plans // 4`` random three-segment paths; see the module doc.

    Args:
        n_plans: number of random start/goal pairs.
        seed: seed of the random configurations.
        progress: show a tqdm bar on stderr.
        sample_rate_hz: rate at which every plan is sampled to look for limit violations, Hz.

    Returns:
        A JSON-ready dict: ``single_move`` and ``multi_segment`` each with the median and p95 planning time (ms),
        the median trajectory duration (s), the worst relative violation per quantity and overall, and whether
        it is within 1 %; plus the limits used.
    """
    kin = ArmKinematics(urdf_path(ROBOT_URDF), TOOL_FRAME, ARM_JOINTS)
    limits = JointMotionLimits.from_urdf_limits(kin.lower_limits_rad, kin.upper_limits_rad, kin.velocity_limits_radps)
    rng = np.random.default_rng(seed)
    single = ([], [], [])
    multi = ([], [], [])
    n_multi = max(1, n_plans // 4)
    with tqdm(total=n_plans + n_multi, desc="trajectory bench", file=sys.stderr, disable=not progress) as bar:
        for _ in range(n_plans):
            q0, q1 = kin.random_configuration(rng), kin.random_configuration(rng)
            t0 = time.perf_counter()
            traj = plan_joint_move(q0, q1, limits)
            single[0].append(time.perf_counter() - t0)
            single[1].append(traj.duration_s)
            single[2].append(_violations(traj, limits, sample_rate_hz))
            bar.update()
        for _ in range(n_multi):
            waypoints = [kin.random_configuration(rng) for _ in range(4)]
            t0 = time.perf_counter()
            traj = plan_joint_path(waypoints, limits)
            multi[0].append(time.perf_counter() - t0)
            multi[1].append(traj.duration_s)
            multi[2].append(_violations(traj, limits, sample_rate_hz))
            bar.update()
    return {
        "n_plans": n_plans,
        "seed": seed,
        "sample_rate_hz": sample_rate_hz,
        "limits": {"velocity_radps": list(limits.velocity_radps),
                   "acceleration_radps2": list(limits.acceleration_radps2),
                   "jerk_radps3": list(limits.jerk_radps3)},
        "single_move": _summary(*single),
        "multi_segment": _summary(*multi),
    }
