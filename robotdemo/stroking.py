"""A stroke executed in PyBullet: the controllers' force-regulated press-and-slide on a scene object.

Each control tick the measured pad normal force goes into :class:`controllers.stroke.StrokeController`, its
commanded pad pose is solved by IK (seeded with the last solution) and sent to the joint motors (URDF efforts).
Every physics step in between, until shortly after the lift-off, is recorded as a
:class:`perception.contact_trace.ContactTrace` row, which the sensor emulation turns into the four streams.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from controllers.stroke import StrokeCommand, StrokeConfig, StrokeController, StrokePhase
from perception.contact_trace import ContactTrace
from robotdemo.motion import ArmMotion, UnreachableError, hold, run_to_completion
from robotdemo.robot import GripperPosture
from robotdemo.scene import Scene, SceneObject

RAW_CONTACT_POINTS = 8
"""PyBullet's contact manifold holds at most 4 points per pair; room for a few more from edge contacts."""
STROKE_IK_LIMIT_M = 1e-3
"""A stroke fails when IK leaves the commanded pad pose this far away (m): the pose is out of reach. The force
IK converges to 0.1 um (``ArmMotion.force_ik``); a tick that stops short of that but within this limit goes on."""
PATCH_GRID = 4
MAX_CONTACT_POINTS = PATCH_GRID * PATCH_GRID


def distribute_patch(positions_m: np.ndarray, normal_n: np.ndarray, shear_n: np.ndarray,
                     valid: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Spread face-on-face contacts over their patch, for every time step at once.

    For two flat faces PyBullet reports the corners of the contact polygon, each carrying part of the load;
    the real pressure acts over the whole patch. A rigid flat contact has a pressure field linear in position,
    fixed by the total force and its first moments, which the corner forces give. Rows with three or more
    points get that field sampled at the centres of a PATCH_GRID x PATCH_GRID grid over the points' bounding
    rectangle (pad frame), with the shear shared in proportion to the local pressure (Coulomb friction).
    Rows with fewer points (an edge or a corner touching) keep them as they are.

    Args:
        positions_m: (T, P, 2) contact points on the pad, pad frame, m.
        normal_n: (T, P) normal force per point, N.
        shear_n: (T, P, 2) shear per point, pad frame, N.
        valid: (T, P) which points exist.

    Returns:
        positions (T, G, 2), normal (T, G), shear (T, G, 2), valid (T, G) with G = MAX_CONTACT_POINTS.
    """
    n_steps, n_points = normal_n.shape
    g = MAX_CONTACT_POINTS
    out_pos, out_normal = np.zeros((n_steps, g, 2)), np.zeros((n_steps, g))
    out_shear, out_valid = np.zeros((n_steps, g, 2)), np.zeros((n_steps, g), bool)
    k = min(n_points, g)
    out_pos[:, :k], out_normal[:, :k], out_shear[:, :k], out_valid[:, :k] = (
        positions_m[:, :k], normal_n[:, :k], shear_n[:, :k], valid[:, :k])
    normal = np.where(valid, normal_n, 0.0)
    total = normal.sum(axis=1)
    lo = np.where(valid[..., None], positions_m, np.inf).min(axis=1)
    hi = np.where(valid[..., None], positions_m, -np.inf).max(axis=1)
    patch = (valid.sum(axis=1) >= 3) & (total > 0) & np.all(hi - lo >= 1e-4, axis=1)
    if not patch.any():
        return out_pos, out_normal, out_shear, out_valid
    lo, hi, total = lo[patch], hi[patch], total[patch]
    centre, half = (lo + hi) / 2, (hi - lo) / 2  # (R, 2)
    offsets = (np.arange(PATCH_GRID) + 0.5) / PATCH_GRID * 2 - 1  # cell centres in [-1, 1]
    unit = np.stack(np.meshgrid(offsets, offsets, indexing="ij"), axis=-1).reshape(-1, 2)  # (G, 2)
    grid = unit[None] * half[:, None, :]  # (R, G, 2) relative to the centre
    moment = (normal[patch][..., None] * (positions_m[patch] - centre[:, None, :])).sum(axis=1)  # (R, 2)
    slope = moment / (total[:, None] / g * np.sum(grid**2, axis=1))
    weights = np.clip(1.0 + np.einsum("rgc,rc->rg", grid, slope), 0.0, None)
    weights /= weights.sum(axis=1, keepdims=True)
    shear_total = np.where(valid[patch][..., None], shear_n[patch], 0.0).sum(axis=1)  # (R, 2)
    out_pos[patch] = grid + centre[:, None, :]
    out_normal[patch] = total[:, None] * weights
    out_shear[patch] = shear_total[:, None, :] * weights[..., None]
    out_valid[patch] = True
    return out_pos, out_normal, out_shear, out_valid


def _rotation_matrices(xyzw: np.ndarray) -> np.ndarray:
    """(T, 4) quaternions (x, y, z, w) -> (T, 3, 3) rotation matrices (body -> world), normalised as Bullet's
    ``getMatrixFromQuaternion`` does (its quaternions are unit only to about 1e-8)."""
    x, y, z, w = xyzw.T
    s = 2.0 / np.sum(xyzw * xyzw, axis=1)
    return np.stack([
        np.stack([1 - s * (y * y + z * z), s * (x * y - z * w), s * (x * z + y * w)], axis=-1),
        np.stack([s * (x * y + z * w), 1 - s * (x * x + z * z), s * (y * z - x * w)], axis=-1),
        np.stack([s * (x * z - y * w), s * (y * z + x * w), 1 - s * (x * x + y * y)], axis=-1)], axis=1)


@dataclass
class _TraceRecorder:
    """Collects one row per physics step as the simulator reports it (flat tuples of floats: logging arrays
    step by step cost as much as a tenth of the physics); :meth:`to_trace` turns the rows into pad-frame
    quantities and spreads face-on-face contacts over their patch, all steps at once.

    Rows: ``pad`` and ``obj`` are :meth:`robotdemo.sim.Simulator.pose_velocity_row` of the pad link and the
    object, ``contacts`` up to ``RAW_CONTACT_POINTS`` :meth:`~robotdemo.sim.Simulator.contact_rows`, ``step_s``
    the physics step that led to the row.
    """

    gravity_mps2: float
    t_s: list = field(default_factory=list)
    step_s: list = field(default_factory=list)
    pad: list = field(default_factory=list)
    obj: list = field(default_factory=list)
    contacts: list = field(default_factory=list)

    def to_trace(self, last: int | None = None) -> ContactTrace:
        """The recorded rows (only the ``last`` ones if given) as a :class:`ContactTrace`."""
        n = len(self.t_s)
        start = max(0, n - last) if last else 0
        before = max(0, start - 1)  # the row before the first, for its acceleration
        pad, obj = np.array(self.pad[before:]).reshape(-1, 10), np.array(self.obj[before:]).reshape(-1, 10)
        accel_w = np.zeros((len(pad), 3))  # the stroke's first row has no velocity before it: 0
        accel_w[1:] = np.diff(pad[:, 7:10], axis=0) / np.array(self.step_s[before + 1:])[:, None]
        accel_w[:, 2] += self.gravity_mps2  # an accelerometer reads a - g
        keep = slice(start - before, None)
        pad, obj, accel_w = pad[keep], obj[keep], accel_w[keep]
        rot, rot_obj = _rotation_matrices(pad[:, 3:7]), _rotation_matrices(obj[:, 3:7])
        raw = np.zeros((len(pad), RAW_CONTACT_POINTS, 12))
        valid = np.zeros((len(pad), RAW_CONTACT_POINTS), bool)
        for i, rows in enumerate(self.contacts[start:]):
            if rows:
                raw[i, :len(rows)], valid[i, :len(rows)] = rows, True
        to_pad = rot[:, :, :2]  # world -> pad frame (x, y): v @ to_pad
        on_pad = np.einsum("tpj,tjk->tpk", raw[..., 0:3] - pad[:, None, 0:3], to_pad) * valid[..., None]
        shear_w = _rows_friction_n(raw)  # friction on the pad (body A)
        velocity = np.einsum("tji,tj->ti", rot, pad[:, 7:10] - obj[:, 7:10])  # pad relative to object, pad frame
        shear = opposing_slip(np.einsum("tpj,tjk->tpk", shear_w, to_pad), velocity[:, :2])
        on_pad, normal, shear, valid = distribute_patch(
            on_pad, np.where(raw[..., 3] > 0.0, raw[..., 3], 0.0), shear, valid)
        return ContactTrace(t_s=np.array(self.t_s[start:]), point_valid=valid, point_normal_force_n=normal,
                            point_shear_force_n=shear, point_position_on_pad_m=on_pad,
                            pad_position_on_object_m=np.einsum("tji,tj->ti", rot_obj, pad[:, 0:3] - obj[:, 0:3])[:, :2],
                            pad_velocity_mps=velocity,
                            pad_acceleration_mps2=np.einsum("tji,tj->ti", rot, accel_w))


@dataclass(frozen=True)
class StrokeResult:
    """What happened during one stroke.

    Attributes:
        success: the controller reached DONE.
        failure_reason: empty on success.
        trace: the contact at every physics step of the stroke, until ``release_record_s`` after the lift-off.
        force_log_n: (K,) measured pad normal force per control tick, N.
        phase_log: (K,) controller phase per control tick.
        commanded_m: (K, 3) commanded pad positions, world, m.
        actual_m: (K, 3) measured pad positions at the same ticks, world, m.
        tracking_error_m: (K,) distance between the commanded and the actual pad position, m.
        slide_start_m, slide_end_m: pad positions (world) where the slide phase began and ended.
        slide_duration_s: time spent in the slide phase, s.
    """

    config: StrokeConfig
    success: bool
    failure_reason: str
    trace: ContactTrace
    force_log_n: np.ndarray
    phase_log: tuple[StrokePhase, ...]
    commanded_m: np.ndarray
    actual_m: np.ndarray
    tracking_error_m: np.ndarray
    slide_start_m: np.ndarray | None
    slide_end_m: np.ndarray | None
    slide_duration_s: float


def top_surface_point(scene: Scene, obj: SceneObject, offset_xy_m=(0.0, 0.0)) -> np.ndarray:
    """World point on the object's top face, ``offset_xy_m`` from its centre in the object's frame."""
    state = scene.sim.link_state(obj.body, -1)
    return state.position_m + state.rotation @ np.array([offset_xy_m[0], offset_xy_m[1], obj.spec.size_m[2] / 2])


def pad_normal_force_n(scene: Scene, obj: SceneObject) -> float:
    """Total normal force between the pad and ``obj`` at the last physics step, N."""
    return float(sum(c.normal_force_n for c in scene.robot.pad_contacts(obj.body)))


def pad_shear_force_n(scene: Scene, obj: SceneObject) -> np.ndarray:
    """Total friction force of ``obj`` on the pad at the last physics step, (3,) world, N."""
    return sum((c.shear_force_n for c in scene.robot.pad_contacts(obj.body)), np.zeros(3))


SLIP_SPEED_MPS = 1e-3
"""Pad speed over the object above which the pad is sliding (:func:`opposing_slip`), m/s."""


def opposing_slip(shear_n: np.ndarray, slip_velocity_mps: np.ndarray,
                  slip_speed_mps: float = SLIP_SPEED_MPS) -> np.ndarray:
    """Friction turned to oppose the slip, its magnitude kept: Coulomb's law for a sliding contact.

    PyBullet solves the two friction directions of a multibody contact (fixed axes of the contact plane, world x
    and y for a level face) as separate constraints with their own effective masses, and only then scales the
    pair back into the friction cone (bullet3 pull request #4539 describes it). Their magnitude comes out right
    (mu N while sliding) but not their direction: sliding at 17 degrees to the world x axis over a clamped
    0.94 kg steel block, the friction on the pad points 29 degrees off the slip, by an angle that grows with the
    object's mass and depends on how the slide lies in the world. A sensor would record Coulomb friction, opposite
    to the slip. So while the pad slides the friction keeps the simulator's magnitude and takes the direction
    against the slip; while it sticks (static friction, no slip to oppose) the simulator's vector stays. The two
    blend with w = v^2 / (v^2 + v_s^2), v the pad's speed over the object and v_s ``slip_speed_mps``.

    Args:
        shear_n: (T, P, 2) friction on the pad at each contact point, pad frame, N.
        slip_velocity_mps: (T, 2) the pad's velocity over the object in the pad plane, pad frame, m/s.
        slip_speed_mps: v_s, m/s.

    Returns:
        (T, P, 2) the friction, pad frame, N.
    """
    speed = np.linalg.norm(slip_velocity_mps, axis=-1, keepdims=True)  # (T, 1)
    against = -slip_velocity_mps / np.maximum(speed, 1e-12)  # (T, 2)
    sliding = (speed**2 / (speed**2 + slip_speed_mps**2))[:, None]  # (T, 1, 1)
    magnitude = np.linalg.norm(shear_n, axis=-1, keepdims=True)  # (T, P, 1)
    return (1.0 - sliding) * shear_n + sliding * magnitude * against[:, None, :]


def _rows_friction_n(raw: np.ndarray) -> np.ndarray:
    """The friction force on body A of each :meth:`~robotdemo.sim.Simulator.contact_rows` row, (..., 3) world,
    N: f1 * dir1 + f2 * dir2, as :attr:`~robotdemo.sim.ContactPoint.shear_force_n`."""
    return raw[..., 4:5] * raw[..., 5:8] + raw[..., 8:9] * raw[..., 9:12]


def _row_shear_n(rows: list[tuple[float, ...]]) -> np.ndarray:
    """The summed friction force on body A of :meth:`~robotdemo.sim.Simulator.contact_rows`, (3,) world, N."""
    return _rows_friction_n(np.asarray(rows)).sum(axis=0) if rows else np.zeros(3)


def move_pad_above(scene: Scene, motion: ArmMotion, config: StrokeConfig) -> np.ndarray:
    """Fold the hand into the stroke posture and move (Ruckig) so the pad hovers over the stroke's start."""
    robot = scene.robot
    scene.sim.use_step_mode("free")  # nothing touched yet: the coarse step (the stroke itself switches to fine)
    robot.command_gripper(GripperPosture.stroke())
    hover = np.asarray(config.start_point_m) + config.normal() * config.approach_height_m
    above = hover + config.normal() * 0.03
    sol_above = motion.solve_pad(above, config.rotation())
    sol_hover = motion.solve_pad(hover, config.rotation(), q=sol_above.q)
    for name, sol, point in (("above", sol_above, above), ("hover", sol_hover, hover)):
        if not sol.success:
            raise UnreachableError(f"stroke {name} point {np.round(point, 3).tolist()} m is unreachable "
                                   f"(IK residual {sol.position_error_m * 1000:.2f} mm)")
    run_to_completion(motion.plan_path([sol_above.q, sol_hover.q]))
    hold(robot, 0.1)
    return hover


@dataclass(frozen=True)
class _LoggedStep:
    """What the last logged physics step measured, for the control tick that follows it."""

    physics_step: int
    pad_force_n: float
    pad_shear_n: np.ndarray
    pad_position_m: np.ndarray


class StrokeExecution:
    """One stroke on ``obj``, advanced one control tick per :meth:`step` (the pad must already hover at the
    start, see :func:`move_pad_above`). :meth:`result` gives the :class:`StrokeResult` once :attr:`finished`.

    Every physics step is recorded at the fine step until the pad, lifting, has touched nothing for
    ``release_record_s``: the recording then ends and the rest of the lift runs at the coarse ``"free"`` step,
    as the move to the hover point did. The whole lift was 15 % of a stroke's physics (0.37 of 2.5 s at
    the fine step, scratch, the data set's draws) with the pad in the air for all but its first tens of ms.
    """

    def __init__(self, scene: Scene, motion: ArmMotion, obj: SceneObject, config: StrokeConfig,
                 max_time_s: float = 20.0, release_record_s: float = 0.1) -> None:
        if not release_record_s > 0.0:
            raise ValueError(f"release_record_s must be > 0 s, got {release_record_s}")
        self.scene, self.motion, self.obj, self.config = scene, motion, obj, config
        self.release_record_s = release_record_s
        self.recording = True
        """Whether the physics steps are still recorded (False once the lift has cleared the surface)."""
        self._clear_steps = 0
        self.max_ticks = int(max_time_s / motion.config.control_period_s)
        self.controller = StrokeController(config, scene.robot.tool_state().position_m)
        self.q = scene.robot.arm_q()
        self.recorder = _TraceRecorder(gravity_mps2=scene.sim.config.gravity_mps2)
        self.forces: list[float] = []
        self.phases: list[StrokePhase] = []
        self.commanded: list[np.ndarray] = []
        self.actual: list[np.ndarray] = []
        self.errors: list[float] = []
        self.slide_start: np.ndarray | None = None
        self.slide_end: np.ndarray | None = None
        self.slide_time_s = 0.0
        self.command: StrokeCommand | None = None
        self.ik_failure = ""
        """Why IK could not follow the stroke's command (then the stroke has failed); empty otherwise."""
        self._last_logged: _LoggedStep | None = None

    @property
    def finished(self) -> bool:
        return self.command is not None and (self.command.done or self.command.failed or bool(self.ik_failure)
                                             or len(self.forces) >= self.max_ticks)

    @property
    def phase(self) -> StrokePhase | None:
        return None if self.command is None else self.command.phase

    def step(self) -> bool:
        """One control tick: measure, update the controller, solve IK, command, step the physics. True when finished."""
        if self.finished:
            return True
        robot, motion = self.scene.robot, self.motion
        dt = motion.config.control_period_s
        if self._last_logged is not None and self._last_logged.physics_step == self.scene.sim.steps:
            logged = self._last_logged
            force, shear, pad_position = logged.pad_force_n, logged.pad_shear_n, logged.pad_position_m
        else:  # nothing logged since the physics last stepped: measure
            force, shear = pad_normal_force_n(self.scene, self.obj), pad_shear_force_n(self.scene, self.obj)
            pad_position = robot.tool_state().position_m
        command = self.command = self.controller.step(force, dt, shear)
        self.forces.append(force)
        self.phases.append(command.phase)
        self.commanded.append(command.position_m)
        self.actual.append(pad_position)
        self.errors.append(float(np.linalg.norm(self.actual[-1] - command.position_m)))
        if command.phase is StrokePhase.SLIDE:
            if self.slide_start is None:
                self.slide_start = self.actual[-1]
            self.slide_time_s += dt
            self.slide_end = self.actual[-1]
        if command.done or command.failed:
            return True
        sol = motion.force_ik.solve_local(motion.to_base(command.position_m, command.rotation), self.q)
        if not sol.success and sol.position_error_m > STROKE_IK_LIMIT_M:
            self.ik_failure = (f"IK cannot follow the stroke in {command.phase.value} at "
                               f"{np.round(command.position_m, 3).tolist()} m (residual "
                               f"{sol.position_error_m * 1000:.1f} mm)")
            return True
        q_from, self.q = self.q, sol.q
        sim = self.scene.sim
        if not self.recording:
            robot.command_arm(self.q)
            sim.use_step_mode("free")
            sim.advance(dt)
            return self.finished
        # The stroke is the measurement: every contact at the fine step, and the joint targets move on at every
        # step, linearly from the last tick's to this one's. A target held for the whole tick makes the position
        # servo jerk the pad forward at each tick and brake it in between: a sawtooth in the sliding speed at the
        # tick rate (46 / 34 / 24 / 16 mm/s at 30 mm/s) that every material would share and the accelerometer
        # would record. (The tick's joint velocity as the motors' target velocity as well would make them push
        # on into the surface at touch-down: 2.3 times the target force on granite, 1.05 times without.)
        sim.use_step_mode("fine")
        for k in range(1, motion.substeps + 1):
            robot.command_arm(q_from + (self.q - q_from) * (k / motion.substeps))
            sim.step()
            self._record_physics_step()
        if command.phase is StrokePhase.LIFT and self._clear_steps * sim.time_step_s >= self.release_record_s - 1e-9:
            self.recording = False
        return self.finished

    def _record_physics_step(self) -> None:
        sim, robot, rec = self.scene.sim, self.scene.robot, self.recorder
        pad = sim.pose_velocity_row(robot.body, robot.tool_link)
        obj = sim.pose_velocity_row(self.obj.body, -1)
        contacts = sim.contact_rows(robot.body, self.obj.body, link_a=robot.pad_link)
        rec.t_s.append(sim.time_s)
        rec.step_s.append(sim.time_step_s)
        rec.pad.append(pad)
        rec.obj.append(obj)
        rec.contacts.append(contacts[:RAW_CONTACT_POINTS])
        self._clear_steps = 0 if contacts else self._clear_steps + 1
        # what the next control tick measures (the same sums as pad_normal_force_n and pad_shear_force_n)
        self._last_logged = _LoggedStep(sim.steps, float(sum(c[3] for c in contacts)), _row_shear_n(contacts),
                                        np.array(pad[0:3]))

    def result(self) -> StrokeResult:
        command = self.command
        if command is None:
            raise RuntimeError("the stroke has not started")
        if self.ik_failure:
            failure = self.ik_failure
        else:
            failure = (command.failure_reason if command.failed
                       else "" if command.done else "stroke did not finish in time")
        return StrokeResult(config=self.config, success=command.done and not self.ik_failure, failure_reason=failure,
                            trace=self.recorder.to_trace(), force_log_n=np.array(self.forces),
                            phase_log=tuple(self.phases), commanded_m=np.array(self.commanded),
                            actual_m=np.array(self.actual), tracking_error_m=np.array(self.errors),
                            slide_start_m=self.slide_start, slide_end_m=self.slide_end,
                            slide_duration_s=self.slide_time_s)


def run_stroke(scene: Scene, motion: ArmMotion, obj: SceneObject, config: StrokeConfig,
               max_time_s: float = 20.0) -> StrokeResult:
    """Execute a whole stroke (see :class:`StrokeExecution`) and return its result."""
    execution = StrokeExecution(scene, motion, obj, config, max_time_s)
    while not execution.step():
        pass
    return execution.result()


def cruise_speed_mps(result: StrokeResult, period_s: float) -> float:
    """Mean pad speed over the middle half of the slide (past the jerk-limited ramps), m/s."""
    ticks = [i for i, phase in enumerate(result.phase_log) if phase is StrokePhase.SLIDE]
    if len(ticks) < 8:
        return 0.0
    a, b = ticks[len(ticks) // 4], ticks[3 * len(ticks) // 4]
    return float(np.linalg.norm(result.actual_m[b] - result.actual_m[a]) / ((b - a) * period_s))


def sliding_friction(trace: ContactTrace, min_speed_mps: float = 0.005, min_normal_n: float = 0.2) -> float | None:
    """The friction coefficient the pad felt while sliding: median over physics steps of |total shear| /
    total normal, over the steps where the pad slid (tangential speed at least ``min_speed_mps``) under at
    least ``min_normal_n``; ``None`` without such steps. What a calibrated three-axis fingertip sensor reads
    as kinetic friction against the pad."""
    valid = trace.point_valid
    normal = np.where(valid, trace.point_normal_force_n, 0.0).sum(axis=1)  # (T,)
    shear = np.where(valid[..., None], trace.point_shear_force_n, 0.0).sum(axis=1)  # (T, 2)
    speed = np.linalg.norm(trace.pad_velocity_mps[:, :2], axis=1)  # (T,)
    sliding = (speed >= min_speed_mps) & (normal >= min_normal_n)
    if not np.any(sliding):
        return None
    return float(np.median(np.linalg.norm(shear[sliding], axis=1) / normal[sliding]))
