"""Fingertip accelerometer (A stream, 500 Hz, 3 axes, pad frame).

a(t) = rigid-body acceleration from the simulator
     + texture/stick-slip force fluctuations and touch-down impacts on the pad through the fingertip's
       mechanical response,
       a single resonance: A(s) / F(s) = (1 / m) s^2 / (s^2 + 2 zeta w s + w^2)
       (a mass on the compliant finger: flat F / m above the resonance, rolled off below it),
     + environment vibration, sensor noise (white, from the noise density) and a per-stroke bias.
The sum is sampled at the IMU rate through its causal decimation filter (:func:`~.resample.sensor_samples`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.signal

from perception.contact_trace import ContactTrace
from perception.materials import FINGERTIP_MASS_KG
from perception.sensors.contact_excitation import ContactExcitation
from perception.sensors.resample import sensor_samples


@dataclass(frozen=True)
class ImuConfig:
    """Accelerometer model.

    Attributes:
        rate_hz: output data rate, Hz.
        resonance_hz: fingertip mount resonance, Hz.
        damping_ratio: its damping ratio.
        fingertip_mass_kg: mass the contact force fluctuations accelerate, kg.
        noise_density_mps2_per_sqrt_hz: white noise density (150 ug/sqrt(Hz), a MEMS IMU).
        bias_spread_mps2: 1-sigma per-stroke bias per axis, m/s^2.
        scale_spread: 1-sigma per-axis scale error.
    """

    rate_hz: float = 500.0
    resonance_hz: float = 180.0
    damping_ratio: float = 0.15
    fingertip_mass_kg: float = FINGERTIP_MASS_KG
    noise_density_mps2_per_sqrt_hz: float = 150e-6 * 9.81
    bias_spread_mps2: float = 0.05
    scale_spread: float = 0.01


def fingertip_response_ba(cfg: ImuConfig, fs_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """Digital (bilinear) filter from force on the pad (N) to fingertip acceleration (m/s^2)."""
    w = 2.0 * math.pi * cfg.resonance_hz
    b, a = scipy.signal.bilinear([1.0 / cfg.fingertip_mass_kg, 0.0, 0.0], [1.0, 2.0 * cfg.damping_ratio * w, w * w], fs=fs_hz)
    return b, a


def band_noise(n: int, fs_hz: float, band_hz: tuple[float, float], rms: float, rng: np.random.Generator,
               channels: int = 1) -> np.ndarray:
    """(n, channels) Gaussian noise band-passed to ``band_hz`` and scaled to ``rms``."""
    if rms <= 0.0 or n == 0:
        return np.zeros((n, channels))
    sos = scipy.signal.butter(2, band_hz, btype="bandpass", fs=fs_hz, output="sos")
    x = scipy.signal.sosfilt(sos, rng.standard_normal((n, channels)), axis=0)
    return x * (rms / (np.std(x) + 1e-300))


def imu_stream(excitation: ContactExcitation, trace: ContactTrace, t0_s: float, rng: np.random.Generator,
               cfg: ImuConfig = ImuConfig(), extra_vibration_rms_mps2: float = 0.0) -> np.ndarray:
    """The accelerometer's samples for one stroke.

    Args:
        excitation: contact force fluctuations at audio rate.
        trace: the contact trace (rigid-body acceleration at the physics rate).
        t0_s: the IMU's clock offset (time of its first sample after the stroke's start), s.
        rng: random generator (noise, bias).
        cfg: IMU model.
        extra_vibration_rms_mps2: environment vibration (fire), m/s^2 RMS per axis.

    Returns:
        (n, 3) acceleration, pad frame, m/s^2.
    """
    fs = excitation.rate_hz
    # Force on the pad: friction fluctuation opposes the motion; the normal fluctuation and the touch-down
    # impact pulse push along -z (the rigid-body trace has the arm's motion but not the finger's compliance).
    force = np.column_stack([
        -excitation.shear_fluctuation_n * excitation.slide_direction[:, 0],
        -excitation.shear_fluctuation_n * excitation.slide_direction[:, 1],
        -(excitation.normal_fluctuation_n + excitation.impact_force_n),
    ])
    b, a = fingertip_response_ba(cfg, fs)
    vibration = scipy.signal.lfilter(b, a, force, axis=0)
    duration = trace.duration_s
    accel = sensor_samples(vibration, fs, cfg.rate_hz, t0_s, duration)
    accel += sensor_samples(trace.pad_acceleration_mps2, trace.rate_hz, cfg.rate_hz, t0_s, duration)
    n = accel.shape[0]
    accel += band_noise(n, cfg.rate_hz, (5.0, 200.0), extra_vibration_rms_mps2, rng, channels=3)
    accel *= 1.0 + cfg.scale_spread * rng.standard_normal(3)
    accel += cfg.bias_spread_mps2 * rng.standard_normal(3)
    accel += cfg.noise_density_mps2_per_sqrt_hz * math.sqrt(0.5 * cfg.rate_hz) * rng.standard_normal((n, 3))
    return accel
