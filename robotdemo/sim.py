"""The thin adapter between robotdemo and PyBullet: every PyBullet call of the project goes through here.

It turns PyBullet's tuples into named records (:class:`ContactPoint`, :class:`LinkState`), checks that nothing
diverged (NaN/inf raise :class:`SimulationError`), and validates description files before PyBullet sees them
(PyBullet's own message for a bad file is ``Cannot load URDF file`` without saying which or why).
"""

from __future__ import annotations

import math
import tempfile
import xml.etree.ElementTree as ET
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Sequence

import numpy as np
import pybullet as p

from robotdemo.errors import AssetError, SimulationError


@dataclass(frozen=True)
class StepMode:
    """A physics step length (s, a multiple of the fine step), the solver iterations per step, whether
    friction uses Bullet's cone model (``False``: the cheaper two-direction pyramid), and the lightest held body
    the mode is good for (kg; :meth:`Simulator.use_step_mode` falls back to the fine step below it)."""

    time_step_s: float
    solver_iterations: int
    cone_friction: bool = True
    min_held_mass_kg: float = 0.0


STEP_MODES = ("fine", "free", "carry")


URDF_FLAGS = p.URDF_USE_INERTIA_FROM_FILE | p.URDF_INITIALIZE_SAT_FEATURES
"""How every URDF body is loaded (the robot, the table, the zones and the cylinders; box objects are made with
``createCollisionShape``, whose boxes collide by Bullet's box-box routine). With ``enableSAT`` the polyhedral
features make convex contacts clip face against face: a pad sliding over a cylinder's top keeps a patch of 4
contact points. Without them GJK gives one new
point per step, and a 3 N press dragged at 30 mm/s over a cylinder read 0.8-7.3 N (5th-95th percentile)
where a box reads a steady 3.5 N (scratch, session 26: ``/work/s26/cyl/contact3.py``, ``contact4.py``)."""


@dataclass(frozen=True)
class SimConfig:
    """Physics settings.

    Attributes:
        time_step_s: physics step; 1 ms keeps finger contacts and the tactile pad stable.
        solver_iterations: constraint solver iterations per step (contact-rich sliding needs many: at 50 or 30
            a stroke on a stiff pine block resting on the table held its median force but spiked to 4.7 N or
            17 N against a 2 N target, where 100 keeps it within +-20 %; scratch, the stroke test's own case).
            A clamped sample free of the table converges in fewer (see ``DatasetConfig.solver_iterations``).
        Friction uses Bullet's cone model: without it a step in contact costs half (0.34 vs 0.67 ms) but the
        pad slid over the objects with almost no friction reported (1e-3 N against 1.3 N expected).
        solver_residual_threshold: the solver stops early once its residual falls below this (PyBullet's
            default 1e-7; at 1e-5 and above the force loop on a hard block no longer settles within +-10 %).
        free_step: the ``"free"`` step mode, for the arm moving with nothing in hand (no contact to resolve).
        carry_step: the ``"carry"`` step mode, for grasping a resting object, lifting, carrying, lowering and
            releasing it: the fine step and the friction cone at 50 solver iterations, for held objects of 10 g
            and more (lighter ones are held at the fine step). Held in three fingers, an object's contacts cost a
            1 ms step at 100 iterations 0.5 ms against 0.2 ms for a stroke step (scratch profile of one
            6-object run: those states took two thirds of the physics' wall time). Fewer iterations resolve a
            light object squeezed between the heavy fingers less well: a 50 mm block squeezed at 0.5 N m (the
            sorting robot's least, ``SortingConfig.grasp_effort_nm``) and carried 15 cm (``tests/test_grasp.py``'s
            case) shifted in the fingers by 0.9 / 0.7 mm at 20 g (100 / 50 iterations), 1.0 / 1.4 mm at 12.5 g,
            1.2 / 4.9 mm at 7.5 g and 3.3 / 12.1 mm at 4 g (scratch). Longer steps lose objects: at 2 ms with
            pyramid friction a 7 g textile slab slipped out in transport, and at 2 ms or 4 ms with the cone a
            1.1 kg brass cylinder did.
        The modes are switched with :meth:`Simulator.use_step_mode`; ``"fine"`` is ``time_step_s`` with
        ``solver_iterations`` and the friction cone, what pressing and stroking (the measurement) need.
        gravity_mps2: gravity along world -z.
        gui: open PyBullet's own GUI window instead of running headless (DIRECT).
    """

    time_step_s: float = 1.0 / 1000.0
    solver_iterations: int = 100
    solver_residual_threshold: float = 1e-7
    free_step: StepMode = StepMode(time_step_s=4.0 / 1000.0, solver_iterations=100)
    carry_step: StepMode = StepMode(time_step_s=1.0 / 1000.0, solver_iterations=50, min_held_mass_kg=0.01)
    gravity_mps2: float = 9.81
    contact_erp: float = 0.2
    friction_erp: float = 0.2
    contact_slop_m: float = 0.0002
    gui: bool = False

    def with_solver_iterations(self, iterations: int) -> "SimConfig":
        """This configuration with every step mode iterating ``iterations`` times per step."""
        if iterations < 1:
            raise ValueError(f"solver iterations must be >= 1, got {iterations}")
        return replace(self, solver_iterations=iterations,
                       free_step=replace(self.free_step, solver_iterations=iterations),
                       carry_step=replace(self.carry_step, solver_iterations=iterations))


@dataclass(frozen=True)
class ContactPoint:
    """One contact point of the last step (PyBullet's ``getContactPoints`` record, named).

    Forces are those the solver applied during the last ``step``; directions are unit vectors in the world frame.
    ``normal_on_b`` points from body B towards body A.
    """

    body_a: int
    body_b: int
    link_a: int
    link_b: int
    position_on_a_m: np.ndarray
    position_on_b_m: np.ndarray
    normal_on_b: np.ndarray
    distance_m: float
    normal_force_n: float
    lateral_friction1_n: float
    lateral_friction_dir1: np.ndarray
    lateral_friction2_n: float
    lateral_friction_dir2: np.ndarray

    @property
    def shear_force_n(self) -> np.ndarray:
        """Friction force vector f1 * dir1 + f2 * dir2 (world, N): the friction acting on body A (it opposes A's
        sliding relative to B; checked in tests/test_stroking.py)."""
        return self.lateral_friction1_n * self.lateral_friction_dir1 + self.lateral_friction2_n * self.lateral_friction_dir2


@dataclass(frozen=True)
class LinkState:
    """World pose and velocity of a link frame (URDF link frame, not the inertial frame)."""

    position_m: np.ndarray
    orientation_xyzw: np.ndarray
    linear_velocity_mps: np.ndarray
    angular_velocity_radps: np.ndarray

    @property
    def rotation(self) -> np.ndarray:
        return np.asarray(p.getMatrixFromQuaternion(self.orientation_xyzw)).reshape(3, 3)


@dataclass(frozen=True)
class JointInfo:
    index: int
    name: str
    kind: int
    lower_rad: float
    upper_rad: float
    effort_nm: float
    velocity_radps: float
    link_name: str


def validate_urdf(path: str | Path) -> Path:
    """Check that ``path`` exists and is a well-formed URDF; a one-line :class:`AssetError` names the file if not."""
    path = Path(path)
    if not path.is_file():
        raise AssetError(f"{path}: URDF file not found")
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise AssetError(f"{path}: malformed URDF (XML error: {exc})") from None
    if root.tag != "robot":
        raise AssetError(f"{path}: malformed URDF (root element is <{root.tag}>, expected <robot>)")
    links = {el.get("name") for el in root.findall("link")}
    if not links:
        raise AssetError(f"{path}: malformed URDF (no <link> elements)")
    for el in root.findall("joint"):
        for tag in ("parent", "child"):
            ref = el.find(tag)
            if ref is None or ref.get("link") not in links:
                raise AssetError(f"{path}: malformed URDF (joint {el.get('name')!r} names a missing {tag} link)")
    for xpath, attr, count, non_negative in _URDF_NUMBERS:
        for el in root.findall(".//" + xpath):
            text = el.get(attr)
            if text is None:
                continue
            try:
                values = [float(v) for v in text.split()]
            except ValueError:
                values = []
            if len(values) != count or not all(math.isfinite(v) for v in values) or (
                    non_negative and min(values) < 0):
                need = f"{count} finite number{'s' if count > 1 else ''}" + (" >= 0" if non_negative else "")
                raise AssetError(f"{path}: malformed URDF (<{xpath.split('/')[-1]} {attr}={text!r}> needs {need})")
    return path


_URDF_NUMBERS = (("origin", "xyz", 3, False), ("origin", "rpy", 3, False), ("axis", "xyz", 3, False),
                 ("inertial/mass", "value", 1, True), *(("inertia", a, 1, a in ("ixx", "iyy", "izz"))
                                                          for a in ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")),
                 ("box", "size", 3, True), ("cylinder", "radius", 1, True), ("cylinder", "length", 1, True),
                 ("sphere", "radius", 1, True), ("mesh", "scale", 3, False), ("limit", "lower", 1, False),
                 ("limit", "upper", 1, False), ("limit", "effort", 1, True), ("limit", "velocity", 1, True))
"""Numeric URDF attributes :func:`validate_urdf` checks: (element, attribute, how many numbers, must be >= 0)."""


class Simulator:
    """One PyBullet physics client. Use as a context manager or call :meth:`close`."""

    def __init__(self, config: SimConfig = SimConfig()) -> None:
        self.config = config
        self.client = p.connect(p.GUI if config.gui else p.DIRECT)
        if self.client < 0:
            raise SimulationError("could not start PyBullet (p.connect failed)")
        p.resetSimulation(physicsClientId=self.client)
        p.setGravity(0, 0, -config.gravity_mps2, physicsClientId=self.client)
        p.setPhysicsEngineParameter(
            fixedTimeStep=config.time_step_s, numSolverIterations=config.solver_iterations,
            numSubSteps=0, deterministicOverlappingPairs=1, solverResidualThreshold=config.solver_residual_threshold, contactERP=config.contact_erp,
            frictionERP=config.friction_erp, contactSlop=config.contact_slop_m, enableConeFriction=1,
            enableSAT=1, physicsClientId=self.client)
        for name, mode in (("free_step", config.free_step), ("carry_step", config.carry_step)):
            if mode.time_step_s < config.time_step_s or mode.solver_iterations < 1:
                raise ValueError(f"SimConfig.{name} must not be shorter than time_step_s, and must iterate")
        self.time_s = 0.0
        self.steps = 0
        self.step_mode = "fine"
        self._modes = {"fine": StepMode(config.time_step_s, config.solver_iterations), "free": config.free_step,
                       "carry": config.carry_step}
        self._mode_start_s = 0.0
        self._mode_steps = 0

    # -- life cycle -------------------------------------------------------------------------------------------
    def close(self) -> None:
        if self.client >= 0 and p.isConnected(self.client):
            p.disconnect(self.client)
        self.client = -1

    def __enter__(self) -> "Simulator":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- loading ----------------------------------------------------------------------------------------------
    def load_urdf(self, path: str | Path, position_m: Sequence[float] = (0, 0, 0),
                  orientation_xyzw: Sequence[float] = (0, 0, 0, 1), fixed_base: bool = False) -> int:
        path = validate_urdf(path)
        try:
            body = p.loadURDF(str(path), basePosition=list(position_m), baseOrientation=list(orientation_xyzw),
                              useFixedBase=fixed_base, flags=URDF_FLAGS, physicsClientId=self.client)
        except p.error as exc:
            raise AssetError(f"{path}: PyBullet could not load it ({exc})") from None
        return body

    def create_primitive(self, shape: str, size_m: Sequence[float], mass_kg: float, position_m: Sequence[float],
                         orientation_xyzw: Sequence[float], rgba: Sequence[float]) -> int:
        """Create a rigid ``box`` (full sizes x, y, z) or ``cylinder`` (diameter, diameter, height) body."""
        if shape == "box":
            half = [s / 2 for s in size_m]
            col = p.createCollisionShape(p.GEOM_BOX, halfExtents=half, physicsClientId=self.client)
            vis = p.createVisualShape(p.GEOM_BOX, halfExtents=half, rgbaColor=list(rgba), physicsClientId=self.client)
        elif shape == "cylinder":
            return self._load_cylinder(size_m[0] / 2, size_m[2], mass_kg, position_m, orientation_xyzw, rgba)
        else:
            raise ValueError(f"unknown primitive shape {shape!r} (expected 'box' or 'cylinder')")
        return p.createMultiBody(baseMass=mass_kg, baseCollisionShapeIndex=col, baseVisualShapeIndex=vis,
                                 basePosition=list(position_m), baseOrientation=list(orientation_xyzw),
                                 physicsClientId=self.client)

    def _load_cylinder(self, radius_m: float, height_m: float, mass_kg: float, position_m: Sequence[float],
                       orientation_xyzw: Sequence[float], rgba: Sequence[float]) -> int:
        """A solid cylinder about its z axis, loaded from a one-link URDF so that it gets the polyhedral features
        of separating-axis contact (``createCollisionShape`` cannot ask for them).

        PyBullet makes it a 32-sided convex hull with a 1 mm collision margin. Against bodies with those features
        (the pad, the fingers, the table: every URDF) the margin does not count; against the scene's box objects
        (``createCollisionShape``) it did, so a cylinder met a box object 1 mm early: the margin is set to 0."""
        radius_m, height_m, mass_kg = float(radius_m), float(height_m), float(mass_kg)  # repr: plain numbers
        ixx = mass_kg * (3.0 * radius_m**2 + height_m**2) / 12.0
        izz = 0.5 * mass_kg * radius_m**2
        geometry = f'<geometry><cylinder radius="{radius_m!r}" length="{height_m!r}"/></geometry>'
        colour = " ".join(repr(float(c)) for c in rgba)
        text = (f'<?xml version="1.0"?><robot name="cylinder"><link name="body"><inertial><mass value="{mass_kg!r}"/>'
                f'<inertia ixx="{ixx!r}" iyy="{ixx!r}" izz="{izz!r}" ixy="0" ixz="0" iyz="0"/></inertial>'
                f'<visual>{geometry}<material name="c"><color rgba="{colour}"/></material></visual>'
                f'<collision>{geometry}</collision></link></robot>')
        with tempfile.TemporaryDirectory(prefix="robotdemo-") as folder:
            path = Path(folder) / "cylinder.urdf"
            path.write_text(text)
            body = p.loadURDF(str(path), basePosition=list(position_m), baseOrientation=list(orientation_xyzw),
                              flags=URDF_FLAGS, physicsClientId=self.client)
        p.changeDynamics(body, -1, collisionMargin=0.0, physicsClientId=self.client)
        return body

    def set_dynamics(self, body: int, link: int = -1, **kwargs: float) -> None:
        """Forward to ``changeDynamics`` (keyword names as PyBullet's: lateralFriction, contactStiffness, ...)."""
        p.changeDynamics(body, link, physicsClientId=self.client, **kwargs)

    def enable_sleeping(self, body: int, threshold: float) -> None:
        """Let ``body`` fall asleep once its linear (m/s) and angular (rad/s) speeds have stayed below
        ``threshold`` for Bullet's deactivation time; contact with an awake body wakes it."""
        if not threshold > 0.0:
            raise ValueError(f"sleep threshold must be > 0, got {threshold}")
        p.changeDynamics(body, -1, sleepThreshold=threshold, activationState=p.ACTIVATION_STATE_ENABLE_SLEEPING,
                         physicsClientId=self.client)

    # -- stepping ---------------------------------------------------------------------------------------------
    @property
    def time_step_s(self) -> float:
        """The physics step in use now, s."""
        return self._modes[self.step_mode].time_step_s

    def use_step_mode(self, mode: str, held_body: int | None = None) -> str:
        """Switch the physics step: ``"fine"`` (``time_step_s``, ``solver_iterations``, friction cone: contact
        that is measured or must be resolved finely), ``"free"`` (``free_step``) or ``"carry"``
        (``carry_step``). With ``held_body`` (the body in the hand), a mode is used only if the body weighs at
        least the mode's ``min_held_mass_kg``; the fine step otherwise. Returns the mode in use."""
        if mode not in self._modes:
            raise ValueError(f"unknown step mode {mode!r}; expected one of {STEP_MODES}")
        if held_body is not None and self._modes[mode].min_held_mass_kg > 0.0:
            if self.mass_kg(held_body) < self._modes[mode].min_held_mass_kg:
                mode = "fine"
        if mode == self.step_mode:
            return mode
        self._mode_start_s, self._mode_steps = self.time_s, 0
        self.step_mode = mode
        p.setPhysicsEngineParameter(fixedTimeStep=self._modes[mode].time_step_s,
                                    numSolverIterations=self._modes[mode].solver_iterations,
                                    enableConeFriction=int(self._modes[mode].cone_friction),
                                    physicsClientId=self.client)
        return mode

    def mass_kg(self, body: int) -> float:
        """Mass of ``body``'s base, kg."""
        return float(p.getDynamicsInfo(body, -1, physicsClientId=self.client)[0])

    def step(self, n: int = 1) -> None:
        """``n`` physics steps of the current mode."""
        for _ in range(n):
            p.stepSimulation(physicsClientId=self.client)
        self.steps += n
        self._mode_steps += n
        self.time_s = self._mode_start_s + self._mode_steps * self.time_step_s

    def advance(self, seconds: float) -> None:
        """Step the physics ``seconds`` of simulated time (a whole number of steps of the current mode)."""
        n = int(round(seconds / self.time_step_s))
        if n < 1 or abs(n * self.time_step_s - seconds) > 1e-9:
            raise ValueError(f"cannot advance {seconds} s in whole physics steps of {self.time_step_s} s")
        self.step(n)

    # -- queries ----------------------------------------------------------------------------------------------
    def joints(self, body: int) -> list[JointInfo]:
        out = []
        for j in range(p.getNumJoints(body, physicsClientId=self.client)):
            info = p.getJointInfo(body, j, physicsClientId=self.client)
            out.append(JointInfo(index=j, name=info[1].decode(), kind=info[2], lower_rad=info[8], upper_rad=info[9],
                                 effort_nm=info[10], velocity_radps=info[11], link_name=info[12].decode()))
        return out

    def joint_positions(self, body: int, joints: Sequence[int]) -> np.ndarray:
        states = p.getJointStates(body, list(joints), physicsClientId=self.client)
        q = np.array([s[0] for s in states])
        self._check_finite(q, f"joint positions of body {body}")
        return q

    def joint_velocities(self, body: int, joints: Sequence[int]) -> np.ndarray:
        states = p.getJointStates(body, list(joints), physicsClientId=self.client)
        return np.array([s[1] for s in states])

    def _link_state_tuples(self, body: int, link: int) -> tuple[tuple[float, ...], ...]:
        """PyBullet's position, orientation (xyzw), linear and angular velocity of a link frame (``link < 0``:
        the base), checked finite."""
        if link < 0:
            pos, orn = p.getBasePositionAndOrientation(body, physicsClientId=self.client)
            lin, ang = p.getBaseVelocity(body, physicsClientId=self.client)
        else:
            st = p.getLinkState(body, link, computeLinkVelocity=1, computeForwardKinematics=1,
                                physicsClientId=self.client)
            pos, orn, lin, ang = st[4], st[5], st[6], st[7]
        if not all(map(math.isfinite, (*pos, *lin))):  # per value: ~10x cheaper than numpy on 6 numbers
            raise SimulationError(f"simulation diverged: state of body {body} link {link} became NaN or inf "
                                  f"at t={self.time_s:.3f} s")
        return pos, orn, lin, ang

    def link_state(self, body: int, link: int) -> LinkState:
        pos, orn, lin, ang = self._link_state_tuples(body, link)
        return LinkState(np.array(pos), np.array(orn), np.array(lin), np.array(ang))

    def base_pose(self, body: int) -> tuple[np.ndarray, np.ndarray]:
        pos, orn = p.getBasePositionAndOrientation(body, physicsClientId=self.client)
        pos = np.array(pos)
        self._check_finite(pos, f"pose of body {body}")
        return pos, np.array(orn)

    def contact_points(self, body_a: int, body_b: int | None = None, link_a: int | None = None) -> list[ContactPoint]:
        """Contact points of the last step between ``body_a`` (optionally one link of it) and ``body_b``."""
        kwargs = {"bodyA": body_a, "physicsClientId": self.client}
        if body_b is not None:
            kwargs["bodyB"] = body_b
        if link_a is not None:
            kwargs["linkIndexA"] = link_a
        points = []
        for c in p.getContactPoints(**kwargs):
            cp = ContactPoint(body_a=c[1], body_b=c[2], link_a=c[3], link_b=c[4], position_on_a_m=np.array(c[5]),
                              position_on_b_m=np.array(c[6]), normal_on_b=np.array(c[7]), distance_m=c[8],
                              normal_force_n=c[9], lateral_friction1_n=c[10], lateral_friction_dir1=np.array(c[11]),
                              lateral_friction2_n=c[12], lateral_friction_dir2=np.array(c[13]))
            if not (math.isfinite(cp.normal_force_n) and math.isfinite(cp.lateral_friction1_n)
                    and math.isfinite(cp.lateral_friction2_n)):
                raise SimulationError(
                    f"simulation diverged: non-finite contact force between bodies {cp.body_a} and {cp.body_b} "
                    f"at t={self.time_s:.3f} s")
            points.append(cp)
        return points

    def pose_velocity_row(self, body: int, link: int) -> tuple[float, ...]:
        """A link frame's world position (3, m), orientation (4, xyzw) and linear velocity (3, m/s) as one flat
        tuple of floats: :meth:`link_state` without the arrays, for loops that log every physics step (building
        the arrays and records cost a stroke's recording as much as a tenth of the physics)."""
        pos, orn, lin, _ = self._link_state_tuples(body, link)
        return (*pos, *orn, *lin)

    def contact_rows(self, body_a: int, body_b: int, link_a: int) -> list[tuple[float, ...]]:
        """Contact points of the last step between one link of ``body_a`` and ``body_b`` as flat tuples of
        floats (the :class:`ContactPoint` fields): position on A (3, m), normal force (N), lateral friction 1
        (N) and its direction (3), lateral friction 2 (N) and its direction (3). For per-step logging."""
        rows = []
        for c in p.getContactPoints(bodyA=body_a, bodyB=body_b, linkIndexA=link_a, physicsClientId=self.client):
            if not (math.isfinite(c[9]) and math.isfinite(c[10]) and math.isfinite(c[12])):
                raise SimulationError(
                    f"simulation diverged: non-finite contact force between bodies {body_a} and {body_b} "
                    f"at t={self.time_s:.3f} s")
            rows.append((*c[5], c[9], c[10], *c[11], c[12], *c[13]))
        return rows

    def all_contact_points(self) -> list[ContactPoint]:
        return [cp for body in range(p.getNumBodies(physicsClientId=self.client))
                for cp in self.contact_points(p.getBodyUniqueId(body, physicsClientId=self.client))
                if cp.body_a < cp.body_b]

    def body_ids(self) -> list[int]:
        return [p.getBodyUniqueId(i, physicsClientId=self.client) for i in range(p.getNumBodies(physicsClientId=self.client))]

    def check_state_finite(self) -> None:
        """Raise :class:`SimulationError` if any body's pose or joint state has become NaN or inf."""
        for body in self.body_ids():
            self.base_pose(body)
            n = p.getNumJoints(body, physicsClientId=self.client)
            if n:
                self.joint_positions(body, range(n))

    def _check_finite(self, values: np.ndarray, what: str) -> None:
        if not np.all(np.isfinite(values)):
            raise SimulationError(f"simulation diverged: {what} became NaN or inf at t={self.time_s:.3f} s")

    # -- control ----------------------------------------------------------------------------------------------
    def disable_default_motors(self, body: int) -> None:
        """Every joint starts with a velocity motor; switch them off before torque control."""
        n = p.getNumJoints(body, physicsClientId=self.client)
        p.setJointMotorControlArray(body, list(range(n)), p.VELOCITY_CONTROL, forces=[0.0] * n,
                                    physicsClientId=self.client)

    def position_control(self, body: int, joints: Sequence[int], targets_rad: Sequence[float],
                         max_forces: Sequence[float], max_velocities: Sequence[float] | None = None,
                         target_velocities: Sequence[float] | None = None,
                         position_gain: float = 0.3, velocity_gain: float = 1.0) -> None:
        """Joint position servos: each motor pushes with at most ``max_forces`` (N m) and, like a real servo,
        moves no faster than ``max_velocities`` (rad/s; the URDF's limits when given)."""
        for k, j in enumerate(joints):
            kwargs = {}
            if max_velocities is not None:
                kwargs["maxVelocity"] = float(max_velocities[k])
            p.setJointMotorControl2(body, j, p.POSITION_CONTROL, targetPosition=float(targets_rad[k]),
                                    targetVelocity=0.0 if target_velocities is None else float(target_velocities[k]),
                                    force=float(max_forces[k]), positionGain=position_gain,
                                    velocityGain=velocity_gain, physicsClientId=self.client, **kwargs)

    def reset_joints(self, body: int, joints: Sequence[int], positions_rad: Sequence[float]) -> None:
        """Set joint positions directly (initialisation only, before the run starts)."""
        for j, q in zip(joints, positions_rad):
            p.resetJointState(body, j, q, 0.0, physicsClientId=self.client)

    def clamp_in_place(self, body: int, max_force_n: float = 1e4) -> int:
        """Hold ``body`` where it is now with a fixed joint to the world (a fixture clamping a sample to the
        table: the base stays put under forces up to ``max_force_n``). Returns the constraint's id. Its contacts
        with what it rests on stay; :meth:`robotdemo.scene.Scene.clamp` also switches those off."""
        position, orientation = p.getBasePositionAndOrientation(body, physicsClientId=self.client)
        constraint = p.createConstraint(body, -1, -1, -1, p.JOINT_FIXED, [0, 0, 0], [0, 0, 0], position,
                                        childFrameOrientation=orientation, physicsClientId=self.client)
        p.changeConstraint(constraint, maxForce=max_force_n, physicsClientId=self.client)
        return constraint

    def disable_collisions(self, body_a: int, body_b: int) -> None:
        """No contact between any link (base included) of ``body_a`` and any of ``body_b`` from now on."""
        links_a = range(-1, p.getNumJoints(body_a, physicsClientId=self.client))
        links_b = range(-1, p.getNumJoints(body_b, physicsClientId=self.client))
        for link_a in links_a:
            for link_b in links_b:
                p.setCollisionFilterPair(body_a, body_b, link_a, link_b, 0, physicsClientId=self.client)

    def remove_body(self, body: int) -> None:
        p.removeBody(body, physicsClientId=self.client)
