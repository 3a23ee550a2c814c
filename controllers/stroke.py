"""Stroke controller: press the tactile pad onto a surface with a set normal force and slide it along a line.

A pure per-tick state machine, no simulator: each :meth:`StrokeController.step` takes the measured normal force
and the elapsed time and returns the desired tool-frame pose (world frame) for the caller to track (IK, joint
targets). Phases::

    APPROACH -> PRESS -> SETTLE -> SLIDE -> LIFT -> DONE        (FAILED with a reason from any active phase)

* APPROACH: straight line (jerk-limited) from the initial tool position to the hover point, ``approach_height_m``
  above the expected contact point along the surface normal. Contact felt on the way starts PRESS at once.
* PRESS: descend along the normal, fast until ``slow_zone_m`` above the expected surface and slowly below it (the
  descent speed changes along jerk-limited ramps, Ruckig's velocity interface, braking where the next tick at
  full speed would leave too little room to slow down, so it enters the slow zone at ``contact_speed_mps``); once
  the force exceeds ``contact_force_n`` an admittance law on the normal offset takes over (below) and the contact
  stiffness is estimated from (offset, force) pairs. PRESS ends when the force reaches the target.
* SETTLE: admittance only, until the force stays within ``settle_tolerance`` of the target for ``settle_time_s``.
  In contact during PRESS and SETTLE the pad also yields in the surface plane to the friction on it (lateral
  admittance, below), so that it comes to the slide carrying no tangential load.
* SLIDE: the contact point moves ``length_m`` along ``direction_rad`` with a jerk-limited profile whose cruise speed
  is ``speed_mps``, the admittance law still regulating the normal force.
* LIFT: back up along the normal by ``approach_height_m`` (jerk-limited); then DONE, which holds the pose.
* FAILED: no contact within ``max_press_depth_m`` below the expected surface, force above ``max_force_n``, force
  not settling in ``settle_timeout_s``, lost contact while sliding, a non-finite force, or the total time budget
  exceeded. The command then holds the last commanded pose; the caller decides how to retreat.

Admittance law (normal offset ``z``, m, along the outward surface normal, relative to the expected contact point;
negative = pressed in): ``z_dot = (F_measured - F_target) / D`` with ``D = k_est * admittance_time_constant_s``,
so the force loop's time constant is about ``admittance_time_constant_s`` whatever the surface stiffness ``k``
(a spring surface gives ``F = k * max(0, -z)``, hence ``F_dot = -k z_dot = -(F - F_target) / T``). ``k_est`` starts
at the conservative (stiff) ``stiffness_guess_n_per_m`` and is refined during PRESS by a least-squares slope of
force against offset; an overestimate only slows the loop down. ``z_dot`` is clamped to ``max_offset_rate_mps``.

Lateral admittance (in-plane yield ``y``, m, world, perpendicular to the normal): ``y_dot = F_t / D_t`` with
``F_t`` the in-plane part of the friction force the surface exerts on the pad and ``D_t =
lateral_damping_n_s_per_m``; its speed is clamped to ``max_offset_rate_mps`` and ``|y|`` to
``max_lateral_yield_m``, and it is held from the slide on. Why: a position-controlled arm is all but rigid, so
a lateral mismatch of a fraction of a micrometre between where the arm holds the pad and where static friction
holds the contact (the press's own micro-motions) is held by friction up to its static limit. Without the yield
a 4 N press on steel carried 1.0-1.5 N of shear before sliding (a third of the friction cone), where a real
tool's compliance, or a force-controlled press, would turn that mismatch into millinewtons; the yield takes
1-4 um (``tests/test_stroking.py``).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field

import numpy as np

from controllers.trajectory import CartesianLimits, PathProfile, plan_path_profile, plan_speed_ramp


class StrokePhase(enum.Enum):
    APPROACH = "approach"
    PRESS = "press"
    SETTLE = "settle"
    SLIDE = "slide"
    LIFT = "lift"
    DONE = "done"
    FAILED = "failed"


Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class StrokeConfig:
    """One stroke: where, how hard, how fast, how far; plus the force loop's settings. All positions in world.

    Attributes:
        target_force_n: normal force to hold while sliding, N, in [0.5, 5].
        speed_mps: cruise speed of the slide, m/s, in [0.005, 0.05].
        length_m: slide length, m, in [0.02, 0.06].
        direction_rad: slide direction in the surface plane, rad, from the plane's first tangent axis ``t1``
            (world x projected onto the plane, or world y if the normal is along x) towards ``t2 = n x t1``.
        start_point_m: expected contact point on the surface where the slide starts, world, m.
        surface_normal: outward unit normal of the surface, world (normalised on use).
        pad_rotation: tool-frame orientation to hold (rows of a 3x3 rotation matrix, world); None gives
            z_pad = -normal (pad facing the surface) and x_pad = the slide direction.
        approach_height_m: hover height above the expected contact point, m (> 0).
        approach_speed_mps: speed of APPROACH and LIFT, m/s.
        press_speed_mps: descent speed in PRESS above the slow zone, m/s.
        contact_speed_mps: descent speed in PRESS within the slow zone and largest admittance descent rate, m/s.
        slow_zone_m: height above the expected surface below which PRESS descends at ``contact_speed_mps``, m.
        max_press_depth_m: how far below the expected surface PRESS may go without reaching the target, m.
        contact_force_n: force above which the pad counts as in contact, N.
        admittance_time_constant_s: desired time constant of the force loop, s.
        stiffness_guess_n_per_m: initial contact stiffness estimate, N/m (high is conservative).
        min_stiffness_n_per_m, max_stiffness_n_per_m: clamp of the stiffness estimate, N/m.
        max_offset_rate_mps: clamp of the admittance's normal speed (both ways) and of the lateral yield's speed, m/s.
        lateral_damping_n_s_per_m: damping of the lateral admittance, N s/m (0 turns it off: the pad holds its
            commanded line while pressing); with the arm's lateral stiffness in contact, about 2e6 N/m in the
            simulation, 2e4 gives a time constant of about 10 ms, stable for stiffnesses up to 2 D / tick.
        max_lateral_yield_m: largest lateral yield, m (a tilted surface would otherwise walk the pad downhill).
        settle_tolerance: relative force band that counts as settled (0.1 = +-10 %).
        settle_time_s: time the force must stay in the band before sliding, s.
        settle_timeout_s: longest SETTLE before failing, s.
        slide_acceleration_mps2, slide_jerk_mps3: limits of the slide profile.
        lost_contact_time_s: a slide fails after the force stays below ``contact_force_n`` this long, s.
        max_force_n: force that aborts the stroke at once, N.
        time_budget_s: longest whole stroke before failing, s.
    """

    target_force_n: float = 2.0
    speed_mps: float = 0.02
    length_m: float = 0.04
    direction_rad: float = 0.0
    start_point_m: Vec3 = (0.0, 0.0, 0.0)
    surface_normal: Vec3 = (0.0, 0.0, 1.0)
    pad_rotation: tuple[Vec3, Vec3, Vec3] | None = None
    approach_height_m: float = 0.02
    approach_speed_mps: float = 0.05
    press_speed_mps: float = 0.01
    contact_speed_mps: float = 0.002
    slow_zone_m: float = 0.004
    max_press_depth_m: float = 0.015
    contact_force_n: float = 0.1
    admittance_time_constant_s: float = 0.05
    stiffness_guess_n_per_m: float = 1e5
    min_stiffness_n_per_m: float = 2e2
    max_stiffness_n_per_m: float = 1e6
    max_offset_rate_mps: float = 0.01
    lateral_damping_n_s_per_m: float = 2e4
    max_lateral_yield_m: float = 5e-4
    settle_tolerance: float = 0.1
    settle_time_s: float = 0.2
    settle_timeout_s: float = 3.0
    slide_acceleration_mps2: float = 0.25
    slide_jerk_mps3: float = 5.0
    lost_contact_time_s: float = 0.1
    max_force_n: float = 20.0
    time_budget_s: float = 30.0

    def __post_init__(self) -> None:
        def check(ok: bool, message: str) -> None:
            if not ok:
                raise ValueError(f"StrokeConfig: {message}")

        check(0.5 <= self.target_force_n <= 5.0, f"target_force_n must be in [0.5, 5] N, got {self.target_force_n}")
        check(0.005 <= self.speed_mps <= 0.05, f"speed_mps must be in [0.005, 0.05] m/s, got {self.speed_mps}")
        check(0.02 <= self.length_m <= 0.06, f"length_m must be in [0.02, 0.06] m, got {self.length_m}")
        check(math.isfinite(self.direction_rad), f"direction_rad must be finite, got {self.direction_rad}")
        check(len(self.start_point_m) == 3 and all(map(math.isfinite, self.start_point_m)),
              f"start_point_m must be 3 finite numbers, got {self.start_point_m}")
        check(len(self.surface_normal) == 3 and math.isfinite(sum(self.surface_normal))
              and math.hypot(*self.surface_normal) > 1e-9, f"surface_normal must be a non-zero 3-vector, got "
              f"{self.surface_normal}")
        if self.pad_rotation is not None:
            r = np.asarray(self.pad_rotation, dtype=float)
            check(r.shape == (3, 3) and np.allclose(r @ r.T, np.eye(3), atol=1e-6) and np.linalg.det(r) > 0,
                  "pad_rotation must be a 3x3 rotation matrix")
        for name in ("approach_height_m", "approach_speed_mps", "press_speed_mps", "contact_speed_mps",
                     "max_press_depth_m", "contact_force_n", "admittance_time_constant_s", "stiffness_guess_n_per_m",
                     "min_stiffness_n_per_m", "max_stiffness_n_per_m", "max_offset_rate_mps", "settle_tolerance",
                     "settle_timeout_s", "slide_acceleration_mps2", "slide_jerk_mps3", "lost_contact_time_s",
                     "time_budget_s"):
            value = getattr(self, name)
            check(math.isfinite(value) and value > 0, f"{name} must be positive, got {value}")
        check(self.slow_zone_m >= 0 and self.settle_time_s >= 0, "slow_zone_m and settle_time_s must be >= 0")
        for name in ("lateral_damping_n_s_per_m", "max_lateral_yield_m"):
            value = getattr(self, name)
            check(math.isfinite(value) and value >= 0, f"{name} must be >= 0, got {value}")
        check(self.contact_force_n < self.target_force_n * (1 - self.settle_tolerance),
              f"contact_force_n ({self.contact_force_n} N) must be below the settle band of the target force")
        check(self.settle_tolerance < 1.0, f"settle_tolerance must be < 1, got {self.settle_tolerance}")
        check(self.max_force_n > self.target_force_n * (1 + self.settle_tolerance),
              f"max_force_n ({self.max_force_n} N) must exceed the target's settle band")
        check(self.min_stiffness_n_per_m <= self.stiffness_guess_n_per_m <= self.max_stiffness_n_per_m,
              "stiffness_guess_n_per_m must lie within [min_stiffness_n_per_m, max_stiffness_n_per_m]")

    def normal(self) -> np.ndarray:
        """Unit outward surface normal, world."""
        n = np.asarray(self.surface_normal, dtype=float)
        return n / np.linalg.norm(n)

    def slide_direction(self) -> np.ndarray:
        """Unit slide direction in the surface plane, world."""
        n = self.normal()
        ref = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        t1 = ref - (ref @ n) * n
        t1 /= np.linalg.norm(t1)
        t2 = np.cross(n, t1)
        return math.cos(self.direction_rad) * t1 + math.sin(self.direction_rad) * t2

    def rotation(self) -> np.ndarray:
        """Tool orientation held during the stroke (3x3, world)."""
        if self.pad_rotation is not None:
            return np.asarray(self.pad_rotation, dtype=float)
        z = -self.normal()
        x = self.slide_direction()
        return np.column_stack([x, np.cross(z, x), z])


@dataclass(frozen=True)
class StrokeCommand:
    """What the controller wants this tick.

    Attributes:
        position_m: (3,) desired tool-frame origin, world, m.
        rotation: (3, 3) desired tool-frame orientation, world.
        phase: the phase after this tick.
        time_s: time since the stroke started, s.
        normal_offset_m: commanded offset along the surface normal from the expected surface, m (negative = in).
        slide_progress_m: distance slid so far, m.
        in_contact: the measured force is above the contact threshold.
        force_control_active: the admittance loop is driving the normal offset.
        stiffness_estimate_n_per_m: current contact stiffness estimate, N/m.
        lateral_yield_m: (3,) the lateral admittance's in-plane yield included in ``position_m``, world, m.
        done: the stroke finished (DONE).
        failed: the stroke failed (FAILED); ``failure_reason`` says why.
        failure_reason: empty unless failed.
    """

    position_m: np.ndarray
    rotation: np.ndarray
    phase: StrokePhase
    time_s: float
    normal_offset_m: float
    slide_progress_m: float
    in_contact: bool
    force_control_active: bool
    stiffness_estimate_n_per_m: float
    done: bool
    failed: bool
    failure_reason: str = ""
    lateral_yield_m: np.ndarray = field(default_factory=lambda: np.zeros(3))


class StrokeController:
    """Per-tick stroke state machine (see the module docstring).

    Args:
        config: the stroke.
        initial_position_m: (3,) tool origin when the stroke starts, world, m (the tool should already hold
            ``config.rotation()``; APPROACH moves the position only).
    """

    def __init__(self, config: StrokeConfig, initial_position_m: np.ndarray) -> None:
        self.config = config
        self._n = config.normal()
        self._d = config.slide_direction()
        self._rotation = config.rotation()
        self._start = np.asarray(config.start_point_m, dtype=float)
        self.reset(initial_position_m)

    def reset(self, initial_position_m: np.ndarray) -> None:
        """Start over from ``initial_position_m`` (world, m)."""
        cfg = self.config
        p0 = np.asarray(initial_position_m, dtype=float)
        if p0.shape != (3,) or not np.all(np.isfinite(p0)):
            raise ValueError(f"initial_position_m must be 3 finite numbers, got {initial_position_m}")
        self.phase = StrokePhase.APPROACH
        self._time_s = 0.0
        self._phase_time_s = 0.0
        self._anchor = self._start.copy()  # contact point of the slide's start, on the expected surface plane
        self._offset_m = float((p0 - self._start) @ self._n)
        self._lateral = p0 - self._start - self._offset_m * self._n  # in-plane deviation from the anchor
        self._yield = np.zeros(3)  # the lateral admittance's in-plane yield, m
        self._approach_from = p0
        hover = self._start + cfg.approach_height_m * self._n
        self._approach_dir = hover - p0
        length = float(np.linalg.norm(self._approach_dir))
        self._approach_dir = self._approach_dir / length if length > 0 else np.zeros(3)
        self._profile: PathProfile = plan_path_profile(length, self._limits(cfg.approach_speed_mps))
        self._slide_m = 0.0
        self._descent_mps, self._descent_mps2 = 0.0, 0.0  # PRESS descent speed and its rate, before contact
        brake = plan_speed_ramp(cfg.press_speed_mps, 0.0, cfg.contact_speed_mps, self._limits(cfg.press_speed_mps))
        self._brake_m = brake.at(brake.duration_s)[0]  # travel while slowing to the contact speed
        self._in_contact = False
        self._force_control = False
        self._k_est = cfg.stiffness_guess_n_per_m
        self._fit = np.zeros(5)  # sums of 1, z, F, z^2, z F over contact samples in PRESS
        self._settled_s = 0.0
        self._no_contact_s = 0.0
        self._lift_from_m = 0.0
        self._failure = ""

    def _limits(self, speed_mps: float) -> CartesianLimits:
        return CartesianLimits(speed_mps, self.config.slide_acceleration_mps2, self.config.slide_jerk_mps3)

    # ---------------------------------------------------------------------------------------------------------
    def step(self, measured_normal_force_n: float, dt_s: float,
             measured_shear_force_n: np.ndarray | None = None) -> StrokeCommand:
        """Advance one tick.

        Args:
            measured_normal_force_n: normal force on the pad, N (positive = pressing).
            dt_s: time since the previous call, s (> 0).
            measured_shear_force_n: (3,) friction force of the surface on the pad, world, N, for the lateral
                admittance; None (no shear sensing) leaves the pad on its commanded line.

        Returns:
            The :class:`StrokeCommand` for this tick.
        """
        cfg = self.config
        if not dt_s > 0 or not math.isfinite(dt_s):
            raise ValueError(f"dt_s must be positive and finite, got {dt_s}")
        if self.phase in (StrokePhase.DONE, StrokePhase.FAILED):
            return self._command()
        force = float(measured_normal_force_n)
        self._time_s += dt_s
        self._phase_time_s += dt_s
        if not math.isfinite(force):
            return self._fail(f"non-finite normal force {force} in {self.phase.value}")
        shear = None if measured_shear_force_n is None else np.asarray(measured_shear_force_n, dtype=float)
        if shear is not None and (shear.shape != (3,) or not np.all(np.isfinite(shear))):
            return self._fail(f"shear force must be 3 finite numbers, got {measured_shear_force_n} in "
                              f"{self.phase.value}")
        if force > cfg.max_force_n:
            return self._fail(f"normal force {force:.2f} N above max_force_n {cfg.max_force_n} N in "
                              f"{self.phase.value}")
        if self._time_s > cfg.time_budget_s:
            return self._fail(f"time budget {cfg.time_budget_s} s exceeded in {self.phase.value}")
        self._in_contact = force >= cfg.contact_force_n
        handler = {StrokePhase.APPROACH: self._approach, StrokePhase.PRESS: self._press,
                   StrokePhase.SETTLE: self._settle, StrokePhase.SLIDE: self._slide,
                   StrokePhase.LIFT: self._lift}[self.phase]
        handler(force, dt_s)
        if shear is not None and self._in_contact and self.phase in (StrokePhase.PRESS, StrokePhase.SETTLE):
            self._yield_laterally(shear, dt_s)
        return self._command()

    # ---------------------------------------------------------------------------------------------------------
    def _enter(self, phase: StrokePhase) -> None:
        self.phase = phase
        self._phase_time_s = 0.0

    def _fail(self, reason: str) -> StrokeCommand:
        self._failure = reason
        self._force_control = False
        self._enter(StrokePhase.FAILED)
        return self._command()

    def _admittance(self, force: float, dt_s: float) -> float:
        """Move the normal offset by the admittance law; returns its rate, m/s (positive = away from the surface)."""
        cfg = self.config
        damping = self._k_est * cfg.admittance_time_constant_s  # N s/m
        rate = (force - cfg.target_force_n) / damping
        rate = min(max(rate, -min(cfg.contact_speed_mps, cfg.max_offset_rate_mps)), cfg.max_offset_rate_mps)
        self._offset_m += rate * dt_s
        self._force_control = True
        return rate

    def _yield_laterally(self, shear_n: np.ndarray, dt_s: float) -> None:
        """Move the in-plane yield by the lateral admittance law (module docstring)."""
        cfg = self.config
        if cfg.lateral_damping_n_s_per_m <= 0.0:
            return
        in_plane = shear_n - (shear_n @ self._n) * self._n
        velocity = in_plane / cfg.lateral_damping_n_s_per_m
        speed = float(np.linalg.norm(velocity))
        if speed > cfg.max_offset_rate_mps:
            velocity *= cfg.max_offset_rate_mps / speed
        self._yield = self._yield + velocity * dt_s
        size = float(np.linalg.norm(self._yield))
        if size > cfg.max_lateral_yield_m:
            self._yield *= cfg.max_lateral_yield_m / size

    def _approach(self, force: float, dt_s: float) -> None:
        if self._in_contact:  # surface higher than expected: start pressing from here
            self._enter(StrokePhase.PRESS)
            self._press(force, dt_s)
            return
        s, _, _ = self._profile.at(self._phase_time_s)
        p = self._approach_from + s * self._approach_dir
        self._offset_m = float((p - self._start) @ self._n)
        self._lateral = p - self._start - self._offset_m * self._n
        if self._phase_time_s >= self._profile.duration_s:
            self._enter(StrokePhase.PRESS)

    def _press(self, force: float, dt_s: float) -> None:
        cfg = self.config
        if self._in_contact:
            self._update_stiffness(force)
            self._descent_mps, self._descent_mps2 = -self._admittance(force, dt_s), 0.0  # if contact is lost again
            if force >= cfg.target_force_n * (1 - cfg.settle_tolerance):
                self._enter(StrokePhase.SETTLE)
                return
        else:
            limits = self._limits(cfg.press_speed_mps)
            step = plan_speed_ramp(self._descent_mps, self._descent_mps2, cfg.press_speed_mps, limits).at(dt_s)
            if self._offset_m - step[0] <= cfg.slow_zone_m + self._brake_m:  # would start braking late: brake now
                step = plan_speed_ramp(self._descent_mps, self._descent_mps2, cfg.contact_speed_mps, limits).at(dt_s)
            travel, self._descent_mps, self._descent_mps2 = step
            self._offset_m -= travel
        if self._offset_m < -cfg.max_press_depth_m:
            self._fail(f"target force not reached within max_press_depth_m {cfg.max_press_depth_m * 1e3:.1f} mm "
                       f"below the expected surface (last force {force:.3f} N)")

    def _update_stiffness(self, force: float) -> None:
        cfg = self.config
        z = -self._offset_m
        self._fit += (1.0, z, force, z * z, z * force)
        n, sz, sf, szz, szf = self._fit
        var = n * szz - sz * sz
        if n >= 4 and var > (n * 1e-5) ** 2:  # at least 4 samples spread over about 10 um
            slope = (n * szf - sz * sf) / var
            self._k_est = min(max(slope, cfg.min_stiffness_n_per_m), cfg.max_stiffness_n_per_m)

    def _settle(self, force: float, dt_s: float) -> None:
        cfg = self.config
        self._admittance(force, dt_s)
        if abs(force - cfg.target_force_n) <= cfg.settle_tolerance * cfg.target_force_n:
            self._settled_s += dt_s
        else:
            self._settled_s = 0.0
        if self._settled_s >= cfg.settle_time_s:
            self._profile = plan_path_profile(cfg.length_m, self._limits(cfg.speed_mps))
            self._enter(StrokePhase.SLIDE)
        elif self._phase_time_s > cfg.settle_timeout_s:
            self._fail(f"force did not settle within +-{cfg.settle_tolerance * 100:.0f} % of "
                       f"{cfg.target_force_n} N in {cfg.settle_timeout_s} s (last {force:.3f} N)")
        elif self._offset_m < -cfg.max_press_depth_m:
            self._fail(f"pressed {cfg.max_press_depth_m * 1e3:.1f} mm below the expected surface while settling")

    def _slide(self, force: float, dt_s: float) -> None:
        cfg = self.config
        self._admittance(force, dt_s)
        self._slide_m, _, _ = self._profile.at(self._phase_time_s)
        self._no_contact_s = 0.0 if self._in_contact else self._no_contact_s + dt_s
        if self._no_contact_s > cfg.lost_contact_time_s:
            self._fail(f"lost contact while sliding at {self._slide_m * 1e3:.1f} mm")
        elif self._offset_m < -cfg.max_press_depth_m:
            self._fail(f"pressed {cfg.max_press_depth_m * 1e3:.1f} mm below the expected surface while sliding")
        elif self._phase_time_s >= self._profile.duration_s:
            self._slide_m = cfg.length_m
            self._force_control = False
            self._lift_from_m = self._offset_m
            target = max(self._offset_m + cfg.approach_height_m, cfg.approach_height_m)
            self._profile = plan_path_profile(target - self._offset_m, self._limits(cfg.approach_speed_mps))
            self._enter(StrokePhase.LIFT)

    def _lift(self, force: float, dt_s: float) -> None:
        s, _, _ = self._profile.at(self._phase_time_s)
        self._offset_m = self._lift_from_m + s
        if self._phase_time_s >= self._profile.duration_s:
            self._enter(StrokePhase.DONE)

    # ---------------------------------------------------------------------------------------------------------
    def _command(self) -> StrokeCommand:
        position = self._anchor + self._lateral + self._yield + self._slide_m * self._d + self._offset_m * self._n
        return StrokeCommand(
            position_m=position, rotation=self._rotation.copy(), phase=self.phase, time_s=self._time_s,
            normal_offset_m=self._offset_m, slide_progress_m=self._slide_m, in_contact=self._in_contact,
            force_control_active=self._force_control and self.phase not in (StrokePhase.DONE, StrokePhase.FAILED),
            stiffness_estimate_n_per_m=self._k_est, done=self.phase is StrokePhase.DONE,
            failed=self.phase is StrokePhase.FAILED, failure_reason=self._failure, lateral_yield_m=self._yield.copy())
