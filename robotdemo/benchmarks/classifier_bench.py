"""The robot's classifier on its own checkpoint's held-out strokes: category accuracy, and the zone decided as
the sorting machine decides it (:func:`robotdemo.classifier.decide_zone`), per single stroke and split by the
confidence threshold that makes the robot stroke again.

The test part is the checkpoint's: :func:`perception.train.task_split` with the seed, task and
``split_by_object`` stored in its training config, on the data set it was trained on (checked against the
manifest hash in its meta). So the figure is what ``robotdemo train`` held out, never a training stroke.
"""

from __future__ import annotations

import os
from typing import Sequence

import numpy as np

from perception.dataset import load_dataset
from perception.materials import default_catalogue
from perception.train import TrainConfig, task_split
from robotdemo.classifier import TouchFormerClassifier, decide_zone
from robotdemo.errors import RobotDemoError


def run_classifier_benchmark(checkpoint_dir: str | os.PathLike, data_dir: str | os.PathLike,
                             thresholds: Sequence[float] = (0.7, 0.85, 0.95)) -> dict:
    """Per-stroke category and zone accuracy on the checkpoint's test part of ``data_dir``.

    Returns:
        {"n_test", "split_by_object", "category_accuracy", "zone_accuracy", "by_threshold": [{"threshold",
        "share_at_or_above", "zone_accuracy_at_or_above", "zone_accuracy_below"}]}.

    Raises:
        RobotDemoError: the checkpoint has no training config, or was trained on another data set.
    """
    classifier = TouchFormerClassifier.from_checkpoint(checkpoint_dir)
    meta = classifier.checkpoint.meta
    if "train_config" not in meta:
        raise RobotDemoError(f"{os.fspath(checkpoint_dir)}: no training config in its meta; cannot find its test part")
    config = TrainConfig.from_dict(meta["train_config"])
    data = load_dataset(data_dir)
    trained_on = meta.get("data_manifest_sha256")
    if trained_on and trained_on != data.manifest_sha256:
        raise RobotDemoError(f"{os.fspath(checkpoint_dir)} was trained on another data set (manifest sha256 "
                             f"{trained_on[:12]}..., {os.fspath(data_dir)} has {data.manifest_sha256[:12]}...)")
    records = data.records
    _, _, test_idx = task_split(records, config, fold=int(meta.get("fold", 0)))
    combustible = default_catalogue().combustible
    rows = []
    for i in test_idx:
        record = records[i]
        result = classifier(record)
        zone = decide_zone(result, combustible)
        rows.append((result.category == record.category, zone.combustible == record.combustible, zone.confidence))
    hits = np.array(rows, dtype=float).reshape(-1, 3)
    bands = []
    for threshold in thresholds:
        sure = hits[:, 2] >= threshold
        bands.append({"threshold": threshold, "share_at_or_above": round(float(sure.mean()), 4),
                      "zone_accuracy_at_or_above": round(float(hits[sure, 1].mean()), 4) if sure.any() else None,
                      "zone_accuracy_below": round(float(hits[~sure, 1].mean()), 4) if (~sure).any() else None})
    return {"checkpoint": os.fspath(checkpoint_dir), "data": os.fspath(data_dir), "n_test": int(len(hits)),
            "split_by_object": config.split_by_object, "category_accuracy": round(float(hits[:, 0].mean()), 4),
            "zone_accuracy": round(float(hits[:, 1].mean()), 4), "by_threshold": bands}
