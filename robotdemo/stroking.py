"""A stroke executed in PyBullet: the controllers' force-regulated press-and-slide on a scene object.

Each control tick the measured pad normal force goes into :class:`controllers.stroke.StrokeController`, its
commanded pad pose is solved by IK (seeded with the last solution) and sent to the joint motors (URDF efforts).
Every physics step in between is recorded as a :class:`perception.contact_trace.ContactTrace` row, which the
sensor emulation turns into the four streams.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from controllers.stroke import StrokeCommand, StrokeConfig, StrokeController, StrokePhase
from perception.contact_trace import ContactTrace
from robotdemo.motion import ArmMotion, hold, run_to_completion
from robotdemo.robot import GripperPosture
from robotdemo.scene import Scene, SceneObject

MAX_CONTACT_POINTS = 8


@dataclass
class _TraceRecorder:
    """Collects one row per physics step."""

    t_s: list = field(default_factory=list)
    valid: list = field(default_factory=list)
    normal: list = field(default_factory=list)
    shear: list = field(default_factory=list)
    on_pad: list = field(default_factory=list)
    on_object: list = field(default_factory=list)
    velocity: list = field(default_factory=list)
    acceleration: list = field(default_factory=list)

    def to_trace(self) -> ContactTrace:
        return ContactTrace(t_s=np.array(self.t_s), point_valid=np.array(self.valid),
                            point_normal_force_n=np.array(self.normal), point_shear_force_n=np.array(self.shear),
                            point_position_on_pad_m=np.array(self.on_pad),
                            pad_position_on_object_m=np.array(self.on_object),
                            pad_velocity_mps=np.array(self.velocity), pad_acceleration_mps2=np.array(self.acceleration))


@dataclass(frozen=True)
class StrokeResult:
    """What happened during one stroke.

    Attributes:
        success: the controller reached DONE.
        failure_reason: empty on success.
        trace: the contact at every physics step of the stroke.
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
    pos, orn = scene.object_pose(obj)
    rot = np.asarray(scene.sim.link_state(obj.body, -1).rotation)
    return pos + rot @ np.array([offset_xy_m[0], offset_xy_m[1], obj.spec.size_m[2] / 2])


def pad_normal_force_n(scene: Scene, obj: SceneObject) -> float:
    """Total normal force between the pad and ``obj`` at the last physics step, N."""
    return float(sum(c.normal_force_n for c in scene.robot.pad_contacts(obj.body)))


def move_pad_above(scene: Scene, motion: ArmMotion, config: StrokeConfig) -> np.ndarray:
    """Fold the hand into the stroke posture and move (Ruckig) so the pad hovers over the stroke's start."""
    robot = scene.robot
    robot.command_gripper(GripperPosture.stroke())
    hover = np.asarray(config.start_point_m) + config.normal() * config.approach_height_m
    above = hover + config.normal() * 0.03
    sol_above = motion.solve_pad(above, config.rotation())
    sol_hover = motion.solve_pad(hover, config.rotation(), q=sol_above.q)
    for name, sol, point in (("above", sol_above, above), ("hover", sol_hover, hover)):
        if not sol.success:
            from robotdemo.motion import UnreachableError
            raise UnreachableError(f"stroke {name} point {np.round(point, 3).tolist()} m is unreachable "
                                   f"(IK residual {sol.position_error_m * 1000:.2f} mm)")
    run_to_completion(motion.plan_path([sol_above.q, sol_hover.q]))
    hold(robot, 0.1)
    return hover


def run_stroke(scene: Scene, motion: ArmMotion, obj: SceneObject, config: StrokeConfig,
               max_time_s: float = 20.0) -> StrokeResult:
    """Execute one stroke on ``obj`` (the pad must already hover at the start, see :func:`move_pad_above`)."""
    robot, sim = scene.robot, scene.sim
    dt = motion.config.control_period_s
    physics_dt = sim.config.time_step_s
    pad_pos = robot.tool_state().position_m
    controller = StrokeController(config, pad_pos)
    q = robot.arm_q()
    rec = _TraceRecorder()
    forces, phases, commanded, actual, errors = [], [], [], [], []
    slide_start = slide_end = None
    slide_time = 0.0
    prev_velocity = None
    command: StrokeCommand | None = None
    gravity = np.array([0.0, 0.0, sim.config.gravity_mps2])
    for _tick in range(int(max_time_s / dt)):
        force = pad_normal_force_n(scene, obj)
        command = controller.step(force, dt)
        forces.append(force)
        phases.append(command.phase)
        commanded.append(command.position_m)
        actual.append(robot.tool_state().position_m)
        errors.append(float(np.linalg.norm(actual[-1] - command.position_m)))
        if command.phase is StrokePhase.SLIDE:
            if slide_start is None:
                slide_start = robot.tool_state().position_m
            slide_time += dt
            slide_end = robot.tool_state().position_m
        if command.done or command.failed:
            break
        sol = motion.pad_ik.solve_local(motion.to_base(command.position_m, command.rotation), q)
        q = sol.q
        robot.command_arm(q)
        for _ in range(motion.substeps):
            sim.step()
            pad = robot.tool_state()
            rot = pad.rotation
            obj_state = sim.link_state(obj.body, -1)
            velocity_w = pad.linear_velocity_mps - obj_state.linear_velocity_mps
            accel_w = np.zeros(3) if prev_velocity is None else (pad.linear_velocity_mps - prev_velocity) / physics_dt
            prev_velocity = pad.linear_velocity_mps
            valid = np.zeros(MAX_CONTACT_POINTS, bool)
            normal = np.zeros(MAX_CONTACT_POINTS)
            shear = np.zeros((MAX_CONTACT_POINTS, 2))
            on_pad = np.zeros((MAX_CONTACT_POINTS, 2))
            for k, c in enumerate(robot.pad_contacts(obj.body)[:MAX_CONTACT_POINTS]):
                valid[k] = True
                normal[k] = max(0.0, c.normal_force_n)
                # PyBullet reports the friction impulse acting on body B (the object); the pad feels the opposite
                shear[k] = (rot.T @ (-c.shear_force_n))[:2]
                on_pad[k] = (rot.T @ (c.position_on_a_m - pad.position_m))[:2]
            rec.t_s.append(sim.time_s)
            rec.valid.append(valid)
            rec.normal.append(normal)
            rec.shear.append(shear)
            rec.on_pad.append(on_pad)
            rec.on_object.append((obj_state.rotation.T @ (pad.position_m - obj_state.position_m))[:2])
            rec.velocity.append(rot.T @ velocity_w)
            rec.acceleration.append(rot.T @ (accel_w + gravity))
    assert command is not None
    failure = command.failure_reason if command.failed else ("" if command.done else "stroke did not finish in time")
    return StrokeResult(config=config, success=command.done, failure_reason=failure, trace=rec.to_trace(),
                        force_log_n=np.array(forces), phase_log=tuple(phases), commanded_m=np.array(commanded),
                        actual_m=np.array(actual),                         tracking_error_m=np.array(errors), slide_start_m=slide_start, slide_end_m=slide_end,
                        slide_duration_s=slide_time)


def cruise_speed_mps(result: StrokeResult, period_s: float) -> float:
    """Mean pad speed over the middle half of the slide (past the jerk-limited ramps), m/s."""
    ticks = [i for i, phase in enumerate(result.phase_log) if phase is StrokePhase.SLIDE]
    if len(ticks) < 8:
        return 0.0
    a, b = ticks[len(ticks) // 4], ticks[3 * len(ticks) // 4]
    return float(np.linalg.norm(result.actual_m[b] - result.actual_m[a]) / ((b - a) * period_s))
