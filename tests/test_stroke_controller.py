"""Stroke controller against a simulated spring surface (F = k * max(0, penetration)) with first-order lags."""

from dataclasses import dataclass

import numpy as np
import pytest

from controllers.stroke import StrokeCommand, StrokeConfig, StrokeController, StrokePhase

DT_S = 1.0 / 240.0
START_M = (0.35, 0.05, 0.10)


@dataclass
class SpringSurface:
    """Plane z = height_m + tilt * (x - x0) of stiffness k; the tool tracks the command with a first-order lag
    (``tool_lag_s``, the arm's position loop) and the sensor reading lags the true force (``sensor_lag_s``)."""

    stiffness_n_per_m: float
    height_m: float = START_M[2]
    tilt: float = 0.0
    tool_lag_s: float = 0.01
    sensor_lag_s: float = 0.01

    def __post_init__(self) -> None:
        self.measured_n = 0.0

    def step(self, tool_m: np.ndarray, command: StrokeCommand) -> tuple[np.ndarray, float]:
        tool_m = tool_m + (command.position_m - tool_m) * min(1.0, DT_S / self.tool_lag_s)
        surface_z = self.height_m + self.tilt * (tool_m[0] - START_M[0])
        true_n = self.stiffness_n_per_m * max(0.0, surface_z - tool_m[2])
        self.measured_n += (true_n - self.measured_n) * min(1.0, DT_S / self.sensor_lag_s)
        return tool_m, self.measured_n


def run_stroke(config: StrokeConfig, surface: SpringSurface, max_time_s: float = 20.0):
    tool = np.array(config.start_point_m) + np.array([0.0, 0.0, 0.03])
    controller = StrokeController(config, tool)
    log, force = [], 0.0
    for _ in range(int(max_time_s / DT_S)):
        command = controller.step(force, DT_S)
        tool, force = surface.step(tool, command)
        log.append((command, force, tool.copy()))
        if command.done or command.failed:
            break
    return log


@pytest.mark.parametrize("stiffness_n_per_m", [2e3, 1e5], ids=["soft", "hard"])
@pytest.mark.parametrize("target_force_n, speed_mps, length_m",
                         [(0.5, 0.05, 0.02), (2.0, 0.02, 0.04), (5.0, 0.005, 0.06)])
def test_stroke_holds_force_and_slides_at_speed(stiffness_n_per_m, target_force_n, speed_mps, length_m):
    config = StrokeConfig(target_force_n=target_force_n, speed_mps=speed_mps, length_m=length_m,
                          direction_rad=0.7, start_point_m=START_M)
    log = run_stroke(config, SpringSurface(stiffness_n_per_m))
    commands = [c for c, _, _ in log]
    assert commands[-1].done, commands[-1].failure_reason
    phases = [c.phase for c in commands]
    assert phases.index(StrokePhase.PRESS) < phases.index(StrokePhase.SETTLE) < phases.index(StrokePhase.SLIDE) \
        < phases.index(StrokePhase.LIFT) < phases.index(StrokePhase.DONE)
    forces = np.array([f for _, f, _ in log])
    assert np.max(forces[[p in (StrokePhase.PRESS, StrokePhase.SETTLE) for p in phases]]) >= 0.9 * target_force_n

    sliding = [i for i, p in enumerate(phases) if p is StrokePhase.SLIDE]
    assert np.all(np.abs(forces[sliding] - target_force_n) <= 0.2 * target_force_n)

    # Distance and speed of the actual (lagging) tool along the slide direction.
    direction = config.slide_direction()
    tools = np.array([t for _, _, t in log])
    along = tools @ direction
    slid = along[sliding[-1] + 1] - along[sliding[0] - 1]
    assert slid == pytest.approx(length_m, rel=0.02)
    speed = np.diff(along[sliding]) / DT_S
    assert np.max(speed) == pytest.approx(speed_mps, rel=0.1)
    assert np.median(speed[speed > 0.5 * speed_mps]) == pytest.approx(speed_mps, rel=0.1)
    assert abs(np.diff(tools[sliding] @ config.normal()).max()) < 1e-3  # no jumps along the normal

    # Held orientation: pad z against the surface normal; lifted clear at the end.
    np.testing.assert_allclose(commands[-1].rotation[:, 2], -config.normal(), atol=1e-12)
    assert tools[-1][2] > START_M[2] + 0.5 * config.approach_height_m
    assert forces[-1] == pytest.approx(0.0, abs=1e-6)


def test_press_descends_within_the_acceleration_limit_and_meets_the_surface_slowly():
    # before: PRESS jumped from rest to 10 mm/s in one tick (2.4 m/s^2 at 240 Hz), then to 2 mm/s in another
    config = StrokeConfig(target_force_n=2.0, start_point_m=START_M)
    log = run_stroke(config, SpringSurface(1e4))
    assert log[-1][0].done, log[-1][0].failure_reason
    press = [c for c, _, _ in log if c.phase is StrokePhase.PRESS and not c.force_control_active]
    offsets = np.array([c.normal_offset_m for c in press])
    speed = -np.diff(offsets) / DT_S
    acceleration = np.diff(speed) / DT_S
    assert speed.max() == pytest.approx(config.press_speed_mps, rel=1e-6)
    assert np.abs(acceleration).max() <= config.slide_acceleration_mps2 * 1.001
    assert np.abs(np.diff(acceleration)).max() / DT_S <= config.slide_jerk_mps3 * 1.001
    in_slow_zone = offsets[1:] <= config.slow_zone_m
    assert in_slow_zone.any()
    assert speed[in_slow_zone].max() <= config.contact_speed_mps * (1 + 1e-6)  # braked before it
    assert speed[-1] == pytest.approx(config.contact_speed_mps, rel=1e-6)  # at contact


def test_force_tracks_a_slightly_tilted_soft_surface():
    config = StrokeConfig(target_force_n=2.0, speed_mps=0.02, length_m=0.05, start_point_m=START_M)
    log = run_stroke(config, SpringSurface(2e3, tilt=0.02))
    assert log[-1][0].done
    forces = np.array([f for c, f, _ in log if c.phase is StrokePhase.SLIDE])
    assert np.all(np.abs(forces - 2.0) <= 0.2 * 2.0)


@pytest.mark.parametrize("offset_m", [0.004, -0.006, 0.025])
def test_surface_away_from_where_expected(offset_m):
    config = StrokeConfig(target_force_n=1.0, start_point_m=START_M)
    log = run_stroke(config, SpringSurface(1e4, height_m=START_M[2] + offset_m))
    assert log[-1][0].done, log[-1][0].failure_reason


def test_missing_surface_fails_with_a_reason():
    config = StrokeConfig(start_point_m=START_M)
    log = run_stroke(config, SpringSurface(1e5, height_m=START_M[2] - 0.1))
    last = log[-1][0]
    assert last.failed and last.phase is StrokePhase.FAILED
    assert "max_press_depth_m" in last.failure_reason
    assert last.normal_offset_m >= -config.max_press_depth_m - 1e-3


def test_non_finite_force_and_overload_fail():
    config = StrokeConfig(start_point_m=START_M)
    controller = StrokeController(config, np.array(START_M) + [0, 0, 0.02])
    controller.step(0.0, DT_S)
    command = controller.step(float("nan"), DT_S)
    assert command.failed and "non-finite" in command.failure_reason
    # FAILED holds the last pose.
    again = controller.step(0.0, DT_S)
    np.testing.assert_array_equal(again.position_m, command.position_m)
    controller.reset(np.array(START_M) + [0, 0, 0.02])
    command = controller.step(config.max_force_n + 1.0, DT_S)
    assert command.failed and "max_force_n" in command.failure_reason


def test_time_budget():
    config = StrokeConfig(start_point_m=START_M, time_budget_s=1.0)
    log = run_stroke(config, SpringSurface(2e3))
    assert log[-1][0].failed and "time budget" in log[-1][0].failure_reason


@pytest.mark.parametrize("field, value", [("target_force_n", 6.0), ("target_force_n", 0.2), ("speed_mps", 0.1),
                                          ("length_m", 0.01), ("approach_height_m", 0.0),
                                          ("surface_normal", (0.0, 0.0, 0.0))])
def test_config_is_validated(field, value):
    with pytest.raises(ValueError, match=field):
        StrokeConfig(**{field: value})


def test_direction_lies_in_the_surface_plane():
    config = StrokeConfig(surface_normal=(0.0, 1.0, 1.0), direction_rad=1.1)
    d, n = config.slide_direction(), config.normal()
    assert abs(d @ n) < 1e-12 and np.linalg.norm(d) == pytest.approx(1.0)
    R = config.rotation()
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)


@dataclass
class StickySurface(SpringSurface):
    """A spring surface whose contact also carries Coulomb friction through a lateral contact spring
    (``lateral_stiffness_n_per_m``, stuck below ``friction * normal``, slipping above), on a tool that sags
    sideways under load by ``sag_m_per_n`` along x: the sub-micrometre mismatch a rigid arm's press makes."""

    lateral_stiffness_n_per_m: float = 2e6
    friction: float = 0.8
    sag_m_per_n: float = 0.5e-6

    def __post_init__(self) -> None:
        super().__post_init__()
        self.anchor_m: np.ndarray | None = None
        self.shear_n = np.zeros(3)

    def step(self, tool_m: np.ndarray, command: StrokeCommand) -> tuple[np.ndarray, float]:
        tool_m, measured_n = super().step(tool_m, command)
        if measured_n <= 0.0:
            self.anchor_m, self.shear_n = None, np.zeros(3)
            return tool_m, measured_n
        contact_m = tool_m + np.array([self.sag_m_per_n * measured_n, 0.0, 0.0])
        contact_m[2] = 0.0
        if self.anchor_m is None:
            self.anchor_m = contact_m.copy()
        shear = self.lateral_stiffness_n_per_m * (self.anchor_m - contact_m)
        limit = self.friction * measured_n
        if np.linalg.norm(shear) > limit:  # slipping: the anchor trails the contact at the friction limit
            shear *= limit / np.linalg.norm(shear)
            self.anchor_m = contact_m + shear / self.lateral_stiffness_n_per_m
        self.shear_n = shear
        return tool_m, measured_n


def _pre_slide_shear_n(config: StrokeConfig) -> tuple[float, list[StrokeCommand]]:
    """|shear| at the last tick before the slide on a :class:`StickySurface`, and the commands."""
    surface = StickySurface(1e5)
    tool = np.array(config.start_point_m) + np.array([0.0, 0.0, 0.03])
    controller = StrokeController(config, tool)
    commands, force, before_slide = [], 0.0, None
    for _ in range(int(20.0 / DT_S)):
        command = controller.step(force, DT_S, surface.shear_n)
        commands.append(command)
        if command.phase is StrokePhase.SLIDE and before_slide is None:
            before_slide = float(np.linalg.norm(surface.shear_n))
        if command.done or command.failed:
            break
        tool, force = surface.step(tool, command)
    assert commands[-1].done, commands[-1].failure_reason
    return before_slide, commands


def test_lateral_admittance_sheds_the_press_shear_and_holds_its_yield_while_sliding():
    """A press on a sticky surface with a sagging tool builds shear (about k * sag * F = 4 N, capped by
    friction); yielding to it, the pad reaches the slide all but unloaded, and the yield stays put from then on."""
    rigid, _ = _pre_slide_shear_n(StrokeConfig(target_force_n=4.0, start_point_m=START_M,
                                               lateral_damping_n_s_per_m=0.0))
    yielding, commands = _pre_slide_shear_n(StrokeConfig(target_force_n=4.0, start_point_m=START_M))
    assert rigid > 2.0
    assert yielding < 0.05
    slide = [c for c in commands if c.phase in (StrokePhase.SLIDE, StrokePhase.LIFT, StrokePhase.DONE)]
    yields = np.array([c.lateral_yield_m for c in slide])
    assert np.linalg.norm(yields[0]) > 1e-6  # it did yield, along the sag (x) ...
    np.testing.assert_array_equal(yields, np.broadcast_to(yields[0], yields.shape))  # ... and holds it
    assert abs(yields[0][2]) < 1e-12  # in the surface plane


def test_lateral_yield_ignores_the_normal_part_and_is_capped():
    config = StrokeConfig(target_force_n=2.0, start_point_m=START_M, settle_timeout_s=10.0, settle_time_s=8.0)
    controller = StrokeController(config, np.array(START_M))  # at the surface: contact at once
    for _ in range(200):
        command = controller.step(2.0, DT_S, np.array([0.0, 0.0, 5.0]))  # a purely normal "shear"
    np.testing.assert_array_equal(command.lateral_yield_m, np.zeros(3))
    for _ in range(1000):  # 4.2 s: the yield reaches its cap after about 3.3 s at 3 N / 2e4 N s/m
        command = controller.step(2.0, DT_S, np.array([0.0, 3.0, 0.0]))  # a shear that never goes away
    assert command.phase is StrokePhase.SETTLE
    assert np.linalg.norm(command.lateral_yield_m) == pytest.approx(config.max_lateral_yield_m)
    assert command.lateral_yield_m[1] > 0  # the pad gives way in the direction the surface pushes it


def test_non_finite_shear_fails():
    controller = StrokeController(StrokeConfig(start_point_m=START_M), np.array(START_M))
    command = controller.step(1.0, DT_S, np.array([0.0, float("nan"), 0.0]))
    assert command.failed and "shear" in command.failure_reason
