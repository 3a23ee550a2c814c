"""Forward kinematics of the arm's tool frame on a reduced Pinocchio model (gripper joints locked).

The full description carries the arm and the gripper; the tool frame (``pad_center``) sits on a finger, so its
placement depends on the gripper posture too. :class:`ArmKinematics` builds the model once with every joint that
is not an arm joint locked at a given value (``pin.buildReducedModel``), so ``q`` is always the arm's
configuration alone, ordered as ``arm_joint_names``. The posture changes between stroking and grasping: build one
:class:`ArmKinematics` per posture.

Frames: ``o`` is the URDF root (the robot base), ``f`` the tool frame. ``fk`` returns ``oMf``.
Pinocchio's ``data`` is a working buffer: every solver that must not share one calls :meth:`new_data`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pinocchio as pin


@dataclass(frozen=True)
class ToolPose:
    """Placement of the tool frame in the base frame.

    Attributes:
        position_m: (3,) origin of the tool frame in the base frame, m.
        rotation: (3, 3) rotation matrix, columns = tool axes expressed in the base frame.
    """

    position_m: np.ndarray
    rotation: np.ndarray

    def as_se3(self) -> pin.SE3:
        """The same placement as a ``pin.SE3`` (``oMf``)."""
        return pin.SE3(np.asarray(self.rotation, dtype=float), np.asarray(self.position_m, dtype=float))

    @staticmethod
    def from_se3(oMf: pin.SE3) -> "ToolPose":
        return ToolPose(position_m=np.array(oMf.translation), rotation=np.array(oMf.rotation))


class ArmKinematics:
    """Tool-frame kinematics of a serial arm read from a URDF.

    Args:
        urdf_path: path of the URDF holding the arm (and possibly a gripper).
        tool_frame: name of the tool frame (a link or joint frame of the URDF), e.g. ``"pad_center"``.
        arm_joint_names: the joints the solvers move, in configuration order, e.g. ``("joint1", ..., "joint6")``.
        locked_joint_values: values (rad or m) at which every other joint is locked; joints not named here are
            locked at 0.

    Raises:
        ValueError: an unknown joint or frame name, a multi-DoF arm joint, or a locked value outside its limits.
    """

    def __init__(self, urdf_path: str | Path, tool_frame: str, arm_joint_names: Sequence[str],
                 locked_joint_values: Mapping[str, float] | None = None) -> None:
        full = pin.buildModelFromUrdf(str(urdf_path))
        arm_joint_names = tuple(arm_joint_names)
        locked_joint_values = dict(locked_joint_values or {})
        known = set(full.names[1:])
        for name in (*arm_joint_names, *locked_joint_values):
            if name not in known:
                raise ValueError(f"{urdf_path}: no joint named {name!r} (joints: {sorted(known)})")
        q_lock = pin.neutral(full)
        lock_ids = []
        for jid in range(1, full.njoints):
            name = full.names[jid]
            if name in arm_joint_names:
                if full.joints[jid].nq != 1:
                    raise ValueError(f"{urdf_path}: arm joint {name!r} has {full.joints[jid].nq} DoF; need 1")
                continue
            lock_ids.append(jid)
            if name in locked_joint_values:
                idx = full.joints[jid].idx_q
                value = float(locked_joint_values[name])
                lo, hi = full.lowerPositionLimit[idx], full.upperPositionLimit[idx]
                if not lo - 1e-9 <= value <= hi + 1e-9:
                    raise ValueError(f"locked joint {name!r} = {value} outside its limits [{lo}, {hi}]")
                q_lock[idx] = value
        self.model: pin.Model = pin.buildReducedModel(full, lock_ids, q_lock)
        if not self.model.existFrame(tool_frame):
            raise ValueError(f"{urdf_path}: no frame named {tool_frame!r}")
        self.urdf_path = Path(urdf_path)
        self.tool_frame = tool_frame
        self.tool_frame_id: int = self.model.getFrameId(tool_frame)
        self.locked_joint_values: dict[str, float] = {full.names[j]: float(q_lock[full.joints[j].idx_q])
                                                      for j in lock_ids if full.joints[j].nq == 1}
        # Configuration order of the reduced model follows the URDF tree; map it to the caller's order.
        reduced_names = list(self.model.names[1:])
        if sorted(reduced_names) != sorted(arm_joint_names):
            raise ValueError(f"reduced model joints {reduced_names} differ from arm joints {list(arm_joint_names)}")
        if reduced_names != list(arm_joint_names):
            raise ValueError(f"arm_joint_names must follow the URDF order {reduced_names}")
        self.joint_names: tuple[str, ...] = arm_joint_names
        self.nq: int = self.model.nq
        self.lower_limits_rad = np.array(self.model.lowerPositionLimit, dtype=float)
        self.upper_limits_rad = np.array(self.model.upperPositionLimit, dtype=float)
        self.velocity_limits_radps = np.array(self.model.velocityLimit, dtype=float)
        self.effort_limits_nm = np.array(self.model.effortLimit, dtype=float)
        self._data = self.model.createData()

    def new_data(self) -> pin.Data:
        """A fresh Pinocchio working buffer for a solver that keeps its own."""
        return self.model.createData()

    def fk(self, q: np.ndarray, data: pin.Data | None = None) -> ToolPose:
        """Placement of the tool frame in the base frame.

        Args:
            q: (nq,) arm configuration, rad.
            data: working buffer (default: this object's own).

        Returns:
            ``oMf`` as a :class:`ToolPose` (position in m, rotation matrix).
        """
        return ToolPose.from_se3(self.fk_se3(q, data))

    def fk_se3(self, q: np.ndarray, data: pin.Data | None = None) -> pin.SE3:
        """Like :meth:`fk` but returns a copy of ``oMf`` as ``pin.SE3``."""
        data = self._data if data is None else data
        pin.forwardKinematics(self.model, data, np.asarray(q, dtype=float))
        return pin.SE3(pin.updateFramePlacement(self.model, data, self.tool_frame_id))

    def jacobian(self, q: np.ndarray, reference_frame: pin.ReferenceFrame = pin.LOCAL_WORLD_ALIGNED,
                 data: pin.Data | None = None) -> np.ndarray:
        """Geometric Jacobian of the tool frame.

        Args:
            q: (nq,) arm configuration, rad.
            reference_frame: ``pin.LOCAL`` (twist in the tool frame), ``pin.LOCAL_WORLD_ALIGNED`` (default: at the
                tool origin, axes of the base frame) or ``pin.WORLD``.
            data: working buffer (default: this object's own).

        Returns:
            (6, nq) Jacobian mapping qd (rad/s) to the twist [v (m/s); omega (rad/s)].
        """
        data = self._data if data is None else data
        return pin.computeFrameJacobian(self.model, data, np.asarray(q, dtype=float), self.tool_frame_id,
                                        reference_frame).copy()

    def within_limits(self, q: np.ndarray, tol_rad: float = 1e-9) -> bool:
        """Whether ``q`` lies within the joint position limits (with ``tol_rad`` slack)."""
        q = np.asarray(q, dtype=float)
        return bool(np.all(q >= self.lower_limits_rad - tol_rad) and np.all(q <= self.upper_limits_rad + tol_rad))

    def random_configuration(self, rng: np.random.Generator) -> np.ndarray:
        """A configuration drawn uniformly within the joint limits, rad."""
        return rng.uniform(self.lower_limits_rad, self.upper_limits_rad)
