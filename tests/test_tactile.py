"""Sensor emulation: the four streams carry the physics, and nothing but the physics."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import scipy.signal

from perception.contact_trace import ContactTrace, ContactTraceError, ObjectInfo, synthetic_press_slide_trace
from perception.materials import MaterialSample, default_catalogue, nominal_sample
from perception.sensors.contact_excitation import ContactConfig, compute_contact_excitation
from perception.sensors.imu import ImuConfig, imu_stream
from perception.sensors.sound import modal_impulse_response
from perception.sensors.taxels import TaxelArrayConfig, taxel_centres_m
from perception.sensors.texture import make_surface_texture
from perception.streams import MODALITIES, NOMINAL_RATE_HZ, NUM_CHANNELS, StrokeRecord
from perception.tactile import ENVIRONMENTS, EnvironmentProfile, emulate_stroke

SIZE_M = (0.15, 0.06, 0.02)
SLIDE_START_S = 0.15 + 0.25  # approach + press of the default synthetic trace
SLIDE_END_S = SLIDE_START_S + 1.0


def _sample(name: str) -> MaterialSample:
    return nominal_sample(default_catalogue().instance(name))


def _record(sample: MaterialSample, seed: int = 0, env: str = "clean", **trace_kwargs) -> StrokeRecord:
    trace = synthetic_press_slide_trace(friction_coefficient=sample.friction_kinetic, **trace_kwargs)
    return emulate_stroke(trace, ObjectInfo(sample, SIZE_M, "box", surface_seed=7), ENVIRONMENTS[env],
                          np.random.default_rng(seed))


def _window(rec: StrokeRecord, key: str, start_s: float, end_s: float) -> np.ndarray:
    stream = rec.streams[key]
    times = stream.times_s()
    return stream.data[(times >= start_s) & (times < end_s)]


def test_streams_have_the_recorded_format_and_no_nan():
    rec = _record(_sample("oak"))
    assert rec.category == "wood" and rec.instance == "oak" and rec.combustible
    for key in MODALITIES:
        stream = rec.streams[key]
        assert stream is not None
        assert stream.rate_hz == NOMINAL_RATE_HZ[key]
        assert stream.data.shape[1] == NUM_CHANNELS[key]
        assert stream.data.dtype == np.float32
        assert np.all(np.isfinite(stream.data))
        assert 0.0 <= stream.t0_s <= ENVIRONMENTS["clean"].clock_offset_max_s
        assert abs(stream.duration_s + stream.t0_s - 1.6) < 0.05  # the trace lasts 1.6 s
    offsets = rec.meta["clock_offsets_s"]
    assert len(set(offsets.values())) == 3  # uSkin, IMU and microphone clocks differ


def test_same_seed_same_record_other_seed_other_record():
    a, b, c = (_record(_sample("granite"), seed=s) for s in (3, 3, 4))
    for key in MODALITIES:
        np.testing.assert_array_equal(a.streams[key].data, b.streams[key].data)
        assert a.streams[key].t0_s == b.streams[key].t0_s
    assert not np.array_equal(a.streams["sound"].data[:1000], c.streams["sound"].data[:1000])


def test_labels_do_not_leak_only_physics_matters():
    sample = _sample("maple")
    renamed = dataclasses.replace(sample, instance="steel", category="metal", combustible=False)
    a, b = _record(sample, seed=5), _record(renamed, seed=5)
    for key in MODALITIES:
        np.testing.assert_array_equal(a.streams[key].data, b.streams[key].data)
    assert b.category == "metal"


def test_total_normal_force_rises_with_press_force():
    sample = _sample("abs")
    sums = []
    for force in (0.25, 0.5, 1.0, 2.0, 4.0):
        rec = _record(sample, seed=1, press_force_n=force)
        sums.append(_window(rec, "normal", 0.3, SLIDE_START_S).sum(axis=1).mean())
    assert all(b > a * 1.5 for a, b in zip(sums, sums[1:])), sums
    assert sums[2] == pytest.approx(1.0, rel=0.3)


@pytest.mark.parametrize("category", ["metal", "paper", "polymer", "rubber", "stone", "textiles", "wood"])
def test_sliding_shear_over_normal_matches_kinetic_friction(category):
    cat = default_catalogue()
    for name in cat.instances_of(category):
        sample = nominal_sample(cat.instance(name))
        rec = _record(sample, seed=2)
        normal = _window(rec, "normal", SLIDE_START_S + 0.15, SLIDE_END_S - 0.15).sum(axis=1)
        friction = _window(rec, "friction", SLIDE_START_S + 0.15, SLIDE_END_S - 0.15)
        shear = np.hypot(friction[:, 0::2].sum(axis=1), friction[:, 1::2].sum(axis=1))
        ratio = shear.mean() / normal.mean()
        assert ratio == pytest.approx(sample.friction_kinetic, rel=0.15), (name, ratio)


def _vibration_energy(rec: StrokeRecord) -> float:
    accel = _window(rec, "accel", SLIDE_START_S + 0.1, SLIDE_END_S - 0.1).astype(float)
    sos = scipy.signal.butter(2, 20.0, btype="highpass", fs=500.0, output="sos")
    return float(np.mean(scipy.signal.sosfiltfilt(sos, accel, axis=0) ** 2))


def test_rougher_surface_gives_more_vibration():
    smooth = _sample("oak")
    rough = dataclasses.replace(smooth, roughness_rms_m=smooth.roughness_rms_m * 4.0)
    assert _vibration_energy(_record(rough, seed=3)) > 1.2 * _vibration_energy(_record(smooth, seed=3))
    # Across the catalogue, too: sandstone (Rq 25 um) against polished marble (Rq 0.6 um), no stick-slip gap.
    no_stick_slip = {"friction_static": 0.7, "friction_kinetic": 0.7}
    sandstone = dataclasses.replace(_sample("sandstone"), **no_stick_slip)
    marble = dataclasses.replace(_sample("marble"), **no_stick_slip)
    assert _vibration_energy(_record(sandstone, seed=3)) > 2.0 * _vibration_energy(_record(marble, seed=3))


def _decay_time_s(pressure: np.ndarray, fs_hz: float, drop_db: float = 20.0) -> float:
    """Time for the Schroeder energy-decay curve to fall by ``drop_db``."""
    energy = np.cumsum((pressure**2)[::-1])[::-1]
    curve_db = 10.0 * np.log10(energy / energy[0] + 1e-30)
    return float(np.argmax(curve_db < -drop_db) / fs_hz)


def test_metal_rings_longer_than_rubber():
    size = (0.2, 0.05, 0.01)
    steel = modal_impulse_response(_sample("steel"), size, duration_s=1.0, position_on_object_m=(0.02, 0.005))
    rubber = modal_impulse_response(_sample("nitrile"), size, duration_s=1.0, position_on_object_m=(0.02, 0.005))
    t_steel, t_rubber = _decay_time_s(steel, 44_100.0), _decay_time_s(rubber, 44_100.0)
    assert t_steel > 5.0 * t_rubber, (t_steel, t_rubber)
    assert t_steel > 0.05


def test_normal_centroid_follows_the_contact_along_the_stroke():
    centres = taxel_centres_m(TaxelArrayConfig())
    for direction in ((1.0, 0.0), (0.0, -1.0)):
        drift = (0.004 * direction[0], 0.004 * direction[1])
        rec = _record(_sample("pine"), seed=4, slide_direction=direction, contact_drift_on_pad_m=drift)
        early = _window(rec, "normal", SLIDE_START_S - 0.1, SLIDE_START_S).mean(axis=0)
        late = _window(rec, "normal", SLIDE_END_S - 0.1, SLIDE_END_S).mean(axis=0)
        shift = late @ centres / late.sum() - early @ centres / early.sum()
        assert shift @ np.asarray(direction) > 0.002, shift
        assert abs(shift @ np.array([-direction[1], direction[0]])) < 0.001


def _excitation(sample: MaterialSample, trace: ContactTrace, config: ContactConfig = ContactConfig()):
    return compute_contact_excitation(trace, ObjectInfo(sample, SIZE_M, "box", surface_seed=7),
                                      make_surface_texture(sample, SIZE_M, 7), np.random.default_rng(0), config)


def test_sliding_friction_follows_the_textures_normal_force():
    """Coulomb: while the pad slides, F = mu N, so where the texture presses the surface harder into the pad the
    friction rises by the same share. With the slope's tilt and stick-slip switched off, nothing else moves the
    friction: its relative change is the normal force's."""
    sample = dataclasses.replace(_sample("sandstone"), friction_static=_sample("sandstone").friction_kinetic)
    trace = synthetic_press_slide_trace(friction_coefficient=sample.friction_kinetic)
    excitation = _excitation(sample, trace, dataclasses.replace(ContactConfig(), max_texture_slope=0.0))
    times = np.arange(excitation.num_samples) / excitation.rate_hz
    steady = (times > SLIDE_START_S + 0.1) & (times < SLIDE_END_S - 0.1)
    assert np.std(excitation.normal_modulation[steady]) > 0.01  # the texture does move the normal force
    np.testing.assert_allclose(excitation.shear_modulation[steady], excitation.normal_modulation[steady],
                               rtol=0.0, atol=0.01 * np.std(excitation.normal_modulation[steady]))


def test_slide_direction_on_object_is_the_pads_motion_over_the_object():
    """The object's modes lie along its own x and y extents, so the sound needs the slide's direction in the
    object frame, which differs from the pad frame whenever the pad is turned on the object: here the pad slides
    along its own x while it moves along the object's -y."""
    sample = _sample("nylon")
    trace = synthetic_press_slide_trace(friction_coefficient=sample.friction_kinetic, start_on_object_m=(0.0, 0.015))
    on_object = trace.pad_position_on_object_m - trace.pad_position_on_object_m[0]
    turned = dataclasses.replace(trace, pad_position_on_object_m=trace.pad_position_on_object_m[0]
                                 + np.column_stack([on_object[:, 1], -on_object[:, 0]]))
    excitation = _excitation(sample, turned)
    times = np.arange(excitation.num_samples) / excitation.rate_hz
    steady = (times > SLIDE_START_S + 0.1) & (times < SLIDE_END_S - 0.1)
    np.testing.assert_allclose(excitation.slide_direction[steady], np.tile([1.0, 0.0], (steady.sum(), 1)), atol=1e-6)
    np.testing.assert_allclose(excitation.slide_direction_on_object[steady], np.tile([0.0, -1.0], (steady.sum(), 1)),
                               atol=1e-6)
    assert np.all(excitation.slide_direction_on_object[times < SLIDE_START_S - 0.05] == 0.0)  # still: no direction


def test_touch_down_impact_reaches_the_accelerometer():
    sample = _sample("steel")
    trace = synthetic_press_slide_trace(friction_coefficient=sample.friction_kinetic)
    obj = ObjectInfo(sample, SIZE_M, "box", surface_seed=7)
    excitation = compute_contact_excitation(trace, obj, make_surface_texture(sample, SIZE_M, 7),
                                            np.random.default_rng(0))
    onset_s = np.flatnonzero(excitation.impact_force_n)[0] / excitation.rate_hz
    with_impact = imu_stream(excitation, trace, 0.0, np.random.default_rng(1))
    quiet = dataclasses.replace(excitation, impact_force_n=np.zeros_like(excitation.impact_force_n))
    without = imu_stream(quiet, trace, 0.0, np.random.default_rng(1))
    times = np.arange(with_impact.shape[0]) / ImuConfig().rate_hz
    effect = np.abs(with_impact - without)
    assert np.all(effect[times < onset_s] == 0.0)  # causal: nothing before the touch-down
    after = effect[(times >= onset_s) & (times < onset_s + 0.05), 2]
    assert after.max() > 10 * np.std(without[times < 0.05, 2])  # the knock stands out of the sensor noise


def test_dropout_marks_modalities_missing_never_all():
    env = EnvironmentProfile(name="flaky", dropout_probability=0.9)
    trace = synthetic_press_slide_trace(friction_coefficient=0.5, slide_s=0.3)
    obj = ObjectInfo(_sample("slate"), SIZE_M)
    seen_missing = set()
    for seed in range(6):
        rec = emulate_stroke(trace, obj, env, np.random.default_rng(seed))
        missing = {k for k in MODALITIES if rec.streams[k] is None}
        assert missing == set(rec.meta["dropped"])
        assert ("normal" in missing) == ("friction" in missing)  # one uSkin streams both
        assert len(rec.present) >= 1
        seen_missing |= missing
        for key in rec.present:
            assert np.any(rec.streams[key].data != 0)
    assert seen_missing


def test_fire_is_noisier_than_clean():
    sample = _sample("steel")
    quiet = {"clean": [], "fire": []}
    for env in quiet:
        for seed in range(6):
            rec = _record(sample, seed=seed, env=env, slide_s=0.3)
            if rec.streams["sound"] is not None:
                quiet[env].append(np.std(_window(rec, "sound", 0.05, 0.14)))
    # roar, crackles and alarms on top of the room noise: louder before the pad touches down (about 3 dB:
    # the fire is set against the quiet contact sound of metal, see perception.sensors.environment.FIRE)
    assert np.median(quiet["fire"]) > 1.25 * np.median(quiet["clean"])


def test_bad_inputs_raise_clear_errors():
    trace = synthetic_press_slide_trace(friction_coefficient=0.5, slide_s=0.2)
    fields = {f.name: getattr(trace, f.name) for f in dataclasses.fields(ContactTrace)}
    forces = fields["point_normal_force_n"].copy()
    forces[10, 0] = np.nan
    with pytest.raises(ContactTraceError, match="point_normal_force_n: NaN or inf"):
        ContactTrace(**{**fields, "point_normal_force_n": forces})
    with pytest.raises(ContactTraceError, match="pad_velocity_mps: expected shape"):
        ContactTrace(**{**fields, "pad_velocity_mps": fields["pad_velocity_mps"][:, :2]})
    with pytest.raises(ContactTraceError, match="uniform"):
        ContactTrace(**{**fields, "t_s": fields["t_s"] ** 1.1})
    with pytest.raises(ContactTraceError, match="shape"):
        ObjectInfo(_sample("oak"), SIZE_M, shape="torus")
    with pytest.raises(TypeError, match="EnvironmentProfile"):
        emulate_stroke(trace, ObjectInfo(_sample("oak"), SIZE_M), "clean", np.random.default_rng(0))
