"""How much of an object's material the strokes keep (`robotdemo bench parameters`).

A diagnostic for the evaluation's "find out why", one step behind :mod:`perception.pooled_statistics`. Each
recorded object has its own physical parameters, drawn around its catalogue instance
(:class:`perception.materials.MaterialSample`); the sensor emulation reads nothing else of the material. Two
questions, each answered on the strokes of a data set and those parameters (which the caller supplies: the
strokes do not store them, and drawing them again needs the recorder, ``robotdemo.dataset.drawn_material``):

- **Oracle**: how well does a classifier do that is given the exact parameters (their logs,
  :data:`PARAMETER_FIELDS`) instead of the strokes? It is fitted and scored on the very splits the networks use
  (:func:`perception.pooled_statistics.splits_of`, :func:`perception.train.task_split`). Far above the
  networks, the catalogue's spreads leave the category in the material and what binds is what the sensors keep
  of it; near them, the spreads bind. Beside it the same classifiers on the parameters as read back from the
  strokes (:func:`read_back_parameters`): the category as far as it passes through the physics the strokes keep.
- **Recovery**: how much of each log parameter can be read back from a stroke? Each is regressed on the stroke's
  pooled front-end and reference statistics (the ``"both"`` set of :func:`perception.pooled_statistics.stroke_matrices`)
  and scored as out-of-fold R^2, the folds holding out whole objects (sklearn's ``GroupKFold``), by a
  standardised ridge regression and by gradient-boosted trees. The stroke's own commanded force, speed and
  length are regressed the same way, as a check that the probe can read what the strokes do hold. Beside each,
  the share of its variance that lies between the catalogue instances (the rest is the spread of objects, or
  strokes, within an instance).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
from sklearn.ensemble import HistGradientBoostingRegressor
from sklearn.linear_model import RidgeCV
from sklearn.metrics import r2_score
from sklearn.model_selection import GroupKFold
from sklearn.pipeline import make_pipeline
from sklearn.preprocessing import StandardScaler
from tqdm import tqdm

from perception.materials import MaterialSample
from perception.pooled_statistics import PooledStatisticsConfig, means_of, score_split, splits_of, stroke_matrices
from perception.streams import StrokeRecord

PARAMETER_FIELDS: tuple[str, ...] = (
    "density_kg_m3", "youngs_modulus_pa", "friction_static", "friction_kinetic", "roughness_rms_m",
    "correlation_length_m", "hurst_exponent", "loss_factor", "speed_of_sound_mps", "restitution")
"""The physical fields of a :class:`perception.materials.MaterialSample`, the only ones the emulation reads."""

STROKE_FIELDS: tuple[str, ...] = ("target_force_n", "speed_mps", "length_m")
"""The stroke's commanded parameters in its meta: the recovery's positive controls."""

REGRESSORS: tuple[str, ...] = ("ridge", "trees")


@dataclass(frozen=True)
class ParameterProbeConfig:
    """What to run.

    Attributes:
        splits: the oracle's splits and classifiers (seeds, folds, classifiers, ``read_test``) and the front end
            whose frames are pooled (``features``), as for ``robotdemo bench statistics``; its ``feature_sets`` is
            not read.
        recovery_folds: folds of the recovery's ``GroupKFold`` over objects.
        regressors: among :data:`REGRESSORS`.
    """

    splits: PooledStatisticsConfig = PooledStatisticsConfig()
    recovery_folds: int = 5
    regressors: tuple[str, ...] = REGRESSORS

    def __post_init__(self) -> None:
        if self.recovery_folds < 2:
            raise ValueError(f"recovery_folds must be >= 2, got {self.recovery_folds}")
        if not self.regressors or any(r not in REGRESSORS for r in self.regressors):
            raise ValueError(f"regressors must be among {REGRESSORS}, got {self.regressors}")


def log_parameters(samples: Sequence[MaterialSample]) -> np.ndarray:
    """(N, len(:data:`PARAMETER_FIELDS`)) natural logs of each sample's physical parameters (all positive)."""
    return np.array([[math.log(getattr(s, name)) for name in PARAMETER_FIELDS] for s in samples], dtype=np.float64)


def log_stroke_parameters(records: Sequence[StrokeRecord]) -> np.ndarray:
    """(N, len(:data:`STROKE_FIELDS`)) natural logs of each stroke's commanded parameters, from its meta.

    Raises:
        ValueError: a stroke lacks one of them or it is not positive.
    """
    rows = []
    for i, record in enumerate(records):
        values = [record.meta.get(name) for name in STROKE_FIELDS]
        if any(not isinstance(v, (int, float)) or not v > 0 for v in values):
            raise ValueError(f"stroke {i} ({record.instance!r}) has no positive {', '.join(STROKE_FIELDS)} in its "
                             f"meta: {dict(zip(STROKE_FIELDS, values))}")
        rows.append([math.log(float(v)) for v in values])
    return np.array(rows, dtype=np.float64)


def object_groups(records: Sequence[StrokeRecord]) -> np.ndarray:
    """One integer per stroke naming its physical object (meta ``object_id``, else ``surface_seed``).

    Raises:
        ValueError: a stroke names neither.
    """
    names = []
    for i, record in enumerate(records):
        name = record.meta.get("object_id", record.meta.get("surface_seed"))
        if name is None:
            raise ValueError(f"stroke {i} ({record.instance!r}) names no object (no object_id or surface_seed)")
        names.append(f"{record.instance}/{name}")
    _, groups = np.unique(np.array(names), return_inverse=True)
    return groups


def between_share(values: np.ndarray, labels: Sequence[str]) -> float:
    """The share of ``values``' variance that lies between the groups ``labels`` (one-way ANOVA's R^2)."""
    values = np.asarray(values, dtype=np.float64)
    total = float(np.sum((values - values.mean()) ** 2))
    if total == 0.0:
        return 0.0
    labels = np.asarray(labels)
    within = sum(float(np.sum((values[labels == g] - values[labels == g].mean()) ** 2)) for g in np.unique(labels))
    return 1.0 - within / total


def _regressor(name: str, seed: int):
    if name == "ridge":
        return make_pipeline(StandardScaler(), RidgeCV(alphas=np.logspace(-2, 4, 13)))
    if name == "trees":
        return HistGradientBoostingRegressor(random_state=seed)
    raise ValueError(f"unknown regressor {name!r}; expected one of {REGRESSORS}")


def recovery_r2(features: np.ndarray, targets: np.ndarray, groups: np.ndarray, regressor: str, folds: int = 5,
                seed: int = 0) -> np.ndarray:
    """Out-of-fold R^2 of each target column regressed on ``features``, the folds holding out whole ``groups``.

    Returns:
        (targets.shape[1],) R^2 (1 perfect, 0 no better than the mean, below 0 worse).
    """
    if features.shape[0] != targets.shape[0] or groups.shape[0] != targets.shape[0]:
        raise ValueError(f"{features.shape[0]} feature rows, {targets.shape[0]} target rows and {groups.shape[0]} "
                         "groups: one of each per stroke")
    if len(np.unique(groups)) < folds:
        raise ValueError(f"{len(np.unique(groups))} objects cannot fill {folds} folds")
    predicted = _predicted_out_of_fold(features, targets, groups, regressor, folds, seed)
    return np.array([r2_score(targets[:, j], predicted[:, j]) for j in range(targets.shape[1])])


def _predicted_out_of_fold(features: np.ndarray, targets: np.ndarray, groups: np.ndarray, regressor: str, folds: int,
                           seed: int = 0) -> np.ndarray:
    predicted = np.zeros_like(targets)
    for train, held in GroupKFold(n_splits=folds).split(features, groups=groups):
        for j in range(targets.shape[1]):
            model = _regressor(regressor, seed).fit(features[train], targets[train, j])
            predicted[held, j] = model.predict(features[held])
    return predicted


def read_back_parameters(features: np.ndarray, params: np.ndarray, groups: np.ndarray, train_idx: np.ndarray,
                         folds: int = 5, regressor: str = "ridge") -> np.ndarray:
    """Each stroke's parameters as regressed from its statistics, the regressors fitted on training rows only:
    a training row's by the regressors of the ``GroupKFold`` fold that held its object out, every other row's
    by regressors fitted on all training rows. A classifier on this matrix goes through the physics as far as
    the strokes let it be read, and never sees a validation or test row's true parameters.

    Returns:
        (N, params.shape[1]) float64.
    """
    read = np.zeros_like(params)
    others = np.setdiff1d(np.arange(params.shape[0]), train_idx)
    read[train_idx] = _predicted_out_of_fold(features[train_idx], params[train_idx], groups[train_idx], regressor,
                                             folds)
    for j in range(params.shape[1]):
        model = _regressor(regressor, 0).fit(features[train_idx], params[train_idx, j])
        read[others, j] = model.predict(features[others])
    return read


def run_parameter_probe(records: Sequence[StrokeRecord], samples: Sequence[MaterialSample],
                        config: ParameterProbeConfig = ParameterProbeConfig(), progress: bool = False
                        ) -> dict[str, Any]:
    """The oracle and the recovery (module docstring) on ``records``, ``samples[i]`` being the physical
    parameters of the object that ``records[i]`` touched.

    Returns:
        {"oracle": score_on_splits's result with two feature sets, ``"parameters"`` (the exact logs) and
        ``"read_back"`` (:func:`read_back_parameters` by ridge), "recovery": {field: {"r2": {regressor: R^2},
        "between_instance_share"}} for :data:`PARAMETER_FIELDS` then :data:`STROKE_FIELDS`, "recovery_folds",
        "n_objects", "feature_config": the front end the statistics pooled (``config.splits.features``) as JSON
        data}.

    Raises:
        ValueError: ``samples`` and ``records`` differ in length or a sample's instance is not its record's.
    """
    from perception.dataset import labels_of
    from perception.train import TrainConfig, task_split

    if len(samples) != len(records):
        raise ValueError(f"{len(samples)} material samples for {len(records)} strokes: one per stroke")
    for i, (record, sample) in enumerate(zip(records, samples)):
        if sample.instance != record.instance:
            raise ValueError(f"stroke {i} is of {record.instance!r} but its material sample of {sample.instance!r}")
    params = log_parameters(samples)
    features = stroke_matrices(records, config.splits.features, progress=progress)["both"]
    groups = object_groups(records)
    splits = splits_of(config.splits)
    labels = {task: np.array(labels_of(records, task)) for task in {task for task, _, _ in splits}}
    runs = []
    for task, seed, fold in tqdm(splits, desc="oracle", unit="split", disable=not progress):
        parts = task_split(records, TrainConfig(task=task, seed=seed), fold)
        y = labels[task]
        read = read_back_parameters(features, params, groups, parts[0], config.recovery_folds)
        for name, x in (("parameters", params), ("read_back", read)):
            runs += [score_split((task, seed, fold), parts, y, name, x, c, config.splits.read_test)
                     for c in config.splits.classifiers]
    oracle = {"runs": runs, "means": means_of(runs), "read_test": config.splits.read_test}

    targets = np.concatenate([params, log_stroke_parameters(records)], axis=1)
    instances = [r.instance for r in records]
    r2 = {}
    for name in tqdm(config.regressors, desc="recovery", unit="regressor", disable=not progress):
        r2[name] = recovery_r2(features, targets, groups, name, config.recovery_folds)
    recovery = {field: {"r2": {name: round(float(r2[name][j]), 3) for name in config.regressors},
                        "between_instance_share": round(between_share(targets[:, j], instances), 3)}
                for j, field in enumerate(PARAMETER_FIELDS + STROKE_FIELDS)}
    return {"oracle": oracle, "recovery": recovery, "recovery_folds": config.recovery_folds,
            "n_objects": int(len(np.unique(groups))), "feature_config": dataclasses.asdict(config.splits.features)}


def plot_parameter_probe(path: str | Path, result: Mapping[str, Any]) -> Path:
    """Draw :func:`run_parameter_probe`'s result as a PNG: the recovery's R^2 per field beside each field's share
    of variance between instances, and the oracle's accuracy per task and input (test where it was read, else
    validation). Returns the path written (its folder is made)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    recovery = result["recovery"]
    fields = list(recovery)
    regressors = list(next(iter(recovery.values()))["r2"])
    fig, (left, right) = plt.subplots(1, 2, figsize=(13, 4.8), gridspec_kw={"width_ratios": [3, 2]})
    width = 0.8 / (len(regressors) + 1)
    x = np.arange(len(fields))
    for k, name in enumerate(regressors):
        left.bar(x + k * width, [recovery[f]["r2"][name] for f in fields], width, label=f"R^2 from the stroke, {name}")
    left.bar(x + len(regressors) * width, [recovery[f]["between_instance_share"] for f in fields], width,
             color="0.75", label="variance share between instances")
    left.set_xticks(x + width * len(regressors) / 2, [f.replace("_", " ") for f in fields], rotation=55, ha="right",
                    fontsize=7)
    left.axvline(len(PARAMETER_FIELDS) - 0.5 + width, color="0.5", lw=0.8, ls="--")
    left.set_ylim(min(0.0, min(min(v["r2"].values()) for v in recovery.values())), 1.05)
    left.set_title(f"what a stroke keeps: out-of-fold R^2 ({result['recovery_folds']} folds over "
                   f"{result['n_objects']} objects)", fontsize=9)
    left.legend(fontsize=7, loc="lower left")

    oracle = result["oracle"]
    key = "test_accuracy_pct" if oracle["read_test"] else "val_accuracy_pct"
    tasks = list(oracle["means"])
    bars = [(inp, clf) for inp in ("parameters", "read_back") for clf in next(iter(oracle["means"].values()))[inp]]
    width = 0.8 / len(bars)
    for k, (inp, clf) in enumerate(bars):
        right.bar(np.arange(len(tasks)) + k * width, [oracle["means"][t][inp][clf][key] for t in tasks], width,
                  label=f"{'exact' if inp == 'parameters' else 'read back'}, {clf}")
    right.set_xticks(np.arange(len(tasks)) + width * (len(bars) - 1) / 2, tasks)
    right.set_ylim(0, 100)
    right.set_ylabel(f"{'test' if oracle['read_test'] else 'validation'} accuracy [%]")
    right.set_title("classifiers given the material parameters", fontsize=9)
    right.legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
