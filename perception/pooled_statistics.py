"""How far classifiers with no temporal model go on the networks' own splits (`robotdemo bench statistics`).

A diagnostic for the evaluation's "find out why": if a classifier that sees only per-stroke statistics comes
close to the networks, the strokes carry little that a sequence model (TouchFormer's attention, MTCNN's
convolutions, the LSTM) could add on top of those statistics.

Each stroke becomes one vector, in one of three sets (:data:`FEATURE_SETS`):

- ``"reference"``: the reference classifier's stream statistics (:func:`perception.reference_classifier.summary_features`);
- ``"pooled"``: the networks' own front-end frames (:func:`perception.features.featurize`), pooled over time per
  channel by mean, standard deviation and maximum, and a present indicator per modality (all 0 where a stream
  is missing);
- ``"both"``: the two side by side.

Two classifiers (:data:`CLASSIFIERS`): ``"logreg"``, a standardised logistic regression as the reference's, and
``"trees"``, sklearn's gradient-boosted trees (``HistGradientBoostingClassifier``, its defaults, seeded), which
can combine one sensor's statistics with another's non-linearly. Each is fitted on the training part of every
split that ``robotdemo train`` uses (:func:`perception.train.task_split`: SSMC and fine-grained seeds, USMC
folds, the validation part carved off the same way) and scored on its validation part, which is what the
networks' best epochs were chosen on; the test part is scored only when asked (``read_test``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np
from sklearn.ensemble import HistGradientBoostingClassifier
from sklearn.pipeline import Pipeline
from tqdm import tqdm

from perception.features import FeatureConfig, StrokeFeatures, feature_dims, featurize
from perception.reference_classifier import ReferenceClassifier, ReferenceConfig, summary_features
from perception.streams import MODALITIES, StrokeRecord

FEATURE_SETS = ("reference", "pooled", "both")
CLASSIFIERS = ("logreg", "trees")


@dataclass(frozen=True)
class PooledStatisticsConfig:
    """Which splits, feature sets and classifiers to run.

    Attributes:
        ssmc_seeds: SSMC 7:3 splits, by seed (the evaluation's seeds 0-2).
        usmc_folds: USMC leave-instances-out folds of seed 0 (the evaluation's folds 0-4).
        fine_seeds: fine-grained 7:3 splits, by seed.
        feature_sets: among :data:`FEATURE_SETS`.
        classifiers: among :data:`CLASSIFIERS`.
        read_test: also score each split's test part (leave off while choosing anything).
        features: the networks' front end whose frames the ``"pooled"`` set pools (the default: the evaluation's).
    """

    ssmc_seeds: tuple[int, ...] = (0, 1, 2)
    usmc_folds: tuple[int, ...] = (0, 1, 2, 3, 4)
    fine_seeds: tuple[int, ...] = (0, 1, 2)
    feature_sets: tuple[str, ...] = FEATURE_SETS
    classifiers: tuple[str, ...] = CLASSIFIERS
    read_test: bool = False
    features: FeatureConfig = FeatureConfig()

    def __post_init__(self) -> None:
        unknown = [f for f in self.feature_sets if f not in FEATURE_SETS]
        if unknown or not self.feature_sets:
            raise ValueError(f"feature_sets must be among {FEATURE_SETS}, got {self.feature_sets}")
        unknown = [c for c in self.classifiers if c not in CLASSIFIERS]
        if unknown or not self.classifiers:
            raise ValueError(f"classifiers must be among {CLASSIFIERS}, got {self.classifiers}")
        if not (self.ssmc_seeds or self.usmc_folds or self.fine_seeds):
            raise ValueError("no split to run: give at least one SSMC seed, USMC fold or fine-grained seed")


def pooled_frame_statistics(features: StrokeFeatures, dims: Mapping[str, int]) -> np.ndarray:
    """One stroke's front-end frames pooled over time: per modality (:data:`MODALITIES` order) the mean, std and
    max of each of its ``dims[m]`` channels, then 1 if present; a missing modality is all 0.

    Returns:
        (sum over modalities of 3 C_m + 1,) float64.
    """
    parts = []
    for key in MODALITIES:
        x = features.get(key)
        if x is None or x.shape[0] == 0:
            parts.append(np.zeros(3 * dims[key] + 1))
            continue
        x = np.asarray(x, dtype=np.float64)
        parts.append(np.concatenate([x.mean(axis=0), x.std(axis=0), x.max(axis=0), [1.0]]))
    return np.concatenate(parts)


def stroke_matrices(records: Sequence[StrokeRecord], config: FeatureConfig = FeatureConfig(),
                    progress: bool = False) -> dict[str, np.ndarray]:
    """Every feature set of :data:`FEATURE_SETS` for ``records``: name -> (N, D) float64."""
    dims = feature_dims(config)
    reference, pooled = [], []
    for record in tqdm(records, desc="statistics", unit="stroke", disable=not progress):
        reference.append(summary_features(record))
        pooled.append(pooled_frame_statistics(featurize(record, config), dims))
    matrices = {"reference": np.stack(reference), "pooled": np.stack(pooled)}
    matrices["both"] = np.concatenate([matrices["reference"], matrices["pooled"]], axis=1)
    return matrices


def make_classifier(name: str, seed: int) -> Pipeline | HistGradientBoostingClassifier:
    """A fresh classifier of :data:`CLASSIFIERS` (trees seeded by ``seed``)."""
    if name == "logreg":  # the reference classifier's own pipeline, given more solver iterations for wider inputs
        return ReferenceClassifier(ReferenceConfig(max_iter=5000)).pipeline
    if name == "trees":
        return HistGradientBoostingClassifier(random_state=seed)
    raise ValueError(f"unknown classifier {name!r}; expected one of {CLASSIFIERS}")


def splits_of(config: PooledStatisticsConfig) -> list[tuple[str, int, int]]:
    """(task, seed, fold) of every split to run."""
    return ([("ssmc", s, 0) for s in config.ssmc_seeds] + [("usmc", 0, k) for k in config.usmc_folds]
            + [("fine", s, 0) for s in config.fine_seeds])


def _accuracy_percent(pred: np.ndarray, truth: np.ndarray) -> float:
    from perception.train import _accuracy

    return round(100.0 * _accuracy(pred, truth), 2)


def run_pooled_statistics(records: Sequence[StrokeRecord], config: PooledStatisticsConfig = PooledStatisticsConfig(),
                          progress: bool = False) -> dict[str, Any]:
    """Fit and score every (split, feature set, classifier) of ``config`` on ``records``.

    Returns:
        {"runs": [{"task", "seed", "fold", "features", "classifier", "n_train", "n_val", "val_accuracy_pct"
        [, "n_test", "test_accuracy_pct"]}, ...], "means": {task: {features: {classifier: {"val_accuracy_pct"
        [, "test_accuracy_pct"]}}}}, "read_test": bool, "feature_config": the front end ``config.features`` as
        JSON data}. Accuracies in percent.
    """
    matrices = stroke_matrices(records, config.features, progress=progress)
    return {**score_on_splits(records, {name: matrices[name] for name in config.feature_sets}, config, progress),
            "feature_config": dataclasses.asdict(config.features)}


def score_on_splits(records: Sequence[StrokeRecord], matrices: Mapping[str, np.ndarray],
                    config: PooledStatisticsConfig, progress: bool = False) -> dict[str, Any]:
    """Fit each of ``config.classifiers`` on every split's training part of each matrix (name -> (N, D), one row
    per record) and score its validation part (and test part with ``config.read_test``); the result as
    :func:`run_pooled_statistics`'s, with the matrices' names as the feature sets."""
    from perception.dataset import labels_of
    from perception.train import TrainConfig, task_split

    for name, x in matrices.items():
        if x.shape[0] != len(records):
            raise ValueError(f"feature matrix {name!r} has {x.shape[0]} rows for {len(records)} strokes")
        if not np.all(np.isfinite(x)):
            raise ValueError(f"feature matrix {name!r} holds NaN or infinite values")
    splits = splits_of(config)
    labels = {task: np.array(labels_of(records, task)) for task in {task for task, _, _ in splits}}
    runs = []
    bar = tqdm(total=len(splits) * len(matrices) * len(config.classifiers), desc="fit", unit="fit",
               disable=not progress)
    for task, seed, fold in splits:
        train_idx, val_idx, test_idx = task_split(records, TrainConfig(task=task, seed=seed), fold)
        y = labels[task]
        for features, x in matrices.items():
            for name in config.classifiers:
                runs.append(score_split((task, seed, fold), (train_idx, val_idx, test_idx), y, features, x, name,
                                        config.read_test))
                bar.update()
    bar.close()
    return {"runs": runs, "means": means_of(runs), "read_test": config.read_test}


def score_split(split: tuple[str, int, int], parts: tuple[np.ndarray, np.ndarray, np.ndarray], y: np.ndarray,
                features: str, x: np.ndarray, classifier: str, read_test: bool) -> dict[str, Any]:
    """Fit ``classifier`` on the training rows of ``x`` (``parts``: training, validation and test indices of the
    split ``(task, seed, fold)``) and score the validation rows, and the test rows with ``read_test``; one run
    of :func:`score_on_splits`'s result."""
    (task, seed, fold), (train_idx, val_idx, test_idx) = split, parts
    clf = make_classifier(classifier, seed).fit(x[train_idx], y[train_idx])
    run = {"task": task, "seed": seed, "fold": fold, "features": features, "classifier": classifier,
           "n_train": int(len(train_idx)), "n_val": int(len(val_idx)),
           "val_accuracy_pct": _accuracy_percent(clf.predict(x[val_idx]), y[val_idx])}
    if read_test:
        run["n_test"] = int(len(test_idx))
        run["test_accuracy_pct"] = _accuracy_percent(clf.predict(x[test_idx]), y[test_idx])
    return run


def means_of(runs: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Mean accuracy over the seeds or folds of each (task, feature set, classifier)."""
    means: dict[str, Any] = {}
    keys = ("val_accuracy_pct", "test_accuracy_pct")
    for run in runs:
        cell = means.setdefault(run["task"], {}).setdefault(run["features"], {}).setdefault(run["classifier"], {})
        for key in keys:
            if key in run:
                cell.setdefault(key, []).append(run[key])
    for by_features in means.values():
        for by_classifier in by_features.values():
            for cell in by_classifier.values():
                for key, values in cell.items():
                    cell[key] = round(float(np.mean(values)), 2)
    return means
