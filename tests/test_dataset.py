"""Data set folders and evaluation splits (perception.dataset).

Also home of :func:`make_material_strokes`, a seeded toy data set with categories, instances and objects
that the training and evaluation tests import.
"""

from __future__ import annotations

import json
from collections import Counter

import numpy as np
import pytest

from perception.dataset import (DatasetError, SplitError, fine_split, labels_of, load_dataset, ssmc_split,
                                usmc_folds, validation_split, write_dataset)
from perception.streams import MODALITIES, NOMINAL_RATE_HZ, Stream, StrokeRecord

SOUND_HZ = (300.0, 1500.0, 5000.0, 9000.0)  # per category
ACCEL_HZ = (15.0, 45.0, 110.0, 200.0)
NORMAL_N = (0.4, 0.8, 1.2, 1.6)
FRICTION = (0.2, 0.45, 0.7, 0.95)


def make_material_strokes(seed: int, n_categories: int = 3, n_instances: int = 3, n_objects: int = 2,
                          n_strokes: int = 3, duration_s: float = 0.4, noise: float = 0.3,
                          env: str = "clean") -> list[StrokeRecord]:
    """Seeded toy materials: category sets each stream's physics, instances shift it by +-6 %.

    Category k of instance j has sound at ``SOUND_HZ[k] * (1 + 0.06 (j - mid))``, vibration likewise, normal
    force and friction coefficient likewise; each object jitters the instance by 1.5 %, each stroke adds
    noise. ``env="fire"`` adds a broadband roar to the sound and doubles the sensor noise (a domain shift).
    """
    rng = np.random.default_rng(seed)
    records = []
    for k in range(n_categories):
        for j in range(n_instances):
            shift = 1.0 + 0.06 * (j - (n_instances - 1) / 2)
            for o in range(n_objects):
                obj = shift * rng.uniform(0.985, 1.015)
                for s in range(n_strokes):
                    nz = noise * (2.0 if env == "fire" else 1.0)
                    streams = {}
                    for key in MODALITIES:
                        rate = NOMINAL_RATE_HZ[key]
                        n = int(duration_s * rate)
                        t = np.arange(n) / rate
                        if key == "sound":
                            f = SOUND_HZ[k] * obj * rng.uniform(0.99, 1.01)
                            x = np.sin(2 * np.pi * f * t + rng.uniform(0, 6.3)) + nz * rng.normal(size=n)
                            if env == "fire":
                                x = x + 0.5 * np.cumsum(rng.normal(size=n)) / np.sqrt(n)
                            data = x[:, None]
                        elif key == "accel":
                            f = ACCEL_HZ[k] * obj
                            data = np.sin(2 * np.pi * f * t)[:, None] * rng.normal(size=3)[None, :]
                            data = data + nz * rng.normal(size=(n, 3))
                        elif key == "normal":
                            data = NORMAL_N[k] * obj * rng.uniform(0.8, 1.2, 16)[None, :] + 0.1 * nz * rng.normal(size=(n, 16))
                        else:
                            data = FRICTION[k] * obj * NORMAL_N[k] * rng.uniform(0.8, 1.2, 32)[None, :]
                            data = data + 0.1 * nz * rng.normal(size=(n, 32))
                        streams[key] = Stream(data.astype(np.float32), rate_hz=rate, t0_s=float(rng.uniform(0, 0.02)))
                    records.append(StrokeRecord(
                        streams=streams, category=f"cat{k}", instance=f"cat{k}_inst{j}", combustible=bool(k % 2),
                        meta={"object_id": f"obj{k}-{j}-{o}", "stroke": s, "env": env}))
    order = rng.permutation(len(records))
    return [records[i] for i in order]


# ----------------------------------------------------------------------------------------------------------
# folder format


def test_write_and_load_round_trip(tmp_path):
    recs = make_material_strokes(0, n_categories=2, n_instances=2, n_objects=1, n_strokes=2, duration_s=0.1)
    write_dataset(tmp_path / "ds", recs, env="clean", seed=3, config={"k": 1}, shard_size=3)
    data = load_dataset(tmp_path / "ds")
    manifest = json.loads((tmp_path / "ds" / "manifest.json").read_text())
    assert len(manifest["shards"]) == 3 and data.env == "clean" and len(data) == len(recs)
    assert len(data.manifest_sha256) == 64
    assert [r.instance for r in data.records] == [r.instance for r in recs]
    assert data.records[0].meta["object_id"] == recs[0].meta["object_id"]
    assert np.array_equal(data.records[1].streams["sound"].data, recs[1].streams["sound"].data)


@pytest.mark.parametrize("damage", ["no_manifest", "bad_json", "wrong_format", "missing_shard", "sha", "count",
                                    "corrupt_shard", "no_folder", "file_not_a_string", "count_not_a_number"])
def test_load_errors_name_the_file(tmp_path, damage):
    recs = make_material_strokes(1, n_categories=2, n_instances=2, n_objects=1, n_strokes=1, duration_s=0.05)
    root = tmp_path / "ds"
    write_dataset(root, recs, env="fire", seed=0, shard_size=2)
    manifest_path = root / "manifest.json"
    manifest = json.loads(manifest_path.read_text())
    shard = root / manifest["shards"][0]["file"]
    expect = "manifest.json"
    if damage == "no_manifest":
        manifest_path.unlink()
    elif damage == "bad_json":
        manifest_path.write_text("{not json")
    elif damage == "wrong_format":
        manifest_path.write_text(json.dumps({**manifest, "format": "other"}))
    elif damage == "missing_shard":
        shard.unlink()
        expect = shard.name
    elif damage == "sha":
        manifest["shards"][0]["sha256"] = "0" * 64
        manifest_path.write_text(json.dumps(manifest))
        expect = shard.name
    elif damage == "count":
        manifest["shards"][0]["n_strokes"] = 5
        manifest_path.write_text(json.dumps(manifest))
        expect = shard.name
    elif damage == "corrupt_shard":
        shard.write_bytes(b"garbage")
        manifest["shards"][0]["sha256"] = __import__("hashlib").sha256(b"garbage").hexdigest()
        manifest_path.write_text(json.dumps(manifest))
        expect = shard.name
    elif damage == "file_not_a_string":
        manifest["shards"][0]["file"] = 5
        manifest_path.write_text(json.dumps(manifest))
    elif damage == "count_not_a_number":
        manifest["shards"][0]["n_strokes"] = "ten"
        manifest_path.write_text(json.dumps(manifest))
    else:
        root = tmp_path / "nowhere"
        expect = "nowhere"
    with pytest.raises(DatasetError, match=expect) as info:
        load_dataset(root)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("edit, message", [
    (lambda index: [1], "index.json is not a JSON object"),
    (lambda index: {**index, "strokes": 7}, "'strokes' is not a list"),
    (lambda index: {**index, "strokes": [{**index["strokes"][0], "meta": 7}]}, "stroke 0: 'meta' is not a JSON"),
    (lambda index: {**index, "strokes": [5]}, "stroke 0 index entry is malformed"),
])
def test_malformed_stroke_index_is_named(tmp_path, edit, message):
    from perception.recording_io import RecordingFormatError, read_strokes, write_strokes

    recs = make_material_strokes(2, n_categories=1, n_instances=1, n_objects=1, n_strokes=1, duration_s=0.05)
    path = write_strokes(tmp_path / "s.npz", recs[:1])
    with np.load(path, allow_pickle=False) as npz:
        arrays = {name: npz[name] for name in npz.files}
    index = json.loads(arrays["index.json"].tobytes().decode("utf-8"))
    arrays["index.json"] = np.frombuffer(json.dumps(edit(index)).encode("utf-8"), dtype=np.uint8)
    with open(path, "wb") as fh:
        np.savez_compressed(fh, **arrays)
    with pytest.raises(RecordingFormatError, match=message) as info:
        read_strokes(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


# ----------------------------------------------------------------------------------------------------------
# splits


def _check_disjoint_cover(train, test, n):
    assert not set(train) & set(test)
    assert sorted(set(train) | set(test)) == list(range(n))


def test_ssmc_split_stratified_7_3():
    recs = make_material_strokes(2, n_categories=3, n_instances=2, n_objects=2, n_strokes=5, duration_s=0.02)
    train, test = ssmc_split(recs, seed=0)
    _check_disjoint_cover(train, test, len(recs))
    per_cat = Counter(labels_of([recs[i] for i in test], "ssmc"))
    assert set(per_cat.values()) == {6}  # 30 % of 20 strokes per category
    again, _ = ssmc_split(recs, seed=0)
    other, _ = ssmc_split(recs, seed=1)
    assert np.array_equal(train, again) and not np.array_equal(train, other)
    # the stricter variant keeps each object on one side
    train_o, test_o = ssmc_split(recs, seed=0, group_by_object=True)
    objs = lambda idx: {recs[i].meta["object_id"] for i in idx}  # noqa: E731
    assert not objs(train_o) & objs(test_o)


def test_fine_split_stratified_by_instance():
    recs = make_material_strokes(3, n_categories=2, n_instances=3, n_objects=2, n_strokes=5, duration_s=0.02)
    train, test = fine_split(recs, seed=0)
    _check_disjoint_cover(train, test, len(recs))
    assert set(Counter(labels_of([recs[i] for i in test], "fine")).values()) == {3}
    assert set(labels_of([recs[i] for i in train], "fine")) == set(labels_of(recs, "fine"))


@pytest.mark.parametrize("n_instances, k", [(5, 5), (3, 5), (7, 5), (2, 2)])
def test_usmc_folds_hold_unseen_instances(n_instances, k):
    recs = make_material_strokes(4, n_categories=3, n_instances=n_instances, n_objects=1, n_strokes=2,
                                 duration_s=0.02)
    folds = usmc_folds(recs, k=k, seed=0)
    assert len(folds) == k
    seen_test = []
    for train, test in folds:
        _check_disjoint_cover(train, test, len(recs))
        train_inst = {recs[i].instance for i in train}
        test_inst = {recs[i].instance for i in test}
        assert not train_inst & test_inst
        assert {recs[i].category for i in train} == {r.category for r in recs}  # every category in training
        seen_test.extend(test.tolist())
    assert sorted(seen_test) == list(range(len(recs)))  # every stroke tested exactly once


def test_usmc_needs_two_instances_per_category():
    recs = make_material_strokes(5, n_categories=2, n_instances=1, n_objects=2, n_strokes=2, duration_s=0.02)
    with pytest.raises(SplitError, match="cat0"):
        usmc_folds(recs, k=2)


def test_validation_comes_from_training_only():
    recs = make_material_strokes(6, n_categories=3, n_instances=3, n_objects=2, n_strokes=3, duration_s=0.02)
    for task in ("ssmc", "usmc"):
        train, test = ssmc_split(recs, seed=0) if task == "ssmc" else usmc_folds(recs, k=3, seed=0)[0]
        tr, val = validation_split(recs, train, task, seed=0, fraction=0.3)
        assert not set(val) & set(test) and not set(tr) & set(val)
        assert sorted(set(tr) | set(val)) == sorted(train.tolist())
        assert {recs[i].category for i in val} == {recs[i].category for i in train}
        if task == "usmc":  # whole objects go to validation
            objs = lambda idx: {recs[i].meta["object_id"] for i in idx}  # noqa: E731
            assert not objs(tr) & objs(val)
    tr, val = validation_split(recs, np.arange(len(recs)), "ssmc", seed=0, fraction=0.0)
    assert val.size == 0 and tr.size == len(recs)


def test_validation_by_instance_holds_out_whole_instances():
    recs = make_material_strokes(6, n_categories=3, n_instances=4, n_objects=2, n_strokes=3, duration_s=0.02)
    instances = lambda idx: {recs[i].instance for i in idx}  # noqa: E731
    for task in ("ssmc", "usmc"):
        train, _ = ssmc_split(recs, seed=0) if task == "ssmc" else usmc_folds(recs, k=4, seed=0)[0]
        tr, val = validation_split(recs, train, task, seed=0, fraction=0.3, group_by_instance=True)
        assert val.size > 0 and not instances(tr) & instances(val)
        assert sorted(set(tr) | set(val)) == sorted(train.tolist())
        assert {recs[i].category for i in tr} == {recs[i].category for i in train}  # no class emptied
    with pytest.raises(ValueError, match="fine-grained"):
        validation_split(recs, np.arange(len(recs)), "fine", seed=0, group_by_instance=True)


def test_validation_fraction_holds_with_many_small_classes():
    recs = make_material_strokes(7, n_categories=4, n_instances=5, n_objects=1, n_strokes=4, duration_s=0.01)
    train, _ = fine_split(recs, seed=0)  # 20 instances, 3 training strokes each
    tr, val = validation_split(recs, train, "fine", seed=0, fraction=0.15)
    assert len(val) == round(0.15 * len(train))
    assert set(labels_of([recs[i] for i in tr], "fine")) == set(labels_of(recs, "fine"))  # no class emptied
