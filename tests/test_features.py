"""Front ends, normalisation and batching (perception.features).

Also home of :func:`make_synthetic_strokes`, the seeded toy data set the model tests import.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from perception.features import (ACCEL_NORMAL_TANGENTIAL, FeatureConfig, NormStats, SpectralConfig, collate,
                                  feature_dims, featurize, fit_norm_stats, normalize, spectral_features,
                                  taxel_features)
from perception.streams import MODALITIES, NOMINAL_RATE_HZ, NUM_CHANNELS, Stream, StrokeRecord

torch.set_num_threads(2)

SOUND_FREQ_HZ = (300.0, 1200.0, 4000.0)  # dominant sound frequency per class
ACCEL_FREQ_HZ = (12.0, 40.0, 110.0)  # dominant vibration frequency per class
NORMAL_FORCE_N = (0.4, 0.8, 1.2)  # mean normal force per taxel per class
FRICTION_COEF = (0.2, 0.5, 0.8)  # shear = coef * normal


def make_synthetic_strokes(n_per_class: int, seed: int, n_classes: int = 3, p_missing: float = 0.0,
                           duration_s: tuple[float, float] = (0.8, 1.3)) -> list[StrokeRecord]:
    """A seeded toy classification problem: the class sets each stream's physical property.

    Class k has sound at ``SOUND_FREQ_HZ[k]``, vibration at ``ACCEL_FREQ_HZ[k]``, normal force
    ``NORMAL_FORCE_N[k]`` and friction coefficient ``FRICTION_COEF[k]``, each with random jitter, amplitude,
    noise, duration and clock offset. Each stream is dropped with probability ``p_missing`` (never all four).
    """
    rng = np.random.default_rng(seed)
    records = []
    for k in range(n_classes):
        for _ in range(n_per_class):
            dur = rng.uniform(*duration_s)
            streams: dict[str, Stream | None] = {}
            for key in MODALITIES:
                rate = NOMINAL_RATE_HZ[key]
                n = int(dur * rate)
                t = np.arange(n) / rate
                if key == "sound":
                    f = SOUND_FREQ_HZ[k] * rng.uniform(0.93, 1.07)
                    x = rng.uniform(0.3, 1.0) * np.sin(2 * np.pi * f * t + rng.uniform(0, 6.3))
                    data = (x + 0.3 * rng.normal(size=n))[:, None]
                elif key == "accel":
                    f = ACCEL_FREQ_HZ[k] * rng.uniform(0.93, 1.07)
                    axis = rng.normal(size=3)
                    data = np.sin(2 * np.pi * f * t)[:, None] * axis[None, :] + 0.3 * rng.normal(size=(n, 3))
                elif key == "normal":
                    pattern = rng.uniform(0.5, 1.5, size=16)
                    data = NORMAL_FORCE_N[k] * pattern[None, :] + 0.1 * rng.normal(size=(n, 16))
                else:
                    normal = NORMAL_FORCE_N[k] * rng.uniform(0.7, 1.3)
                    data = FRICTION_COEF[k] * normal * rng.uniform(0.5, 1.5, size=32)[None, :]
                    data = data + 0.1 * rng.normal(size=(n, 32))
                streams[key] = Stream(data.astype(np.float32), rate_hz=rate, t0_s=float(rng.uniform(0, 0.05)))
            if p_missing > 0:
                drop = rng.random(len(MODALITIES)) < p_missing
                if drop.all():
                    drop[rng.integers(len(MODALITIES))] = False
                for key, d in zip(MODALITIES, drop):
                    if d:
                        streams[key] = None
            records.append(StrokeRecord(streams=streams, category=f"class{k}", instance=f"class{k}_inst",
                                        combustible=bool(k % 2), meta={"label": k}))
    order = rng.permutation(len(records))
    return [records[i] for i in order]


def labels_of(records: list[StrokeRecord]) -> list[int]:
    return [int(r.meta["label"]) for r in records]


# ----------------------------------------------------------------------------------------------------------


def test_featurize_shapes_and_dims():
    cfg = FeatureConfig()
    dims = feature_dims(cfg)
    rec = make_synthetic_strokes(1, seed=0, duration_s=(1.0, 1.0))[0]
    feats = featurize(rec, cfg)
    assert set(feats) == set(MODALITIES)
    lengths = {}
    for key in MODALITIES:
        x = feats[key]
        assert x.dtype == np.float32 and x.ndim == 2 and x.shape[1] == dims[key]
        assert np.all(np.isfinite(x))
        lengths[key] = x.shape[0]
    # each modality keeps its own frame rate: 1 s of sound at 23.2 ms hop, taxels at 50 ms, accel at 64 ms
    assert lengths["sound"] == pytest.approx(1.0 / cfg.sound.hop_s, abs=3)
    assert lengths["normal"] == pytest.approx(1.0 / cfg.normal.hop_s, abs=2)
    assert lengths["accel"] == pytest.approx(1.0 / cfg.accel.hop_s, abs=2)
    assert len(set(lengths.values())) > 1


def test_window_in_seconds_is_rate_independent():
    cfg = FeatureConfig().sound
    rng = np.random.default_rng(1)
    a = spectral_features(Stream(rng.normal(size=(44_100, 1)).astype(np.float32), 44_100.0), cfg)
    b = spectral_features(Stream(rng.normal(size=(48_000, 1)).astype(np.float32), 48_000.0), cfg)
    assert a.shape == b.shape


def test_spectral_bands_follow_the_dominant_frequency():
    cfg = SpectralConfig(window_s=0.05, hop_s=0.025, n_bands=24, fmin_hz=50.0, fmax_hz=16_000.0, mel=True)
    t = np.arange(44_100) / 44_100.0
    peaks = []
    for f in SOUND_FREQ_HZ:
        x = np.sin(2 * np.pi * f * t)[:, None].astype(np.float32)
        peaks.append(int(np.argmax(spectral_features(Stream(x, 44_100.0), cfg).mean(axis=0))))
    assert peaks == sorted(peaks) and len(set(peaks)) == 3


def _normal_tangential_accel() -> SpectralConfig:
    return dataclasses.replace(FeatureConfig().accel, channel_groups=ACCEL_NORMAL_TANGENTIAL)


def test_accel_normal_tangential_keeps_each_direction_in_its_own_half():
    cfg = _normal_tangential_accel()
    assert cfg.n_channels == 2 * FeatureConfig().accel.n_channels == 32
    t = np.arange(1000) / 500.0
    rng = np.random.default_rng(3)
    floor = 1e-4 * rng.normal(size=(1000, 3))
    tone = np.sin(2 * np.pi * 60.0 * t)
    along_normal = spectral_features(Stream((floor + tone[:, None] * [0, 0, 1]).astype(np.float32), 500.0), cfg)
    along_x = spectral_features(Stream((floor + tone[:, None] * [1, 0, 0]).astype(np.float32), 500.0), cfg)
    assert along_normal.shape[1] == 32
    # the 60 Hz vibration raises the normal half's peak band far above the in-plane half's, and the other way
    assert along_normal[:, :16].max() - along_normal[:, 16:].max() > 10.0
    assert along_x[:, 16:].max() - along_x[:, :16].max() > 10.0
    # each half is the plain front end of its own channels; the default sums all three
    stream = Stream(rng.normal(size=(1000, 3)).astype(np.float32), 500.0, t0_s=0.01)
    split = spectral_features(stream, cfg)
    plain = FeatureConfig().accel
    assert np.array_equal(split[:, :16], spectral_features(Stream(stream.data[:, 2:], 500.0, 0.01), plain))
    assert np.array_equal(split[:, 16:], spectral_features(Stream(stream.data[:, :2], 500.0, 0.01), plain))
    assert spectral_features(stream, plain).shape[1] == 16


def test_accel_normal_tangential_does_not_depend_on_the_slide_direction():
    # rotating the vibration within the pad's plane (another slide direction) leaves the features as they were
    cfg = _normal_tangential_accel()
    rng = np.random.default_rng(4)
    x = rng.normal(size=(800, 3))
    angle = 0.7
    rotation = np.array([[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0.0, 0.0, 1.0]])
    a = spectral_features(Stream(x.astype(np.float32), 500.0), cfg)
    b = spectral_features(Stream((x @ rotation.T).astype(np.float32), 500.0), cfg)
    assert np.allclose(a, b, atol=1e-4)


def test_channel_groups_are_validated_and_need_the_stream_s_channels():
    for bad in (((),), ((0, 0),), ((-1,),), ((0,), (1.5,))):
        with pytest.raises(ValueError, match="channel_groups must be non-empty groups"):
            dataclasses.replace(FeatureConfig().accel, channel_groups=bad)
    one_axis = Stream(np.zeros((500, 1), np.float32), 500.0)  # e.g. a DFT321-combined accelerometer (LMT)
    with pytest.raises(ValueError, match=r"need 3 channels; the stream has 1"):
        spectral_features(one_axis, _normal_tangential_accel())


def test_taxel_features_mean_and_std():
    rng = np.random.default_rng(2)
    x = (2.0 + 0.5 * rng.normal(size=(400, 16))).astype(np.float32)
    feats = taxel_features(Stream(x, 100.0), FeatureConfig().normal)
    assert feats.shape[1] == 32
    assert np.allclose(feats[:, :16].mean(), 2.0, atol=0.05)
    assert np.allclose(feats[:, 16:].mean(), 0.5, atol=0.05)


def test_short_streams_give_one_frame():
    cfg = FeatureConfig()
    rec = StrokeRecord(streams={
        "sound": Stream(np.ones((100, 1), np.float32), 44_100.0),
        "normal": Stream(np.ones((3, 16), np.float32), 100.0),
        "friction": Stream(np.ones((1, 32), np.float32), 100.0),
        "accel": Stream(np.ones((5, 3), np.float32), 500.0)}, category="c", instance="i", combustible=False)
    feats = featurize(rec, cfg)
    for key in MODALITIES:
        assert feats[key].shape[0] == 1 and np.all(np.isfinite(feats[key]))


def test_missing_stream_is_none_and_collate_masks():
    cfg = FeatureConfig()
    dims = feature_dims(cfg)
    recs = make_synthetic_strokes(2, seed=3)
    recs[0] = dataclasses.replace(recs[0], streams={**recs[0].streams, "accel": None})
    feats = [featurize(r, cfg) for r in recs]
    assert feats[0]["accel"] is None
    batch = collate(feats, dims, labels=[0, 1, 2, 0, 1, 2])
    assert batch.batch_size == 6 and batch.labels.tolist() == [0, 1, 2, 0, 1, 2]
    for key in MODALITIES:
        b, t_max, c = batch.x[key].shape
        assert (b, c) == (6, dims[key]) and batch.padding[key].shape == (6, t_max)
        for i, f in enumerate(feats):
            n = 0 if f[key] is None else f[key].shape[0]
            assert batch.present[key][i].item() == (f[key] is not None)
            assert not batch.padding[key][i, :n].any() and batch.padding[key][i, n:].all()
            assert torch.all(batch.x[key][i, n:] == 0)
            if n:
                assert torch.equal(batch.x[key][i, :n], torch.from_numpy(f[key]))
    assert batch.present_matrix().shape == (6, 4)


def test_modality_missing_from_whole_batch():
    cfg = FeatureConfig()
    recs = make_synthetic_strokes(1, seed=4, n_classes=2)
    recs = [dataclasses.replace(r, streams={**r.streams, "sound": None}) for r in recs]
    batch = collate([featurize(r, cfg) for r in recs], feature_dims(cfg))
    assert batch.x["sound"].shape == (2, 1, 24)
    assert batch.padding["sound"].all() and not batch.present["sound"].any()


def test_norm_stats_fit_on_training_only_and_serialise():
    cfg = FeatureConfig()
    dims = feature_dims(cfg)
    train = [featurize(r, cfg) for r in make_synthetic_strokes(3, seed=5, p_missing=0.3)]
    stats = fit_norm_stats(train, dims)
    for key in MODALITIES:
        assert len(stats.mean[key]) == dims[key] and min(stats.std[key]) > 0
        frames = np.concatenate([normalize(f, stats)[key] for f in train if f[key] is not None])
        assert np.allclose(frames.mean(axis=0), 0.0, atol=1e-3)
        assert np.allclose(frames.std(axis=0)[np.asarray(stats.std[key]) > 1e-5], 1.0, atol=1e-3)
    again = NormStats.from_dict(json.loads(json.dumps(stats.to_dict())))
    assert again == stats
    # collate applies the statistics and keeps padding at exactly 0
    batch = collate(train[:2], dims, stats=stats)
    assert torch.all(batch.x["sound"][batch.padding["sound"]] == 0)


def test_norm_stats_for_never_seen_modality():
    cfg = FeatureConfig()
    dims = feature_dims(cfg)
    recs = [dataclasses.replace(r, streams={**r.streams, "friction": None})
            for r in make_synthetic_strokes(1, seed=6)]
    stats = fit_norm_stats([featurize(r, cfg) for r in recs], dims)
    assert stats.mean["friction"] == (0.0,) * dims["friction"]
    assert stats.std["friction"] == (1.0,) * dims["friction"]


def test_collate_rejects_wrong_channels():
    cfg = FeatureConfig()
    bad = {"sound": np.zeros((4, 7), np.float32), "normal": None, "friction": None, "accel": None}
    with pytest.raises(ValueError, match="sound"):
        collate([bad], feature_dims(cfg))


def test_synthetic_strokes_are_valid_records():
    recs = make_synthetic_strokes(2, seed=7, p_missing=0.5)
    assert len(recs) == 6
    for r in recs:
        assert len(r.present) >= 1
        for key in r.present:
            assert r.streams[key].data.shape[1] == NUM_CHANNELS[key]
