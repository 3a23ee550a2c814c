"""How much of the material the strokes keep (perception.parameter_probe): the oracle and the recovery."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from perception.materials import MaterialSample
from perception.parameter_probe import (PARAMETER_FIELDS, STROKE_FIELDS, ParameterProbeConfig, between_share,
                                        log_parameters, log_stroke_parameters, object_groups, read_back_parameters,
                                        recovery_r2, run_parameter_probe)
from perception.pooled_statistics import PooledStatisticsConfig, stroke_matrices
from perception.train import TrainConfig, task_split
from robotdemo.cli import main
from tests.test_dataset import make_material_strokes

SPLITS = PooledStatisticsConfig(ssmc_seeds=(0,), usmc_folds=(0,), fine_seeds=(), classifiers=("logreg",))


def toy_strokes_and_samples(seed: int) -> tuple[list, list[MaterialSample]]:
    """Toy strokes (3 categories x 3 instances x 4 objects x 3 strokes) and one material per object: its density
    is the object's mean taxel force (which the strokes carry), its roughness an independent draw (which they do
    not), the rest independent draws too. Each stroke's commanded force is its own taxel force; its speed and
    length are drawn apart from it."""
    rng = np.random.default_rng(seed)
    records = make_material_strokes(seed, noise=0.2, n_objects=4, n_strokes=3)
    level = {}
    for r in records:
        level.setdefault(r.meta["object_id"], []).append(float(r.streams["normal"].data.sum(axis=1).mean()))
    samples_by_object = {}
    for obj, levels in sorted(level.items()):
        draws = np.exp(0.3 * rng.standard_normal(len(PARAMETER_FIELDS)))
        values = dict(zip(PARAMETER_FIELDS, draws))
        values["density_kg_m3"] = 100.0 * float(np.mean(levels))
        values["friction_static"] = values["friction_kinetic"] * 1.2
        samples_by_object[obj] = values
    out_records, samples = [], []
    for r in records:
        meta = {**r.meta, "target_force_n": float(r.streams["normal"].data.sum(axis=1).mean()),
                "speed_mps": float(rng.uniform(0.01, 0.05)), "length_m": float(rng.uniform(0.02, 0.06))}
        out_records.append(dataclasses.replace(r, meta=meta))
        samples.append(MaterialSample(instance=r.instance, category=r.category, combustible=r.combustible,
                                      **samples_by_object[r.meta["object_id"]]))
    return out_records, samples


@pytest.fixture(scope="module")
def probed():
    records, samples = toy_strokes_and_samples(0)
    return records, samples, run_parameter_probe(records, samples, ParameterProbeConfig(splits=SPLITS,
                                                                                        regressors=("ridge",)))


def test_recovery_reads_back_what_the_strokes_carry_and_not_what_they_do_not(probed):
    records, samples, result = probed
    recovery = result["recovery"]
    assert list(recovery) == list(PARAMETER_FIELDS + STROKE_FIELDS) and result["n_objects"] == 36
    assert result["feature_config"]["accel"]["channel_groups"] == ()  # the front end the statistics pooled, named
    assert recovery["density_kg_m3"]["r2"]["ridge"] > 0.8, recovery["density_kg_m3"]
    assert recovery["target_force_n"]["r2"]["ridge"] > 0.8, recovery["target_force_n"]
    for field in ("roughness_rms_m", "loss_factor", "speed_mps"):  # independent of every stream
        assert recovery[field]["r2"]["ridge"] < 0.2, (field, recovery[field])
    # the trees on the same folds (two columns, to keep the test short): density read, roughness not
    columns = [PARAMETER_FIELDS.index("density_kg_m3"), PARAMETER_FIELDS.index("roughness_rms_m")]
    trees = recovery_r2(stroke_matrices(records)["both"], log_parameters(samples)[:, columns], object_groups(records),
                        "trees")
    assert trees[0] > 0.8 and trees[1] < 0.2, trees
    # density is set by the category (taxel force level): nearly all its variance lies between instances
    assert recovery["density_kg_m3"]["between_instance_share"] > 0.9
    assert recovery["roughness_rms_m"]["between_instance_share"] < 0.5


def test_oracle_classifies_from_the_parameters_on_the_networks_splits_and_leaves_test_unread(probed):
    records, samples, result = probed
    oracle = result["oracle"]
    assert not oracle["read_test"]
    assert all("test_accuracy_pct" not in r for r in oracle["runs"])
    # density alone separates the three toy categories (chance 33 %)
    assert oracle["means"]["ssmc"]["parameters"]["logreg"]["val_accuracy_pct"] >= 80.0
    # through the physics as read back from the strokes: density is read (R^2 > 0.8 above), so the category too
    assert {r["features"] for r in oracle["runs"]} == {"parameters", "read_back"}
    assert oracle["means"]["ssmc"]["read_back"]["logreg"]["val_accuracy_pct"] >= 70.0
    read = run_parameter_probe(records, samples, ParameterProbeConfig(
        splits=dataclasses.replace(SPLITS, usmc_folds=(), read_test=True), regressors=("ridge",)))
    assert all(r["test_accuracy_pct"] >= 80.0 for r in read["oracle"]["runs"])
    assert list(read["recovery"]["density_kg_m3"]["r2"]) == ["ridge"]


def test_read_back_never_sees_the_parameters_of_a_row_outside_training():
    records, samples = toy_strokes_and_samples(0)
    features, params, groups = stroke_matrices(records)["both"], log_parameters(samples), object_groups(records)
    train_idx, val_idx, test_idx = task_split(records, TrainConfig(task="usmc", seed=0), 0)
    read = read_back_parameters(features, params, groups, train_idx)
    scrambled = params.copy()
    scrambled[np.concatenate([val_idx, test_idx])] = np.random.default_rng(0).normal(size=(len(val_idx) + len(test_idx),
                                                                                        params.shape[1]))
    np.testing.assert_array_equal(read_back_parameters(features, scrambled, groups, train_idx), read)
    density = PARAMETER_FIELDS.index("density_kg_m3")
    assert np.corrcoef(read[test_idx, density], params[test_idx, density])[0, 1] > 0.9  # unseen instances


def test_oracle_is_at_chance_when_the_parameters_carry_no_category():
    records, samples = toy_strokes_and_samples(1)
    rng = np.random.default_rng(3)
    noise = [dataclasses.replace(s, density_kg_m3=float(np.exp(rng.standard_normal()))) for s in samples]
    result = run_parameter_probe(records, noise, ParameterProbeConfig(
        splits=dataclasses.replace(SPLITS, ssmc_seeds=(0, 1, 2), usmc_folds=()), regressors=("ridge",)))
    assert result["oracle"]["means"]["ssmc"]["parameters"]["logreg"]["val_accuracy_pct"] < 55.0  # chance 33 %


def test_log_parameters_and_groups():
    records, samples = toy_strokes_and_samples(2)
    logs = log_parameters(samples[:2])
    assert logs.shape == (2, len(PARAMETER_FIELDS))
    assert logs[0, PARAMETER_FIELDS.index("density_kg_m3")] == pytest.approx(math.log(samples[0].density_kg_m3))
    np.testing.assert_allclose(log_stroke_parameters(records[:1])[0],
                               [math.log(records[0].meta[f]) for f in STROKE_FIELDS])
    groups = object_groups(records)
    same = [r.meta["object_id"] == records[0].meta["object_id"] for r in records]
    np.testing.assert_array_equal(groups == groups[0], same)


def test_between_share_is_the_anova_r2():
    assert between_share(np.array([1.0, 1.0, 3.0, 3.0]), ["a", "a", "b", "b"]) == pytest.approx(1.0)
    assert between_share(np.array([0.0, 2.0, 0.0, 2.0]), ["a", "a", "b", "b"]) == pytest.approx(0.0)
    # group means 1 and 2 about a grand mean of 1.5: total SS 2, within-group SS 4 x 0.25 = 1
    assert between_share(np.array([0.5, 1.5, 1.5, 2.5]), ["a", "a", "b", "b"]) == pytest.approx(1.0 / 2.0)


def test_bad_input_is_named():
    records, samples = toy_strokes_and_samples(2)
    with pytest.raises(ValueError, match="one per stroke"):
        run_parameter_probe(records, samples[:-1])
    swapped = next(i for i, s in enumerate(samples) if s.instance != samples[0].instance)
    with pytest.raises(ValueError, match="but its material sample of"):
        run_parameter_probe(records, [samples[swapped]] + samples[1:])
    with pytest.raises(ValueError, match="no positive target_force_n"):
        log_stroke_parameters([dataclasses.replace(records[0], meta={"object_id": "x"})])
    with pytest.raises(ValueError, match="names no object"):
        object_groups([dataclasses.replace(records[0], meta={})])
    with pytest.raises(ValueError, match="cannot fill 5 folds"):
        recovery_r2(np.zeros((4, 2)), np.zeros((4, 1)), np.array([0, 0, 1, 1]), "ridge")
    with pytest.raises(ValueError, match="recovery_folds must be >= 2"):
        ParameterProbeConfig(recovery_folds=1)
    with pytest.raises(ValueError, match="regressors must be among"):
        ParameterProbeConfig(regressors=("svr",))


def test_cli_without_data_is_one_line(capsys):
    assert main(["bench", "parameters"]) != 0
    err = capsys.readouterr().err.strip()
    assert "bench parameters needs --data DIR" in err and len(err.splitlines()) == 1


def test_plot_is_a_png_and_the_cli_refuses_a_folder_as_its_file(probed, tmp_path, capsys):
    from perception.parameter_probe import plot_parameter_probe

    path = plot_parameter_probe(tmp_path / "new" / "probe.png", probed[2])
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and path.stat().st_size > 10_000
    assert main(["bench", "parameters", "--data", str(tmp_path / "nowhere"), "--plot", str(tmp_path)]) != 0
    err = capsys.readouterr().err.strip()
    assert "--plot" in err and "is a folder" in err and len(err.splitlines()) == 1
