"""Microphone (S stream, 44.1 kHz): modal synthesis of the object plus friction noise.

Modes (bounding-box beam approximation, for every shape), with c the material's bar wave speed:

* flexural modes along each in-plane axis L (x and y) of a free-free beam of thickness h (z):
  f_n = (beta_n L)^2 / (2 pi L^2) * c * h / sqrt(12),   beta_n L = 4.730, 7.853, 10.996, 14.137, ...
  driven by the normal force (and, through the surface's offset from the neutral plane, by friction);
* extensional modes along x and y: f_n = n c / (2 L), driven by the friction force along that axis.

Each mode's damping comes from the loss factor: decay rate pi f eta, eta = material loss factor plus a
small support loss (the object rests on a table, touched by the pad; the same for every material). The
drive is weighted by the mode shape at the pad's position (cos of the mode's wavenumber along the axis),
and each mode is a two-pole resonator (``scipy.signal.lfilter``) whose impulse response is the mode's
acceleration per unit impulse, exp(-pi f eta t) sin(w t) w / M_modal, M_modal a quarter of the mass.
Only modes between ``min_frequency_hz`` and ``max_frequency_hz`` are kept: a small steel block's modes lie
above hearing (it clicks), a long bar or a plate rings. A rubber block's modes are low and die within a
few periods (eta ~ 0.1-0.3): it thuds.

Thick blocks get Timoshenko's shear/rotary-inertia correction, f / sqrt(1 + (beta r)^2 (1 + E / (k G))),
r = h / sqrt(12): a 5 cm steel cube's lowest modes land near 35 kHz, as measured on real blocks.

Microphone pressure (arbitrary units, roughly pascals at the fingertip microphone at distance d): every
vibrating surface radiates like a compact source, p = rho0 A a sigma / (4 pi d), A its area, a its
acceleration, sigma = (kL)^2 / (1 + (kL)^2) its radiation efficiency (bending surfaces smaller than the
wavelength radiate poorly; L the surface's size, k = 2 pi f / c0). The surfaces are

  * the object's modes (above), A the top face;
  * the object's local rigid-body response to the contact force, a = F / m_object above its support
    (table) resonance: light objects are louder than heavy ones for the same rubbing;
  * the fingertip, a = F / m_fingertip (friction noise: mostly the asperity hiss above a few kHz);

plus environment noise (room, fire; :mod:`.environment`), then the microphone's high-pass.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.signal

from perception.contact_trace import ObjectInfo
from perception.materials import FINGERTIP_MASS_KG, MaterialSample, object_volume_m3
from perception.sensors.contact_excitation import ContactExcitation

_BETA_L = (4.730040745, 7.853204624, 10.995607838, 14.137165491, 17.278759657)
_AIR_DENSITY_KG_M3 = 1.2
_AIR_SOUND_SPEED_MPS = 343.0
_SHEAR_COEFF = 5.0 / 6.0  # Timoshenko shear coefficient of a rectangular section


@dataclass(frozen=True)
class SoundConfig:
    """Modal synthesis and microphone model.

    Attributes:
        rate_hz: microphone rate, Hz.
        support_loss_factor: loss factor added to every mode by the support and the touching pad.
        modal_mass_fraction: modal mass as a fraction of the object mass.
        flexure_from_friction: share of the friction force that drives flexural modes (surface offset).
        min_frequency_hz, max_frequency_hz: band of kept modes, Hz.
        max_modes: at most this many modes (lowest first).
        extensional_orders: extensional mode orders per axis.
        mic_distance_range_m: microphone distance from the contact, drawn per stroke, m.
        poisson_ratio: for Timoshenko's shear correction (E / G = 2 (1 + nu)).
        fingertip_mass_kg: fingertip mass (its acceleration radiates friction noise), kg.
        fingertip_size_m: fingertip radiating size (square side), m.
        support_resonance_hz: the object's rigid-body resonance on its support, Hz.
        highpass_hz: microphone/preamp high-pass, Hz.
    """

    rate_hz: float = 44_100.0
    support_loss_factor: float = 6.0e-4
    modal_mass_fraction: float = 0.25
    flexure_from_friction: float = 0.5
    min_frequency_hz: float = 40.0
    max_frequency_hz: float = 18_000.0
    max_modes: int = 12
    extensional_orders: int = 3
    mic_distance_range_m: tuple[float, float] = (0.02, 0.05)
    poisson_ratio: float = 0.3
    fingertip_mass_kg: float = FINGERTIP_MASS_KG
    fingertip_size_m: float = 0.02
    support_resonance_hz: float = 150.0
    highpass_hz: float = 30.0


@dataclass(frozen=True)
class Mode:
    """One vibration mode of the object.

    Attributes:
        frequency_hz: natural frequency, Hz.
        loss_factor: total loss factor (material + support); decay rate pi f eta, 1/s.
        modal_mass_kg: modal mass, kg.
        kind: ``"flexural"`` (driven by normal force) or ``"extensional"`` (by friction along ``axis``).
        axis: 0 (x) or 1 (y), the axis along which the mode shape varies.
        wavenumber_rad: the mode shape is cos(wavenumber_rad * (x / L + 1/2)) along the axis.
    """

    frequency_hz: float
    loss_factor: float
    modal_mass_kg: float
    kind: str
    axis: int
    wavenumber_rad: float

    @property
    def decay_rate_per_s(self) -> float:
        return math.pi * self.frequency_hz * self.loss_factor


def object_modes(material: MaterialSample, size_m: tuple[float, float, float], shape: str = "box",
                 cfg: SoundConfig = SoundConfig(), support_loss_factor: float | None = None) -> tuple[Mode, ...]:
    """The object's audible modes, lowest first.

    Args:
        material: speed of sound, loss factor, density.
        size_m: bounding size (x, y, z), m.
        shape: object shape (for the mass).
        cfg: synthesis settings.
        support_loss_factor: overrides ``cfg.support_loss_factor`` (varied per stroke).

    Returns:
        Up to ``cfg.max_modes`` modes inside the kept band.
    """
    eta = material.loss_factor + (cfg.support_loss_factor if support_loss_factor is None else support_loss_factor)
    c = material.speed_of_sound_mps
    thickness = size_m[2]
    modal_mass = cfg.modal_mass_fraction * material.density_kg_m3 * object_volume_m3(size_m, shape)
    modes: list[Mode] = []
    for axis in (0, 1):
        length = size_m[axis]
        for order, beta_l in enumerate(_BETA_L, start=1):
            f = beta_l**2 / (2.0 * math.pi * length**2) * c * thickness / math.sqrt(12.0)
            shear = (beta_l * thickness / (math.sqrt(12.0) * length)) ** 2 * (1.0 + 2.0 * (1.0 + cfg.poisson_ratio) / _SHEAR_COEFF)
            f /= math.sqrt(1.0 + shear)
            modes.append(Mode(f, eta, modal_mass, "flexural", axis, math.pi * (order + 1)))
        for order in range(1, cfg.extensional_orders + 1):
            modes.append(Mode(order * c / (2.0 * length), eta, modal_mass, "extensional", axis, math.pi * order))
    kept = [m for m in modes if cfg.min_frequency_hz <= m.frequency_hz <= cfg.max_frequency_hz]
    kept.sort(key=lambda m: m.frequency_hz)
    return tuple(kept[: cfg.max_modes])


def _resonator_ba(mode: Mode, fs_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """Two-pole filter: force samples (N) -> the mode's acceleration (m/s^2), impulse-invariant."""
    w = 2.0 * math.pi * mode.frequency_hz
    sigma = mode.decay_rate_per_s
    w_d = math.sqrt(max(w * w - sigma * sigma, 1e-12))
    r = math.exp(-sigma / fs_hz)
    theta = w_d / fs_hz
    gain = w * w / (fs_hz * mode.modal_mass_kg * w_d)
    return np.array([0.0, gain * r * math.sin(theta)]), np.array([1.0, -2.0 * r * math.cos(theta), r * r])


def modal_impulse_response(material: MaterialSample, size_m: tuple[float, float, float], shape: str = "box",
                           duration_s: float = 0.5, cfg: SoundConfig = SoundConfig(),
                           position_on_object_m: tuple[float, float] = (0.0, 0.0),
                           mic_distance_m: float = 0.03) -> np.ndarray:
    """Sound pressure of the object's modes after a unit normal impulse (1 N s) on its top face.

    Args:
        material, size_m, shape: the object.
        duration_s: length of the response, s.
        cfg: synthesis settings.
        position_on_object_m: where the impulse lands, object frame, m.
        mic_distance_m: microphone distance, m.

    Returns:
        (n,) radiated pressure (same units as the S stream) at ``cfg.rate_hz``.
    """
    n = int(round(duration_s * cfg.rate_hz))
    impulse = np.zeros(n)
    impulse[0] = cfg.rate_hz  # 1 N s as one sample of force
    face_size = math.sqrt(size_m[0] * size_m[1])
    out = np.zeros(n)
    for mode in object_modes(material, size_m, shape, cfg):
        if mode.kind != "flexural":
            continue
        xi = position_on_object_m[mode.axis] / size_m[mode.axis] + 0.5
        b, a = _resonator_ba(mode, cfg.rate_hz)
        weight = radiation_efficiency(mode.frequency_hz, face_size) * math.cos(mode.wavenumber_rad * xi)
        out += weight * scipy.signal.lfilter(b, a, impulse)
    return _AIR_DENSITY_KG_M3 * size_m[0] * size_m[1] / (4.0 * math.pi * mic_distance_m) * out


def radiation_efficiency(frequency_hz: float | np.ndarray, size_m: float) -> float | np.ndarray:
    """Compact-source radiation efficiency (kL)^2 / (1 + (kL)^2) of a surface of size L."""
    kl = 2.0 * np.pi * np.asarray(frequency_hz) / _AIR_SOUND_SPEED_MPS * size_m
    return kl**2 / (1.0 + kl**2)


def _radiating_surface_sos(size_m: float, fs_hz: float, support_hz: float | None = None) -> np.ndarray:
    """High-pass sections: radiation efficiency of a surface (and its support resonance, if any)."""
    corner = min(_AIR_SOUND_SPEED_MPS / (2.0 * math.pi * size_m), 0.45 * fs_hz)
    sections = [scipy.signal.butter(1, corner, btype="highpass", fs=fs_hz, output="sos")] * 2
    if support_hz is not None:
        sections.append(scipy.signal.butter(2, support_hz, btype="highpass", fs=fs_hz, output="sos"))
    return np.concatenate(sections, axis=0)


def contact_sound(excitation: ContactExcitation, obj: ObjectInfo, rng: np.random.Generator,
                  cfg: SoundConfig = SoundConfig()) -> np.ndarray:
    """Sound at the microphone from the contact, before environment noise, at the excitation's rate.

    Args:
        excitation: contact force signals (rate must equal ``cfg.rate_hz``).
        obj: the object (modes from its material and size).
        rng: random generator (microphone distance, support loss of this stroke).
        cfg: synthesis settings.

    Returns:
        (M,) pressure, arbitrary units (about pascals).
    """
    if excitation.rate_hz != cfg.rate_hz:
        raise ValueError(f"excitation rate {excitation.rate_hz} Hz != microphone rate {cfg.rate_hz} Hz")
    fs = cfg.rate_hz
    size = obj.size_m
    distance = rng.uniform(*cfg.mic_distance_range_m)
    support = cfg.support_loss_factor * math.exp(0.3 * rng.standard_normal())
    # along the object's x and y extents (the modes' axes), not the pad's
    friction_along = excitation.shear_fluctuation_n[:, None] * excitation.slide_direction_on_object  # (M, 2)
    flexural_drive = (excitation.normal_fluctuation_n + excitation.impact_force_n
                      + cfg.flexure_from_friction * excitation.shear_fluctuation_n)
    xi = excitation.position_on_object_m / np.asarray(size[:2]) + 0.5  # (M, 2)
    face_size = math.sqrt(size[0] * size[1])
    surface_accel = np.zeros(excitation.num_samples)
    for mode in object_modes(obj.material, size, obj.shape, cfg, support_loss_factor=support):
        drive = flexural_drive if mode.kind == "flexural" else friction_along[:, mode.axis]
        b, a = _resonator_ba(mode, fs)
        weight = radiation_efficiency(mode.frequency_hz, face_size)
        surface_accel += weight * scipy.signal.lfilter(b, a, drive * np.cos(mode.wavenumber_rad * xi[:, mode.axis]))
    contact_force = excitation.normal_fluctuation_n + excitation.shear_fluctuation_n + excitation.impact_force_n
    object_mass = obj.material.density_kg_m3 * object_volume_m3(size, obj.shape)
    rigid = scipy.signal.sosfilt(_radiating_surface_sos(face_size, fs, cfg.support_resonance_hz),
                                 contact_force / object_mass)
    fingertip = scipy.signal.sosfilt(_radiating_surface_sos(cfg.fingertip_size_m, fs),
                                     contact_force / cfg.fingertip_mass_kg)
    scale = _AIR_DENSITY_KG_M3 / (4.0 * math.pi * distance)
    return scale * (size[0] * size[1] * (surface_accel + rigid) + cfg.fingertip_size_m**2 * fingertip)


def microphone_highpass(x: np.ndarray, cfg: SoundConfig = SoundConfig()) -> np.ndarray:
    """The microphone and preamp's high-pass."""
    sos = scipy.signal.butter(2, cfg.highpass_hz, btype="highpass", fs=cfg.rate_hz, output="sos")
    return scipy.signal.sosfilt(sos, x)
