"""The logistic-regression reference classifier (perception.reference_classifier)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from perception.reference_classifier import (ReferenceClassifier, ReferenceConfig, stream_statistics,
                                             summary_features)
from perception.streams import MODALITIES, Stream
from tests.test_features import make_synthetic_strokes


def test_summary_features_shape_and_missing_fill():
    rec = make_synthetic_strokes(1, seed=40)[0]
    full = summary_features(rec, n_bands=8)
    per_stream = 5 + 8 + 1
    assert full.shape == (4 * per_stream,) and np.all(np.isfinite(full))
    assert np.all(full[per_stream - 1::per_stream] == 1.0)  # indicators
    missing = summary_features(dataclasses.replace(rec, streams={**rec.streams, "normal": None}), n_bands=8)
    j = MODALITIES.index("normal")
    assert np.all(missing[j * per_stream:(j + 1) * per_stream] == 0.0)
    assert np.all(np.isfinite(missing))


def test_spectral_centroid_follows_frequency():
    t = np.arange(4410) / 44_100.0
    low = stream_statistics(Stream(np.sin(2 * np.pi * 300 * t)[:, None].astype(np.float32), 44_100.0), 8)
    high = stream_statistics(Stream(np.sin(2 * np.pi * 5000 * t)[:, None].astype(np.float32), 44_100.0), 8)
    assert high[4] > low[4]  # centroid / Nyquist


def test_constant_and_single_sample_streams_are_finite():
    for data in (np.ones((50, 16), np.float32), np.ones((1, 16), np.float32)):
        assert np.all(np.isfinite(stream_statistics(Stream(data, 100.0), 8)))


def test_beats_chance_on_held_out():
    train = make_synthetic_strokes(15, seed=41, p_missing=0.2)
    test = make_synthetic_strokes(8, seed=42, p_missing=0.2)
    clf = ReferenceClassifier().fit(train)
    assert clf.classes == ("class0", "class1", "class2")
    assert clf.score(test) >= 0.8  # chance is 1/3
    pred = clf.predict(test)
    assert len(pred) == len(test) and set(pred) <= set(clf.classes)
    proba = clf.predict_proba(test)
    assert proba.shape == (len(test), 3) and np.allclose(proba.sum(axis=1), 1.0)


def test_explicit_labels_and_instance_label():
    train = make_synthetic_strokes(6, seed=43)
    combust = ["yes" if r.combustible else "no" for r in train]
    clf = ReferenceClassifier().fit(train, combust)
    assert set(clf.classes) == {"yes", "no"}
    assert clf.score(train, combust) >= 0.8
    inst = ReferenceClassifier(ReferenceConfig(label="instance")).fit(train)
    assert inst.classes == ("class0_inst", "class1_inst", "class2_inst")
    with pytest.raises(ValueError, match="labels"):
        clf.fit(train, combust[:3])
    with pytest.raises(ValueError, match="label"):
        ReferenceConfig(label="colour")


def test_honesty_check_flags_an_emulation_that_is_too_easy():
    from perception.reference_classifier import honesty_check
    from tests.test_dataset import make_material_strokes

    easy = honesty_check(make_material_strokes(0, noise=0.05, n_strokes=4), seed=0)
    assert easy["category_accuracy"] > 0.9 and easy["too_easy"]
    hard = honesty_check(make_material_strokes(0, noise=50.0, n_strokes=4), seed=0)
    assert hard["category_accuracy"] < easy["category_accuracy"] and not hard["too_easy"]
    assert set(easy) >= {"n_train", "n_test", "category_accuracy", "instance_accuracy"}


def test_stream_accuracies_find_the_stream_that_carries_the_category():
    """Each stream's own classifier: a stream shuffled across strokes (it carries no category) scores near
    chance while the intact streams of the same strokes score high; honesty_check reports them."""
    from perception.reference_classifier import honesty_check, stream_accuracies
    from tests.test_dataset import make_material_strokes

    records = make_material_strokes(0, noise=0.05, n_strokes=6)  # 3 categories, 108 strokes
    rng = np.random.default_rng(3)
    donors = rng.permutation(len(records))
    shuffled = [dataclasses.replace(r, streams={**r.streams, "sound": records[d].streams["sound"]})
                for r, d in zip(records, donors)]
    train, test = shuffled[0::2], shuffled[1::2]
    acc = stream_accuracies(train, test)
    assert set(acc) == set(MODALITIES)
    assert acc["sound"] < 0.6  # chance is 1/3
    assert min(acc["normal"], acc["friction"], acc["accel"]) > 0.9
    report = honesty_check(shuffled, seed=0)
    assert set(report["category_accuracy_by_stream"]) == set(MODALITIES)
    assert report["category_accuracy_by_stream"]["sound"] < report["category_accuracy"]
