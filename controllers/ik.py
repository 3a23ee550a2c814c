"""Full-pose inverse kinematics of the tool frame: bounded Levenberg-Marquardt in SE(3) with seeded restarts.

Each attempt starts from a seed and iterates damped Gauss-Newton steps on the pose error
``e = log6(oMf(q)^-1 * oMdes)`` (a 6-vector twist in the tool frame), with the error Jacobian
``Je = -Jlog6(fMd^-1) * J_local`` (Pinocchio's convention) and the step projected onto the joint limits after
every update. The damping adapts (Levenberg-Marquardt): a step that lowers the error is kept and the damping
shrinks, one that does not is undone and the damping grows. An attempt ends when the error is below tolerance,
when it stalls, or after ``max_iterations``.

The first attempt starts at the caller's current configuration; if it fails, seeded random configurations drawn
uniformly within the limits are tried (``max_restarts`` of them, the same sequence on every call, so results are
reproducible). Among converged solutions the one nearest to the current configuration is returned. A target beyond
the arm's reach (a rigorous bound: the sum of the link offsets) gets one attempt only, so unreachable targets come
back quickly with ``success=False`` and the best residual found.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pinocchio as pin
from scipy.linalg import lapack

from controllers.kinematics import ArmKinematics


@dataclass(frozen=True)
class IKConfig:
    """Settings of :class:`IKSolver`.

    Attributes:
        position_tolerance_m: success threshold on the tool-origin position error, m.
        orientation_tolerance_rad: success threshold on the tool-frame rotation error (angle of the relative
            rotation), rad.
        damping: initial Levenberg-Marquardt damping (added to ``Je^T Je``), in the error units squared.
        min_damping: floor of the adaptive damping.
        max_step_rad: largest joint step (infinity norm) taken in one iteration, rad.
        max_iterations: iterations of the attempt from the current configuration.
        restart_iterations: iterations of each random-restart attempt.
        max_restarts: random restarts after the first attempt fails (0 disables them).
        solutions_to_compare: when the first attempt fails, how many converged restart solutions to gather before
            returning the one nearest the current configuration (1 returns the first found).
        stall_ratio: an attempt stops when the error norm has not dropped below this fraction of its value
            ``stall_window`` iterations earlier.
        stall_window: see ``stall_ratio``.
        seed: seed of the random restart configurations.
    """

    position_tolerance_m: float = 1e-5
    orientation_tolerance_rad: float = 1e-4
    damping: float = 1e-2
    min_damping: float = 1e-9
    max_step_rad: float = 1.0
    max_iterations: int = 60
    restart_iterations: int = 40
    max_restarts: int = 30
    solutions_to_compare: int = 2
    stall_ratio: float = 0.9
    stall_window: int = 8
    seed: int = 0

    def __post_init__(self) -> None:
        if self.position_tolerance_m <= 0 or self.orientation_tolerance_rad <= 0:
            raise ValueError("IKConfig: tolerances must be positive")
        if self.damping < 0 or self.min_damping < 0 or self.max_step_rad <= 0:
            raise ValueError("IKConfig: damping must be >= 0 and max_step_rad > 0")
        if self.max_iterations < 1 or self.restart_iterations < 1 or self.max_restarts < 0:
            raise ValueError("IKConfig: max_iterations, restart_iterations >= 1 and max_restarts >= 0 required")
        if self.solutions_to_compare < 1:
            raise ValueError("IKConfig: solutions_to_compare must be >= 1")


@dataclass(frozen=True)
class IKResult:
    """Outcome of one IK solve.

    Attributes:
        q: (nq,) best configuration found, rad, within the joint limits (also when ``success`` is False).
        success: whether both errors are within the configured tolerances.
        iterations: Gauss-Newton iterations spent over all attempts.
        attempts: attempts made (1 = solved or abandoned from the current configuration).
        position_error_m: distance between the reached and the desired tool origin, m.
        orientation_error_rad: angle of the rotation between the reached and the desired tool frame, rad.
        reachable_bound: False when the target lies beyond the rigorous reach bound (certainly unreachable).
    """

    q: np.ndarray
    success: bool
    iterations: int
    attempts: int
    position_error_m: float
    orientation_error_rad: float
    reachable_bound: bool = True


@dataclass(frozen=True)
class _Attempt:
    q: np.ndarray
    converged: bool
    iterations: int
    position_error_m: float
    orientation_error_rad: float
    cost: float


class IKSolver:
    """Full-pose IK of the tool frame of an :class:`ArmKinematics`, within the joint limits.

    Args:
        kinematics: the arm (its model is shared; this solver keeps its own ``data`` buffer).
        config: solver settings.
    """

    def __init__(self, kinematics: ArmKinematics, config: IKConfig = IKConfig()) -> None:
        self.kinematics = kinematics
        self.config = config
        self._model = kinematics.model
        self._data = kinematics.new_data()
        self._fid = kinematics.tool_frame_id
        self._lower = kinematics.lower_limits_rad
        self._upper = kinematics.upper_limits_rad
        self._eye = np.eye(kinematics.nq)
        rng = np.random.default_rng(config.seed)
        self._restart_seeds = rng.uniform(self._lower, self._upper, size=(config.max_restarts, kinematics.nq))
        self._base_position_m, self._reach_m = self._reach_bound()

    def _reach_bound(self) -> tuple[np.ndarray, float]:
        """Origin of the first joint in the base frame (m) and an upper bound of the tool's distance from it (m).

        Joint rotations do not change the length of the offsets that follow them, so the tool origin lies within
        the sum of the offset lengths from the first joint's origin.
        """
        model = self._model
        first = 1
        origin = np.array(model.jointPlacements[first].translation)
        reach = sum(float(np.linalg.norm(model.jointPlacements[j].translation))
                    for j in range(first + 1, model.njoints))
        frame = model.frames[self._fid]
        reach += float(np.linalg.norm(frame.placement.translation))
        return origin, reach

    def solve(self, oMdes: pin.SE3, q_current: np.ndarray) -> IKResult:
        """Configuration placing the tool frame at ``oMdes``, preferring the one nearest ``q_current``.

        Args:
            oMdes: desired placement of the tool frame in the base frame (translation m, rotation matrix).
            q_current: (nq,) current arm configuration, rad: the first seed and the reference for "nearest".

        Returns:
            An :class:`IKResult`; never raises for an unreachable target (``success=False``, best residual).
        """
        cfg = self.config
        q_current = np.clip(np.asarray(q_current, dtype=float), self._lower, self._upper)
        in_bound = float(np.linalg.norm(oMdes.translation - self._base_position_m)) <= self._reach_m + 1e-9
        first = self._attempt(oMdes, q_current, cfg.max_iterations)
        iterations, attempts = first.iterations, 1
        if first.converged or not in_bound:
            return self._result(first, iterations, attempts, in_bound)
        best, solutions = first, []
        for seed in self._restart_seeds:
            attempt = self._attempt(oMdes, seed, cfg.restart_iterations)
            iterations += attempt.iterations
            attempts += 1
            if attempt.cost < best.cost:
                best = attempt
            if attempt.converged:
                solutions.append(attempt)
                if len(solutions) >= cfg.solutions_to_compare:
                    break
        if solutions:
            best = min(solutions, key=lambda a: float(np.sum((a.q - q_current) ** 2)))
        return self._result(best, iterations, attempts, in_bound)

    def solve_pose(self, position_m: np.ndarray, rotation: np.ndarray, q_current: np.ndarray) -> IKResult:
        """Like :meth:`solve` with the target given as a position (m) and a rotation matrix (base frame)."""
        return self.solve(pin.SE3(np.asarray(rotation, dtype=float), np.asarray(position_m, dtype=float)), q_current)

    def solve_local(self, oMdes: pin.SE3, q_seed: np.ndarray) -> IKResult:
        """One attempt from ``q_seed``, no restarts: for tracking a path sample by sample without branch jumps."""
        attempt = self._attempt(oMdes, np.clip(np.asarray(q_seed, dtype=float), self._lower, self._upper),
                                self.config.max_iterations)
        in_bound = float(np.linalg.norm(oMdes.translation - self._base_position_m)) <= self._reach_m + 1e-9
        return self._result(attempt, attempt.iterations, 1, in_bound)

    @staticmethod
    def _result(attempt: _Attempt, iterations: int, attempts: int, in_bound: bool) -> IKResult:
        return IKResult(q=attempt.q, success=attempt.converged, iterations=iterations, attempts=attempts,
                        position_error_m=attempt.position_error_m,
                        orientation_error_rad=attempt.orientation_error_rad, reachable_bound=in_bound)

    def _evaluate(self, q: np.ndarray, oMdes: pin.SE3) -> tuple[np.ndarray, np.ndarray, float, float, float]:
        """Error twist ``e`` (tool frame), its Jacobian ``dE/dq``, position error (m), rotation angle (rad), cost."""
        model, data, fid = self._model, self._data, self._fid
        pin.computeJointJacobians(model, data, q)
        oMf = pin.updateFramePlacement(model, data, fid)
        fMd = oMf.actInv(oMdes)
        err = pin.log6(fMd).vector
        # d/dq log6(oMf(q)^-1 oMdes) = -Jlog6(fMd^-1) J_local (Pinocchio's IK example).
        Je = pin.Jlog6(fMd.inverse()) @ pin.getFrameJacobian(model, data, fid, pin.LOCAL)
        t = fMd.translation
        position_error_m = math.sqrt(t[0] * t[0] + t[1] * t[1] + t[2] * t[2])
        orientation_error_rad = math.sqrt(err[3] * err[3] + err[4] * err[4] + err[5] * err[5])
        return err, Je, position_error_m, orientation_error_rad, float(err @ err)

    def _attempt(self, oMdes: pin.SE3, q0: np.ndarray, max_iterations: int) -> _Attempt:
        """Levenberg-Marquardt from ``q0`` with the step clamped to the joint limits.

        ``Je`` here is ``-dE/dq``, so the Gauss-Newton step is ``dq = (Je^T Je + lambda I)^-1 Je^T e``.
        """
        cfg = self.config
        lower, upper, eye = self._lower, self._upper, self._eye
        pos_tol, rot_tol, max_step = cfg.position_tolerance_m, cfg.orientation_tolerance_rad, cfg.max_step_rad
        q = q0.copy()
        err, Je, pos_err, rot_err, cost = self._evaluate(q, oMdes)
        damping = cfg.damping
        history = [cost]
        iterations = 0
        while iterations < max_iterations and not (pos_err <= pos_tol and rot_err <= rot_tol):
            iterations += 1
            g = Je.T @ err
            H = Je.T @ Je
            accepted = False
            while damping <= 1e6:
                _, dq, info = lapack.dposv(H + damping * eye, g)
                if info != 0:
                    damping = max(damping * 10.0, 1e-6)
                    continue
                step = np.abs(dq).max()
                if step > max_step:
                    dq *= max_step / step
                q_new = np.minimum(np.maximum(q + dq, lower), upper)
                trial = self._evaluate(q_new, oMdes)
                if trial[4] < cost:
                    q = q_new
                    err, Je, pos_err, rot_err, cost = trial
                    damping = max(damping * 0.3, cfg.min_damping)
                    accepted = True
                    break
                damping *= 10.0
            if not accepted:
                break
            history.append(cost)
            if len(history) > cfg.stall_window and cost > cfg.stall_ratio * history[-1 - cfg.stall_window]:
                break
        converged = pos_err <= pos_tol and rot_err <= rot_tol
        return _Attempt(q, converged, iterations, pos_err, rot_err, cost)
