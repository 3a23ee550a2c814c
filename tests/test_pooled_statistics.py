"""Classifiers with no temporal model on the networks' own splits (perception.pooled_statistics)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from perception.dataset import write_dataset
from perception.pooled_statistics import (PooledStatisticsConfig, pooled_frame_statistics, run_pooled_statistics,
                                          stroke_matrices)
from perception.streams import MODALITIES
from perception.train import TrainConfig, task_split
from robotdemo.cli import main
from tests.test_dataset import make_material_strokes

DIMS = {"sound": 2, "normal": 3, "friction": 1, "accel": 2}


def test_pooled_frame_statistics_are_mean_std_max_per_channel_and_zero_for_a_missing_stream():
    frames = {"sound": np.array([[0.0, 1.0], [2.0, 5.0]], np.float32), "normal": None,
              "friction": np.array([[4.0], [4.0], [1.0]], np.float32), "accel": np.zeros((0, 2), np.float32)}
    row = pooled_frame_statistics(frames, DIMS)
    assert row.shape == (sum(3 * c + 1 for c in DIMS.values()),)
    sound, normal, friction, accel = np.split(row, np.cumsum([3 * DIMS[m] + 1 for m in MODALITIES])[:-1])
    np.testing.assert_allclose(sound, [1.0, 3.0, 1.0, 2.0, 2.0, 5.0, 1.0])  # means, stds, maxima, present
    np.testing.assert_allclose(friction, [3.0, np.std([4.0, 4.0, 1.0]), 4.0, 1.0])
    assert not normal.any() and not accel.any()  # missing and empty streams: all 0, indicator 0


def test_stroke_matrices_put_the_reference_statistics_beside_the_pooled_frames():
    records = make_material_strokes(5, n_categories=2, n_instances=2, n_objects=1, n_strokes=2, duration_s=0.2)
    records[0] = dataclasses.replace(records[0], streams={**records[0].streams, "normal": None})
    m = stroke_matrices(records)
    assert m["reference"].shape[0] == m["pooled"].shape[0] == len(records)
    np.testing.assert_array_equal(m["both"], np.concatenate([m["reference"], m["pooled"]], axis=1))
    assert np.all(np.isfinite(m["both"]))


def test_statistics_classifiers_beat_chance_on_validation_of_the_networks_splits_and_leave_test_unread():
    """Three toy categories whose streams carry the category: every classifier scores well above chance (1/3)
    on each split's validation part, the same parts `robotdemo train` carves, and no test figure is made
    unless asked for."""
    records = make_material_strokes(0, noise=0.2, n_strokes=4)  # 3 categories x 3 instances x 2 objects x 4
    config = PooledStatisticsConfig(ssmc_seeds=(0,), usmc_folds=(0, 1), fine_seeds=())
    result = run_pooled_statistics(records, config)
    assert len(result["runs"]) == 3 * 3 * 2 and not result["read_test"]
    _, val_idx, _ = task_split(records, TrainConfig(task="ssmc", seed=0))
    for run in result["runs"]:
        assert "test_accuracy_pct" not in run
        assert run["val_accuracy_pct"] >= 70.0, run
        if run["task"] == "ssmc":
            assert run["n_val"] == len(val_idx)
    usmc = [r["val_accuracy_pct"] for r in result["runs"]
            if (r["task"], r["features"], r["classifier"]) == ("usmc", "both", "trees")]
    assert result["means"]["usmc"]["both"]["trees"]["val_accuracy_pct"] == pytest.approx(np.mean(usmc), abs=0.01)

    read = run_pooled_statistics(records, dataclasses.replace(config, usmc_folds=(), read_test=True))
    assert all(r["test_accuracy_pct"] >= 70.0 and r["n_test"] > 0 for r in read["runs"])
    same = [r for r in result["runs"] if r["task"] == "ssmc"]
    assert [r["val_accuracy_pct"] for r in read["runs"]] == [r["val_accuracy_pct"] for r in same]  # seeded


def test_statistics_classifiers_fall_to_chance_when_the_labels_carry_nothing():
    """The same strokes with their categories shuffled across strokes: no classifier may find a category."""
    records = make_material_strokes(1, noise=0.2, n_strokes=4)
    labels = np.random.default_rng(7).permutation([r.category for r in records])
    shuffled = [dataclasses.replace(r, category=str(c)) for r, c in zip(records, labels)]
    result = run_pooled_statistics(shuffled, PooledStatisticsConfig(ssmc_seeds=(0, 1), usmc_folds=(), fine_seeds=()))
    mean = np.mean([r["val_accuracy_pct"] for r in result["runs"]])
    assert mean < 55.0  # chance is 33 %; the toy categories themselves score >= 70 above


def test_config_refuses_unknown_names_and_an_empty_run():
    with pytest.raises(ValueError, match="feature_sets must be among"):
        PooledStatisticsConfig(feature_sets=("spectra",))
    with pytest.raises(ValueError, match="classifiers must be among"):
        PooledStatisticsConfig(classifiers=("svm",))
    with pytest.raises(ValueError, match="no split to run"):
        PooledStatisticsConfig(ssmc_seeds=(), usmc_folds=(), fine_seeds=())


def test_bench_statistics_needs_data_and_writes_json(tmp_path, capsys):
    code = main(["bench", "statistics"])
    err = capsys.readouterr().err
    assert code == 2 and "bench statistics needs --data DIR" in err and len(err.strip().splitlines()) == 1
    records = make_material_strokes(2, n_categories=2, n_instances=3, n_objects=1, n_strokes=3, duration_s=0.2)
    write_dataset(tmp_path / "ds", records, env="clean", seed=2)
    assert main(["bench", "statistics", "--data", str(tmp_path / "ds"), "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["data"] == str(tmp_path / "ds") and not result["read_test"]
    assert {r["task"] for r in result["runs"]} == {"ssmc", "usmc", "fine"}
    assert set(result["means"]["ssmc"]) == {"reference", "pooled", "both"}
    assert result["feature_config"]["accel"]["channel_groups"] == []  # the evaluation's front end, said in the JSON
    assert main(["bench", "statistics", "--data", str(tmp_path / "ds"), "--accel-axes", "normal-tangential",
                 "--json"]) == 0
    split = json.loads(capsys.readouterr().out)
    assert split["feature_config"]["accel"]["channel_groups"] == [[2], [0, 1]]


def test_stroke_matrices_pool_the_front_end_they_are_given():
    from perception.features import ACCEL_NORMAL_TANGENTIAL, FeatureConfig, feature_dims, featurize

    records = make_material_strokes(5, n_categories=2, n_instances=2, n_objects=1, n_strokes=2, duration_s=0.2)
    plain = FeatureConfig()
    split = dataclasses.replace(plain, accel=dataclasses.replace(plain.accel, channel_groups=ACCEL_NORMAL_TANGENTIAL))
    m_plain, m_split = stroke_matrices(records, plain)["pooled"], stroke_matrices(records, split)["pooled"]
    assert m_split.shape[1] - m_plain.shape[1] == 3 * 16  # mean, std and max of 16 more accelerometer bands
    np.testing.assert_array_equal(m_split[1], pooled_frame_statistics(featurize(records[1], split), feature_dims(split)))
