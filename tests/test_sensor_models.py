"""Individual sensor models: surface texture, taxel spread and readout, resampling, sound modes."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from perception.contact_trace import synthetic_press_slide_trace
from perception.materials import default_catalogue, nominal_sample
from perception.sensors.resample import decimation_delay_s, sensor_samples
from perception.sensors.sound import object_modes
from perception.sensors.taxels import TaxelArrayConfig, taxel_forces, uskin_readout
from perception.sensors.texture import make_surface_texture


def test_texture_rms_matches_material_and_is_seeded():
    sample = nominal_sample(default_catalogue().instance("sandstone"))
    texture = make_surface_texture(sample, (0.1, 0.06, 0.03), seed=11)
    xy = np.random.default_rng(0).uniform(-0.05, 0.05, (20_000, 2))
    full, smooth = texture.sample(xy)
    assert np.std(full) == pytest.approx(sample.roughness_rms_m, rel=0.25)
    assert np.std(smooth) < np.std(full)
    again, _ = make_surface_texture(sample, (0.1, 0.06, 0.03), seed=11).sample(xy)
    np.testing.assert_array_equal(full, again)


def test_centred_contact_is_fully_sensed_and_readout_recovers_force():
    cfg = TaxelArrayConfig()
    trace = synthetic_press_slide_trace(friction_coefficient=0.5, press_force_n=2.0, slide_s=0.2)
    forces = taxel_forces(trace, cfg)  # (T, 16, 3)
    steady = forces[int(0.35 * trace.rate_hz)]
    assert steady[:, 2].sum() == pytest.approx(2.0, rel=1e-3)
    ideal = dataclasses.replace(cfg, gain_spread=0.0, neighbour_crosstalk=0.0, axis_crosstalk_spread=0.0,
                                noise_counts=0.0, drift_counts_per_s=0.0, drift_walk_counts_per_sqrt_s=0.0)
    reported = uskin_readout(np.repeat(steady[None], 20, axis=0), np.random.default_rng(0), ideal)
    np.testing.assert_allclose(reported[:, :, 2].sum(axis=1), 2.0, atol=0.01)  # quantisation only


def test_neighbour_crosstalk_spreads_a_taxels_force_without_adding_to_it():
    cfg = dataclasses.replace(TaxelArrayConfig(), gain_spread=0.0, axis_crosstalk_spread=0.0, noise_counts=0.0,
                              drift_counts_per_s=0.0, drift_walk_counts_per_sqrt_s=0.0)
    forces = np.zeros((10, 16, 3))
    forces[:, 5, 2] = 1.0  # one inner taxel (4 neighbours)
    reported = uskin_readout(forces, np.random.default_rng(0), cfg)[:, :, 2]
    np.testing.assert_allclose(reported[:, 5], 1.0 - 4 * cfg.neighbour_crosstalk, atol=1e-3)
    np.testing.assert_allclose(reported[:, [1, 4, 6, 9]], cfg.neighbour_crosstalk, atol=1e-3)
    np.testing.assert_allclose(reported.sum(axis=1), 1.0, atol=2e-3)  # before the fix: 1.16 N
    trace = synthetic_press_slide_trace(friction_coefficient=0.5, press_force_n=2.0, slide_s=0.2)
    steady = taxel_forces(trace, cfg)[int(0.35 * trace.rate_hz)]
    centred = uskin_readout(np.repeat(steady[None], 10, axis=0), np.random.default_rng(0), cfg)
    np.testing.assert_allclose(centred[:, :, 2].sum(axis=1), 2.0, atol=0.01)  # before the fix: 2.3 N


def test_neighbour_crosstalk_is_checked():
    with pytest.raises(ValueError, match="neighbour_crosstalk"):
        TaxelArrayConfig(neighbour_crosstalk=0.3)


def test_taxel_saturates_near_overload():
    cfg = dataclasses.replace(TaxelArrayConfig(), neighbour_crosstalk=0.0, noise_counts=0.0)
    forces = np.zeros((5, 16, 3))
    forces[:, 5, 2] = [1.0, 3.0, 6.0, 12.0, 24.0]
    reported = uskin_readout(forces, np.random.default_rng(0), cfg)[:, 5, 2]
    assert np.all(np.diff(reported) >= -0.05)
    assert reported[-1] < 3.6  # overload: the taxel stops following the force


@pytest.mark.parametrize("rate_in_hz", [1000.0, 240.0])  # a fine input, and one interpolated first
def test_sensor_samples_apply_clock_offset_and_the_filter_delay(rate_in_hz):
    t = np.arange(int(2.0 * rate_in_hz)) / rate_in_hz
    ramp = t[:, None].copy()
    out = sensor_samples(ramp, rate_in_hz, 100.0, t0_s=0.025, duration_s=2.0)
    times = 0.025 + np.arange(out.shape[0]) / 100.0
    delay = decimation_delay_s(rate_in_hz, 100.0)
    assert 0.01 < delay < 0.02  # three boxcars of 10 ms lag by about 15 ms
    np.testing.assert_allclose(out[5:-5, 0], times[5:-5] - delay, atol=1e-3)


def test_sensor_samples_of_a_press_step_do_not_ring_before_or_after_it():
    # a zero-phase resampler read -0.35 N 10 ms before a 0 -> 4 N step; a sensor's causal filter reads nothing
    t = np.arange(0.0, 1.0, 1e-3)
    step = np.where(t >= 0.5, 4.0, 0.0)[:, None]
    out = sensor_samples(step, 1000.0, 100.0, t0_s=0.0, duration_s=1.0)[:, 0]
    times = np.arange(out.size) / 100.0
    assert np.all(out[times < 0.5] == 0.0)
    assert np.all(np.diff(out) >= 0.0) and out.max() <= 4.0 + 1e-12
    np.testing.assert_allclose(out[times >= 0.5 + 3 * 0.01], 4.0)  # settled after three periods


def test_sensor_samples_refuse_an_empty_signal():
    with pytest.raises(ValueError, match="at least one input sample"):
        sensor_samples(np.zeros((0, 3)), 1000.0, 100.0, t0_s=0.0, duration_s=1.0)


def test_sensor_samples_reject_aliases_and_pass_the_band():
    fs = 44_100.0
    t = np.arange(0.0, 2.0, 1.0 / fs)

    def gain(freq_hz):
        out = sensor_samples(np.sin(2 * np.pi * freq_hz * t)[:, None], fs, 500.0, t0_s=0.0, duration_s=2.0)
        return np.std(out[50:, 0]) / np.sqrt(0.5)

    assert gain(50.0) > 0.95
    assert gain(750.0) < 0.02  # would alias to 250 Hz
    assert gain(3000.0) < 0.01


def test_small_steel_cube_has_no_audible_modes_but_a_plate_does():
    steel = nominal_sample(default_catalogue().instance("steel"))
    assert object_modes(steel, (0.05, 0.05, 0.05)) == ()
    modes = object_modes(steel, (0.25, 0.15, 0.005))
    assert modes and modes[0].frequency_hz < 2000.0
    assert all(a.frequency_hz <= b.frequency_hz for a, b in zip(modes, modes[1:]))
