"""What the surface does to the contact forces, at audio rate: texture, stick-slip, touch-down impact.

The simulator's contact forces are the quasi-static part (its friction is plain Coulomb with the kinetic
coefficient). On top of them this module adds what a 1 kHz rigid-body step cannot resolve:

* Texture. The pad centre's path over the object's height field (:mod:`.texture`), traversed at the
  sliding velocity, gives a height signal h(t). The arm's force control absorbs changes below
  ``force_control_cutoff_hz``; above it the contact stiffness turns height into force,
  dN = k_local h, with k_local the pad and object surface stiffnesses in series (growing as N^(1/3), a
  Hertz-like contact). The local slope along the path tilts the contact: mu_eff ~ mu_k + (1 + mu_k^2)
  slope. Both are averaged over the contact width: a patch of width 2a over a surface of correlation
  length xi holds ~2a / xi independent asperities, so fluctuations scale by kappa = sqrt(min(1, xi / 2a)).
  While the pad slides, friction follows both (Coulomb, F = mu N): dF / F = (1 + dN / N)(1 + dmu / mu) - 1.
  Sub-probe roughness (the full profile minus the probe-smoothed one) gives the broadband asperity force
  that makes friction noise.
* Stick-slip (spring-block, Karnopp-style, solved in closed form). The pad's elastomer is a tangential
  spring k_t dragged at the sliding speed V. While stuck, the spring force climbs at k_t V; it slips when
  it reaches the static limit and overshoots below the kinetic level by ``slip_overshoot`` x the
  static-kinetic gap. The force therefore follows a sawtooth between mu_k N - r dF and mu_k N + dF,
  dF = (mu_s - mu_k) N / (1 + (V / V_c)^2) (velocity strengthening damps it out at high speed), with
  stick period dF (1 + r) / (k_t V). It is integrated as a phase, so it is vectorised and exact for
  slowly varying N and V. Slips take ``slip_time_s``. Where mu_s == mu_k there is no stick-slip.
* Touch-down impact: at each contact onset, a half-sine force pulse of impulse m_tip v (1 + e) and
  duration pi sqrt(m_tip / k), k the same series contact stiffness.

Nothing here depends on anything but the material's physical parameters and the trace.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.signal

from perception.contact_trace import ContactTrace, ObjectInfo
from perception.materials import FINGERTIP_MASS_KG, ContactModelConfig, local_contact_stiffness_n_per_m
from perception.sensors.resample import interpolate_uniform
from perception.sensors.texture import SurfaceTexture


@dataclass(frozen=True)
class ContactConfig:
    """Contact micro-mechanics constants (the same for every material).

    Attributes:
        fine_rate_hz: rate of the excitation signals, Hz (the microphone's).
        pad_stiffness_n_per_m: local normal stiffness of the silicone pad at ``reference_normal_force_n``.
        reference_normal_force_n: force at which the stiffnesses are quoted, N.
        contact_half_width_m: half width a of the contact patch (asperity averaging), m.
        tangential_stiffness_n_per_m: elastomer shear stiffness k_t loading the stick phase, N/m.
        slip_overshoot: r, how far below the kinetic level a slip overshoots (fraction of the gap).
        stick_slip_critical_speed_mps: V_c, speed scale above which stick-slip dies out, m/s.
        min_slide_speed_mps: below this the pad is not sliding (texture and stick-slip fade out), m/s.
        max_stick_slip_rate_hz: cap on the stick-slip rate (numerical guard for tiny gaps), Hz.
        slip_time_s: duration of a slip (first-order smoothing of the force drop), s.
        slip_threshold_jitter: 1-sigma log spread of each stick's amplitude (asperity-to-asperity).
        force_control_cutoff_hz: height changes slower than this are absorbed by the arm, Hz.
        max_texture_slope: clip on the path slope (steep asperity flanks), dimensionless.
        max_normal_modulation: clip on dN / N.
        contact_threshold_n: total normal force above which the pad is in contact, N.
        fingertip_mass_kg: effective fingertip mass in impacts, kg.
        impact_quiet_s: an onset counts as a touch-down after this long without contact, s.
    """

    fine_rate_hz: float = 44_100.0
    pad_stiffness_n_per_m: float = 1.0e4
    reference_normal_force_n: float = 1.0
    contact_half_width_m: float = 2.0e-3
    tangential_stiffness_n_per_m: float = 3.0e3
    slip_overshoot: float = 0.5
    stick_slip_critical_speed_mps: float = 0.02
    min_slide_speed_mps: float = 1.0e-3
    max_stick_slip_rate_hz: float = 1500.0
    slip_time_s: float = 3.0e-4
    slip_threshold_jitter: float = 0.3
    force_control_cutoff_hz: float = 5.0
    max_texture_slope: float = 0.3
    max_normal_modulation: float = 0.5
    contact_threshold_n: float = 0.02
    fingertip_mass_kg: float = FINGERTIP_MASS_KG
    impact_quiet_s: float = 0.02


@dataclass(frozen=True)
class ContactExcitation:
    """Contact signals at ``rate_hz``, time 0 = the trace's first step.

    Attributes:
        rate_hz: sampling rate, Hz.
        normal_force_n: (M,) simulator's total normal force, interpolated, N.
        slide_speed_mps: (M,) tangential pad speed over the object, m/s.
        slide_direction: (M, 2) unit direction of the pad's motion, pad frame (zero when still).
        slide_direction_on_object: (M, 2) the same direction in the object frame (zero when still): what the
            object's own modes along its x and y extents see.
        position_on_object_m: (M, 2) pad centre on the top face, object frame, m.
        normal_modulation: (M,) relative change of the normal force from texture, dN / N.
        shear_modulation: (M,) relative change of the friction force while sliding: the texture's change of the
            normal force (Coulomb), its slope and stick-slip.
        normal_fluctuation_n: (M,) texture force on the pad along its normal (coherent + asperity), N.
        shear_fluctuation_n: (M,) friction force fluctuation along the slide direction, N.
        impact_force_n: (M,) touch-down force pulses, N.
    """

    rate_hz: float
    normal_force_n: np.ndarray
    slide_speed_mps: np.ndarray
    slide_direction: np.ndarray
    slide_direction_on_object: np.ndarray
    position_on_object_m: np.ndarray
    normal_modulation: np.ndarray
    shear_modulation: np.ndarray
    normal_fluctuation_n: np.ndarray
    shear_fluctuation_n: np.ndarray
    impact_force_n: np.ndarray

    @property
    def num_samples(self) -> int:
        return int(self.normal_force_n.shape[0])


def _speed_and_direction(velocity_mps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(M,) speed, m/s, and (M, 2) unit direction of a planar velocity (zero where it is still)."""
    speed = np.hypot(velocity_mps[:, 0], velocity_mps[:, 1])
    return speed, velocity_mps / np.maximum(speed, 1e-12)[:, None] * (speed > 1e-9)[:, None]


def _stick_slip_ripple(normal_n: np.ndarray, speed_mps: np.ndarray, sliding: np.ndarray, mu_s: float, mu_k: float,
                       rng: np.random.Generator, cfg: ContactConfig) -> np.ndarray:
    """Relative friction ripple (F - mu_k N) / (mu_k N) of the spring-block sawtooth, (M,)."""
    if mu_s <= mu_k:
        return np.zeros_like(normal_n)
    gap_rel = (mu_s / mu_k - 1.0) / (1.0 + (speed_mps / cfg.stick_slip_critical_speed_mps) ** 2)
    r = cfg.slip_overshoot
    force_range = np.maximum(gap_rel * (1.0 + r) * mu_k * normal_n, 1e-9)
    rate = np.minimum(cfg.tangential_stiffness_n_per_m * speed_mps / force_range, cfg.max_stick_slip_rate_hz)
    phase = rng.uniform() + np.cumsum(rate * sliding) / cfg.fine_rate_hz
    cycle = np.floor(phase)
    saw = phase - cycle
    # Each stick ends at its own threshold: the static limit varies with the asperities caught.
    jitter = np.exp(cfg.slip_threshold_jitter * np.clip(rng.standard_normal(int(cycle[-1]) + 2), -2.5, 2.5))
    ripple = gap_rel * ((1.0 + r) * saw - r) * sliding * jitter[cycle.astype(np.int64)]
    alpha = 1.0 - math.exp(-1.0 / (cfg.slip_time_s * cfg.fine_rate_hz))
    return scipy.signal.lfilter([alpha], [1.0, alpha - 1.0], ripple, zi=[ripple[0] * (1.0 - alpha)])[0]


def _impact_pulses(trace: ContactTrace, n_fine: int, stiffness_n_per_m: float, restitution: float,
                   cfg: ContactConfig) -> np.ndarray:
    """Half-sine touch-down pulses at contact onsets, (n_fine,) N."""
    out = np.zeros(n_fine)
    contact = trace.total_normal_force_n() > cfg.contact_threshold_n
    quiet = max(int(round(cfg.impact_quiet_s * trace.rate_hz)), 1)
    duration = math.pi * math.sqrt(cfg.fingertip_mass_kg / stiffness_n_per_m)
    t_rel = trace.t_s - trace.t_s[0]
    for i in np.flatnonzero(contact[1:] & ~contact[:-1]) + 1:
        if i < quiet or np.any(contact[i - quiet:i]):
            continue
        approach_speed = max(float(trace.pad_velocity_mps[i - 1, 2]), 0.0)
        impulse = cfg.fingertip_mass_kg * approach_speed * (1.0 + restitution)
        start = int(round(t_rel[i] * cfg.fine_rate_hz))
        n = max(int(round(duration * cfg.fine_rate_hz)), 1)
        stop = min(start + n, n_fine)
        tau = np.arange(stop - start) / cfg.fine_rate_hz
        out[start:stop] += impulse * math.pi / (2.0 * duration) * np.sin(np.pi * tau / duration)
    return out


def compute_contact_excitation(trace: ContactTrace, obj: ObjectInfo, texture: SurfaceTexture,
                               rng: np.random.Generator, cfg: ContactConfig = ContactConfig()) -> ContactExcitation:
    """Texture, stick-slip and impact signals for one stroke.

    Args:
        trace: the simulator's contact trace.
        obj: the touched object (its material's physical parameters).
        texture: the object's surface height field.
        rng: random generator (the stick-slip cycle's initial phase).
        cfg: contact constants.

    Returns:
        The :class:`ContactExcitation` at ``cfg.fine_rate_hz``.
    """
    mat = obj.material
    fs = cfg.fine_rate_hz
    n_fine = int(math.floor(trace.duration_s * fs)) + 1
    t_fine = np.arange(n_fine) / fs
    velocity_on_object = np.gradient(trace.pad_position_on_object_m, trace.t_s, axis=0)  # (T, 2) m/s
    physics = np.column_stack([trace.total_normal_force_n(), trace.pad_position_on_object_m, trace.pad_velocity_mps[:, :2],
                               velocity_on_object])
    fine = interpolate_uniform(physics, trace.rate_hz, t_fine)  # (M, 7)
    normal = np.maximum(fine[:, 0], 0.0)
    position = fine[:, 1:3]
    velocity = fine[:, 3:5]
    speed, direction = _speed_and_direction(velocity)
    _, direction_on_object = _speed_and_direction(fine[:, 5:7])
    in_contact = normal > cfg.contact_threshold_n
    sliding = in_contact * (speed**2 / (speed**2 + cfg.min_slide_speed_mps**2))

    # Contact stiffness: pad and object surface in series, Hertz-like growth with load.
    k_obj = local_contact_stiffness_n_per_m(mat, ContactModelConfig())
    k_series = 1.0 / (1.0 / cfg.pad_stiffness_n_per_m + 1.0 / k_obj)
    k_local = k_series * np.cbrt(normal / cfg.reference_normal_force_n) * in_contact
    kappa = math.sqrt(min(1.0, mat.correlation_length_m / (2.0 * cfg.contact_half_width_m)))

    h_full, h_smooth = texture.sample(position)
    sos = scipy.signal.butter(2, cfg.force_control_cutoff_hz, btype="highpass", fs=fs, output="sos")
    h_coherent = scipy.signal.sosfilt(sos, h_smooth - h_smooth[0])
    h_asperity = scipy.signal.sosfilt(sos, (h_full - h_smooth) - (h_full[0] - h_smooth[0]))
    dn_texture = kappa * k_local * h_coherent
    dn_asperity = kappa * k_local * h_asperity
    slope = np.gradient(h_smooth) * fs / np.maximum(speed, cfg.min_slide_speed_mps)
    slope = np.clip(slope, -cfg.max_texture_slope, cfg.max_texture_slope) * sliding
    mu_k = mat.friction_kinetic
    dmu_rel = kappa * (1.0 + mu_k**2) * slope / mu_k
    ripple = _stick_slip_ripple(normal, speed, sliding, mat.friction_static, mu_k, rng, cfg)

    normal_mod = np.clip(dn_texture / np.maximum(normal, cfg.contact_threshold_n),
                         -cfg.max_normal_modulation, cfg.max_normal_modulation)
    shear_mod = (1.0 + normal_mod * sliding) * (1.0 + dmu_rel + ripple) - 1.0  # Coulomb: F = mu N
    impact = _impact_pulses(trace, n_fine, k_series, mat.restitution, cfg)
    return ContactExcitation(
        rate_hz=fs,
        normal_force_n=normal,
        slide_speed_mps=speed,
        slide_direction=direction,
        slide_direction_on_object=direction_on_object,
        position_on_object_m=position,
        normal_modulation=normal_mod,
        shear_modulation=shear_mod,
        normal_fluctuation_n=dn_texture + dn_asperity,
        shear_fluctuation_n=mu_k * (normal * shear_mod + dn_asperity * sliding),
        impact_force_n=impact,
    )
