"""The sensor-timing positive control (perception.timing_control): strokes whose class is only in when the
friction's event comes against the sound's, and the run over models and seeds. What the models learn of it is
``robotdemo bench timing``'s (minutes per model); ``tests/test_touchformer.py`` tests the time bias itself."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from perception.features import FeatureConfig, feature_dims, frame_clock_s
from perception.streams import MODALITIES
from perception.timing_control import EVENT_CHANNELS, TimingControlConfig, run_timing_control, timing_strokes

torch.set_num_threads(2)


def _event_time_s(x: np.ndarray, modality: str) -> float:
    """Centre time of the frame where a stroke's event peaks."""
    hop_s, first_s = dict(zip(MODALITIES, frame_clock_s(FeatureConfig())))[modality]
    return first_s + hop_s * int(np.argmax(x[:, :EVENT_CHANNELS].mean(axis=1)))


def test_strokes_have_the_front_ends_layout_and_the_class_only_in_the_relative_timing():
    config = TimingControlConfig(event_amplitude=6.0)  # peaks well above the noise, to read them back
    strokes, labels = timing_strokes(400, seed=3, config=config)
    dims = feature_dims(FeatureConfig())
    assert labels.sum() == 200
    clock = dict(zip(MODALITIES, frame_clock_s(FeatureConfig())))
    for stroke in strokes[:20]:
        assert all(stroke[m].shape[1] == dims[m] and stroke[m].dtype == np.float32 for m in MODALITIES)
        # one duration per stroke, different frame rates: the frame counts follow the hops
        durations = [clock[m][1] * 2 + clock[m][0] * (len(stroke[m]) - 1) for m in MODALITIES]
        assert max(durations) - min(durations) <= max(c[0] for c in clock.values()) + 1e-9
    gaps = np.array([abs(_event_time_s(s["friction"], "friction") - _event_time_s(s["sound"], "sound"))
                     for s in strokes])
    assert np.all(gaps[labels == 0] <= 0.1)  # the same instant, to a frame
    assert np.all(gaps[labels == 1] >= 0.3)  # at least 0.3 x 0.8 x 1.8 s apart, wrapped or not
    # each sensor alone: its event's time is spread alike in both classes
    for m in ("sound", "friction"):
        times = np.array([_event_time_s(s[m], m) for s in strokes])
        assert abs(np.median(times[labels == 0]) - np.median(times[labels == 1])) < 0.25


def test_run_reports_every_model_and_seed_and_the_config_is_validated():
    config = TimingControlConfig(n_train=16, n_test=8, epochs=2, seeds=(0, 1),
                                 models=(("lstm", "lstm", ()), ("tf", "touchformer", (("time_bias", True),))),
                                 model_overrides=(("d_model", 16), ("n_heads", 2), ("hidden", 8)))
    result = json.loads(json.dumps(run_timing_control(config)))
    assert set(result["models"]) == {"lstm", "tf"} and result["chance"] == 0.5
    for row in result["models"].values():
        assert len(row["test_accuracy"]) == 2 and 0.0 <= row["test_accuracy_mean"] <= 1.0
    with pytest.raises(ValueError, match="offset_share"):
        TimingControlConfig(offset_share=(0.5, 1.2))
    with pytest.raises(ValueError, match="n_train"):
        TimingControlConfig(n_train=1)
