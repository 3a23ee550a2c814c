"""Sensor emulation: a simulated contact trace -> the four streams a real sensing rig records.

The simulator gives quasi-static contact (forces, positions, velocities at the physics rate); the sensor
models in :mod:`perception.sensors` add what a real fingertip would feel and hear:

==========  ==========  ===================================================================================
stream      rate        model
==========  ==========  ===================================================================================
N, F        100 Hz      uSkin-like 4 x 4 three-axis taxels: elastomer spread, crosstalk, saturation, gain,
                        offset and drift, noise, 16-bit counts, bias taken at rest (:mod:`.sensors.taxels`)
A           500 Hz      fingertip IMU: rigid-body acceleration + texture/stick-slip vibration through the
                        fingertip resonance + noise (:mod:`.sensors.imu`)
S           44.1 kHz    microphone: modal synthesis of the object driven by texture, stick-slip and
                        touch-down + friction noise + environment noise (:mod:`.sensors.sound`)
==========  ==========  ===================================================================================

Texture and stick-slip (:mod:`.sensors.contact_excitation`) come from the object's surface height field
(:mod:`.sensors.texture`) and its static/kinetic friction. Each device (uSkin, IMU, microphone) has its own
clock offset, drawn per stroke; N and F come from the same uSkin and share one.

Honesty: the emulation reads only the material's physical parameters (``ObjectInfo.material`` fields), the
object's size and shape, and the trace. The labels ride along untouched; every noise level and disturbance
is drawn from the environment profile, independently of the object.

Typical use::

    rec = emulate_stroke(trace, ObjectInfo(sample, (0.1, 0.06, 0.03)), ENVIRONMENTS["clean"],
                         np.random.default_rng(seed))
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

from perception.contact_trace import ContactTrace, ContactTraceError, ObjectInfo
from perception.sensors.contact_excitation import ContactConfig, compute_contact_excitation
from perception.sensors.environment import (
    ENVIRONMENTS,
    SENSOR_DEVICES,
    EnvironmentProfile,
    draw_dropouts,
    environment_sound,
)
from perception.sensors.imu import ImuConfig, imu_stream
from perception.sensors.resample import sensor_samples
from perception.sensors.sound import SoundConfig, contact_sound, microphone_highpass
from perception.sensors.taxels import TaxelArrayConfig, taxel_forces, uskin_readout
from perception.sensors.texture import TextureConfig, make_surface_texture
from perception.streams import MODALITIES, Stream, StrokeRecord

__all__ = ["ENVIRONMENTS", "EmulatorConfig", "EnvironmentProfile", "emulate_stroke"]


@dataclass(frozen=True)
class EmulatorConfig:
    """All sensor-model settings (use ``dataclasses.replace`` for variants).

    Attributes:
        texture: surface synthesis.
        contact: texture / stick-slip / impact micro-mechanics (its ``fine_rate_hz`` must equal the
            microphone rate).
        taxels: uSkin model.
        imu: accelerometer model.
        sound: modal synthesis and microphone.
    """

    texture: TextureConfig = field(default_factory=TextureConfig)
    contact: ContactConfig = field(default_factory=ContactConfig)
    taxels: TaxelArrayConfig = field(default_factory=TaxelArrayConfig)
    imu: ImuConfig = field(default_factory=ImuConfig)
    sound: SoundConfig = field(default_factory=SoundConfig)

    def __post_init__(self) -> None:
        if self.contact.fine_rate_hz != self.sound.rate_hz:
            raise ValueError("contact.fine_rate_hz must equal sound.rate_hz (the excitation is the mic's signal)")


DEFAULT_CONFIG = EmulatorConfig()


def emulate_stroke(trace: ContactTrace, obj: ObjectInfo, env: EnvironmentProfile, rng: np.random.Generator,
                   *, config: EmulatorConfig = DEFAULT_CONFIG, meta: Mapping[str, Any] | None = None) -> StrokeRecord:
    """Turn one simulated stroke into a recorded one.

    Args:
        trace: contact between the pad and the object at the physics rate (validated on construction:
            NaN/inf raise :class:`~perception.contact_trace.ContactTraceError`).
        obj: the touched object; its material sample's names become the record's labels.
        env: environment profile, e.g. ``ENVIRONMENTS["fire"]``.
        rng: the stroke's random generator (same seed, same record).
        config: sensor-model settings.
        meta: extra JSON-serialisable fields stored in the record's meta (stroke parameters, seed, ...).

    Returns:
        The :class:`~perception.streams.StrokeRecord`: S (44.1 kHz, 1 ch), N (100 Hz, 16 ch, N),
        F (100 Hz, 32 ch, N, taxel-major x, y), A (500 Hz, 3 ch, m/s^2); a dropped modality is ``None``.
    """
    if not isinstance(trace, ContactTrace):
        raise TypeError(f"trace must be a ContactTrace, got {type(trace).__name__}")
    if not isinstance(obj, ObjectInfo):
        raise TypeError(f"obj must be an ObjectInfo, got {type(obj).__name__}")
    if not isinstance(env, EnvironmentProfile):
        raise TypeError(f"env must be an EnvironmentProfile, got {type(env).__name__}")
    if trace.duration_s < 0.05:
        raise ContactTraceError(f"trace too short for the sensors: {trace.duration_s:.3f} s (need >= 0.05 s)")

    dropped = draw_dropouts(SENSOR_DEVICES, env, rng)
    offsets = {device: float(rng.uniform(0.0, env.clock_offset_max_s)) for device in ("uskin", "imu", "mic")}
    offsets = {device: min(t0, 0.5 * trace.duration_s) for device, t0 in offsets.items()}
    fs = config.sound.rate_hz
    offsets["mic"] = round(offsets["mic"] * fs) / fs  # whole samples: no interpolation of audio
    duration = trace.duration_s

    texture = make_surface_texture(obj.material, obj.size_m, obj.surface_seed, config.texture)
    excitation = compute_contact_excitation(trace, obj, texture, rng, config.contact)
    streams: dict[str, Stream | None] = {m: None for m in MODALITIES}

    if not {"normal", "friction"} <= dropped:
        tax = config.taxels
        forces = taxel_forces(trace, tax)  # (T, 16, 3)
        cells = sensor_samples(forces.reshape(forces.shape[0], -1), trace.rate_hz, tax.rate_hz, offsets["uskin"], duration)
        cells = cells.reshape(cells.shape[0], tax.num_taxels, 3)  # (n, 16, 3)
        mods = sensor_samples(np.column_stack([excitation.normal_modulation, excitation.shear_modulation]),
                              fs, tax.rate_hz, offsets["uskin"], duration)  # (n, 2)
        cells[..., 2] *= 1.0 + mods[:, 0:1]
        cells[..., :2] *= 1.0 + mods[:, 1, None, None]
        reported = uskin_readout(cells, rng, tax, env.taxel_drift_scale, env.heat_drift_counts_per_s)
        if "normal" not in dropped:
            streams["normal"] = Stream(reported[..., 2].astype(np.float32), tax.rate_hz, offsets["uskin"])
        if "friction" not in dropped:
            friction = reported[..., :2].reshape(reported.shape[0], 2 * tax.num_taxels)
            streams["friction"] = Stream(friction.astype(np.float32), tax.rate_hz, offsets["uskin"])

    if "accel" not in dropped:
        extra = float(rng.uniform(*env.accel_vibration_rms_mps2))
        accel = imu_stream(excitation, trace, offsets["imu"], rng, config.imu, extra)
        streams["accel"] = Stream(accel.astype(np.float32), config.imu.rate_hz, offsets["imu"])

    if "sound" not in dropped:
        sound = contact_sound(excitation, obj, rng, config.sound)
        sound = microphone_highpass(sound + environment_sound(sound.shape[0], fs, env, rng), config.sound)
        start = int(round(offsets["mic"] * fs))
        streams["sound"] = Stream(sound[start:, None].astype(np.float32), fs, offsets["mic"])

    material = obj.material
    record_meta: dict[str, Any] = {
        "environment": env.name,
        "dropped": sorted(dropped),
        "clock_offsets_s": {k: float(v) for k, v in offsets.items()},
        "object_size_m": [float(s) for s in obj.size_m],
        "object_shape": obj.shape,
        "surface_seed": int(obj.surface_seed),
        "physics_rate_hz": float(trace.rate_hz),
    }
    record_meta.update(meta or {})
    return StrokeRecord(streams=streams, category=material.category, instance=material.instance,
                        combustible=material.combustible, meta=record_meta)
