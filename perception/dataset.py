"""Stroke data sets on disk, and the paper's evaluation splits.

A data set is a folder::

    DIR/manifest.json          {"format": "robotdemo-dataset", "version": 1, "env": "clean" | "fire",
                                "seed": int, "config": {...},
                                "shards": [{"file": "shards/shard-00000.npz", "n_strokes": int,
                                            "sha256": hex}, ...]}
    DIR/shards/shard-*.npz     perception.recording_io stroke files

Labels live on each :class:`~perception.streams.StrokeRecord` (``category``, ``instance``, ``combustible``);
``meta["object_id"]`` names the physical object a stroke was taken on (several strokes per object).

Splits (all return index arrays into the record list, sorted, never overlapping):

- SSMC (seen materials): :func:`ssmc_split`, a random 7:3 split *by stroke*, stratified by category, as in
  the paper (LMTHM: five strokes per material, split at random). Strokes of one object can therefore sit
  on both sides; pass ``group_by_object=True`` for the stricter split.
- USMC (unseen materials of seen classes): :func:`usmc_folds`, k folds over *instances*: each category's
  instances are dealt to the folds, so a test fold holds instances never seen in training, and every
  category keeps at least one instance in every training fold. Since an object is one instance, no object
  straddles train and test.
- Fine-grained: :func:`fine_split`, a 7:3 split by stroke stratified by instance (the label is the instance).
- Validation: :func:`validation_split` carves the validation part out of the *training* indices only; the
  best epoch is chosen on it, never on the test part.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import numpy as np

from perception.atomic import atomic_write_json
from perception.recording_io import RecordingFormatError, read_strokes, write_strokes
from perception.streams import StrokeRecord

FORMAT_NAME = "robotdemo-dataset"
FORMAT_VERSION = 1
MANIFEST_FILE = "manifest.json"
ENVIRONMENTS = ("clean", "fire")
TASKS = ("ssmc", "usmc", "fine")


class DatasetError(ValueError):
    """A data set folder cannot be read; the one-line message is ``"<file>: <problem>"``."""

    def __init__(self, path: Path | str, problem: str) -> None:
        super().__init__(f"{path}: {problem}")
        self.path = Path(path)
        self.problem = problem


class SplitError(ValueError):
    """The records cannot be split as asked (too few strokes or instances per class)."""


@dataclass(frozen=True)
class Dataset:
    """A loaded data set.

    Attributes:
        root: the data set folder.
        records: every stroke, in shard order.
        manifest: the parsed manifest.json.
        manifest_sha256: sha256 (hex) of manifest.json's bytes: the data set's identity for provenance (the
            manifest holds every shard's sha256, so it pins the strokes too).
    """

    root: Path
    records: tuple[StrokeRecord, ...]
    manifest: Mapping[str, Any]
    manifest_sha256: str

    @property
    def env(self) -> str:
        return str(self.manifest.get("env", ""))

    def __len__(self) -> int:
        return len(self.records)


def sha256_file(path: str | os.PathLike) -> str:
    """Hex sha256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _read_manifest(path: Path) -> tuple[dict[str, Any], str]:
    if not path.is_file():
        raise DatasetError(path, "manifest not found (is this a data set folder?)")
    raw = path.read_bytes()
    try:
        manifest = json.loads(raw.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DatasetError(path, f"manifest is not valid JSON ({exc})") from None
    if not isinstance(manifest, dict) or manifest.get("format") != FORMAT_NAME:
        raise DatasetError(path, f"not a {FORMAT_NAME} manifest")
    if manifest.get("version") != FORMAT_VERSION:
        raise DatasetError(path, f"manifest version {manifest.get('version')!r}, expected {FORMAT_VERSION}")
    if manifest.get("env") not in ENVIRONMENTS:
        raise DatasetError(path, f"env {manifest.get('env')!r}, expected one of {ENVIRONMENTS}")
    shards = manifest.get("shards")
    if not isinstance(shards, list) or not shards:
        raise DatasetError(path, "manifest lists no shards")
    for i, shard in enumerate(shards):
        if not isinstance(shard, dict) or not {"file", "n_strokes", "sha256"} <= set(shard):
            raise DatasetError(path, f"shard entry {i} needs 'file', 'n_strokes' and 'sha256'")
        if not (isinstance(shard["file"], str) and shard["file"] and isinstance(shard["sha256"], str)
                and isinstance(shard["n_strokes"], int) and not isinstance(shard["n_strokes"], bool)
                and shard["n_strokes"] >= 0):
            raise DatasetError(path, f"shard entry {i}: 'file' and 'sha256' must be strings and 'n_strokes' a "
                                     f"whole number >= 0")
    return manifest, hashlib.sha256(raw).hexdigest()


def load_dataset(directory: str | os.PathLike, verify: bool = True) -> Dataset:
    """Read a data set folder.

    Args:
        directory: the folder holding manifest.json.
        verify: check every shard's sha256 against the manifest (reads each shard twice; cheap next to
            decoding).

    Returns:
        The :class:`Dataset`.

    Raises:
        DatasetError: missing or corrupt manifest, a recording that has not finished, missing shard, sha256 or
            stroke-count mismatch, or a shard that is not a readable stroke file. The message names the file.
    """
    root = Path(directory)
    if not root.is_dir():
        raise DatasetError(root, "data set folder not found")
    manifest, digest = _read_manifest(root / MANIFEST_FILE)
    if manifest.get("complete") is False:  # written by a recording that has not finished (older ones say nothing)
        raise DatasetError(root / MANIFEST_FILE, f"the recording is not finished ({len(manifest['shards'])} of "
                           f"{manifest.get('expected_shards', '?')} shards); run the same dataset command again "
                           "to resume it")
    records: list[StrokeRecord] = []
    for shard in manifest["shards"]:
        path = root / shard["file"]
        if not path.is_file():
            raise DatasetError(path, "shard listed in the manifest is missing")
        if verify and sha256_file(path) != shard["sha256"]:
            raise DatasetError(path, "sha256 does not match the manifest (corrupt or replaced shard)")
        try:
            strokes = read_strokes(path)
        except RecordingFormatError as exc:
            raise DatasetError(path, f"unreadable shard ({exc})") from None
        if len(strokes) != int(shard["n_strokes"]):
            raise DatasetError(path, f"holds {len(strokes)} strokes, the manifest says {shard['n_strokes']}")
        records.extend(strokes)
    return Dataset(root=root, records=tuple(records), manifest=manifest, manifest_sha256=digest)


def write_dataset(directory: str | os.PathLike, records: Iterable[StrokeRecord], env: str, seed: int,
                  config: Mapping[str, Any] | None = None, shard_size: int = 256) -> Path:
    """Write records as a data set folder (shards first, the manifest last and atomically).

    Args:
        directory: output folder (created; existing shards of the same names are replaced).
        records: the strokes.
        env: "clean" or "fire".
        seed: the generator's seed (recorded).
        config: JSON-serialisable generator/converter settings (recorded).
        shard_size: strokes per shard file.

    Returns:
        The manifest path.
    """
    if env not in ENVIRONMENTS:
        raise ValueError(f"env must be one of {ENVIRONMENTS}, got {env!r}")
    if shard_size < 1:
        raise ValueError(f"shard_size must be >= 1, got {shard_size}")
    root = Path(directory)
    records = list(records)
    shards = []
    for i, start in enumerate(range(0, len(records), shard_size)):
        rel = f"shards/shard-{i:05d}.npz"
        chunk = records[start:start + shard_size]
        write_strokes(root / rel, chunk)
        shards.append({"file": rel, "n_strokes": len(chunk), "sha256": sha256_file(root / rel)})
    manifest = {"format": FORMAT_NAME, "version": FORMAT_VERSION, "env": env, "seed": int(seed),
                "config": dict(config or {}), "shards": shards}
    path = root / MANIFEST_FILE
    return atomic_write_json(path, manifest, sort_keys=True)


# ----------------------------------------------------------------------------------------------------------
# labels


def label_key(task: str) -> str:
    """Which record attribute a task classifies: "category" (ssmc, usmc) or "instance" (fine)."""
    if task not in TASKS:
        raise ValueError(f"unknown task {task!r}; expected one of {TASKS}")
    return "instance" if task == "fine" else "category"


def labels_of(records: Sequence[StrokeRecord], task: str) -> list[str]:
    """Label string of every record for ``task``."""
    key = label_key(task)
    return [str(getattr(r, key)) for r in records]


def object_id(record: StrokeRecord, index: int) -> str:
    """The physical object a stroke was taken on: ``meta["object_id"]``, else the stroke itself."""
    oid = record.meta.get("object_id")
    return f"{record.instance}/{oid}" if oid is not None else f"__stroke_{index}"


# ----------------------------------------------------------------------------------------------------------
# splits


def _stratified_pick(labels: Sequence[str], groups: Sequence[str], candidates: np.ndarray, fraction: float,
                     rng: np.random.Generator, what: str, at_least_one: bool = True) -> np.ndarray:
    """Pick about ``fraction`` of each label's groups from ``candidates``, always leaving one group behind.

    With ``at_least_one`` every label gets at least one picked group (test splits: every class is tested).
    Without it, the picks are allotted by largest remainder so the total is ``round(fraction * groups)``
    (validation splits: a class with few strokes is not forced to give one up). Returns sorted indices.
    """
    by_label: dict[str, dict[str, list[int]]] = defaultdict(lambda: defaultdict(list))
    for i in candidates:
        by_label[labels[i]][groups[i]].append(int(i))
    order = sorted(by_label)
    sizes = np.array([len(by_label[label]) for label in order])
    if at_least_one:
        for label, size in zip(order, sizes):
            if size < 2:
                raise SplitError(f"{what}: class {label!r} has {size} stroke(s)/object(s) to split; need at least 2")
        quota = np.clip(np.round(fraction * sizes).astype(int), 1, sizes - 1)
    else:
        exact = fraction * sizes
        quota = np.floor(exact).astype(int)
        extra = int(round(fraction * sizes.sum())) - int(quota.sum())
        remainder = exact - quota + rng.uniform(0, 1e-6, size=len(sizes))  # random tie-break
        for j in np.argsort(-remainder)[:max(extra, 0)]:
            quota[j] += 1
        quota = np.minimum(quota, np.maximum(sizes - 1, 0))
    picked: list[int] = []
    for label, n_pick in zip(order, quota):
        for g in rng.permutation(sorted(by_label[label]))[:n_pick]:
            picked.extend(by_label[label][str(g)])
    return np.array(sorted(picked), dtype=np.int64)


def _complement(candidates: np.ndarray, picked: np.ndarray) -> np.ndarray:
    return np.array(sorted(set(candidates.tolist()) - set(picked.tolist())), dtype=np.int64)


def _groups(records: Sequence[StrokeRecord], by_object: bool) -> list[str]:
    return [object_id(r, i) if by_object else f"__stroke_{i}" for i, r in enumerate(records)]


def ssmc_split(records: Sequence[StrokeRecord], seed: int, test_fraction: float = 0.3,
               group_by_object: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """SSMC: random train/test split stratified by category (paper: 7:3).

    Args:
        records: all strokes.
        seed: split seed.
        test_fraction: share of each category's strokes (or objects) in the test part.
        group_by_object: keep all strokes of one object on one side (stricter than the paper).

    Returns:
        (train indices, test indices), sorted int64 arrays.
    """
    rng = np.random.default_rng(seed)
    labels = labels_of(records, "ssmc")
    everything = np.arange(len(records))
    test = _stratified_pick(labels, _groups(records, group_by_object), everything, test_fraction, rng, "ssmc")
    return _complement(everything, test), test


def fine_split(records: Sequence[StrokeRecord], seed: int, test_fraction: float = 0.3,
               group_by_object: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Fine-grained: random train/test split by stroke (or by object with ``group_by_object``), stratified by
    instance (paper: 7:3)."""
    rng = np.random.default_rng(seed)
    labels = labels_of(records, "fine")
    everything = np.arange(len(records))
    test = _stratified_pick(labels, _groups(records, group_by_object), everything, test_fraction, rng, "fine")
    return _complement(everything, test), test


def usmc_folds(records: Sequence[StrokeRecord], k: int = 5, seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    """USMC: k folds whose test parts hold unseen instances of seen categories.

    Each category's instances are shuffled and dealt round-robin to the folds, starting at a random fold, so
    instance counts per fold stay balanced. A category with fewer instances than k is absent from some test
    folds but, having at least two instances, is always present in every training fold.

    Returns:
        k (train indices, test indices) pairs.

    Raises:
        SplitError: a category with fewer than 2 instances, or a fold with an empty test part.
    """
    if k < 2:
        raise SplitError(f"usmc needs k >= 2 folds, got {k}")
    rng = np.random.default_rng(seed)
    instances: dict[str, set[str]] = defaultdict(set)
    for r in records:
        instances[r.category].add(r.instance)
    fold_of: dict[tuple[str, str], int] = {}
    for category in sorted(instances):
        names = sorted(instances[category])
        if len(names) < 2:
            raise SplitError(f"usmc: category {category!r} has {len(names)} instance(s); need at least 2 so "
                             f"that it stays in every training fold")
        start = int(rng.integers(k))
        for j, name in enumerate(rng.permutation(names)):
            fold_of[(category, str(name))] = (start + j) % k
    fold_ids = np.array([fold_of[(r.category, r.instance)] for r in records])
    folds = []
    for f in range(k):
        test = np.flatnonzero(fold_ids == f).astype(np.int64)
        if test.size == 0:
            raise SplitError(f"usmc: fold {f} of {k} has no test strokes (too few instances for {k} folds)")
        folds.append((np.flatnonzero(fold_ids != f).astype(np.int64), test))
    return folds


def validation_split(records: Sequence[StrokeRecord], train_idx: np.ndarray, task: str, seed: int,
                     fraction: float = 0.15, group_by_object: bool | None = None,
                     group_by_instance: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Carve a validation part out of the training indices (never out of the test part).

    Stratified by the task's label: every class gives at least one stroke (object) when that fits within
    ``fraction``; otherwise (many small classes, e.g. fine-grained with 3-4 training strokes per instance) the
    picks are allotted by largest remainder, some classes give none and the total stays at ``fraction``. By
    default, USMC validation keeps whole objects together (closer to the unseen-instance test condition than
    a stroke split), SSMC and fine-grained split by stroke. ``group_by_instance`` (SSMC and USMC only) keeps
    whole material instances together instead, as the USMC test part does. A class never gives up its last
    stroke (object, instance).

    Returns:
        (train indices, validation indices), sorted; empty validation if ``fraction`` is 0.
    """
    train_idx = np.asarray(train_idx, dtype=np.int64)
    if fraction <= 0:
        return np.sort(train_idx), np.zeros(0, dtype=np.int64)
    if group_by_object is None:
        group_by_object = task == "usmc"
    if group_by_instance and task == "fine":
        raise ValueError("fine-grained labels are the instances: its validation cannot hold out whole instances")
    rng = np.random.default_rng(seed + 7919)
    labels = labels_of(records, task)
    groups = [r.instance for r in records] if group_by_instance else _groups(records, group_by_object)
    by_label: dict[str, set[str]] = defaultdict(set)
    for i in train_idx:
        by_label[labels[i]].add(groups[i])
    splittable = np.array([i for i in train_idx if len(by_label[labels[i]]) >= 2], dtype=np.int64)
    if splittable.size == 0:
        return np.sort(train_idx), np.zeros(0, dtype=np.int64)
    n_groups = len({groups[i] for i in splittable})
    n_classes = len({labels[i] for i in splittable})
    every_class = n_classes <= round(fraction * n_groups)  # one per class fits within the fraction
    val = _stratified_pick(labels, groups, splittable, fraction, rng, f"{task} validation", at_least_one=every_class)
    return _complement(train_idx, val), val
