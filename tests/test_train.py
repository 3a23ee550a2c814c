"""Training loop (perception.train): learns, resumes to identical weights, saves loadable checkpoints."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import safetensors.torch
import torch

from perception.checkpoint import load_checkpoint
from perception.dataset import labels_of, ssmc_split, validation_split, write_dataset
from perception.features import FeatureConfig, collate, feature_dims, featurize, frame_clock_s
from perception.baselines import build_model
from perception.streams import MODALITIES
from perception.train import (TEST_CORRUPTION_SEED_OFFSET, StaleRunError, TrainConfig, TrainError,
                              class_balanced_batches, class_balanced_steps, corrupt_batch, cosine_lr, crop_in_time,
                              drop_modalities, featurize_records, length_grouped_batches, mask_features, mixup_batch,
                              model_overrides, predict, run_identity, scheduled_lr, strokes_fingerprint, task_split,
                              train, train_command)
from tests.test_dataset import make_material_strokes

TINY = {
    "touchformer": (("d_model", 16), ("n_heads", 2), ("n_layers", 1), ("gate_hidden", 8), ("emb_dim", 16)),
    "lstm": (("hidden", 16), ("n_steps", 16), ("emb_dim", 16)),
    "mtcnn": (("channels", 8), ("emb_dim", 16)),
}


@pytest.fixture(scope="module")
def toy():
    """Split and featurized toy materials (3 categories, chance 1/3)."""
    torch.set_num_threads(1)
    recs = make_material_strokes(0, n_categories=3, n_instances=2, n_objects=2, n_strokes=4, duration_s=0.3)
    train_idx, test_idx = ssmc_split(recs, seed=0)
    tr, val = validation_split(recs, train_idx, "ssmc", seed=0)
    cfg = TrainConfig().feature_config
    feats = featurize_records(recs, cfg)
    pick = lambda idx: [recs[i] for i in idx]  # noqa: E731
    return {"recs": recs, "tr": tr, "val": val, "test": test_idx, "feats": feats, "pick": pick}


def _config(model="touchformer", **changes):
    base = TrainConfig(model=model, epochs=6, batch_size=16, lr=3e-3, device="cpu", num_threads=1,
                       model_overrides=TINY["touchformer" if model.startswith("touchformer") else model])
    return dataclasses.replace(base, **changes)


def _fit(toy, config, out_dir, **kwargs):
    f = toy["feats"]
    return train(toy["pick"](toy["tr"]), toy["pick"](toy["val"]), config, out_dir, progress=False,
                 features_train=[f[i] for i in toy["tr"]], features_val=[f[i] for i in toy["val"]], **kwargs)


def _test_accuracy(toy, checkpoint_dir):
    ckpt = load_checkpoint(checkpoint_dir)
    preds = predict(ckpt.model, [toy["feats"][i] for i in toy["test"]], feature_dims(ckpt.feature_config),
                    stats=ckpt.norm_stats)
    y = [ckpt.class_names.index(l) for l in labels_of(toy["pick"](toy["test"]), "ssmc")]
    return float(np.mean(preds.pred == np.array(y)))


@pytest.mark.parametrize("model", ["touchformer", "lstm", "mtcnn"])
def test_training_beats_chance_on_held_out_strokes(toy, tmp_path, model):
    result = _fit(toy, _config(model), tmp_path / model)
    assert 1 <= result.best_epoch <= 6 and len(result.history) == 6
    assert result.history[-1]["train_loss"] < result.history[0]["train_loss"]
    assert _test_accuracy(toy, result.checkpoint_dir) >= 0.6  # chance is 1/3


def _stopped_after_two_epochs_then_resumed(toy, config, out_dir, **kwargs):
    """Train ``config`` into ``out_dir``, interrupted at the end of epoch 2, then run it again to resume
    (``kwargs`` to :func:`perception.train.train` both times)."""

    class Interrupt(Exception):
        pass

    def stop_after_two(row):
        if row["epoch"] == 2:
            raise Interrupt

    with pytest.raises(Interrupt):
        _fit(toy, config, out_dir, on_epoch_end=stop_after_two, **kwargs)
    return _fit(toy, config, out_dir, **kwargs)


def _resumed_run_ends_as_the_whole(toy, config, whole_dir, cut_dir) -> bool:
    """Train ``config`` into ``cut_dir`` interrupted after epoch 2 and resumed: whether it resumed at epoch 2 and
    ends with the resume state of the uninterrupted run in ``whole_dir``, tensor for tensor."""
    resumed = _stopped_after_two_epochs_then_resumed(toy, config, cut_dir)
    a = safetensors.torch.load_file(str(whole_dir / "resume" / "state.safetensors"))
    b = safetensors.torch.load_file(str(cut_dir / "resume" / "state.safetensors"))
    return resumed.resumed_from_epoch == 2 and all(torch.equal(a[k], b[k]) for k in a)


def test_resume_gives_identical_weights(toy, tmp_path):
    config = _config(epochs=3)
    full = _fit(toy, config, tmp_path / "full")

    resumed = _stopped_after_two_epochs_then_resumed(toy, config, tmp_path / "cut")
    assert resumed.resumed_from_epoch == 2 and full.resumed_from_epoch == 0
    assert resumed.best_epoch == full.best_epoch
    strip = lambda h: [{k: v for k, v in row.items() if k != "seconds"} for row in h]  # noqa: E731
    assert strip(resumed.history) == strip(full.history)
    for rel in ("resume/state.safetensors", "checkpoint/model.safetensors"):
        a = safetensors.torch.load_file(str(tmp_path / "full" / rel))
        b = safetensors.torch.load_file(str(tmp_path / "cut" / rel))
        assert a.keys() == b.keys()
        assert all(torch.equal(a[k], b[k]) for k in a), rel
    # a finished run is not retrained
    again = _fit(toy, config, tmp_path / "full")
    assert again.resumed_from_epoch == 3 and again.best_epoch == full.best_epoch
    # a resume folder from another config is refused
    with pytest.raises(TrainError, match="another config"):
        _fit(toy, dataclasses.replace(config, lr=1e-2), tmp_path / "full")


def test_weight_average_is_validated_kept_and_resumed(toy, tmp_path):
    plain = _fit(toy, _config(epochs=3), tmp_path / "plain")
    # a vanishing decay: the average is the live weights, so the run is the plain one
    copy = _fit(toy, _config(epochs=3, ema_decay=1e-12), tmp_path / "copy")
    assert [r["val_accuracy"] for r in copy.history] == [r["val_accuracy"] for r in plain.history]
    config = _config(epochs=3, ema_decay=0.9)
    full = _fit(toy, config, tmp_path / "full")
    state = safetensors.torch.load_file(str(tmp_path / "full" / "resume" / "state.safetensors"))
    live = {k[len("model."):]: v for k, v in state.items() if k.startswith("model.")}
    averaged = {k[len("ema.module."):]: v for k, v in state.items() if k.startswith("ema.module.")}
    assert averaged.keys() == live.keys()
    assert int(state["ema.n_averaged"]) == 3 * -(-len(toy["tr"]) // 16)  # once per training step
    assert any(not torch.equal(averaged[k], live[k]) for k in live)  # the average lags the live weights
    assert full.best_epoch == 3  # (seeded) so the checkpoint holds the last average, not the live weights
    kept = safetensors.torch.load_file(str(full.checkpoint_dir / "model.safetensors"))
    assert all(torch.equal(kept[k], averaged[k]) for k in kept)

    resumed = _stopped_after_two_epochs_then_resumed(toy, config, tmp_path / "cut")
    assert resumed.resumed_from_epoch == 2
    assert [r["val_accuracy"] for r in resumed.history] == [r["val_accuracy"] for r in full.history]
    again = safetensors.torch.load_file(str(tmp_path / "cut" / "resume" / "state.safetensors"))
    assert again.keys() == state.keys() and all(torch.equal(again[k], state[k]) for k in state)
    # the average is part of what a run is; off, it leaves stored runs' identities as they were
    assert "ema_decay" not in run_identity(_config(), 3)["config"]
    assert run_identity(config, 3)["config"]["ema_decay"] == 0.9
    with pytest.raises(TrainError, match="another config|weight average"):
        _fit(toy, config, tmp_path / "plain")
    with pytest.raises(ValueError, match="ema_decay"):
        TrainConfig(ema_decay=1.0)


def test_sharpness_aware_steps_learn_resume_exactly_and_name_the_run(toy, tmp_path):
    plain = _fit(toy, _config(epochs=3), tmp_path / "plain")
    config = _config(sam_rho=0.05)
    full = _fit(toy, config, tmp_path / "sam")
    assert full.history[-1]["train_loss"] < full.history[0]["train_loss"]
    assert _test_accuracy(toy, full.checkpoint_dir) >= 0.6  # chance is 1/3
    assert [r["train_loss"] for r in full.history[:3]] != [r["train_loss"] for r in plain.history]  # it steps otherwise
    assert _resumed_run_ends_as_the_whole(toy, config, tmp_path / "sam", tmp_path / "cut")
    # off, it leaves stored runs' identities as they were; on, it is part of what the run is
    assert "sam_rho" not in run_identity(_config(), 3)["config"]
    assert run_identity(config, 3)["config"]["sam_rho"] == 0.05
    with pytest.raises(TrainError, match="another config"):
        _fit(toy, _config(epochs=3, sam_rho=0.1), tmp_path / "plain")
    with pytest.raises(ValueError, match="sam_rho"):
        TrainConfig(sam_rho=-0.1)


def test_run_folder_resumes_whatever_its_device_and_thread_count(toy, tmp_path):
    config = _config(epochs=2)
    first = _fit(toy, config, tmp_path / "run")
    again = _fit(toy, dataclasses.replace(config, device="auto", num_threads=2), tmp_path / "run")
    assert again.resumed_from_epoch == 2 and again.history == first.history  # finished: not retrained
    assert not list(tmp_path.glob("run.stale-*"))
    with pytest.raises(TrainError, match="another config"):  # what is trained still counts
        _fit(toy, dataclasses.replace(config, device="auto", seed=1), tmp_path / "run")


def test_length_grouped_batches_cover_every_stroke_once_with_less_padding():
    rng = np.random.default_rng(0)
    lengths = rng.lognormal(4.0, 0.5, size=700).astype(int) + 20
    order = torch.randperm(700, generator=torch.Generator().manual_seed(1)).numpy()
    batches = length_grouped_batches(order, lengths, 32, torch.Generator().manual_seed(2))
    assert len(batches) == int(np.ceil(700 / 32))
    assert sorted(np.concatenate(batches).tolist()) == list(range(700))
    plain = [order[i:i + 32] for i in range(0, 700, 32)]
    padded = lambda bs: sum(len(b) * lengths[b].max() for b in bs) / lengths.sum()  # noqa: E731
    assert padded(plain) > 2.0 and padded(batches) < 1.25  # frames computed per real frame (2.15, 1.21)
    again = length_grouped_batches(order, lengths, 32, torch.Generator().manual_seed(2))
    assert all(np.array_equal(a, b) for a, b in zip(batches, again))


def test_class_balanced_batches_give_every_stroke_positives_once_per_epoch():
    rng = np.random.default_rng(0)
    labels = rng.integers(0, 42, size=756)  # the fine-grained task's shape: 42 labels, about 18 strokes each
    lengths = rng.lognormal(4.0, 0.5, size=756).astype(int) + 20
    order = torch.randperm(756, generator=torch.Generator().manual_seed(1)).numpy()
    plain = [order[i:i + 32] for i in range(0, 756, 32)]
    for by_length in (None, lengths):
        batches = class_balanced_batches(order, labels, 32, 4, torch.Generator().manual_seed(2), by_length)
        assert sorted(np.concatenate(batches).tolist()) == list(range(756))
        assert len(batches) == class_balanced_steps(labels, 32, 4) and all(len(b) <= 32 for b in batches)
        # a label met in a batch comes as a chunk: up to 4 strokes, and a stroke lacks company only where its
        # label has a single stroke left over after cutting it into chunks of 4
        alone = [i for b in batches for i in b if (labels[b] == labels[i]).sum() == 1]
        leftover = sum(1 for count in np.bincount(labels) if count % 4 == 1)
        assert len(alone) <= leftover
        again = class_balanced_batches(order, labels, 32, 4, torch.Generator().manual_seed(2), by_length)
        assert all(np.array_equal(a, b) for a, b in zip(batches, again))
    with_positive = lambda bs: np.mean([(labels[b] == labels[i]).sum() > 1 for b in bs for i in b])  # noqa: E731
    assert with_positive(plain) < 0.7 and with_positive(batches) > 0.9
    padded = lambda bs: sum(len(b) * lengths[b].max() for b in bs) / lengths.sum()  # noqa: E731
    assert padded(batches) < 0.8 * padded(plain)  # grouped by length as well


def test_class_balanced_training_learns_resumes_and_names_the_run(toy, tmp_path):
    config = _config(batch_per_class=4, group_by_length=True)
    full = _fit(toy, config, tmp_path / "pk")
    assert _test_accuracy(toy, full.checkpoint_dir) >= 0.6  # chance is 1/3
    assert _resumed_run_ends_as_the_whole(toy, config, tmp_path / "pk", tmp_path / "cut")
    assert "batch_per_class" not in run_identity(_config(), 3)["config"]
    assert run_identity(config, 3)["config"]["batch_per_class"] == 4
    for bad in (-1, 17, 2.5, True):
        with pytest.raises(ValueError, match="batch_per_class"):
            TrainConfig(batch_size=16, batch_per_class=bad)


def test_grouped_training_learns_and_resumes(toy, tmp_path):
    config = _config(epochs=4, group_by_length=True)
    result = _fit(toy, config, tmp_path / "grouped")
    assert _test_accuracy(toy, result.checkpoint_dir) >= 0.6
    assert TrainConfig.from_dict(config.to_dict()) == config
    again = _fit(toy, config, tmp_path / "grouped")
    assert again.resumed_from_epoch == 4 and again.best_epoch == result.best_epoch


def test_checkpoint_records_provenance(toy, tmp_path):
    result = _fit(toy, _config(epochs=1), tmp_path / "run", provenance={"command": "robotdemo train --x"})
    ckpt = load_checkpoint(result.checkpoint_dir)
    assert ckpt.model_name == "touchformer" and ckpt.class_names == ("cat0", "cat1", "cat2")
    assert ckpt.meta["command"] == "robotdemo train --x" and ckpt.meta["seed"] == 0
    assert TrainConfig.from_dict(ckpt.meta["train_config"]) == _config(epochs=1)
    assert json.loads((tmp_path / "run" / "train_result.json").read_text())["best_epoch"] == 1


def test_unknown_validation_label_is_refused(toy, tmp_path):
    with pytest.raises(TrainError, match="not among"):
        _fit(toy, _config(epochs=1), tmp_path / "x", class_names=("cat0", "cat1"))


def test_corruption_and_schedule():
    recs = make_material_strokes(1, n_categories=2, n_instances=1, n_objects=1, n_strokes=3, duration_s=0.2)
    cfg = TrainConfig().feature_config
    batch = collate([featurize(r, cfg) for r in recs], feature_dims(cfg))
    gen = torch.Generator().manual_seed(0)
    assert corrupt_batch(batch, 0.0, 1.0, gen) is batch
    hit = corrupt_batch(batch, 1.0, 1.0, gen)
    for m, x in hit.x.items():
        valid = ~batch.padding[m]
        assert not torch.equal(x[valid], batch.x[m][valid])
        assert torch.all(x[batch.padding[m]] == 0)
    assert cosine_lr(1e-3, 0, 100) == pytest.approx(1e-3)
    assert cosine_lr(1e-3, 50, 100) == pytest.approx(5e-4)
    assert cosine_lr(1e-3, 100, 100) == pytest.approx(0.0)


def test_warmup_rises_linearly_then_decays_and_is_validated():
    cfg = TrainConfig(epochs=10, lr=1e-3, warmup_epochs=2)
    steps = 4  # per epoch: warmup covers steps 0-7, the cosine the 32 after
    lrs = [scheduled_lr(cfg, k, steps) for k in range(40)]
    assert lrs[:8] == pytest.approx([1e-3 * (k + 1) / 8 for k in range(8)])
    assert lrs[8] == pytest.approx(1e-3) and lrs[24] == pytest.approx(5e-4)
    assert all(a >= b for a, b in zip(lrs[8:], lrs[9:]))
    assert scheduled_lr(TrainConfig(epochs=10, lr=1e-3), 0, steps) == pytest.approx(1e-3)  # no warmup: the paper's
    const = TrainConfig(epochs=10, lr=1e-3, warmup_epochs=1, schedule="constant")
    assert [scheduled_lr(const, k, steps) for k in (0, 3, 4, 39)] == pytest.approx([2.5e-4, 1e-3, 1e-3, 1e-3])
    with pytest.raises(ValueError, match="warmup_epochs"):
        TrainConfig(epochs=5, warmup_epochs=5)
    with pytest.raises(ValueError, match="label_smoothing"):
        TrainConfig(label_smoothing=1.0)


def test_time_crop_keeps_the_same_span_of_every_stream():
    rng = np.random.default_rng(0)
    feats = {"sound": rng.normal(size=(200, 3)), "normal": rng.normal(size=(50, 2)), "friction": None,
             "accel": rng.normal(size=(7, 2))}
    gen = torch.Generator().manual_seed(0)
    untouched = crop_in_time(feats, 1.0, gen)  # off: the same arrays, and no draw from the generator
    assert all(untouched[m] is feats[m] for m in feats)
    assert torch.equal(gen.get_state(), torch.Generator().manual_seed(0).get_state())
    spans = []
    for _ in range(50):
        out = crop_in_time(feats, 0.5, gen)
        assert out["friction"] is None
        for m in ("sound", "normal", "accel"):
            f, c = feats[m], out[m]
            assert 1 <= len(c) <= len(f)
            start = next(i for i in range(len(f) - len(c) + 1) if np.array_equal(f[i:i + len(c)], c))  # a window
            spans.append((m, start / len(f), len(c) / len(f)))
        sound, normal = spans[-3][1:], spans[-2][1:]
        assert abs(sound[0] - normal[0]) <= 1 / 50 and abs(sound[1] - normal[1]) <= 2 / 50  # same span
        assert sound[1] >= 0.5 - 1e-9
    shares = [s for m, _, s in spans if m == "sound"]
    assert min(shares) < 0.6 and max(shares) > 0.9  # shares spread over [0.5, 1]
    with pytest.raises(ValueError, match="time_crop"):
        TrainConfig(time_crop=0.0)


def _features_one_stream_missing(seed: int, n_categories: int, n_strokes: int):
    """Toy strokes, the default front end and their features, with stroke 0's acceleration missing."""
    recs = make_material_strokes(seed, n_categories=n_categories, n_instances=2, n_objects=2, n_strokes=n_strokes,
                                 duration_s=0.2)
    cfg = TrainConfig().feature_config
    feats = [featurize(r, cfg) for r in recs]
    feats[0] = {**feats[0], "accel": None}
    return recs, cfg, feats


def test_feature_mask_zeroes_one_channel_band_and_one_step_span_of_valid_steps():
    _, cfg, feats = _features_one_stream_missing(3, n_categories=2, n_strokes=8)  # a missing stream stays missing
    batch = collate(feats, feature_dims(cfg))
    gen = torch.Generator().manual_seed(0)
    assert mask_features(batch, 0.0, gen) is batch  # off: the batch as it is, and no draw from the generator
    assert torch.equal(gen.get_state(), torch.Generator().manual_seed(0).get_state())
    masked = mask_features(batch, 0.5, gen)
    assert masked.padding is batch.padding and masked.present is batch.present
    widths = []
    for m in batch.x:
        x, y, pad = batch.x[m], masked.x[m], batch.padding[m]
        assert torch.equal(y[pad], x[pad])  # padding (and missing streams) untouched
        assert torch.all((y == x) | (y == 0))  # only zeroes
        for b in range(x.shape[0]):
            if not batch.present[m][b]:
                continue
            zero = (y[b] == 0) & (x[b] != 0)  # (T, C) what the mask removed
            valid = int((~pad[b]).sum())
            rows, cols = zero[:valid].all(dim=1), zero[:valid].all(dim=0)
            n_rows, n_cols = int(rows.sum()), int(cols.sum())
            assert n_rows <= 0.5 * valid and n_cols <= 0.5 * x.shape[2]
            for band in (rows, cols):  # each band is one run of consecutive indices
                idx = torch.nonzero(band).flatten()
                assert len(idx) == 0 or int(idx[-1] - idx[0]) + 1 == len(idx)
            outside = ~(rows[:, None] | cols[None, :])
            assert torch.equal(y[b, :valid][outside], x[b, :valid][outside])  # the rest as it was
            widths.append((n_rows / valid, n_cols / x.shape[2]))
    assert max(w for w, _ in widths) > 0.3 and max(w for _, w in widths) > 0.3  # bands reach up to the share
    assert min(w for w, _ in widths) < 0.1
    again = mask_features(batch, 0.5, torch.Generator().manual_seed(0))
    assert all(torch.equal(again.x[m], masked.x[m]) for m in batch.x)  # seeded
    assert "feature_mask" not in run_identity(TrainConfig(), 3)["config"]  # off: stored runs stay valid
    assert run_identity(TrainConfig(feature_mask=0.2), 3)["config"]["feature_mask"] == 0.2
    with pytest.raises(ValueError, match="feature_mask"):
        TrainConfig(feature_mask=1.0)


def test_mixup_blends_each_stroke_with_a_partner_at_one_share_and_keeps_the_union_of_steps():
    recs, cfg, feats = _features_one_stream_missing(4, n_categories=3, n_strokes=4)  # present where either has it
    feats[1] = {m: (None if f is None else f[: max(1, len(f) // 2)]) for m, f in feats[1].items()}  # shorter
    names = sorted(set(labels_of(recs, "ssmc")))
    batch = collate(feats, feature_dims(cfg), labels=[names.index(c) for c in labels_of(recs, "ssmc")])
    gen = torch.Generator().manual_seed(0)
    off = mixup_batch(batch, 0.0, gen)
    assert off.batch is batch and off.share == 1.0 and torch.equal(off.partner_labels, batch.labels)
    assert torch.equal(gen.get_state(), torch.Generator().manual_seed(0).get_state())  # off: no draw
    shares, partners_differ = [], False
    for seed in range(20):
        mixed = mixup_batch(batch, 0.4, torch.Generator().manual_seed(seed))
        assert 0.5 <= mixed.share <= 1.0
        shares.append(mixed.share)
        for m in batch.x:
            x, y = batch.x[m], mixed.batch.x[m]
            assert torch.equal(mixed.batch.padding[m] | batch.padding[m], batch.padding[m])  # no step lost
            assert bool(torch.all(mixed.batch.present[m] >= batch.present[m]))
        assert torch.equal(mixed.batch.labels, batch.labels)  # the larger share keeps its label
        partners_differ |= bool(torch.any(mixed.partner_labels != batch.labels))
    assert partners_differ and min(shares) < 0.75 and max(shares) > 0.9  # Beta(0.4, 0.4): wide spread of shares
    again = mixup_batch(batch, 0.4, torch.Generator().manual_seed(3))
    mixed = mixup_batch(batch, 0.4, torch.Generator().manual_seed(3))
    assert again.share == mixed.share and all(torch.equal(again.batch.x[m], mixed.batch.x[m]) for m in batch.x)
    # the blend itself: with the partner order drawn the same way, x' = share x + (1 - share) x[partner]
    gen = torch.Generator().manual_seed(3)
    torch.rand(1, generator=gen, dtype=torch.float64)
    partner = torch.randperm(batch.batch_size, generator=gen)
    for m in batch.x:
        expected = mixed.share * batch.x[m] + (1.0 - mixed.share) * batch.x[m][partner]
        assert torch.allclose(mixed.batch.x[m], expected)
        assert torch.equal(mixed.batch.padding[m], batch.padding[m] & batch.padding[m][partner])
    assert torch.equal(mixed.partner_labels, batch.labels[partner])
    with pytest.raises(ValueError, match="labelled"):
        mixup_batch(dataclasses.replace(batch, labels=None), 0.4, gen)
    assert "mixup_alpha" not in run_identity(TrainConfig(), 3)["config"]  # off: stored runs stay valid
    assert run_identity(TrainConfig(mixup_alpha=0.2), 3)["config"]["mixup_alpha"] == 0.2
    for bad in (-0.1, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="mixup_alpha"):
            TrainConfig(mixup_alpha=bad)


def test_modality_dropout_marks_streams_missing_and_keeps_one():
    recs = make_material_strokes(2, n_categories=2, n_instances=2, n_objects=2, n_strokes=16, duration_s=0.2)
    cfg = TrainConfig().feature_config
    batch = collate([featurize(r, cfg) for r in recs], feature_dims(cfg))
    gen = torch.Generator().manual_seed(0)
    assert drop_modalities(batch, 0.0, gen) is batch
    dropped = drop_modalities(batch, 0.9, gen)
    before, after = batch.present_matrix(), dropped.present_matrix()
    assert torch.all(after.sum(dim=1) >= 1)  # every stroke keeps a stream
    assert torch.all(before | ~after) and after.sum() < before.sum() * 0.5  # only removes, and many at 0.9
    for i, m in enumerate(batch.x):
        gone = before[:, i] & ~after[:, i]
        assert torch.all(dropped.x[m][gone] == 0) and torch.all(dropped.padding[m][gone])
        kept = after[:, i]
        assert torch.equal(dropped.x[m][kept], batch.x[m][kept])
        assert torch.equal(dropped.padding[m][kept], batch.padding[m][kept])
    again = drop_modalities(batch, 0.9, torch.Generator().manual_seed(0))
    assert torch.equal(again.present_matrix(), after)
    with pytest.raises(ValueError, match="modality_dropout"):
        TrainConfig(modality_dropout=1.0)


def test_modality_dropout_training_learns_and_predicts_without_sound(toy, tmp_path):
    config = _config(epochs=6, modality_dropout=0.3)
    result = _fit(toy, config, tmp_path / "md")
    assert _test_accuracy(toy, result.checkpoint_dir) >= 0.6
    ckpt = load_checkpoint(result.checkpoint_dir)
    assert TrainConfig.from_dict(ckpt.meta["train_config"]).modality_dropout == 0.3
    preds = predict(ckpt.model, [toy["feats"][i] for i in toy["test"]], feature_dims(ckpt.feature_config),
                    stats=ckpt.norm_stats, drop=("sound",))
    assert np.all(np.isfinite(preds.logits)) and np.all(preds.alphas[:, 0] == 0)


def test_mixup_training_learns_and_records_its_alpha(toy, tmp_path):
    result = _fit(toy, _config(epochs=6, mixup_alpha=0.4), tmp_path / "mix")
    assert _test_accuracy(toy, result.checkpoint_dir) >= 0.6  # chance is 1/3
    assert all(np.isfinite(row["train_loss"]) for row in result.history)
    ckpt = load_checkpoint(result.checkpoint_dir)
    assert TrainConfig.from_dict(ckpt.meta["train_config"]).mixup_alpha == 0.4


def test_resume_state_from_before_a_config_field_existed_is_resumed(toy, tmp_path):
    config = _config(epochs=2)
    full = _fit(toy, config, tmp_path / "run")
    state = tmp_path / "run" / "resume" / "state.json"
    record = json.loads(state.read_text())
    del record["config"]["modality_dropout"]  # as written before the field was added
    del record["data_sha256"]  # as written before runs fingerprinted their strokes
    del record["model_config"]["residual_base"]  # a model field added since, at its default
    state.write_text(json.dumps(record))
    again = _fit(toy, config, tmp_path / "run")
    assert again.resumed_from_epoch == 2 and again.best_epoch == full.best_epoch
    # a model field added since whose saved value was not the default: that run is another one
    record = json.loads(state.read_text())
    del record["model_config"]["final_norm"]  # saved before final_norm existed: it had the LayerNorm
    state.write_text(json.dumps(record))
    with pytest.raises(TrainError, match="another config"):
        _fit(toy, config, tmp_path / "run")


def test_run_folder_is_not_reused_after_a_model_default_changed(toy, tmp_path, monkeypatch):
    config = _config(epochs=1)
    _fit(toy, config, tmp_path / "run")
    state = tmp_path / "run" / "resume" / "state.json"
    record = json.loads(state.read_text())
    assert record["model_config"]["final_norm"] is False and record["model_config"]["d_model"] == 16
    # a default that keeps the weights' shapes, changed since the run was saved
    record["model_config"]["gate_temperature"] = 0.5
    state.write_text(json.dumps(record))
    with pytest.raises(TrainError, match="another config, class list or data"):
        _fit(toy, config, tmp_path / "run")
    # a record from before records kept the model config is checked against the run's checkpoint
    del record["model_config"]
    state.write_text(json.dumps(record))
    again = _fit(toy, config, tmp_path / "run")
    assert again.resumed_from_epoch == 1
    ckpt_json = tmp_path / "run" / "checkpoint" / "config.json"
    saved = json.loads(ckpt_json.read_text())
    saved["model_config"]["gate_temperature"] = 0.5
    ckpt_json.write_text(json.dumps(saved))
    with pytest.raises(TrainError, match="another config, class list or data"):
        _fit(toy, config, tmp_path / "run")
    # a default that changes the weights (a closing LayerNorm) is named as another architecture
    import perception.train as train_module
    real_build = train_module.build_model
    monkeypatch.setattr(train_module, "build_model",
                        lambda name, in_dims, n, **kw: real_build(name, in_dims, n, **{**kw, "final_norm": True}))
    with pytest.raises(StaleRunError, match=r"another architecture \((Missing|Unexpected) key"):
        _fit(toy, config, tmp_path / "run")
    # the evaluation's cache keeps such a folder aside and trains the run afresh
    fresh = _fit(toy, config, tmp_path / "run", replace_stale=True)
    assert fresh.resumed_from_epoch == 0 and (tmp_path / "run.stale-1" / "resume" / "state.json").is_file()
    assert json.loads((tmp_path / "run" / "resume" / "state.json").read_text())["model_config"]["final_norm"] is True
    again = _fit(toy, config, tmp_path / "run", replace_stale=True)  # now the same run: resumed, nothing moved
    assert again.resumed_from_epoch == 1 and not (tmp_path / "run.stale-2").exists()


def test_run_folder_is_not_reused_for_other_strokes_of_the_same_count(toy, tmp_path):
    config = _config(epochs=1)
    _fit(toy, config, tmp_path / "run")
    other = make_material_strokes(1, n_categories=3, n_instances=2, n_objects=2, n_strokes=4, duration_s=0.3)
    assert len(other) == len(toy["recs"])
    pick = lambda idx: [other[i] for i in idx]  # noqa: E731
    with pytest.raises(TrainError, match="another config, class list or data"):
        train(pick(toy["tr"]), pick(toy["val"]), config, tmp_path / "run", progress=False)
    # the fingerprint follows the samples, not only the labels
    changed = [dataclasses.replace(r) for r in toy["pick"](toy["tr"])]
    stream = changed[0].streams["normal"]
    changed[0] = dataclasses.replace(changed[0], streams={**changed[0].streams, "normal": dataclasses.replace(
        stream, data=stream.data + 1.0)})
    assert strokes_fingerprint(changed) != strokes_fingerprint(toy["pick"](toy["tr"]))
    assert strokes_fingerprint(toy["pick"](toy["tr"])) == strokes_fingerprint(toy["pick"](toy["tr"]))


def test_unknown_model_option_names_the_field():
    with pytest.raises(ValueError, match="unknown model option.*'d_modle'"):
        build_model("touchformer", (4, 4, 4, 4), 3, d_modle=32)


def test_time_bias_takes_its_clock_from_the_front_ends_never_from_an_option():
    fast = dataclasses.replace(FeatureConfig().accel, hop_s=0.064)
    cfg = TrainConfig(model_overrides=(("time_bias", True),),
                      feature_config=dataclasses.replace(FeatureConfig(), accel=fast))
    clock = model_overrides(cfg)["frame_clock_s"]
    assert clock == frame_clock_s(cfg.feature_config) and clock[MODALITIES.index("accel")][0] == 0.064
    assert run_identity(cfg, 3)["model_config"]["frame_clock_s"] == [list(c) for c in clock]
    assert "frame_clock_s" not in model_overrides(TrainConfig())
    default = run_identity(TrainConfig(), 3)["model_config"]
    assert "time_bias" not in default and "frame_clock_s" not in default  # the stored runs' identity is kept
    with pytest.raises(ValueError, match="frame_clock_s comes from the data"):
        TrainConfig(model_overrides=(("frame_clock_s", ((0.1, 0.1),) * 4),))


# sha256 (first 16 hex digits) of run_identity(TrainConfig(model=M, task="ssmc", group_by_length=True), 7) as
# JSON with sorted keys, from the code that trained the committed run store (reports/outcomes.jsonl, at 0822a36)
STORED_RUN_IDENTITIES = {"touchformer": "8946364544825d22", "touchformer_soft": "13612aaf14802193",
                         "touchformer_fusion": "5b55cdedb2fb7d96", "touchformer_mag": "77c986df995cc705",
                         "lstm": "0edb594cc79ff6c6", "mtcnn": "381ced0842f86149"}


@pytest.mark.parametrize("model", sorted(STORED_RUN_IDENTITIES))
def test_the_evaluations_runs_keep_the_identity_the_run_store_was_written_with(model):
    # A field added to a config since must be left out of the identity at the value the stored runs trained with
    # (TRAIN_IDENTITY_OMITS, SPECTRAL_IDENTITY_OMITS, a model config's IDENTITY_OMITS); otherwise every stored run
    # of that model turns stale and `robotdemo evaluate` trains it again (session 47's frame_clock_s, omitted at
    # () while its JSON is [], did that to every TouchFormer run until session 52). Change a pin here only with
    # a change meant to make the stored runs stale.
    import hashlib

    identity = run_identity(TrainConfig(model=model, task="ssmc", group_by_length=True), 7)
    digest = hashlib.sha256(json.dumps(identity, sort_keys=True).encode()).hexdigest()[:16]
    assert digest == STORED_RUN_IDENTITIES[model], json.dumps(identity, sort_keys=True)


def test_config_validation_and_round_trip():
    with pytest.raises(ValueError, match="unknown model"):
        TrainConfig(model="nope")
    with pytest.raises(ValueError, match="task"):
        TrainConfig(task="xyz")
    cfg = TrainConfig(model="mtcnn", task="fine", model_overrides=(("dilations", (1, 2)),))
    assert TrainConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg


def test_train_command_usmc(tmp_path):
    recs = make_material_strokes(2, n_categories=2, n_instances=2, n_objects=2, n_strokes=2, duration_s=0.2)
    write_dataset(tmp_path / "ds", recs, env="clean", seed=2)
    metrics = train_command(tmp_path / "ds", tmp_path / "run", _config(task="usmc", epochs=1), fold=1, n_folds=2,
                            command="robotdemo train", progress=False)
    assert metrics["n_train"] + metrics["n_val"] + metrics["n_test"] == len(recs)
    assert 0.0 <= metrics["test_accuracy"] <= 1.0 and len(metrics["data_manifest_sha256"]) == 64
    assert json.loads((tmp_path / "run" / "metrics.json").read_text())["fold"] == 1
    # the temperature fitted on the validation strokes is stored with the checkpoint, and lowers their NLL
    assert load_checkpoint(metrics["checkpoint_dir"]).temperature == pytest.approx(metrics["temperature"])
    assert metrics["val_nll_calibrated"] <= metrics["val_nll"] + 1e-9


@pytest.mark.parametrize("task", ["ssmc", "fine"])
def test_split_by_object_keeps_objects_on_one_side(task):
    recs = make_material_strokes(4, n_categories=2, n_instances=2, n_objects=6, n_strokes=2, duration_s=0.02)
    objects = lambda idx: {(recs[i].instance, recs[i].meta["object_id"]) for i in idx}  # noqa: E731
    train_idx, val_idx, test_idx = task_split(recs, TrainConfig(task=task, split_by_object=True))
    assert sorted(np.concatenate([train_idx, val_idx, test_idx]).tolist()) == list(range(len(recs)))
    assert len(val_idx) and len(test_idx)
    assert not objects(train_idx) & objects(test_idx) and not objects(train_idx) & objects(val_idx)
    assert not objects(val_idx) & objects(test_idx)
    # the paper's split by stroke shares objects between the sides
    train_s, _, test_s = task_split(recs, TrainConfig(task=task))
    assert objects(train_s) & objects(test_s)


def test_val_by_instance_validates_on_instances_not_trained_on():
    recs = make_material_strokes(4, n_categories=2, n_instances=5, n_objects=2, n_strokes=2, duration_s=0.02)
    instances = lambda idx: {recs[i].instance for i in idx}  # noqa: E731
    config = TrainConfig(task="usmc", val_by_instance=True, val_fraction=0.3)
    train_idx, val_idx, test_idx = task_split(recs, config)
    assert sorted(np.concatenate([train_idx, val_idx, test_idx]).tolist()) == list(range(len(recs)))
    assert len(val_idx) and not instances(train_idx) & instances(val_idx)
    # by default USMC validation shares instances (not objects) with training
    train_d, val_d, _ = task_split(recs, TrainConfig(task="usmc", val_fraction=0.3))
    assert instances(train_d) & instances(val_d)


@pytest.mark.parametrize("task", ["ssmc", "usmc"])
def test_train_fraction_keeps_a_stratified_share_and_the_same_validation_and_test(task):
    recs = make_material_strokes(5, n_categories=3, n_instances=5, n_objects=2, n_strokes=4, duration_s=0.02)
    full_tr, full_val, full_test = task_split(recs, TrainConfig(task=task))
    tr, val, test = task_split(recs, TrainConfig(task=task, train_fraction=0.5))
    assert np.array_equal(val, full_val) and np.array_equal(test, full_test)
    assert set(tr) < set(full_tr) and len(tr) == pytest.approx(0.5 * len(full_tr), abs=1)
    counts = lambda idx: np.unique(labels_of([recs[i] for i in idx], task), return_counts=True)  # noqa: E731
    (names_full, n_full), (names_half, n_half) = counts(full_tr), counts(tr)
    assert list(names_half) == list(names_full) and np.all(np.abs(n_half - n_full / 2) <= 1)
    assert np.array_equal(task_split(recs, TrainConfig(task=task, train_fraction=0.5))[0], tr)  # seeded
    with pytest.raises(ValueError, match="train_fraction"):
        TrainConfig(train_fraction=0.0)
    with pytest.raises(TrainError, match="train_fraction 0.01"):
        task_split(recs, TrainConfig(task=task, train_fraction=0.01))


def test_classifier_bench_scores_the_checkpoints_own_test_part(tmp_path):
    from robotdemo.benchmarks.classifier_bench import run_classifier_benchmark
    from robotdemo.errors import RobotDemoError

    real = {"cat0": "metal", "cat1": "wood", "cat2": "stone"}  # the robot's classifier wants catalogue names
    recs = [dataclasses.replace(r, category=real[r.category], instance=real[r.category] + r.instance[4:],
                                combustible=real[r.category] == "wood")
            for r in make_material_strokes(5, n_categories=3, n_instances=2, n_objects=4, n_strokes=2, duration_s=0.2)]
    write_dataset(tmp_path / "ds", recs, env="clean", seed=5)
    metrics = train_command(tmp_path / "ds", tmp_path / "run", _config(epochs=2, split_by_object=True),
                            progress=False)
    result = run_classifier_benchmark(tmp_path / "run" / "checkpoint", tmp_path / "ds")
    assert result["n_test"] == metrics["n_test"] and result["split_by_object"]
    assert result["category_accuracy"] == pytest.approx(metrics["test_accuracy"], abs=1e-4)
    assert 0.0 <= result["zone_accuracy"] <= 1.0
    band = result["by_threshold"][0]
    assert 0.0 <= band["share_at_or_above"] <= 1.0
    write_dataset(tmp_path / "other", recs[:-1], env="clean", seed=5)
    with pytest.raises(RobotDemoError, match="trained on another data set"):
        run_classifier_benchmark(tmp_path / "run" / "checkpoint", tmp_path / "other")


def test_train_cli_model_option_errors_are_one_line(tmp_path, capsys):
    from robotdemo.cli import _model_option, main

    assert _model_option("d_model=32") == ("d_model", 32)
    assert _model_option("kernel_sizes=(3, 3, 3, 3)") == ("kernel_sizes", (3, 3, 3, 3))
    assert _model_option("gate_pool='hidden'") == ("gate_pool", "hidden")
    for bad, message in (("d_model", "expects KEY=VALUE"), ("d_model=wide", "not a number")):
        code = main(["train", "--data", str(tmp_path), "--out", str(tmp_path / "o"), "--model-option", bad])
        err = capsys.readouterr().err
        assert code == 2 and message in err and len(err.strip().splitlines()) == 1


def _train_small_mtcnn_by_cli(tmp_path, seed, *options):
    """``robotdemo train`` of a small MTCNN on toy materials written to ``tmp_path/ds`` (3 categories, 2
    instances each, seeded), out to ``tmp_path/run``; returns the exit code."""
    from robotdemo.cli import main

    recs = make_material_strokes(seed, n_categories=3, n_instances=2, n_objects=2, n_strokes=3, duration_s=0.2)
    write_dataset(tmp_path / "ds", recs, env="clean", seed=seed)
    return main(["train", "--data", str(tmp_path / "ds"), "--out", str(tmp_path / "run"), "--model", "mtcnn",
                 "--model-option", "channels=8", "--quiet", *options])


def test_train_cli_corruption_ratio_corrupts_the_test_strokes_too(tmp_path, capsys):
    from perception.dataset import load_dataset
    from robotdemo.cli import main

    code = _train_small_mtcnn_by_cli(tmp_path, 6, "--epochs", "2", "--corruption-ratio", "1.0")
    capsys.readouterr()
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert code == 0 and metrics["corruption_ratio"] == 1.0 and metrics["corruption_std"] == 1.0
    # the reported test accuracy is that of the test strokes with every sensor corrupted, as evaluate's curve
    data = load_dataset(tmp_path / "ds").records
    _, _, test_idx = task_split(data, TrainConfig(task="ssmc", seed=0))
    ckpt = load_checkpoint(metrics["checkpoint_dir"])
    y = np.array([ckpt.class_names.index(l) for l in labels_of([data[i] for i in test_idx], "ssmc")])
    feats = featurize_records([data[i] for i in test_idx], ckpt.feature_config)
    preds = {ratio: predict(ckpt.model, feats, feature_dims(ckpt.feature_config), stats=ckpt.norm_stats,
                            corruption_ratio=ratio, seed=0 + TEST_CORRUPTION_SEED_OFFSET)  # seed 0: the run's
             for ratio in (0.0, 1.0)}
    assert metrics["test_accuracy"] == pytest.approx(float(np.mean(preds[1.0].pred == y)))
    assert not np.allclose(preds[0.0].logits, preds[1.0].logits)  # the corruption reached the strokes
    for bad, message in ((["--corruption-ratio", "1.5"], "corruption_ratio must lie in [0, 1]"),
                         (["--corruption-std", "-1"], "corruption_std must be >= 0")):
        code = main(["train", "--data", str(tmp_path / "ds"), "--out", str(tmp_path / "bad"), *bad])
        err = capsys.readouterr().err
        assert code == 2 and message in err and len(err.strip().splitlines()) == 1


def test_train_cli_offers_every_registered_model():
    from perception.baselines import MODEL_REGISTRY
    from robotdemo.cli import build_parser

    for name in MODEL_REGISTRY:
        args = build_parser().parse_args(["train", "--data", "d", "--out", "o", "--model", name])
        assert args.model == name
    with pytest.raises(SystemExit):
        build_parser().parse_args(["train", "--data", "d", "--out", "o", "--model", "transformer"])


def test_training_on_a_subset_of_sensors_ignores_the_others(toy, tmp_path):
    fc = dataclasses.replace(TrainConfig().feature_config, modalities=("friction", "normal"))
    assert fc.modalities == ("normal", "friction")  # kept in MODALITIES order
    result = _fit(toy, _config(epochs=6, feature_config=fc), tmp_path / "nf")
    ckpt = load_checkpoint(result.checkpoint_dir)
    assert ckpt.feature_config.modalities == ("normal", "friction")
    assert _test_accuracy(toy, result.checkpoint_dir) >= 0.6  # the taxels alone tell the toy categories apart
    test = toy["pick"](toy["test"])
    feats = [featurize(rec, ckpt.feature_config) for rec in test]
    assert all(f["sound"] is None and f["accel"] is None and f["normal"] is not None for f in feats)
    # fed through the checkpoint's own front end, the sound and acceleration streams change nothing
    silenced = [dataclasses.replace(rec, streams={**rec.streams, "sound": None, "accel": None}) for rec in test]
    dims = feature_dims(ckpt.feature_config)
    a = predict(ckpt.model, feats, dims, stats=ckpt.norm_stats)
    b = predict(ckpt.model, [featurize(rec, ckpt.feature_config) for rec in silenced], dims, stats=ckpt.norm_stats)
    np.testing.assert_array_equal(a.logits, b.logits)
    assert np.all(a.alphas[:, [0, 3]] == 0)  # sound and accel carry no weight


def test_modalities_option_is_validated_and_old_configs_keep_all_four(tmp_path, capsys):
    from perception.checkpoint import config_from_dict
    from robotdemo.cli import main

    for bad in ((), ("sound", "smell"), ("sound", "sound")):
        with pytest.raises(ValueError, match="modalities must be distinct names"):
            FeatureConfig(modalities=bad)
    old = {k: v for k, v in dataclasses.asdict(FeatureConfig()).items() if k != "modalities"}  # as saved before
    assert config_from_dict(FeatureConfig, old).modalities == MODALITIES
    code = main(["train", "--data", str(tmp_path), "--out", str(tmp_path / "o"), "--modalities", "sound,smell"])
    err = capsys.readouterr().err
    assert code == 2 and "modalities must be distinct names" in err and len(err.strip().splitlines()) == 1


def test_unimodal_heads_enter_the_training_loss_and_the_checkpoint(toy, tmp_path):
    # the per-sensor heads' cross-entropy is part of the training loss (so it exceeds eq. 14's terms); the
    # heads are saved with the rest, and the checkpoint loads with them
    overrides = TINY["touchformer"] + (("unimodal_lambda", 1.0),)
    result = _fit(toy, _config(model_overrides=overrides), tmp_path / "uni")
    first = result.history[0]
    assert first["train_loss"] > first["train_ce"] + 0.1 * first["train_contrastive"] + 0.5
    assert result.history[-1]["train_loss"] < first["train_loss"]
    assert load_checkpoint(result.checkpoint_dir).model.unimodal_heads is not None


def test_run_identity_leaves_out_a_field_added_since_at_what_stored_runs_did():
    # the run store names outcomes by run_identity: a field added later (unimodal_lambda) must not rename every
    # stored run at its default, and must tell a run that sets it apart
    base = _config()
    plain = run_identity(base, 3)
    assert "unimodal_lambda" not in plain["model_config"] and "final_norm" in plain["model_config"]
    aux = run_identity(dataclasses.replace(base, model_overrides=base.model_overrides + (("unimodal_lambda", 1.0),)), 3)
    assert aux["model_config"]["unimodal_lambda"] == 1.0
    assert {**aux["model_config"], "unimodal_lambda": 0.0} != plain["model_config"]
    assert {k: v for k, v in aux["model_config"].items() if k != "unimodal_lambda"} == plain["model_config"]


def test_train_cli_accel_axes_gives_a_checkpoint_with_the_split_front_end(tmp_path, capsys):
    from perception.checkpoint import config_from_dict
    from perception.dataset import load_dataset
    from perception.features import ACCEL_NORMAL_TANGENTIAL
    from robotdemo.cli import main

    code = _train_small_mtcnn_by_cli(tmp_path, 8, "--epochs", "1", "--accel-axes", "normal-tangential")
    capsys.readouterr()
    assert code == 0
    ckpt = load_checkpoint(json.loads((tmp_path / "run" / "metrics.json").read_text())["checkpoint_dir"])
    assert ckpt.feature_config.accel.channel_groups == ACCEL_NORMAL_TANGENTIAL
    assert feature_dims(ckpt.feature_config)["accel"] == 32
    feats = featurize_records(load_dataset(tmp_path / "ds").records[:4], ckpt.feature_config)
    assert predict(ckpt.model, feats, feature_dims(ckpt.feature_config), stats=ckpt.norm_stats).pred.shape == (4,)
    # a front end saved before the field existed sums the three axes, as it did then
    old = dataclasses.asdict(FeatureConfig())
    del old["accel"]["channel_groups"]
    assert config_from_dict(FeatureConfig, old) == FeatureConfig()
    # the run's identity names the split front end; the default's leaves the field out, as stored runs have it
    split = run_identity(TrainConfig(feature_config=ckpt.feature_config), 3)["config"]["feature_config"]
    assert split["accel"]["channel_groups"] == [[2], [0, 1]]
    plain = run_identity(TrainConfig(), 3)["config"]["feature_config"]
    assert "channel_groups" not in plain["accel"] and "channel_groups" not in plain["sound"]
    with pytest.raises(SystemExit) as exit_:
        main(["train", "--data", str(tmp_path / "ds"), "--out", str(tmp_path / "bad"), "--accel-axes", "xyz"])
    assert exit_.value.code == 2 and "invalid choice: 'xyz'" in capsys.readouterr().err


def _object_parameters(records, seed=0):
    """Toy material parameters: the category sets the first column, each object draws the other two."""
    rng = np.random.default_rng(seed)
    per_object = {}
    rows = []
    for r in records:
        obj = r.meta["object_id"]
        if obj not in per_object:
            per_object[obj] = [float(r.category[-1]), *rng.normal(size=2)]
        rows.append(per_object[obj])
    return np.array(rows)


def test_aux_parameter_head_learns_the_parameters_resumes_and_stays_out_of_the_checkpoint(toy, tmp_path):
    targets = _object_parameters(toy["pick"](toy["tr"]))
    config = _config(epochs=3, aux_parameters_weight=1.0)
    full = _fit(toy, config, tmp_path / "full", aux_targets_train=targets)
    mse = [row["train_aux_mse"] for row in full.history]
    assert mse[-1] < mse[0] < 2.0  # z-scored targets: the head starts near their variance and learns them
    state = safetensors.torch.load_file(str(tmp_path / "full" / "resume" / "state.safetensors"))
    assert state["aux_head.weight"].shape == (3, 16)  # P parameters from the E = 16 embedding
    kept = load_checkpoint(full.checkpoint_dir)  # the model's own weights only: loads as any checkpoint
    assert not any("aux" in k for k in safetensors.torch.load_file(str(full.checkpoint_dir / "model.safetensors")))
    assert kept.model_name == "touchformer"

    resumed = _stopped_after_two_epochs_then_resumed(toy, config, tmp_path / "cut", aux_targets_train=targets)
    assert resumed.resumed_from_epoch == 2
    assert [r["train_aux_mse"] for r in resumed.history] == mse
    again = safetensors.torch.load_file(str(tmp_path / "cut" / "resume" / "state.safetensors"))
    assert all(torch.equal(again[k], state[k]) for k in state)
    # other targets are another run (a shift alone is not: the targets are z-scored); the weight is part of a
    # run's identity, left out at 0
    assert _fit(toy, config, tmp_path / "full", aux_targets_train=targets + 1.0).resumed_from_epoch == 3
    with pytest.raises(TrainError, match="another config"):
        _fit(toy, config, tmp_path / "full", aux_targets_train=targets * np.array([1.0, 1.0, -1.0]))
    assert "aux_parameters_weight" not in run_identity(_config(), 3)["config"]
    assert run_identity(config, 3)["config"]["aux_parameters_weight"] == 1.0
    plain = _fit(toy, _config(epochs=3), tmp_path / "plain", aux_targets_train=targets)  # read only when on
    assert "train_aux_mse" not in plain.history[0]


def test_aux_parameter_head_refuses_missing_or_bad_targets(toy, tmp_path):
    config = _config(epochs=1, aux_parameters_weight=0.5)
    targets = _object_parameters(toy["pick"](toy["tr"]))
    with pytest.raises(TrainError, match="needs each training stroke's material parameters"):
        _fit(toy, config, tmp_path / "a")
    with pytest.raises(TrainError, match="one row of material parameters per training stroke"):
        _fit(toy, config, tmp_path / "b", aux_targets_train=targets[:-1])
    bad = targets.copy()
    bad[0, 1] = np.nan
    with pytest.raises(TrainError, match="NaN or infinite"):
        _fit(toy, config, tmp_path / "c", aux_targets_train=bad)
    with pytest.raises(ValueError, match="aux_parameters_weight must be a finite number >= 0"):
        TrainConfig(aux_parameters_weight=-1.0)
    with pytest.raises(ValueError, match="cannot both be on"):
        TrainConfig(aux_parameters_weight=1.0, mixup_alpha=0.2)


def test_train_cli_aux_parameters_needs_strokes_recorded_by_robotdemo(tmp_path, capsys):
    from robotdemo.cli import main

    recs = make_material_strokes(7, n_categories=3, n_instances=2, n_objects=2, n_strokes=3, duration_s=0.2)
    write_dataset(tmp_path / "ds", recs, env="clean", seed=7)
    code = main(["train", "--data", str(tmp_path / "ds"), "--out", str(tmp_path / "run"), "--epochs", "1",
                 "--aux-parameters", "1.0", "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and "no surface_seed or size_m" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "run" / "resume").exists()  # refused before any training
