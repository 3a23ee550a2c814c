"""The contact record the simulator hands to the sensor emulation, and a synthetic one for tests.

Frames:
    pad frame: origin at the pad centre, x and y in the pad plane (taxel rows run along x, the top row is at
        +y), z along the pad's outward normal, pointing from the fingertip towards the touched surface.
    object frame (top surface): origin at the centre of the object's top face, x and y along the object's
        x and y extents.

Sign conventions: ``point_normal_force_n`` is the magnitude of the normal force the object exerts on the
pad (>= 0). ``point_shear_force_n`` is the tangential force the object exerts on the pad, in pad (x, y):
while the pad slides towards +x, friction points towards -x.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from perception.materials import SHAPES, MaterialSample

_UNIFORM_RTOL = 1e-3  # allowed relative jitter of the physics time step


class ContactTraceError(ValueError):
    """A contact trace or object description is malformed (shape, NaN/inf, non-uniform time)."""


def _array(name: str, value: np.ndarray, shape: tuple[int | None, ...], dtype: type = np.float64) -> np.ndarray:
    arr = np.asarray(value, dtype=dtype)
    if arr.ndim != len(shape) or any(s is not None and s != a for s, a in zip(shape, arr.shape)):
        raise ContactTraceError(f"{name}: expected shape {shape} (None = any), got {arr.shape}")
    if dtype is np.float64 and not np.all(np.isfinite(arr)):
        bad = np.argwhere(~np.isfinite(arr))[0]
        raise ContactTraceError(f"{name}: NaN or inf at index {tuple(int(i) for i in bad)}")
    arr = arr.copy()
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True)
class ContactTrace:
    """Contact between the fingertip pad and an object over one stroke, at the physics rate.

    Contact points are padded to P per step; ``point_valid`` says which are real. Invalid points must
    still hold finite numbers (zeros).

    Attributes:
        t_s: (T,) simulation time of each physics step, s, uniformly spaced.
        point_valid: (T, P) bool, True where a contact point exists.
        point_normal_force_n: (T, P) normal force magnitude on the pad, N (>= 0).
        point_shear_force_n: (T, P, 2) tangential force on the pad, pad frame (x, y), N.
        point_position_on_pad_m: (T, P, 2) contact point position, pad frame (x, y), m.
        pad_position_on_object_m: (T, 2) pad centre projected on the object's top face, object frame, m
            (indexes the surface texture).
        pad_velocity_mps: (T, 3) pad velocity relative to the object, pad frame, m/s (+z = approaching).
        pad_acceleration_mps2: (T, 3) pad acceleration as an accelerometer at the pad reads it, pad frame,
            m/s^2 (rigid body, from the simulator; include gravity here if the IMU should see it).
    """

    t_s: np.ndarray
    point_valid: np.ndarray
    point_normal_force_n: np.ndarray
    point_shear_force_n: np.ndarray
    point_position_on_pad_m: np.ndarray
    pad_position_on_object_m: np.ndarray
    pad_velocity_mps: np.ndarray
    pad_acceleration_mps2: np.ndarray

    def __post_init__(self) -> None:
        t = _array("t_s", self.t_s, (None,))
        n_steps = t.shape[0]
        if n_steps < 2:
            raise ContactTraceError(f"t_s: need at least 2 steps, got {n_steps}")
        dt = np.diff(t)
        if np.any(dt <= 0):
            raise ContactTraceError("t_s: times must be strictly increasing")
        if np.max(np.abs(dt - dt.mean())) > _UNIFORM_RTOL * dt.mean():
            raise ContactTraceError("t_s: time steps must be uniform (one physics rate)")
        valid = _array("point_valid", self.point_valid, (n_steps, None), dtype=bool)
        n_points = valid.shape[1]
        fields = {
            "t_s": t,
            "point_valid": valid,
            "point_normal_force_n": _array("point_normal_force_n", self.point_normal_force_n, (n_steps, n_points)),
            "point_shear_force_n": _array("point_shear_force_n", self.point_shear_force_n, (n_steps, n_points, 2)),
            "point_position_on_pad_m": _array("point_position_on_pad_m", self.point_position_on_pad_m,
                                              (n_steps, n_points, 2)),
            "pad_position_on_object_m": _array("pad_position_on_object_m", self.pad_position_on_object_m,
                                               (n_steps, 2)),
            "pad_velocity_mps": _array("pad_velocity_mps", self.pad_velocity_mps, (n_steps, 3)),
            "pad_acceleration_mps2": _array("pad_acceleration_mps2", self.pad_acceleration_mps2, (n_steps, 3)),
        }
        if np.any(fields["point_normal_force_n"] < -1e-9):
            raise ContactTraceError("point_normal_force_n: normal force must be >= 0")
        for name, arr in fields.items():
            object.__setattr__(self, name, arr)

    @property
    def rate_hz(self) -> float:
        """Physics rate, Hz."""
        return float((self.t_s.shape[0] - 1) / (self.t_s[-1] - self.t_s[0]))

    @property
    def duration_s(self) -> float:
        return float(self.t_s[-1] - self.t_s[0])

    @property
    def num_points(self) -> int:
        return int(self.point_valid.shape[1])

    def total_normal_force_n(self) -> np.ndarray:
        """(T,) sum of the valid points' normal forces, N."""
        return np.sum(np.where(self.point_valid, self.point_normal_force_n, 0.0), axis=1)

    def total_shear_force_n(self) -> np.ndarray:
        """(T, 2) sum of the valid points' shear forces, pad frame, N."""
        return np.sum(np.where(self.point_valid[..., None], self.point_shear_force_n, 0.0), axis=1)


@dataclass(frozen=True)
class ObjectInfo:
    """The touched object.

    Attributes:
        material: its drawn physical parameters (labels ride along; the emulation reads only physics).
        size_m: bounding size (x, y, z), m.
        shape: ``"box"``, ``"cylinder"`` or ``"sphere"``.
        surface_seed: seeds the object's surface height profile, so a re-stroked object feels the same.
    """

    material: MaterialSample
    size_m: tuple[float, float, float]
    shape: str = "box"
    surface_seed: int = 0

    def __post_init__(self) -> None:
        size = tuple(float(s) for s in self.size_m)
        if len(size) != 3 or not all(s > 0 and math.isfinite(s) for s in size):
            raise ContactTraceError(f"ObjectInfo.size_m: expected three positive finite lengths, got {self.size_m}")
        if self.shape not in SHAPES:
            raise ContactTraceError(f"ObjectInfo.shape: unknown shape {self.shape!r}; expected one of {SHAPES}")
        object.__setattr__(self, "size_m", size)


def _smoothstep(x: np.ndarray) -> np.ndarray:
    """0 -> 1 raised-cosine ramp of x in [0, 1]."""
    x = np.clip(x, 0.0, 1.0)
    return 0.5 - 0.5 * np.cos(np.pi * x)


def synthetic_press_slide_trace(
    *,
    friction_coefficient: float,
    press_force_n: float = 2.0,
    slide_speed_mps: float = 0.03,
    slide_direction: tuple[float, float] = (1.0, 0.0),
    rate_hz: float = 1000.0,
    approach_s: float = 0.15,
    press_s: float = 0.25,
    slide_s: float = 1.0,
    release_s: float = 0.2,
    approach_speed_mps: float = 0.02,
    contact_centre_on_pad_m: tuple[float, float] = (0.0, 0.0),
    contact_drift_on_pad_m: tuple[float, float] = (0.0, 0.0),
    patch_half_width_m: float = 0.002,
    start_on_object_m: tuple[float, float] = (-0.015, 0.0),
    slide_ramp_s: float = 0.05,
    friction_smoothing_speed_mps: float = 1e-3,
) -> ContactTrace:
    """A press-then-slide contact trace, as a simulator would report it.

    Phases: approach (no contact, pad moving towards the object), press (normal force ramps to
    ``press_force_n``; the pad stops), slide (pad moves at ``slide_speed_mps`` along ``slide_direction``;
    shear = ``friction_coefficient`` x normal force opposing the motion), release (force ramps to zero).
    Four contact points sit at the corners of a square patch around the contact centre, which moves by
    ``contact_drift_on_pad_m`` over the slide (the object rolling under the pad).

    Args:
        friction_coefficient: Coulomb coefficient the simulator used (the kinetic one).
        press_force_n: total normal force while pressing and sliding, N.
        slide_speed_mps: sliding speed, m/s.
        slide_direction: (x, y) direction of the pad's motion over the object, pad frame = object frame here.
        rate_hz: physics rate, Hz.
        approach_s, press_s, slide_s, release_s: phase durations, s.
        approach_speed_mps: pad speed towards the object before touch-down, m/s.
        contact_centre_on_pad_m: contact patch centre on the pad at the start, pad frame, m.
        contact_drift_on_pad_m: displacement of the patch centre over the slide phase, m.
        patch_half_width_m: half width of the square patch of the four contact points, m.
        start_on_object_m: pad centre on the object at touch-down, object frame, m.
        slide_ramp_s: speed ramp-up and ramp-down time at both ends of the slide, s.
        friction_smoothing_speed_mps: friction follows mu N v / sqrt(v^2 + v0^2) (regularised Coulomb).

    Returns:
        The :class:`ContactTrace`.
    """
    if not (friction_coefficient >= 0 and press_force_n >= 0 and slide_speed_mps >= 0 and rate_hz > 0):
        raise ContactTraceError("synthetic trace: friction, force, speed and rate must be non-negative")
    direction = np.asarray(slide_direction, dtype=float)
    norm = float(np.linalg.norm(direction))
    if not norm > 0:
        raise ContactTraceError("synthetic trace: slide_direction must be non-zero")
    direction = direction / norm
    total_s = approach_s + press_s + slide_s + release_s
    t = np.arange(int(round(total_s * rate_hz)) + 1) / rate_hz
    t_press, t_slide, t_release = approach_s, approach_s + press_s, approach_s + press_s + slide_s

    # Normal force: 0 until touch-down, ramp up over the first 60 % of the press phase, hold, ramp down.
    force = press_force_n * (_smoothstep((t - t_press) / (0.6 * press_s)) - _smoothstep((t - t_release) / release_s))
    force = np.maximum(force, 0.0)

    # Sliding speed: raised-cosine ramps at both ends of the slide phase.
    ramp = max(slide_ramp_s, 1.0 / rate_hz)
    speed = slide_speed_mps * (_smoothstep((t - t_slide) / ramp) - _smoothstep((t - (t_release - ramp)) / ramp))
    travel = np.cumsum(speed) / rate_hz
    pad_on_object = np.asarray(start_on_object_m, dtype=float) + travel[:, None] * direction

    # Normal velocity: approaching at constant speed, stopping over 20 ms after touch-down.
    v_normal = approach_speed_mps * (1.0 - _smoothstep((t - t_press) / 0.02))
    velocity = np.column_stack([speed * direction[0], speed * direction[1], v_normal])
    acceleration = np.gradient(velocity, 1.0 / rate_hz, axis=0)

    slide_frac = _smoothstep((t - t_slide) / max(slide_s, 1.0 / rate_hz))
    centre = np.asarray(contact_centre_on_pad_m, dtype=float) + slide_frac[:, None] * np.asarray(contact_drift_on_pad_m)
    corners = patch_half_width_m * np.array([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0], [-1.0, 1.0]])
    positions = centre[:, None, :] + corners[None, :, :]  # (T, 4, 2)

    in_contact = force > 1e-9
    valid = np.repeat(in_contact[:, None], 4, axis=1)
    per_point = np.where(valid, force[:, None] / 4.0, 0.0)
    mu_eff = friction_coefficient * speed / np.sqrt(speed**2 + friction_smoothing_speed_mps**2)
    shear = -(mu_eff * force / 4.0)[:, None, None] * direction[None, None, :] * valid[..., None]
    positions = np.where(valid[..., None], positions, 0.0)
    return ContactTrace(
        t_s=t,
        point_valid=valid,
        point_normal_force_n=per_point,
        point_shear_force_n=np.broadcast_to(shear, (t.shape[0], 4, 2)),
        point_position_on_pad_m=positions,
        pad_position_on_object_m=pad_on_object,
        pad_velocity_mps=velocity,
        pad_acceleration_mps2=acceleration,
    )
