"""The paper's evaluation (sections 4-5) rerun on our data, written up beside the paper's numbers.

:func:`evaluate` runs, on one data set folder (and optionally a second one recorded in the fire scene):

1. Table 1: SSMC (7:3 split by stroke, stratified by category), USMC (k-fold, test folds hold unseen
   instances), fine-grained (instance labels, 7:3 split stratified by instance); accuracy and G-mean, mean and
   std over seeds (SSMC, fine) or folds (USMC) for every model of ``models`` (default TouchFormer, LSTM,
   MTCNN and the logistic-regression reference classifier), and TouchFormer against each of them on the same
   test strokes (:mod:`perception.paired`: difference, bootstrap interval over the strokes, McNemar's test).
2. Missing modality (USMC): the Table-1 USMC models tested with each modality removed (stream set missing
   at test time, as a dropped-out sensor; the models were trained on all four).
3. Ablation: transformer fusion only / + MAG / + MAG + CER on the three tasks.
4. Robustness: each modality of each sample is corrupted with probability p, in training and testing, by
   Gaussian noise of std ``corruption_std`` in units of the per-channel training feature std (so std 1 is
   noise as strong as the feature's own spread), p = 0.0, 0.1, ..., 1.0, at each noise intensity of
   ``corruption_stds`` (the paper runs "different gaussian noise intensities"), on the SSMC split of every seed
   (mean and std over the seeds; p = 0 is Table 1's SSMC runs, shared by every intensity).
   The reference classifier reads raw streams, not features, so it is left out of this experiment.
   With ``fire_dir``, every run of the curve is also scored zero-shot on the fire test strokes, without test
   noise (:func:`_robustness_on_fire`): does training on corrupted sensors carry over to the fire room?
5. What the networks use (:mod:`perception.probes`): the Table-1 runs' test strokes altered at inference (frames
   shuffled or reversed in time, sensors shifted against each other, each sensor taken from another stroke of
   the same class); nothing is trained for it.
6. Clean -> fire shift (with ``fire_dir``): TouchFormer and the reference trained on the clean strokes of the
   seed's SSMC training part and tested on the fire test part (zero-shot); TouchFormer fine-tuned from the
   clean checkpoint on the fire training part (its normalisation kept); both trained on fire alone, for
   scale. Fire is split like SSMC, once per seed, and every run is repeated per seed (mean ± std, as Table 1).
   A fire data set recorded with the clean one's seed holds the same strokes in another environment (same
   object, same stroke draw); no clean model trains on the clean twin of a fire test stroke
   (:func:`clean_training_part`).

Every run's checkpoint lives under ``out_dir/runs/``; a rerun with the same settings resumes or reuses them.
What the report reads from a finished run (its test predictions and training summary) is also appended to the
run store ``out_dir/outcomes.jsonl`` (:mod:`perception.run_store`), which is small enough to commit: a rerun
takes every run it holds from it, without the run folders, so an evaluation longer than one sitting resumes on
another machine from the committed store and the data sets recorded again; :func:`evaluation_status`
(``robotdemo evaluate ... --status``) tells how many of each experiment's runs it holds.
Writes ``out_dir/results.json``, ``out_dir/REPORT.md`` from it (:mod:`perception.report`) and PNG figures
(:mod:`perception.report_plots`: confusion matrices, robustness curve and its runs on fire strokes, t-SNE of test
embeddings with and without CER).
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import os
import subprocess
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np
from sklearn.metrics import recall_score
from tqdm.auto import tqdm

from perception.checkpoint import load_checkpoint
from perception.dataset import (Dataset, fine_split, labels_of, load_dataset, ssmc_split, usmc_folds,
                                validation_split)
from perception.features import feature_dims, keep_modalities, with_accel_axes
from perception.numerics import numeric_environment, numerics_differences
from perception.paired import paired_comparison
from perception.probes import ALTERATIONS, alter, swap_summaries
from perception.reference_classifier import ReferenceClassifier, ReferenceConfig, summary_features
from perception.report import MODEL_LABEL, PAPER, TASK_LABEL, write_report
from perception.report_plots import (plot_confusion, plot_probes, plot_robustness, plot_training_curves,
                                     plot_tsne)
from perception.run_store import RunStore, decode_array, encode_array, indices_sha256, outcome_id
from perception.sensor_use import presence_matrix, sensor_use
from perception.streams import MODALITIES, StrokeRecord
from perception.train import (CHECKPOINT_DIR, DEVIATIONS, TEST_CORRUPTION_SEED_OFFSET, TrainConfig, TrainResult,
                             featurize_records, predict, resolve_device, run_identity, train)


EVALUATION_PACKAGES = ("numpy", "scipy", "scikit-learn", "torch")
"""The installed packages whose numerics featurising, training and scoring depend on (distribution names)."""

OUTCOMES_FILE = "outcomes.jsonl"
"""The run store in the report folder (:mod:`perception.run_store`): every network run's test predictions."""

TASK_LABEL = {"ssmc": "SSMC", "usmc": "USMC", "fine": "fine-grained"}
NN_TINY = {
    "touchformer": (("d_model", 16), ("n_heads", 2), ("n_layers", 1), ("gate_hidden", 8), ("emb_dim", 16)),
    "lstm": (("hidden", 16), ("n_steps", 16), ("emb_dim", 16)),
    "mtcnn": (("channels", 8), ("emb_dim", 16)),
}


def _tiny(model: str) -> tuple[tuple[str, Any], ...]:
    return NN_TINY["touchformer" if model.startswith("touchformer") else model]


@dataclass(frozen=True)
class EvalConfig:
    """What :func:`evaluate` runs.

    Attributes:
        models: Table-1 models (registry names and/or "reference"): the paper's TouchFormer, our variant without
            the MAG threshold (``touchformer_soft``, see ``ablation_models``), the baselines.
        seeds: split and training seeds for SSMC and fine-grained; USMC uses the first seed's folds.
        n_folds: USMC folds.
        ablation: run the ``ablation_models`` too.
        ablation_models: the paper's ablation (fusion only, + MAG, + MAG + CER = TouchFormer) and our variant
            "MAG without threshold" (``touchformer_soft``: ``gate_th = 0``, CER on, softmax temperature 1), which
            scored higher than TouchFormer at temperature 1 on validation on every split (SSMC seeds 0-2, USMC
            folds 0-4, fine-grained seeds 0-2).
        missing_modality: test the USMC models with each modality removed.
        probes: test every Table-1 run on its test strokes altered at inference (:mod:`perception.probes`).
        robustness_models: models of the robustness curve, each run at every p and seed (empty: skip it).
        corruption_ratios: p values of the robustness curve.
        corruption_stds: the noise intensities of the robustness curve (one curve each): noise std in units of
            the per-channel training feature std. Std 1 hardly lowers any model (from p = 0 to p = 1 by 2.8
            points at most, mean over SSMC seeds 0-2, session 19's report); std 3 lowered every model by 5-9
            points at p = 0.5 on validation (session 17, SSMC seeds 0-2); std 5 asks whether the order at
            std 3 (TouchFormer above both baselines from p = 0.5, session 23's report) holds under heavier
            noise. The quick run keeps std 1 and 3.
        robustness_fire: with a fire data set, also score every run of the robustness curve zero-shot on the fire
            room's test strokes, without test noise (:func:`_zero_shot_on_fire`): whether training on corrupted
            modalities makes a clean-only model hold up in the fire room (session 29's scratch probe of the
            std-3 runs: TouchFormer from 38 % at p = 0.1 to 54 % at p = 1, its gate trusting the acceleration
            less).
        fire_models: networks of the clean -> fire experiment (each: clean only, fine-tuned, fire only; every
            seed).
        single_sensor_models: networks trained and tested on one sensor at a time (SSMC, every seed; the other
            streams treated as missing, ``FeatureConfig.modalities``): what each sensor carries by itself and
            what fusing them adds (empty: skip it).
        fine_tune_epochs: epochs of clean -> fire fine-tuning.
        fine_tune_lr: fine-tuning learning rate.
        train: training settings shared by every run (model, task and seed are set per run); batches group
            strokes of similar length (``TrainConfig.group_by_length``: a TouchFormer epoch on 695 strokes of
            ``data/clean30`` took 7-8 s instead of 14-16 s, measured side by side on one thread each).
        model_overrides: model name -> config overrides (all TouchFormer variants share "touchformer"'s).
        tsne: draw the t-SNE figure.
    """

    models: tuple[str, ...] = ("touchformer", "touchformer_soft", "lstm", "mtcnn", "reference")
    seeds: tuple[int, ...] = (0, 1, 2)
    n_folds: int = 5
    ablation: bool = True
    ablation_models: tuple[str, ...] = ("touchformer_fusion", "touchformer_mag", "touchformer", "touchformer_soft")
    missing_modality: bool = True
    probes: bool = True
    robustness_models: tuple[str, ...] = ("touchformer", "lstm", "mtcnn", "touchformer_soft")
    corruption_ratios: tuple[float, ...] = tuple(round(0.1 * i, 1) for i in range(11))
    corruption_stds: tuple[float, ...] = (1.0, 3.0, 5.0)
    robustness_fire: bool = True
    fire_models: tuple[str, ...] = ("touchformer", "touchformer_soft")
    single_sensor_models: tuple[str, ...] = ("touchformer_soft", "mtcnn")
    fine_tune_epochs: int = 20
    fine_tune_lr: float = 3e-4
    train: TrainConfig = field(default_factory=lambda: TrainConfig(group_by_length=True))
    model_overrides: Mapping[str, tuple[tuple[str, Any], ...]] = field(default_factory=dict)
    tsne: bool = True

    def __post_init__(self) -> None:
        if not self.corruption_stds or not all(np.isfinite(s) and s > 0 for s in self.corruption_stds):
            raise ValueError(f"corruption_stds must be one or more finite noise stds > 0, got {self.corruption_stds}")


def quick_config() -> EvalConfig:
    """A tiny version for tests and smoke runs: 2 epochs, 1 seed, 2 folds, p in {0, 0.5, 1} at noise std 1 and 3,
    tiny models."""
    return EvalConfig(seeds=(0,), n_folds=2, corruption_ratios=(0.0, 0.5, 1.0), corruption_stds=(1.0, 3.0),
                      fine_tune_epochs=2, single_sensor_models=("touchformer_soft",),
                      train=TrainConfig(epochs=2, batch_size=16, lr=3e-3, num_threads=1, group_by_length=True),
                      model_overrides={m: _tiny(m) for m in ("touchformer", "lstm", "mtcnn")})


# ----------------------------------------------------------------------------------------------------------
# metrics


def g_mean(y_true: Sequence[int], y_pred: Sequence[int], labels: Iterable[int] | None = None) -> float:
    """Geometric mean of the per-class recalls over the classes present in ``y_true``; 0 if any is 0.

    Args:
        y_true, y_pred: class indices.
        labels: candidate classes (default: those in ``y_true``); classes absent from ``y_true`` have no
            recall and are skipped.
    """
    y_true = np.asarray(y_true)
    present = sorted(set(y_true.tolist()) & (set(labels) if labels is not None else set(y_true.tolist())))
    if not present:
        return float("nan")
    recalls = recall_score(y_true, np.asarray(y_pred), labels=present, average=None, zero_division=0)
    if np.any(recalls == 0):
        return 0.0
    return float(np.exp(np.mean(np.log(recalls))))


def _mean_std(values: Sequence[float]) -> dict[str, float]:
    """Mean and sample std (ddof 1; NaN below two values) of the finite values, and how many there were."""
    v = np.asarray([x for x in values if x == x], dtype=np.float64)
    return {"mean": float(v.mean()) if v.size else float("nan"),
            "std": float(v.std(ddof=1)) if v.size >= 2 else float("nan"), "n": int(v.size)}


# ----------------------------------------------------------------------------------------------------------
# runs


@dataclass(frozen=True)
class _FireData:
    """The fire data set of the clean -> fire experiment, featurised once, with its SSMC split per seed."""

    data: Dataset
    features: list
    summaries: np.ndarray
    splits: Mapping[int, tuple[np.ndarray, np.ndarray]]
    class_names: tuple[str, ...]
    clean_train: Mapping[int, np.ndarray]
    """Per seed: the clean strokes the clean-only models train on (:func:`clean_training_part`)."""


@dataclass
class _Context:
    data: Dataset
    out_dir: Path
    config: EvalConfig
    features: list
    summaries: np.ndarray
    progress: bool
    provenance: dict[str, Any]
    cache: dict = field(default_factory=dict)
    fire: _FireData | None = None
    store: RunStore | None = None
    outcomes: dict[str, dict[str, Any]] = field(default_factory=dict)
    """The run store's outcomes by id (:mod:`perception.run_store`)."""
    scored: set[str] = field(default_factory=set)
    """Ids of the outcomes trained or scored by this evaluation (the rest came from the store)."""
    used: set[str] = field(default_factory=set)
    """Ids of the outcomes this evaluation's report reads."""


@dataclass(frozen=True)
class _TrainJob:
    """One run of an experiment cell, as :func:`_run` trains and scores it: train on ``split[0]`` (validation
    carved from it), test on ``split[1]``. ``source`` names the data set (``"clean"`` or ``"fire"``), so a forked
    training worker finds the strokes in its copy of the context instead of receiving them pickled.

    How the run is scored is part of the job, so that a training worker scores it as the report will read it:
    ``drops`` (each modality removed in turn at test time), ``probes`` (the test strokes altered by each of
    :data:`perception.probes.ALTERATIONS`), ``embedding`` (keep the test embeddings, for the t-SNE figure),
    ``score_on`` (also predict the test part of this seed's split of that data set: the clean -> fire zero-shot
    score) and ``parent`` (the run whose checkpoint this one fine-tunes from)."""

    model: str
    task: str
    split_name: str
    seed: int
    split: tuple[np.ndarray, np.ndarray]
    corruption: float = 0.0
    corruption_std: float = 1.0
    source: str = "clean"
    run_name: str | None = None
    class_names: tuple[str, ...] | None = None
    train_changes: tuple[tuple[str, Any], ...] = ()
    drops: tuple[str, ...] = ()
    probes: bool = False
    embedding: bool = False
    score_on: str | None = None
    parent: _TrainJob | None = None

    def run_dir(self, ctx: _Context) -> Path:
        return _run_dir(ctx, self.model, self.task, self.split_name, self.corruption, self.run_name,
                        self.corruption_std)

    def cache_key(self) -> tuple[Any, ...]:
        """Which cell of the experiments this run is (a p = 0 robustness run is its Table-1 run)."""
        return (self.model, self.task, self.split_name, self.seed, self.corruption,
                _noise_std(self.corruption, self.corruption_std), self.run_name)


def _noise_std(corruption: float, corruption_std: float) -> float | None:
    """The noise std a run with corruption ratio ``corruption`` uses: None without corruption, so that a p = 0
    run is one run (one folder, one training config, one cache entry) whatever the intensity."""
    return corruption_std if corruption > 0 else None


def _run_dir(ctx: _Context, model: str, task: str, split_name: str, corruption: float, run_name: str | None,
             corruption_std: float = 1.0) -> Path:
    """The folder of one run: ``run_name``, or task/model/split_p<corruption>[_std<corruption_std>] under
    ``out_dir/runs`` (the std only where there is corruption: p = 0 runs are shared by every intensity)."""
    std = _noise_std(corruption, corruption_std)
    noise = "" if std is None else f"_std{std:g}"
    return ctx.out_dir / "runs" / (run_name or f"{task}/{model}/{split_name}_p{corruption:.1f}{noise}")


def _train_config(ctx: _Context, model: str, task: str, seed: int, **changes: Any) -> TrainConfig:
    overrides = ctx.config.model_overrides.get("touchformer" if model.startswith("touchformer") else model, ())
    return dataclasses.replace(ctx.config.train, model=model, task=task, seed=seed,
                               model_overrides=tuple(overrides), **changes)


def _class_names(records, task: str) -> tuple[str, ...]:
    """The class list of ``task`` on ``records`` (sorted labels), shared by a run and its pre-training."""
    return tuple(sorted(set(labels_of(records, task))))


def _provenance_of(ctx: _Context, records) -> dict[str, Any]:
    """The provenance a run's checkpoint records: the manifest hash of the data set it trains on."""
    if ctx.fire is not None and records is ctx.fire.data.records:
        return {**ctx.provenance, "data_manifest_sha256": ctx.fire.data.manifest_sha256}
    return ctx.provenance


def _train_run(ctx: _Context, model: str, task: str, train_idx: np.ndarray, split_name: str, seed: int,
               corruption: float, records, features, class_names: tuple[str, ...], run_name: str | None,
               train_changes: Mapping[str, Any] | None, corruption_std: float = 1.0
               ) -> tuple[TrainResult, TrainConfig, np.ndarray]:
    """Train (or reuse the finished run in) the run folder of one experiment cell; validation is carved from
    ``train_idx``. Returns the training result, its config and the validation indices. ``corruption_std``
    reaches the training config only where ``corruption`` > 0 (a run without noise is the same run whatever
    the intensity). A folder holding a run of another config or model (a setting or a model default changed
    since) is kept as ``<name>.stale-<n>`` and the cell trained afresh."""
    tr, val = validation_split(records, train_idx, task, seed, ctx.config.train.val_fraction)
    std = _noise_std(corruption, corruption_std)
    noise = {"corruption_ratio": corruption, **({} if std is None else {"corruption_std": std})}
    cfg = _train_config(ctx, model, task, seed, **noise, **dict(train_changes or {}))
    run_dir = _run_dir(ctx, model, task, split_name, corruption, run_name, corruption_std)
    res = train([records[i] for i in tr], [records[i] for i in val], cfg, run_dir, progress=False,
                class_names=class_names, features_train=[features[i] for i in tr],
                features_val=[features[i] for i in val], provenance=_provenance_of(ctx, records), replace_stale=True)
    return res, cfg, val


def _train_job(ctx: _Context, job: _TrainJob) -> tuple[TrainResult, TrainConfig, np.ndarray]:
    """:func:`_train_run` for ``job``: its finished folder reused at once, an unfinished one resumed, a gone one
    (its outcome came from the store) trained again."""
    records, features, _ = _source(ctx, job.source)
    return _train_run(ctx, job.model, job.task, job.split[0], job.split_name, job.seed, job.corruption, records,
                      features, _job_names(ctx, job), job.run_name, dict(job.train_changes) or None,
                      job.corruption_std)


def _job_names(ctx: _Context, job: _TrainJob) -> tuple[str, ...]:
    records, _, _ = _source(ctx, job.source)
    return _class_names(records, job.task) if job.class_names is None else tuple(job.class_names)


def _job_classes(ctx: _Context, job: _TrainJob) -> np.ndarray:
    """Class index (into :func:`_job_names`) of every stroke of ``job``'s data set."""
    records, _, _ = _source(ctx, job.source)
    names = _job_names(ctx, job)
    return np.array([names.index(l) for l in labels_of(records, job.task)])


def _job_config(ctx: _Context, job: _TrainJob) -> TrainConfig:
    """The training config of ``job``, as :func:`_train_run` builds it."""
    std = _noise_std(job.corruption, job.corruption_std)
    noise = {"corruption_ratio": job.corruption, **({} if std is None else {"corruption_std": std})}
    return _train_config(ctx, job.model, job.task, job.seed, **noise, **dict(job.train_changes))


def _outcome_id(ctx: _Context, job: _TrainJob) -> str:
    """The run store's name for ``job``'s outcome: its training config and model config
    (:func:`perception.train.run_identity`; a fine-tuned run names its parent's outcome instead of the parent's
    folder), class names, the data set's strokes (:func:`_strokes_id`), its training, validation and test strokes, and how it
    is scored. Whatever changes one of these is another run."""
    records, _, _ = _source(ctx, job.source)
    tr, val = validation_split(records, job.split[0], job.task, job.seed, ctx.config.train.val_fraction)
    names = _job_names(ctx, job)
    identity = run_identity(_job_config(ctx, job), len(names))
    if job.parent is not None:
        identity["config"].pop("init_checkpoint", None)
        identity["parent"] = _outcome_id(ctx, job.parent)
    strokes = _strokes_id(ctx.data if job.source == "clean" else ctx.fire.data)
    score_on = None
    if job.score_on is not None:
        score_on = {"data": _strokes_id(ctx.fire.data), "test": indices_sha256(_score_split(ctx, job)[1])}
    return outcome_id({**identity, "class_names": list(names), "data": strokes, "train": indices_sha256(tr),
                       "val": indices_sha256(val), "test": indices_sha256(job.split[1]), "drops": list(job.drops),
                       "probes": list(ALTERATIONS) if job.probes else [], "embedding": job.embedding,
                       "score_on": score_on, "test_noise_seed_offset": TEST_CORRUPTION_SEED_OFFSET})


def _strokes_id(data: Dataset) -> str:
    """What a data set's strokes are, for the run store: sha256 over its shards' names and hashes. Not the
    manifest's hash, which also covers the recorder's fingerprint (its source files, even a comment in them):
    the same strokes recorded again by code changed elsewhere keep their stored runs."""
    shards = data.manifest.get("shards")
    if not shards or not all("sha256" in shard for shard in shards):
        return data.manifest_sha256
    text = json.dumps([(str(shard["file"]), str(shard["sha256"])) for shard in shards])  # in loading order
    return hashlib.sha256(text.encode()).hexdigest()


def _score_split(ctx: _Context, job: _TrainJob) -> tuple[np.ndarray, np.ndarray]:
    """The split whose test part ``job.score_on`` names: this seed's SSMC split of that data set."""
    assert job.score_on == "fire" and ctx.fire is not None, "only the fire data set is scored on besides the test part"
    return ctx.fire.splits[job.seed]


def _test_noise(job: _TrainJob) -> dict[str, Any]:
    """The test-time corruption ``job``'s run is scored with (:func:`perception.train.predict`'s arguments)."""
    return dict(corruption_ratio=job.corruption, corruption_std=job.corruption_std,
                seed=job.seed + TEST_CORRUPTION_SEED_OFFSET)


def _train_and_score(ctx: _Context, job: _TrainJob) -> dict[str, Any]:
    """Train ``job``'s run (or reuse its finished folder) and score it: the run store's outcome of it (training
    summary, test predictions by test condition, optionally the test embeddings)."""
    _, features, _ = _source(ctx, job.source)
    y = _job_classes(ctx, job)
    test_idx = job.split[1]
    if job.parent is not None:
        # finished in its folder: reused at once; unfinished or stale: resumed or trained afresh; gone (its
        # outcome came from the store): trained again. Seeded, but on another machine or library version the
        # weights may differ from those its stored outcome was scored with.
        _train_job(ctx, job.parent)
    res, cfg, val = _train_job(ctx, job)
    device = resolve_device(cfg.device)
    ckpt = load_checkpoint(res.checkpoint_dir, device=device)
    dims = feature_dims(ckpt.feature_config)
    noise = _test_noise(job)
    test_feats = [keep_modalities(features[i], ckpt.feature_config.modalities) for i in test_idx]
    pred: dict[str, list[int]] = {}
    outcome: dict[str, Any] = {"git_commit": ckpt.meta.get("git_commit")}  # the code that trained it
    for drop in ("none",) + tuple(job.drops):
        preds = predict(ckpt.model, test_feats, dims, stats=ckpt.norm_stats, device=device, **noise,
                        drop=() if drop == "none" else (drop,))
        pred[drop] = preds.pred.tolist()
        if drop == "none":
            outcome.update(_modality_weights(preds.alphas, test_feats))
            if job.embedding:
                outcome["embedding"] = encode_array(preds.embedding)
    for kind in ALTERATIONS if job.probes else ():
        altered = alter(test_feats, y[test_idx], kind, _probe_rng(job.seed, kind))
        pred[f"probe:{kind}"] = predict(ckpt.model, altered.features, dims, stats=ckpt.norm_stats, device=device,
                                        **noise).pred.tolist()
    if job.score_on is not None:
        _, score_features, _ = _source(ctx, job.score_on)
        pred[f"score:{job.score_on}"] = predict(
            ckpt.model, [keep_modalities(score_features[i], ckpt.feature_config.modalities)
                         for i in _score_split(ctx, job)[1]], dims, stats=ckpt.norm_stats, device=device).pred.tolist()
    outcome.update(pred=pred, best_epoch=res.best_epoch, best_val_accuracy=res.best_val_accuracy,
                   checkpoint=Path(res.checkpoint_dir).relative_to(ctx.out_dir).as_posix(), n_val=int(len(val)),
                   epochs=len(res.history),
                   train_accuracy_curve=[round(float(h["train_accuracy"]), 4) for h in res.history],
                   val_accuracy_curve=[round(float(h["val_accuracy"]), 4) for h in res.history])
    return outcome


def _outcome(ctx: _Context, job: _TrainJob) -> dict[str, Any]:
    """``job``'s outcome: from the run store, or trained and scored now and added to it."""
    run_id = _outcome_id(ctx, job)
    outcome = ctx.outcomes.get(run_id)
    if outcome is None:
        outcome = _train_and_score(ctx, job)
        if ctx.store is not None:
            ctx.store.append(run_id, str(job.run_dir(ctx).relative_to(ctx.out_dir)), outcome)
        ctx.outcomes[run_id] = outcome
        ctx.scored.add(run_id)
    ctx.used.add(run_id)
    return outcome


def _run(ctx: _Context, job: _TrainJob) -> dict[str, Any]:
    """Train ``job.model`` on ``job.split[0]`` (validation carved from it) and test on ``job.split[1]``, both
    corrupted with ratio ``job.corruption`` and noise std ``job.corruption_std``
    (:func:`perception.train.corrupt_batch`), as the job says (:class:`_TrainJob`: with each modality of
    ``drops`` removed in turn, on the probes' altered strokes, ...). A network's outcome comes from the run
    store when it holds it (:func:`_outcome`); the reference classifier, which reads stream statistics rather
    than frames, is fitted here (its probes: ``swap`` only)."""
    key = job.cache_key()
    if key in ctx.cache:
        return ctx.cache[key]
    _, features, summaries = _source(ctx, job.source)
    names = _job_names(ctx, job)
    y = _job_classes(ctx, job)
    train_idx, test_idx = job.split
    std = _noise_std(job.corruption, job.corruption_std)
    result: dict[str, Any] = {"model": job.model, "task": job.task, "split": job.split_name, "seed": job.seed,
                              "corruption_ratio": job.corruption, "corruption_std": 0.0 if std is None else std,
                              "n_train": int(len(train_idx)), "n_test": int(len(test_idx))}
    outputs: dict[str, np.ndarray] = {}
    emb = None
    if job.model == "reference":
        clf = ReferenceClassifier(ReferenceConfig(label="instance" if job.task == "fine" else "category"))
        clf.pipeline.fit(summaries[train_idx], [names[i] for i in y[train_idx]])

        def classify(x: np.ndarray) -> np.ndarray:  # class indices of the summaries x
            return np.array([names.index(str(p)) for p in clf.pipeline.predict(x)])

        block = summaries.shape[1] // len(MODALITIES)
        for drop in ("none",) + tuple(job.drops):
            x = summaries[test_idx].copy()
            if drop != "none":
                j = MODALITIES.index(drop)
                x[:, j * block:(j + 1) * block] = 0.0  # exactly what a missing stream yields
            outputs[drop] = classify(x)
        if job.probes:
            swapped = alter([features[i] for i in test_idx], y[test_idx], "swap", _probe_rng(job.seed, "swap"))
            outputs["probe:swap"] = classify(swap_summaries(summaries[test_idx], swapped.sources))
    else:
        outcome = _outcome(ctx, job)
        result.update({k: v for k, v in outcome.items() if k not in ("pred", "embedding")})
        result["checkpoint"] = str(ctx.out_dir / outcome["checkpoint"])  # stored relative to the report folder
        outputs = {k: np.asarray(v, dtype=np.int64) for k, v in outcome["pred"].items()}
        emb = decode_array(outcome["embedding"]) if "embedding" in outcome else None
    result["_score_pred"] = outputs.pop(f"score:{job.score_on}", None)
    y_test = y[test_idx]
    if len(test_idx) == 0:  # a train-only run (clean model of the fire experiment)
        result.update(accuracy=float("nan"), g_mean=float("nan"), missing={})
        result["_y_true"], result["_y_pred"], result["_embedding"], result["_names"] = y_test, y_test, None, names
        ctx.cache[key] = result
        return result
    result["accuracy"] = float(np.mean(outputs["none"] == y_test))
    result["g_mean"] = g_mean(y_test, outputs["none"], range(len(names)))
    result["missing"] = {d: float(np.mean(p == y_test)) for d, p in outputs.items()
                         if d != "none" and not d.startswith("probe:")}
    result["probes"] = {d.removeprefix("probe:"): float(np.mean(p == y_test)) for d, p in outputs.items()
                        if d.startswith("probe:")}
    result["_y_true"], result["_y_pred"], result["_embedding"], result["_names"] = y_test, outputs["none"], emb, names
    ctx.cache[key] = result
    return result


def _probe_rng(seed: int, kind: str) -> np.random.Generator:
    """The draws of alteration ``kind`` on the test strokes of a split seeded ``seed``: the same for every model
    of the split, so their accuracies compare on the same altered strokes."""
    return np.random.default_rng((seed, ALTERATIONS.index(kind)))


def _source(ctx: _Context, name: str) -> tuple[Sequence, list, np.ndarray]:
    """The strokes, features and summaries of data set ``name`` (``"clean"`` or ``"fire"``)."""
    if name == "clean":
        return ctx.data.records, ctx.features, ctx.summaries
    assert ctx.fire is not None, "fire runs need the fire data set loaded (_load_fire)"
    return ctx.fire.data.records, ctx.fire.features, ctx.fire.summaries


def _single_sensor_jobs(ctx: _Context) -> list[tuple[str, _TrainJob]]:
    """(sensor, run): one SSMC run per single-sensor model, seed and sensor, in which the model sees only that
    sensor (``FeatureConfig.modalities``), in training and testing."""
    fc = ctx.config.train.feature_config
    return [(m, _TrainJob(model, "ssmc", split_name, seed, split, run_name=f"single_sensor/{model}/{split_name}_{m}",
                          train_changes=(("feature_config", dataclasses.replace(fc, modalities=(m,))),)))
            for model in ctx.config.single_sensor_models for split_name, seed, split in _splits(ctx, "ssmc")
            for m in MODALITIES]


def _single_sensor_experiment(ctx: _Context, all_four: Mapping[str, Sequence[Mapping[str, Any]]]) -> dict[str, Any]:
    """Test and best validation accuracy (mean and std over the seeds) of each single-sensor model on each
    sensor alone, beside the same model's Table-1 SSMC runs with all four (``all_four``: model -> runs)."""
    runs: dict[str, dict[str, list]] = {}
    for sensor, job in _single_sensor_jobs(ctx):
        runs.setdefault(job.model, {}).setdefault(sensor, []).append(_run(ctx, job))
    for model, rows in all_four.items():
        if model in runs:
            runs[model]["all"] = list(rows)
    return {model: {sensor: {"accuracy": _mean_std([r["accuracy"] for r in rows]),
                             "best_val_accuracy": _mean_std([r["best_val_accuracy"] for r in rows]),
                             "runs": [_public(r) for r in rows]} for sensor, rows in per_sensor.items()}
            for model, per_sensor in runs.items()}


def _modality_weights(alphas: np.ndarray, features: Sequence[Mapping[str, Any]]) -> dict[str, list[float]]:
    """Per modality (:data:`MODALITIES` order): the mean weight alpha over the strokes where it is present, and
    the share of those strokes on which the gate dropped it (alpha 0); 0 for a modality no stroke carries
    (:func:`perception.sensor_use.sensor_use`, as ``robotdemo train`` records it)."""
    use = sensor_use(alphas, presence_matrix(features))
    return {"alpha_mean": np.array([use[m].mean_alpha or 0.0 for m in MODALITIES]).round(4).tolist(),
            "gate_dropped_share": np.array([use[m].dropped_share or 0.0 for m in MODALITIES]).round(4).tolist()}


_POOL_CONTEXT: _Context | None = None
"""The evaluation a forked training worker serves (set before the pool forks, so nothing is pickled)."""


def _pool_init() -> None:
    import torch

    torch.set_num_threads(1)


def _pretrain_job(item: tuple[_TrainJob, bool]) -> str:
    ctx = _POOL_CONTEXT
    assert ctx is not None, "_pretrain_job runs only in a worker forked by _pretrain"
    job, on_fire = item
    _outcome(ctx, job)
    if on_fire:
        _zero_shot_on_fire(ctx, job)
    return job.run_name or f"{job.task} {job.model} {job.split_name} p={job.corruption} std={job.corruption_std:g}"


def _pretrain(ctx: _Context, jobs: Sequence[_TrainJob], workers: int, on_fire: Sequence[_TrainJob] = ()) -> None:
    """Train and score the runs of ``jobs`` that the run store lacks, in ``workers`` forked processes of one
    torch thread each (one job per run folder, at its first place in ``jobs``); each worker adds its outcomes
    to the store as it finishes them. A run whose folder is also one of ``on_fire``'s (the robustness curve's)
    is scored zero-shot on the fire strokes by the worker that trains it (:func:`_zero_shot_on_fire`, with a fire
    data set and ``robustness_fire``), while its checkpoint is at hand: run folders do not outlive a session, so
    a score left for later would train its run again. A stored run whose score is missing is scored (and, its
    folder gone, trained again) by a worker too. The experiments then run as without workers and find every
    outcome in the store, so the results are those of a sequential evaluation. One torch thread per process, so
    ``workers`` processes share as many cores without oversubscribing them. On a GPU the workers share it; if
    this process has used CUDA already, a forked worker could not, so the runs are trained here one after
    another instead."""
    import multiprocessing as mp

    import torch

    global _POOL_CONTEXT
    unique: dict[Path, _TrainJob] = {}
    for job in jobs:
        if job.model != "reference":
            unique.setdefault(job.run_dir(ctx), job)
    scored_on_fire = ({job.run_dir(ctx) for job in on_fire} if ctx.fire is not None and ctx.config.robustness_fire
                      else set())
    pending = [(job, run_dir in scored_on_fire) for run_dir, job in unique.items()]
    pending = [(job, on_fire) for job, on_fire in pending if _outcome_id(ctx, job) not in ctx.outcomes
               or (on_fire and _zero_shot_id(ctx, job) not in ctx.outcomes)]
    if not pending:
        return
    in_process = resolve_device(ctx.config.train.device).type == "cuda" and torch.cuda.is_initialized()
    if in_process:  # a forked worker could not use the GPU
        tqdm.write(f"CUDA is already in use in this process, so forked workers could not use it: training the "
                   f"{len(pending)} runs here, one after another", file=sys.stderr)
    _POOL_CONTEXT = ctx
    bar = tqdm(total=len(pending), desc="train" if in_process else f"train ({workers} workers)",
               disable=not ctx.progress)
    try:
        with contextlib.ExitStack() as stack:
            if in_process:
                names: Iterable[str] = map(_pretrain_job, pending)
            else:
                pool = stack.enter_context(mp.get_context("fork").Pool(workers, initializer=_pool_init))
                names = pool.imap_unordered(_pretrain_job, pending)
            for name in names:
                bar.set_postfix_str(name)
                bar.update()
    finally:
        _POOL_CONTEXT = None
        bar.close()
        if not in_process and ctx.store is not None:  # what the workers scored
            stored = ctx.store.load()
            ctx.scored.update(set(stored) - set(ctx.outcomes))
            ctx.outcomes.update(stored)


def _splits(ctx: _Context, task: str) -> list[tuple[str, int, tuple[np.ndarray, np.ndarray]]]:
    records, cfg = ctx.data.records, ctx.config
    if task == "ssmc":
        return [(f"seed{s}", s, ssmc_split(records, s)) for s in cfg.seeds]
    if task == "fine":
        return [(f"seed{s}", s, fine_split(records, s)) for s in cfg.seeds]
    s = cfg.seeds[0]
    return [(f"seed{s}_fold{f}", s, fold) for f, fold in enumerate(usmc_folds(records, cfg.n_folds, s))]


def _public(run: Mapping[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in run.items() if not k.startswith("_")}


def _failed_runs(runs: Iterable[Mapping[str, Any]], out_dir: Path | None = None) -> list[dict[str, Any]]:
    """The network runs whose training accuracy never reached twice chance (2 / K for K classes) in any epoch:
    runs that never learned (in session 20 one MTCNN run under strong noise kept the cross-entropy at ln K for
    50 epochs), listed so that a mean over seeds that holds one is not read as the model's. Checkpoint paths
    are given relative to ``out_dir`` where they lie under it."""
    failed = []
    for run in runs:
        curve = run.get("train_accuracy_curve")
        if not curve:
            continue  # the reference classifier, or a run without a history
        chance = 1.0 / len(run["_names"])
        if max(curve) < 2.0 * chance:
            checkpoint = Path(run["checkpoint"])
            if out_dir is not None and checkpoint.is_relative_to(out_dir):
                checkpoint = checkpoint.relative_to(out_dir)
            failed.append({**{k: run[k] for k in ("model", "task", "split", "seed", "corruption_ratio",
                                                   "corruption_std", "accuracy")},
                           "checkpoint": checkpoint.as_posix(), "n_classes": len(run["_names"]),
                           "max_train_accuracy": max(curve)})
    return sorted(failed, key=lambda r: (r["task"], r["model"], r["checkpoint"]))


def _category_recall(runs: Sequence[Mapping[str, Any]]) -> dict[str, float]:
    """Recall of every class over the test strokes of all ``runs`` pooled (sklearn's ``recall_score``)."""
    names = runs[0]["_names"]
    y_true = np.concatenate([r["_y_true"] for r in runs])
    y_pred = np.concatenate([r["_y_pred"] for r in runs])
    recalls = recall_score(y_true, y_pred, labels=range(len(names)), average=None, zero_division=0)
    return {name: float(v) for name, v in zip(names, recalls)}


def _paired(model_runs: Sequence[Mapping[str, Any]], baseline_runs: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """:func:`perception.paired.paired_comparison` of two models' Table-1 runs, split by split."""
    for a, b in zip(model_runs, baseline_runs, strict=True):
        if a["split"] != b["split"] or not np.array_equal(a["_y_true"], b["_y_true"]):
            raise ValueError(f"{a['model']} and {b['model']} were not tested on the same strokes "
                             f"({a['task']} {a['split']} against {b['split']})")
    return paired_comparison([r["_y_true"] for r in model_runs], [r["_y_pred"] for r in model_runs],
                             [r["_y_pred"] for r in baseline_runs], model=model_runs[0]["model"],
                             baseline=baseline_runs[0]["model"]).to_dict()


def _summary(runs: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    return {"accuracy": _mean_std([r["accuracy"] for r in runs]), "g_mean": _mean_std([r["g_mean"] for r in runs]),
            "runs": [_public(r) for r in runs]}


# ----------------------------------------------------------------------------------------------------------
# provenance, plots, report


def _git(*args: str) -> str | None:
    try:
        out = subprocess.run(["git", *args], cwd=Path(__file__).resolve().parents[1], capture_output=True, text=True,
                             timeout=10)
        return out.stdout.strip() if out.returncode == 0 else None
    except (OSError, subprocess.SubprocessError):
        return None


def _git_commit() -> str | None:
    return _git("rev-parse", "HEAD") or None


def _git_dirty() -> bool | None:
    """Whether tracked files differ from the commit (None outside a git checkout)."""
    status = _git("status", "--porcelain", "--untracked-files=no")
    return None if status is None else bool(status)


def _seed_wins(per_seed: Mapping[str, Mapping[str, Sequence[float]]], model: str) -> dict[str, int]:
    """Per corruption ratio: in how many seeds ``model`` is above every other model of that seed (paired by
    seed; a difference of means can come from one seed)."""
    if model not in per_seed:
        return {}
    others = [m for m in per_seed if m != model]
    return {p: int(sum(all(acc > per_seed[o][p][i] for o in others) for i, acc in enumerate(runs)))
            for p, runs in per_seed[model].items()}


def _paired_best_baseline(runs: Mapping[str, Mapping[str, Sequence[Mapping[str, Any]]]]) -> dict[str, Any]:
    """Per corruption ratio: TouchFormer against the baseline (a model that is no TouchFormer variant) with the
    higher mean accuracy there, stroke by stroke on the same test strokes (:func:`_paired`); {} without
    TouchFormer or a baseline."""
    baselines = [m for m in runs if not m.startswith("touchformer")]
    if "touchformer" not in runs or not baselines:
        return {}
    out = {}
    for p, tf_runs in runs["touchformer"].items():
        best = max(baselines, key=lambda m: np.mean([r["accuracy"] for r in runs[m][p]]))
        out[p] = _paired(tf_runs, runs[best][p])
    return out


def _fitting_summary(per: Mapping[tuple[str, str], Sequence[Mapping[str, Any]]], models: Sequence[str]
                     ) -> dict[str, dict[str, dict[str, float]]]:
    """Per task and model, over its runs: the best (chosen) epoch, the training accuracy of the last epoch, the
    best validation accuracy and the test accuracy: how far each model fits its training strokes beyond what
    carries over to strokes it has not seen."""
    out: dict[str, dict[str, dict[str, float]]] = {}
    for task in ("ssmc", "usmc", "fine"):
        for model in models:
            runs = [r for r in per.get((task, model), []) if r.get("train_accuracy_curve")]
            if runs:
                out.setdefault(task, {})[model] = {
                    "best_epoch": _mean_std([r["best_epoch"] for r in runs]),
                    "final_train_accuracy": _mean_std([r["train_accuracy_curve"][-1] for r in runs]),
                    "best_val_accuracy": _mean_std([r["best_val_accuracy"] for r in runs]),
                    "test_accuracy": _mean_std([r["accuracy"] for r in runs])}
    return out


EVAL_DEVIATIONS: dict[str, str] = {
    "ssmc_split": ("random 7:3 split by stroke, stratified by category, like the paper; strokes of one physical "
                   "object can fall on both sides, which favours SSMC over USMC."),
    "usmc_seeds": "USMC folds of the first seed only (k folds, as the paper); SSMC and fine-grained over all seeds.",
    "missing_modality": "modality removed at test time from models trained with all four (the paper does not say).",
    "robustness_noise": ("noise std in units of the per-channel training feature std, at std {stds}; the paper "
                         "runs several intensities without giving them. SSMC split of every seed; the reference "
                         "classifier is not included."),
    "fire_fine_tune": "fine-tuning keeps the clean model's feature normalisation and class list.",
    "baselines": ("LSTM and MTCNN are our re-implementations (perception/baselines.py); DDQN, DALNet and MMUSR "
                  "are not rerun."),
}

ACCEL_FRONT_END_DEVIATION = (
    "every network's accelerometer front end keeps channel groups {groups} apart (robotdemo evaluate "
    "--accel-axes; perception.features.ACCEL_NORMAL_TANGENTIAL: the pad-normal z axis, then the in-plane x + y "
    "power), one set of log bands each, where the paper's LMT data has one DFT321 spectrum of the three axes "
    "(session 51: it reads the texture back from the strokes at R^2 0.86 instead of 0.64 for the roughness). The "
    "reference classifier's summary features do not change.")
"""The report's deviation line for an accelerometer front end that is not the summed one."""


# ----------------------------------------------------------------------------------------------------------
# the evaluation


def _experiment_jobs(ctx: _Context) -> tuple[list[_TrainJob], list[_TrainJob]]:
    """The runs of Table 1 and the ablation (each scored as its sections read it), and those of the robustness
    curve (every seed, model, p and std; a p = 0 run is its Table-1 run, shared by every intensity)."""
    cfg = ctx.config
    ablation = list(cfg.ablation_models) if cfg.ablation else []
    jobs = []
    for task in ("ssmc", "usmc", "fine"):
        for k, (split_name, seed, split) in enumerate(_splits(ctx, task)):
            for model in dict.fromkeys(list(cfg.models) + ablation):
                jobs.append(_TrainJob(
                    model, task, split_name, seed, split,
                    drops=MODALITIES if (task == "usmc" and cfg.missing_modality and model in cfg.models) else (),
                    probes=cfg.probes and model in cfg.models,
                    embedding=cfg.tsne and k == 0 and task != "usmc" and model in ("touchformer", "touchformer_mag")))
    # (model, p, std); p = 0 once, shared by every intensity (Table 1's SSMC run)
    rob_cells = list(dict.fromkeys((m, float(p), std if p > 0 else 1.0) for std in cfg.corruption_stds
                                   for p in cfg.corruption_ratios for m in cfg.robustness_models))
    splits = {s: ssmc_split(ctx.data.records, s) for s in cfg.seeds} if rob_cells else {}  # each seed's SSMC split
    rob = [_TrainJob(m, "ssmc", f"seed{s}", s, splits[s], p, std) for s in cfg.seeds for m, p, std in rob_cells]
    table_job = {job.cache_key(): job for job in jobs}
    return jobs, [table_job.get(job.cache_key(), job) for job in rob]  # p = 0: scored as Table 1 reads it


def evaluation_status(data_dir: str | os.PathLike, out_dir: str | os.PathLike,
                      fire_dir: str | os.PathLike | None = None, config: EvalConfig | None = None) -> dict[str, Any]:
    """How far the evaluation of ``config`` on these data sets has come: per experiment, how many of its network
    runs the run store in ``out_dir`` holds (:func:`_outcome_id`, as :func:`evaluate` names them). Nothing is
    featurised, trained or written. The reference classifier is not counted: it is fitted afresh each time, in
    seconds. A run of two experiments (Table 1's SSMC runs are the robustness curve's p = 0) counts in the
    first. ``data`` says for each data set whether its strokes are those the stored runs were trained on
    (:func:`kept_manifest_match`). ``interim``: the test accuracies the stored runs give so far
    (:func:`_interim_accuracy`)."""
    cfg = config or EvalConfig()
    out_dir = Path(out_dir)
    ctx = _Context(data=load_dataset(data_dir), out_dir=out_dir, config=cfg, features=[],
                   summaries=np.zeros((0, 0)), progress=False, provenance={})
    if fire_dir is not None:
        ctx.fire = _load_fire(ctx, Path(fire_dir), featurize=False)
    jobs, rob = _experiment_jobs(ctx)
    fire_runs = [_fire_runs(ctx, m, s) for s in cfg.seeds for m in cfg.fire_models] if ctx.fire is not None else []
    groups = {"table1": [j for j in jobs if j.model in cfg.models],
              "ablation": [j for j in jobs if j.model not in cfg.models],
              "fire": [r[kind] for r in fire_runs for kind in ("clean", "finetuned", "scratch")],
              "single_sensor": [job for _, job in _single_sensor_jobs(ctx)],
              "robustness": rob}
    outcomes = RunStore(out_dir / OUTCOMES_FILE).load()
    stored = set(outcomes)
    counted: set[str] = set()
    experiments = {}
    for name, group in groups.items():
        ids = {_outcome_id(ctx, job) for job in group if job.model != "reference"} - counted
        counted |= ids
        experiments[name] = {"stored": len(ids & stored), "runs": len(ids)}
    status = {"store": str(out_dir / OUTCOMES_FILE), "stored": len(counted & stored), "runs": len(counted),
              "experiments": experiments,
              "data": {"clean": kept_manifest_match(ctx.data, out_dir, "clean")}}
    if ctx.fire is not None:
        status["data"]["fire"] = kept_manifest_match(ctx.fire.data, out_dir, "fire")
    if ctx.fire is not None and cfg.robustness_fire and rob:  # scores of stored runs, no training of their own
        ids = {_zero_shot_id(ctx, job) for job in rob}
        status["robustness_fire_scores"] = {"stored": len(ids & stored), "scores": len(ids)}
    status["interim"] = _interim_accuracy(ctx.config, groups["table1"] + groups["ablation"], rob,
                                          lambda job: _stored_accuracy(ctx, job, outcomes))
    return status


def _stored_accuracy(ctx: _Context, job: _TrainJob, outcomes: Mapping[str, Mapping[str, Any]]) -> float | None:
    """Test accuracy (fraction) of ``job``'s stored run, read from its stored predictions; None if not stored."""
    outcome = outcomes.get(_outcome_id(ctx, job))
    if outcome is None:
        return None
    y_test = _job_classes(ctx, job)[job.split[1]]
    return float(np.mean(np.asarray(outcome["pred"]["none"], dtype=np.int64) == y_test))


def _interim_accuracy(cfg: EvalConfig, jobs: Sequence[_TrainJob], rob: Sequence[_TrainJob],
                      accuracy: Callable[[_TrainJob], float | None]) -> dict[str, Any]:
    """What the stored runs say before the evaluation is complete: test accuracy [%] of each network's cell
    (Table 1 and the ablation per task; the robustness curve per noise std and p), as the mean over the runs
    stored so far with how many of how many; and per noise std, at how many ratios TouchFormer's mean is above
    that of every baseline (a robustness model that is no TouchFormer variant), over the seeds stored for every
    model and ratio of that std (``seeds``). Read from the run store's predictions: nothing is trained, and the
    reference classifier is left out. ``accuracy``: a run's test accuracy (fraction), None where not stored."""
    def cell(accuracies: Sequence[float | None]) -> dict[str, Any]:
        done = [a for a in accuracies if a is not None]
        return {"mean": round(100 * float(np.mean(done)), 1) if done else None, "stored": len(done),
                "runs": len(accuracies)}

    runs: dict[str, dict[str, list[float | None]]] = {}
    for job in jobs:
        if job.model != "reference":
            runs.setdefault(job.task, {}).setdefault(job.model, []).append(accuracy(job))
    interim: dict[str, Any] = {"tasks": {t: {m: cell(a) for m, a in by_model.items()} for t, by_model in runs.items()}}
    if not rob:
        return interim
    by_cell = {(job.model, job.corruption, _noise_std(job.corruption, job.corruption_std), job.seed): accuracy(job)
               for job in rob}
    models = list(cfg.robustness_models)
    levels = []
    for std in cfg.corruption_stds:
        def acc(m: str, p: float, seed: int, std: float = std) -> float | None:
            return by_cell[(m, float(p), _noise_std(p, std), seed)]

        seeds = [s for s in cfg.seeds if all(acc(m, p, s) is not None for m in models for p in cfg.corruption_ratios)]
        level: dict[str, Any] = {"corruption_std": std, "curves": {
            m: {repr(float(p)): cell([acc(m, p, s) for s in cfg.seeds]) for p in cfg.corruption_ratios}
            for m in models}, "seeds": seeds}
        baselines = [m for m in models if not m.startswith("touchformer")]  # as _paired_best_baseline
        if "touchformer" in models and baselines and seeds:
            mean = {m: [np.mean([acc(m, p, s) for s in seeds]) for p in cfg.corruption_ratios] for m in models}
            level["touchformer_above_the_baselines_at"] = int(sum(
                all(mean["touchformer"][i] > mean[b][i] for b in baselines) for i in range(len(cfg.corruption_ratios))))
        levels.append(level)
    interim["robustness"] = levels
    return interim


def evaluate(data_dir: str | os.PathLike, out_dir: str | os.PathLike, quick: bool = False,
             models: Sequence[str] | None = None, seeds: Sequence[int] | None = None,
             fire_dir: str | os.PathLike | None = None, config: EvalConfig | None = None, device: str | None = None,
             progress: bool = True, command: str | None = None, workers: int = 1) -> dict[str, Any]:
    """Run the paper's experiments on our data and write the report.

    Args:
        data_dir: clean data set folder.
        out_dir: report folder (REPORT.md, results.json, PNGs, runs/).
        quick: use :func:`quick_config` (tests, smoke runs).
        models: Table-1 models (default: the config's).
        seeds: seeds (default: the config's).
        fire_dir: optional data set recorded in the fire scene, for the clean -> fire experiment.
        config: full settings (default :class:`EvalConfig` or the quick one).
        device: "auto", "cpu" or "cuda" (default: the config's).
        progress: tqdm bars.
        command: command line for the provenance record (default: ``sys.argv``).
        workers: train the runs in this many processes first (:func:`_pretrain`); 1 trains each in turn.

    Returns:
        The results dict also written to ``results.json``.
    """
    t_start = time.perf_counter()
    cfg = config or (quick_config() if quick else EvalConfig())
    if models is not None:
        cfg = dataclasses.replace(cfg, models=tuple(models))
    if seeds is not None:
        cfg = dataclasses.replace(cfg, seeds=tuple(int(s) for s in seeds))
    if device is not None:
        cfg = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, device=device))
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    data = load_dataset(data_dir)
    records = data.records
    provenance = {"command": command if command is not None else " ".join(sys.argv), "git_commit": _git_commit(),
                  "git_dirty": _git_dirty(),
                  "data_dir": str(data_dir), "data_manifest_sha256": data.manifest_sha256, "data_env": data.env,
                  "n_strokes": len(records), "n_categories": len({r.category for r in records}),
                  "n_instances": len({r.instance for r in records}), "seeds": list(cfg.seeds), "quick": quick,
                  "device": str(resolve_device(cfg.train.device)), "python": sys.version.split()[0],
                  "numerics": _numerics()}
    _keep_manifest(data, out_dir, "clean")  # after git_dirty: the evaluation's own writes do not count as changes
    features = featurize_records(records, cfg.train.feature_config, progress, "featurize clean")
    summaries = np.stack([summary_features(r) for r in records])
    ctx = _Context(data=data, out_dir=out_dir, config=cfg, features=features, summaries=summaries, progress=progress,
                   provenance={k: provenance[k] for k in ("command", "git_commit", "data_manifest_sha256")})
    figures: list[str] = []
    results: dict[str, Any] = {"paper": PAPER, "provenance": provenance,
                               "config": json.loads(json.dumps(dataclasses.asdict(cfg), default=str)),
                               "deviations": {**DEVIATIONS, **EVAL_DEVIATIONS}}
    stds = [f"{s:g}" for s in cfg.corruption_stds]
    results["deviations"]["robustness_noise"] = results["deviations"]["robustness_noise"].format(
        stds=" and ".join([", ".join(stds[:-1]), stds[-1]] if len(stds) > 1 else stds))
    groups = cfg.train.feature_config.accel.channel_groups
    if groups:
        results["deviations"]["accel_front_end"] = ACCEL_FRONT_END_DEVIATION.format(groups=list(map(list, groups)))

    ablation = list(cfg.ablation_models) if cfg.ablation else []
    if fire_dir is not None:
        ctx.fire = _load_fire(ctx, Path(fire_dir))
        provenance.update(fire_dir=str(fire_dir), fire_manifest_sha256=ctx.fire.data.manifest_sha256)
        _keep_manifest(ctx.fire.data, out_dir, "fire")
    jobs, rob = _experiment_jobs(ctx)
    ctx.store = RunStore(out_dir / OUTCOMES_FILE)
    ctx.outcomes = ctx.store.load()
    if workers > 1:  # Table 1 and the fire shift first, then the one-sensor runs and the robustness curve
        fire_runs = ([_fire_runs(ctx, m, s) for s in cfg.seeds for m in cfg.fire_models]
                     if ctx.fire is not None else [])
        _pretrain(ctx, [j for j in jobs if j.model in cfg.models] + [j for j in jobs if j.model not in cfg.models]
                  + [r[kind] for r in fire_runs for kind in ("clean", "scratch")], workers, on_fire=rob)
        _pretrain(ctx, [r["finetuned"] for r in fire_runs]  # these start from the clean checkpoints
                  + [job for _, job in _single_sensor_jobs(ctx)] + rob, workers, on_fire=rob)
    bar = tqdm(total=len(jobs) + len(rob), desc="evaluate", disable=not progress)

    per: dict[tuple[str, str], list] = {}
    for job in jobs:
        bar.set_postfix_str(f"{job.task} {job.model} {job.split_name}")
        per.setdefault((job.task, job.model), []).append(_run(ctx, job))
        bar.update()
    results["table1"] = {t: {m: _summary(per[(t, m)]) for m in cfg.models} for t in ("ssmc", "usmc", "fine")}
    results["category_recall"] = {t: {m: _category_recall(per[(t, m)]) for m in cfg.models} for t in ("ssmc", "usmc")}
    if "touchformer" in cfg.models:
        results["paired"] = {t: {m: _paired(per[(t, "touchformer")], per[(t, m)]) for m in cfg.models
                                 if m != "touchformer"} for t in ("ssmc", "usmc", "fine")}
    if cfg.missing_modality:
        results["missing_modality"] = {
            m: {**{d: _mean_std([r["missing"][d] for r in per[("usmc", m)]]) for d in MODALITIES},
                "none": _mean_std([r["accuracy"] for r in per[("usmc", m)]])} for m in cfg.models}
    if cfg.probes:
        results["probes"] = {t: {m: {"intact": _mean_std([r["accuracy"] for r in per[(t, m)]]),
                                     **{k: _mean_std([r["probes"][k] for r in per[(t, m)]])
                                        for k in ALTERATIONS if k in per[(t, m)][0]["probes"]}}
                                 for m in cfg.models} for t in ("ssmc", "usmc", "fine")}
        plot_probes(out_dir / "probes.png", results["probes"])
        figures.append("probes.png")
    if ablation:
        results["ablation"] = {m: {t: _mean_std([r["accuracy"] for r in per[(t, m)]]) for t in ("ssmc", "usmc", "fine")}
                               for m in ablation}
        steps = [(a, b) for a, b in (("touchformer_mag", "touchformer_fusion"), ("touchformer", "touchformer_mag"))
                 if a in ablation and b in ablation]  # what adding MAG, then CER, changes, stroke by stroke
        results["ablation_paired"] = [{"task": t, **_paired(per[(t, a)], per[(t, b)])}
                                      for a, b in steps for t in ("ssmc", "usmc", "fine")]

    variants = [m for m in dict.fromkeys(["touchformer"] + ablation) if ("ssmc", m) in per]
    results["modality_weights"] = {
        t: {m: {k: np.mean([r[k] for r in per[(t, m)]], axis=0).round(4).tolist()
                for k in ("alpha_mean", "gate_dropped_share")} for m in variants} for t in ("ssmc", "usmc", "fine")}

    # confusion matrices: each Table-1 model on SSMC (first seed), TouchFormer on USMC (all folds) and fine
    for model in cfg.models:
        run = per[("ssmc", model)][0]
        name = f"confusion_ssmc_{model}.png"
        plot_confusion(out_dir / name, run["_y_true"], run["_y_pred"], run["_names"],
                        f"{MODEL_LABEL.get(model, model)}, SSMC {run['split']}")
        figures.append(name)
    tf = "touchformer"
    if ("usmc", tf) in per:
        runs = per[("usmc", tf)]
        plot_confusion(out_dir / "confusion_usmc_touchformer.png", np.concatenate([r["_y_true"] for r in runs]),
                        np.concatenate([r["_y_pred"] for r in runs]), runs[0]["_names"], "TouchFormer, USMC, all folds")
        run = per[("fine", tf)][0]
        plot_confusion(out_dir / "confusion_fine_touchformer.png", run["_y_true"], run["_y_pred"], run["_names"],
                        f"TouchFormer, fine-grained {run['split']}")
        figures += ["confusion_usmc_touchformer.png", "confusion_fine_touchformer.png"]

    if cfg.tsne and ("ssmc", "touchformer") in per and ("ssmc", "touchformer_mag") in per:
        panels = []
        category_of = {r.instance: r.category for r in ctx.data.records}
        categories = sorted(set(category_of.values()))
        for task in ("ssmc", "fine"):
            for model, title in (("touchformer_mag", "without CER"), ("touchformer", "with CER")):
                run = per[(task, model)][0]
                colour = run["_y_true"]
                if task == "fine":  # 42 instances: coloured by their category, 7 colours a reader can tell apart
                    colour = np.array([categories.index(category_of[run["_names"][i]]) for i in run["_y_true"]])
                panels.append((f"{TASK_LABEL[task]}: {title} (seed {run['seed']}"
                               + (", coloured by category)" if task == "fine" else ")"), run["_embedding"], colour))
        plot_tsne(out_dir / "tsne.png", panels, cfg.seeds[0])
        figures.append("tsne.png")

    fit_runs = {m: per[("ssmc", m)][0] for m in cfg.models if m != "reference" and ("ssmc", m) in per}
    if fit_runs:
        results["fitting"] = _fitting_summary(per, list(dict.fromkeys(list(fit_runs) + ablation)))
        plot_training_curves(out_dir / "training_curves.png", fit_runs)
        figures.append("training_curves.png")

    if rob:
        rob_runs: dict[tuple[str, float, float | None], list[dict[str, Any]]] = {}
        for job in rob:
            model, p, std = job.model, job.corruption, job.corruption_std
            bar.set_postfix_str(f"robustness {model} p={p} std={std:g} {job.split_name}")
            rob_runs.setdefault((model, p, _noise_std(p, std)), []).append(_run(ctx, job))
            bar.update()
        levels = []
        for std in cfg.corruption_stds:
            runs = {m: {repr(float(p)): rob_runs[(m, float(p), _noise_std(p, std))] for p in cfg.corruption_ratios}
                    for m in cfg.robustness_models}
            per_seed = {m: {p: [r["accuracy"] for r in rs] for p, rs in by_p.items()} for m, by_p in runs.items()}
            levels.append({"corruption_std": std, **_curve_tables(per_seed),
                           "seed_wins": _seed_wins(per_seed, "touchformer"),
                           "paired_best_baseline": _paired_best_baseline(runs),
                           "checkpoints": {m: {p: [r.get("checkpoint") for r in rs] for p, rs in by_p.items()}
                                           for m, by_p in runs.items()}})
        results["robustness"] = {"seeds": list(cfg.seeds), "corruption_stds": list(cfg.corruption_stds),
                                 "levels": levels}
        plot_robustness(out_dir / "robustness.png", levels)
        figures.append("robustness.png")
        if ctx.fire is not None and cfg.robustness_fire:
            bar.set_postfix_str("robustness runs on fire strokes")
            results["robustness"]["fire_zero_shot"] = _robustness_on_fire(ctx, rob)
            plot_robustness(out_dir / "robustness_fire.png", results["robustness"]["fire_zero_shot"],
                             ylabel="zero-shot accuracy on fire strokes [%]",
                             title="trained with noise of std {std}; fire strokes, no test noise")
            figures.append("robustness_fire.png")
    bar.close()

    if cfg.single_sensor_models:
        results["single_sensor"] = _single_sensor_experiment(
            ctx, {m: per[("ssmc", m)] for m in cfg.single_sensor_models if ("ssmc", m) in per})
    if ctx.fire is not None:
        results["fire"] = _fire_experiment(ctx)
    results["failed_runs"] = _failed_runs(ctx.cache.values(), out_dir)
    results["figures"] = figures
    commits = Counter(r.get("git_commit") or "unknown" for r in ctx.cache.values() if r["model"] != "reference")
    provenance["run_commits"] = dict(commits.most_common())
    provenance["outcomes"] = {"file": OUTCOMES_FILE, "read": len(ctx.used), "scored_here": len(ctx.used & ctx.scored),
                              "from_store": len(ctx.used - ctx.scored)}
    results["seconds"] = time.perf_counter() - t_start
    (out_dir / "results.json").write_text(json.dumps(results, indent=2, default=_json_default), encoding="utf-8")
    write_report(out_dir / "REPORT.md", results)
    return results


def _keep_manifest(data: Dataset, out_dir: Path, name: str) -> None:
    """Copy the manifest of a data set the evaluation reads to ``out_dir/data_manifests/<name>-<id>.json``,
    ``<id>`` the first 12 digits of :func:`_strokes_id`: its shards' hashes name the strokes of every stored run,
    so a data set recorded again that no longer matches them can be compared shard by shard with the one they
    were trained on (kept under its own name)."""
    folder = out_dir / "data_manifests"
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{name}-{_strokes_id(data)[:12]}.json"
    path.write_text(json.dumps(data.manifest, indent=1, sort_keys=True) + "\n", encoding="utf-8")


def _numerics() -> dict[str, Any]:
    """:func:`perception.numerics.numeric_environment` for featurising, training and scoring, with the CPU code
    path torch chose (its kernels, like BLAS's, round by the CPU)."""
    import torch

    return {**numeric_environment(EVALUATION_PACKAGES), "torch_cpu_capability": torch.backends.cpu.get_cpu_capability()}


def kept_manifest_match(data: Dataset, out_dir: str | os.PathLike, name: str) -> dict[str, Any]:
    """Whether a data set's strokes are those of a manifest kept in ``out_dir/data_manifests/``
    (:func:`_keep_manifest`), that is whether the stored runs trained on ``name`` data can be reused on it.
    When none matches: how many shards differ from the closest kept manifest, and what differs in the numerics
    the two recordings record (:mod:`perception.numerics`; an older manifest has none), so a recording made on
    another machine can be told from one made by other code or options."""
    strokes = _strokes_id(data)[:12]
    folder = Path(out_dir) / "data_manifests"
    if (folder / f"{name}-{strokes}.json").is_file():
        return {"strokes": strokes, "kept": True}
    here = {str(s.get("file")): s.get("sha256") for s in data.manifest.get("shards") or []}
    best: tuple[int, str, dict[str, Any]] | None = None
    for path in sorted(folder.glob(f"{name}-*.json")):
        try:
            kept = json.loads(path.read_text(encoding="utf-8"))
            there = {str(s.get("file")): s.get("sha256") for s in kept.get("shards") or []}
        except (OSError, ValueError, AttributeError):
            continue  # not a manifest: nothing to compare with
        differing = sum(here.get(f) != sha for f, sha in there.items()) + len(set(here) - set(there))
        if best is None or differing < best[0]:
            best = (differing, path.name, kept)
    if best is None:
        return {"strokes": strokes, "kept": False}
    differing, kept_name, kept = best
    same_recorder = (data.manifest.get("recorder_sha256") == kept.get("recorder_sha256")
                     and data.manifest.get("config") == kept.get("config"))
    return {"strokes": strokes, "kept": False, "closest": kept_name, "differing_shards": differing,
            "shards": len(here), "same_code_and_options": same_recorder,
            "numerics_changed": numerics_differences(data.manifest.get("numerics"), kept.get("numerics"),
                                                     results_only=True)}


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return str(value)


def _load_fire(ctx: _Context, fire_dir: Path, featurize: bool = True) -> _FireData:
    """Load and featurise the fire data set (``featurize=False``: only its strokes and splits, to name runs);
    its categories must occur in the clean data."""
    fire = load_dataset(fire_dir)
    names = tuple(sorted({r.category for r in ctx.data.records}))
    unknown = sorted({r.category for r in fire.records} - set(names))
    if unknown:
        raise ValueError(f"{fire_dir}: fire categories {unknown} do not occur in the clean data")
    features, summaries = [], np.zeros((0, 0))
    if featurize:
        features = featurize_records(fire.records, ctx.config.train.feature_config, ctx.progress, "featurize fire")
        summaries = np.stack([summary_features(r) for r in fire.records])
    splits = {s: ssmc_split(fire.records, s) for s in ctx.config.seeds}
    return _FireData(data=fire, features=features, summaries=summaries, splits=splits, class_names=names,
                     clean_train={s: clean_training_part(ctx.data.records, fire.records, splits[s][1], s)
                                  for s in ctx.config.seeds})


def _stroke_key(record: StrokeRecord) -> tuple[Any, ...] | None:
    """What makes two recorded strokes the same physical stroke: material instance, object and stroke draw
    (``None`` for a stroke whose meta lacks them, e.g. a converted real recording)."""
    meta = record.meta or {}
    if "object_id" not in meta or "stroke_seed" not in meta:
        return None
    return record.instance, str(meta["object_id"]), int(meta["stroke_seed"])


def clean_training_part(clean: Sequence[StrokeRecord], fire: Sequence[StrokeRecord], fire_test: np.ndarray,
                        seed: int) -> np.ndarray:
    """Indices of the clean strokes a clean-only model of the clean -> fire experiment trains on: the clean SSMC
    training part of ``seed``, without any stroke that is the clean twin of a fire test stroke (the same
    instance, object and stroke draw recorded in the other environment; ``robotdemo dataset`` with the same
    ``--seed`` records such twins). Trained on all clean strokes, a model had seen the twin of every fire test
    stroke, and zero-shot read high (the reference classifier by about 4 points)."""
    train, _ = ssmc_split(clean, seed)
    twins = {_stroke_key(fire[i]) for i in fire_test} - {None}
    return np.array([i for i in train if _stroke_key(clean[i]) not in twins], dtype=np.int64)


def _fire_runs(ctx: _Context, model: str, seed: int) -> dict[str, _TrainJob]:
    """The three runs of ``model`` with ``seed`` in the clean -> fire experiment: ``clean`` (the clean strokes of
    :func:`clean_training_part`, validation carved from them), ``finetuned`` (from the clean checkpoint, on the
    fire training part of the seed's split) and ``scratch`` (that fire training part only)."""
    assert ctx.fire is not None
    cfg, fire, s = ctx.config, ctx.fire, seed
    clean = _TrainJob(model, "ssmc", "clean_train", s, (fire.clean_train[s], np.zeros(0, dtype=np.int64)),
                      run_name=f"fire/seed{s}/clean_{model}", class_names=fire.class_names, score_on="fire")
    on_fire = dict(source="fire", class_names=fire.class_names)
    tune = (("init_checkpoint", str(clean.run_dir(ctx) / CHECKPOINT_DIR)), ("epochs", cfg.fine_tune_epochs),
            ("lr", cfg.fine_tune_lr))
    return {"clean": clean,
            "finetuned": _TrainJob(model, "ssmc", "fire", s, fire.splits[s], run_name=f"fire/seed{s}/finetuned_{model}",
                                   train_changes=tune, parent=clean, **on_fire),
            "scratch": _TrainJob(model, "ssmc", "fire", s, fire.splits[s], run_name=f"fire/seed{s}/scratch_{model}",
                                 **on_fire)}


def _fire_experiment(ctx: _Context) -> dict[str, Any]:
    """Each row (network or reference, and how it was trained) scored on the fire test part of every seed's
    split: the per-seed figures and their mean ± std."""
    assert ctx.fire is not None
    cfg, fire = ctx.config, ctx.fire
    names = fire.class_names
    combustible = {r.category: r.combustible for r in ctx.data.records}
    rows: dict[str, dict[str, Any]] = {}

    def score(seed: int, label: str, model: str, run_name: str, pred: np.ndarray) -> None:
        """Score ``pred``, class indices of the seed's fire test strokes."""
        fire_test = fire.splits[seed][1]
        y = np.array([names.index(fire.data.records[i].category) for i in fire_test])
        comb_true = np.array([combustible[names[k]] for k in y])
        comb_pred = np.array([combustible[names[k]] for k in pred])
        row = rows.setdefault(label, {"label": label, "model": model, "runs": []})
        row["runs"].append({"seed": seed, "run": run_name, "accuracy": float(np.mean(pred == y)),
                            "g_mean": g_mean(y, pred, range(len(names))),
                            "combustible_accuracy": float(np.mean(comb_true == comb_pred)),
                            "n_test": int(len(fire_test))})

    for seed in cfg.seeds:
        clean_train = fire.clean_train[seed]
        ref = ReferenceClassifier(ReferenceConfig()).pipeline.fit(
            ctx.summaries[clean_train], [ctx.data.records[i].category for i in clean_train])
        for model in cfg.fire_models:
            label, runs = MODEL_LABEL.get(model, model), _fire_runs(ctx, model, seed)
            for kind, title in (("clean", "clean only (zero-shot on fire)"),
                                ("finetuned", "clean + fine-tuned on fire"), ("scratch", "fire only")):
                run = _run(ctx, runs[kind])
                score(seed, f"{label}, {title}", model, runs[kind].run_name,
                      run["_score_pred"] if kind == "clean" else run["_y_pred"])
        fire_test = fire.splits[seed][1]
        score(seed, "reference, clean only (zero-shot on fire)", "reference", "",
              np.array([names.index(str(p)) for p in ref.predict(fire.summaries[fire_test])]))
        ref_fire = _run(ctx, _TrainJob("reference", "ssmc", "fire", seed, fire.splits[seed],
                                           run_name=f"fire/seed{seed}/reference", source="fire", class_names=names))
        score(seed, "reference, fire only", "reference", "", ref_fire["_y_pred"])
    for row in rows.values():
        row.update({key: _mean_std([r[key] for r in row["runs"]])
                    for key in ("accuracy", "g_mean", "combustible_accuracy")})
    s0 = fire.splits[cfg.seeds[0]]
    return {"split": "ssmc seeds " + ", ".join(map(str, cfg.seeds)), "n_fire_train": int(len(s0[0])),
            "n_fire_test": int(len(s0[1])), "n_clean_train": int(len(fire.clean_train[cfg.seeds[0]])),
            "rows": list(rows.values())}


def _zero_shot_test(ctx: _Context, job: _TrainJob) -> np.ndarray:
    """The fire strokes ``job``'s run is scored on zero-shot: the test part of its seed's SSMC split of the fire
    data set, without any stroke whose clean twin (:func:`_stroke_key`) the run trained on (a twin read high,
    see :func:`clean_training_part`; with ``robotdemo dataset``'s splits there is none)."""
    assert ctx.fire is not None
    seen = {_stroke_key(ctx.data.records[i]) for i in job.split[0]} - {None}
    return np.array([i for i in ctx.fire.splits[job.seed][1] if _stroke_key(ctx.fire.data.records[i]) not in seen],
                    dtype=np.int64)


def _zero_shot_id(ctx: _Context, job: _TrainJob) -> str:
    """The run store's name for the zero-shot fire score of ``job``'s run: that run's outcome id, the fire data
    set's strokes and the strokes scored (:func:`_zero_shot_test`)."""
    assert ctx.fire is not None
    return outcome_id({"zero_shot_of": _outcome_id(ctx, job), "data": _strokes_id(ctx.fire.data),
                       "test": indices_sha256(_zero_shot_test(ctx, job))})


def _zero_shot_on_fire(ctx: _Context, job: _TrainJob) -> dict[str, Any]:
    """``job``'s run (a network trained on clean strokes) scored on the fire strokes of :func:`_zero_shot_test`
    without test noise: accuracy, how many strokes, and the gate's modality weights on them
    (:func:`_modality_weights`; even over the present sensors for a model without a gate), and ``stored_test_agreement``: the share of
    the run's own (clean) test strokes on which the scored checkpoint predicts what the run store holds for the
    run. The predictions come from the run store, or from the run's checkpoint now (a gone run folder is trained
    again, :func:`_train_job`: seeded, but on another machine or library version the weights may differ, which
    the agreement shows) and are added to it."""
    assert ctx.fire is not None
    run_id = _zero_shot_id(ctx, job)
    test = _zero_shot_test(ctx, job)
    outcome = ctx.outcomes.get(run_id)
    if outcome is None:
        stored = _outcome(ctx, job)["pred"]["none"]
        res, cfg, _ = _train_job(ctx, job)
        device = resolve_device(cfg.device)
        ckpt = load_checkpoint(res.checkpoint_dir, device=device)
        dims, modalities = feature_dims(ckpt.feature_config), ckpt.feature_config.modalities
        again = predict(ckpt.model, [keep_modalities(ctx.features[i], modalities) for i in job.split[1]], dims,
                        stats=ckpt.norm_stats, device=device, **_test_noise(job)).pred
        feats = [keep_modalities(ctx.fire.features[i], modalities) for i in test]
        preds = predict(ckpt.model, feats, dims, stats=ckpt.norm_stats, device=device)
        outcome = {"pred": preds.pred.tolist(), **_modality_weights(preds.alphas, feats),
                   "stored_test_agreement": round(float(np.mean(again == np.asarray(stored))), 4)}
        if ctx.store is not None:
            ctx.store.append(run_id, f"{job.run_dir(ctx).relative_to(ctx.out_dir).as_posix()} zero-shot on fire",
                             outcome)
        ctx.outcomes[run_id] = outcome
        ctx.scored.add(run_id)
    ctx.used.add(run_id)
    names = _job_names(ctx, job)
    y = np.array([names.index(ctx.fire.data.records[i].category) for i in test], dtype=np.int64)
    pred = np.asarray(outcome["pred"], dtype=np.int64)
    return {"accuracy": float(np.mean(pred == y)) if len(y) else float("nan"), "n_test": int(len(y)),
            "alpha_mean": outcome["alpha_mean"], "stored_test_agreement": outcome["stored_test_agreement"]}


def _curve_tables(per_seed: Mapping[str, Mapping[str, Sequence[float]]]) -> dict[str, Any]:
    """A robustness level's tables from the per-seed figures (model -> p -> one figure per seed): their mean
    (``curves``), sample std (``curves_std``) and the figures themselves (``per_seed``)."""
    stats = {m: {p: _mean_std(values) for p, values in curve.items()} for m, curve in per_seed.items()}
    return {"curves": {m: {p: st["mean"] for p, st in curve.items()} for m, curve in stats.items()},
            "curves_std": {m: {p: st["std"] for p, st in curve.items()} for m, curve in stats.items()},
            "per_seed": {m: dict(curve) for m, curve in per_seed.items()}}


def _robustness_on_fire(ctx: _Context, rob: Sequence[_TrainJob]) -> list[dict[str, Any]]:
    """Per noise intensity: every robustness-curve model's mean ± std (over the seeds) zero-shot accuracy on the
    fire strokes against p (:func:`_zero_shot_on_fire`), and TouchFormer's mean gate weights on them."""
    cfg = ctx.config
    scores: dict[tuple[str, float, float | None], list[dict[str, Any]]] = {}
    for job in tqdm(rob, desc="robustness runs on fire strokes", disable=not ctx.progress, leave=False):
        key = (job.model, job.corruption, _noise_std(job.corruption, job.corruption_std))
        scores.setdefault(key, []).append(_zero_shot_on_fire(ctx, job))
    levels = []
    for std in cfg.corruption_stds:
        cell = {m: {repr(float(p)): scores[(m, float(p), _noise_std(p, std))] for p in cfg.corruption_ratios}
                for m in cfg.robustness_models}
        levels.append({"corruption_std": std,
                       **_curve_tables({m: {p: [r["accuracy"] for r in runs] for p, runs in curve.items()}
                                        for m, curve in cell.items()}),
                       "n_test": {m: {p: [r["n_test"] for r in runs] for p, runs in curve.items()}
                                  for m, curve in cell.items()},
                       "stored_test_agreement": {m: {p: [r["stored_test_agreement"] for r in runs]
                                                     for p, runs in curve.items()} for m, curve in cell.items()},
                       "alpha_mean": {m: {p: np.mean([r["alpha_mean"] for r in runs], axis=0).round(4).tolist()
                                          for p, runs in curve.items()}
                                      for m, curve in cell.items() if m.startswith("touchformer")}})
    return levels


def command_config(quick: bool = False, ablation: bool = True, robustness: bool = True,
                   corruption_stds: Sequence[float] | None = None, seeds: Sequence[int] | None = None,
                   single_sensor: bool = True, accel_axes: str = "sum") -> EvalConfig:
    """The evaluation ``robotdemo evaluate``'s options ask for (``--quick``, ``--no-ablation``,
    ``--no-robustness``, ``--corruption-stds``, ``--seeds``, ``--no-single-sensor``, ``--accel-axes``: a key of
    :data:`perception.features.ACCEL_AXES`, the accelerometer front end of every network run).

    Raises:
        ValueError: ``accel_axes`` is not a key of :data:`~perception.features.ACCEL_AXES`.
    """
    config = quick_config() if quick else EvalConfig()
    train = dataclasses.replace(config.train, feature_config=with_accel_axes(config.train.feature_config, accel_axes))
    return dataclasses.replace(config, ablation=ablation and config.ablation, train=train,
                               robustness_models=config.robustness_models if robustness else (),
                               single_sensor_models=config.single_sensor_models if single_sensor else (),
                               corruption_stds=tuple(float(s) for s in (corruption_stds or config.corruption_stds)),
                               seeds=tuple(int(s) for s in seeds) if seeds is not None else config.seeds)


def evaluate_command(data_dir: str | os.PathLike, out_dir: str | os.PathLike, quick: bool = False,
                     fire_dir: str | os.PathLike | None = None, device: str = "auto",
                     seeds: Sequence[int] | None = None, models: Sequence[str] | None = None,
                     command: str = "", progress: bool = True, workers: int = 1, ablation: bool = True,
                     robustness: bool = True, corruption_stds: Sequence[float] | None = None,
                     single_sensor: bool = True, accel_axes: str = "sum") -> dict[str, Any]:
    """``robotdemo evaluate``: run :func:`evaluate`, return a short summary (report path, headline accuracies).
    ``ablation=False`` / ``robustness=False`` / ``single_sensor=False`` leave those experiments out (the report
    says so); ``corruption_stds`` replaces the robustness curve's noise intensities; ``accel_axes`` names the
    accelerometer front end (:func:`command_config`; the report lists it as a deviation where it is not the
    paper's)."""
    config = command_config(quick, ablation, robustness, corruption_stds, single_sensor=single_sensor,
                            accel_axes=accel_axes)
    results = evaluate(data_dir, out_dir, quick=quick, models=models, seeds=seeds, fire_dir=fire_dir, device=device,
                       progress=progress, command=command or None, config=config, workers=workers)
    headline = {task: {m: s["accuracy"]["mean"] for m, s in per.items()} for task, per in results["table1"].items()}
    return {"report": str(Path(out_dir) / "REPORT.md"), "results": str(Path(out_dir) / "results.json"),
            "accuracy": headline, "seconds": results["seconds"]}
