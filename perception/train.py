"""Training of every registered material classifier: seeded, resumable, best epoch chosen on validation.

One call to :func:`train` featurizes the strokes once, fits the feature normalisation on the training part,
and runs ``epochs`` epochs of mini-batch training with ``L_cls + lambda * L_C`` (the CER term only where the
model config's ``cer_lambda`` > 0, :func:`perception.losses.total_loss`). After each epoch it

1. measures validation accuracy; a strictly better one saves the model with
   :func:`perception.checkpoint.save_checkpoint` to ``out_dir/checkpoint/`` (the "best epoch");
2. writes ``out_dir/resume/state.safetensors`` (model and optimizer tensors) and ``out_dir/resume/state.json``
   (epoch, optimizer hyper-parameters, best so far, history, the run's config).

A second call with the same ``out_dir`` and config continues after the last finished epoch and ends with the
same weights as an uninterrupted run: the data order, dropout and augmentation noise of epoch ``e`` are all
drawn from generators seeded with ``(seed, e)``, and the learning rate is a pure function of the step.

Training settings versus the paper are listed, with the measurements behind them, in :data:`DEVIATIONS`.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np
import safetensors.torch
import scipy.stats
import torch
import torch.nn as nn
from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn
from tqdm.auto import tqdm

from perception.atomic import atomic_write
from perception.baselines import MODEL_REGISTRY, build_model
from perception.calibration import fit_temperature, nll
from perception.checkpoint import (WEIGHTS_FILE, config_from_dict, config_to_dict, load_checkpoint, save_checkpoint,
                                   set_temperature, tuplify)
from perception.dataset import TASKS, labels_of, sha256_file
from perception.features import (FeatureBatch, FeatureConfig, NormStats, StrokeFeatures, collate, feature_dims,
                                 featurize, fit_norm_stats, frame_clock_s, keep_modalities, normalize)
from perception import sam
from perception.losses import LossTerms, total_loss, unimodal_cross_entropy
from perception.sensor_use import presence_matrix, sensor_use
from perception.streams import MODALITIES, StrokeRecord
from perception.touchformer import ModelOutput

RESUME_DIR = "resume"
CHECKPOINT_DIR = "checkpoint"
RESULT_FILE = "train_result.json"
# test-time corruption noise is drawn from seed + this offset (evaluate's robustness runs and train_command),
# so that it differs from the training run's own draws
TEST_CORRUPTION_SEED_OFFSET = 12345
# TrainConfig fields that say where a run trains, not what it trains: a run folder resumes whatever they are
# (a run begun with "auto" on a GPU machine goes on with "cpu" elsewhere, or with another thread count)
PLACEMENT_FIELDS = ("device", "num_threads")
# TrainConfig fields added after runs were stored, left out of a run's identity at the value those runs trained
# with, so that adding a field does not make every stored run stale
TRAIN_IDENTITY_OMITS: dict[str, Any] = {"ema_decay": 0.0, "feature_mask": 0.0, "mixup_alpha": 0.0,
                                         "aux_parameters_weight": 0.0, "sam_rho": 0.0, "batch_per_class": 0}
# The same for fields added to a front end's config (each of feature_config's spectral front ends)
SPECTRAL_IDENTITY_OMITS: dict[str, Any] = {"channel_groups": ()}


def _without_omitted(data: Mapping[str, Any], omits: Mapping[str, Any]) -> dict[str, Any]:
    """``data`` (JSON data) without the fields of ``omits`` that hold the value given there, compared as JSON
    (a tuple default is a list in ``data``)."""
    return {k: v for k, v in data.items() if not (k in omits and v == json.loads(json.dumps(omits[k])))}


DEVIATIONS: dict[str, str] = {
    "optimizer": (
        "AdamW (decoupled weight decay 0.01) at lr 3e-3 instead of the paper's Adam, weight decay 0.1, lr 0.1. "
        "Measured on a seeded synthetic fine-grained task (tests/test_dataset.make_material_strokes, 3 categories x "
        "3 instances, noise 1.5, 81 train / 18 val / 45 test strokes; TouchFormer d_model 32, 1 layer; 30 epochs, "
        "batch 32, cosine; seeds 0 and 1; test accuracy): paper's Adam lr 0.1 wd 0.1 -> 0.49 / 0.56 (training "
        "loss climbs back to ln 9 = chance after epoch 2: divergence); Adam lr 1e-3 wd 0.1 (coupled L2) -> "
        "0.71 / 0.47; AdamW lr 1e-3 wd 0.1 -> 0.82 / 0.91 (wd 0.01 identical); AdamW lr 3e-3 wd 0.01 -> "
        "0.89 / 0.93; AdamW lr 1e-2 wd 0.01 -> 0.98 / 0.84 (less stable). The authors' code uses lr 1e-3."),
    "batch_size": ("32 as in the paper (the authors' code uses 64: 0.48 vs 0.67 test accuracy at 15 epochs, "
                   "lr 1e-3, seed 0 of the task above, fewer steps); the evaluation's quick mode uses 16."),
    "schedule": "cosine decay to 0 as in the paper, applied per step rather than per epoch.",
    "grad_clip": ("gradient norm clipped at 1.0 (not in the paper) as a guard; it did not change the paper-setting "
                  "run above (identical losses with and without: Adam normalises the step)."),
    "validation": (
        "the best epoch is chosen on a validation part carved from the training part (15% by default); the "
        "authors' code picks it on the test fold."),
    "feature_noise": (
        "Gaussian noise of std 0.05 (in units of the per-channel training std) on the normalised features "
        "during training, as in the authors' code (the paper does not mention it)."),
    "gate_temperature": (
        "TouchFormer's MAG weights are softmax(g / 0.2) over the kept gates instead of eq. 3's softmax(g): with "
        "gates in [0, 1], eq. 3 keeps every weight of four modalities at 0.11 or more. Measured on data/clean "
        "(manifest 59c70989), mean best validation accuracy, `robotdemo train --task ssmc|usmc --model "
        "touchformer --epochs 50 --group-by-length`, SSMC seeds 0-4, USMC folds 0-4: temperature 0.2 -> SSMC "
        "78.8 %, USMC 77.6 %; temperature 1 -> 76.1 %, 73.5 %. Fine-grained (seeds 0-2): 44.4 % against 45.2 %. "
        "The ablation '+MAG' shares it; the variant touchformer_soft keeps 1."),
    "final_norm": (
        "TouchFormer's intra-modal Transformer ends without a LayerNorm (MulT and nanoGPT end with one; the paper "
        "names none), so the size of each step's features reaches the pooling as in MTCNN. Measured on data/clean "
        "(manifest 59c70989), mean best validation accuracy, `robotdemo train --task ssmc|usmc|fine --model "
        "touchformer --epochs 50 --group-by-length`, SSMC and fine-grained seeds 0-2, USMC folds 0-4: without it "
        "83.5 / 77.5 / 47.6 %, with it 79.4 / 76.1 / 46.0 %. The ablation rows share it; the variant "
        "touchformer_soft keeps the LayerNorm (without it 83.0 / 76.4 / 48.4 % against 81.5 / 77.5 / 51.3 %). "
        "Read after the choice, in the evaluation rerun with it: test 76.7 / 65.4 / 41.0 % against 75.7 / 64.8 / "
        "40.5 %, and one cost, clean -> fire zero-shot 53.0 % against 63.8 % (seeds 0-2; measured while the "
        "clean models still trained on the clean twin of every fire test stroke, before session 25)."),
}
"""Deviation from the paper -> what we do and the measurement that justified it (quoted in REPORT.md)."""


class TrainError(RuntimeError):
    """Training cannot start or resume (bad config, mismatched resume state, unknown labels)."""


class StaleRunError(TrainError):
    """The run folder holds a run of another config, model, class list or data (or weights of another
    architecture), so it cannot be resumed."""


@dataclass(frozen=True)
class TrainConfig:
    """Everything that determines a training run (saved in the checkpoint and the resume state).

    Attributes:
        model: key of :data:`perception.baselines.MODEL_REGISTRY`.
        task: "ssmc" or "usmc" (label: category) or "fine" (label: instance).
        epochs: training epochs.
        batch_size: strokes per step.
        lr: initial learning rate.
        weight_decay: weight decay (decoupled for "adamw", L2 for "adam").
        optimizer: "adamw" or "adam".
        schedule: "cosine" (per step, to 0 at the last step) or "constant".
        warmup_epochs: the lr rises linearly from 0 over this many epochs (per step) before the schedule; 0
            starts at ``lr`` as the paper does.
        label_smoothing: cross-entropy label smoothing (0: the paper's plain cross-entropy).
        grad_clip: max gradient norm; 0 disables clipping.
        seed: seeds the model init, data order, dropout and augmentation.
        device: "auto" (CUDA when available), "cpu" or "cuda".
        feature_noise_std: augmentation noise on normalised features (units of the training std), training only.
        corruption_ratio: robustness experiment: probability that each modality of a sample gets Gaussian
            noise of std ``corruption_std`` (training and validation; the test uses the same via
            :func:`predict`).
        corruption_std: corruption noise std in units of the per-channel training feature std.
        val_fraction: validation share of the training part (used by :func:`train_command`).
        train_fraction: share of the training part (after validation is carved from it) that is trained on,
            stratified by the task's label and seeded by ``seed`` (:func:`task_split`); validation and test stay
            the same, so runs at several fractions draw a learning curve. 1 trains on all of it.
        split_by_object: SSMC and fine-grained: keep all strokes of one physical object on one side of the
            test split and of the validation split (stricter than the paper's split by stroke; what a robot
            meeting new objects needs to be selected on). USMC always holds out whole instances.
        val_by_instance: SSMC and USMC: the validation part holds out whole material instances of the
            training part (:func:`perception.dataset.validation_split`), as USMC's test part does, so the best
            epoch is the one that does best on instances not trained on. Off by default: validation strokes
            come from objects (USMC) or strokes (SSMC) of instances that are trained on.
        num_threads: torch CPU threads; 0 leaves torch's default.
        group_by_length: batches of strokes of similar length (:func:`length_grouped_batches`) instead of
            uniformly shuffled ones, so that less of each batch is padding. Off by default: the committed robot
            checkpoint was trained without it, and its training command must reproduce it.
        time_crop: training only: each stroke is cut to a random window covering a uniform share in
            [``time_crop``, 1] of its duration, the same share of every stream (:func:`crop_in_time`); 1 disables it.
        modality_dropout: training only: probability that each present modality of a sample is removed (marked
            missing, as a sensor that dropped out; :func:`drop_modalities`), at least one kept per sample.
            Trains a model not to lean on one stream alone. 0 disables it.
        feature_mask: training only: SpecAugment-style masking (Park et al. 2019). In every present modality of
            every sample one band of consecutive feature channels and one span of consecutive valid steps are
            set to 0 (the training mean in normalised units), each as wide as a uniform share in
            [0, ``feature_mask``] of the channels or of the stroke's steps (:func:`mask_features`); 0 disables it.
        mixup_alpha: training only: mixup (Zhang et al. 2018). Each batch is blended with a shuffled copy of
            itself at a weight drawn from Beta(alpha, alpha) (:func:`mixup_batch`), and the cross-entropy is the
            same blend of the two strokes' labels; CER keeps the label of the larger share. 0 disables it.
        model_overrides: (field, value) pairs passed to the model config (e.g. (("d_model", 32),)).
        ema_decay: keep an exponential moving average of the weights (Polyak averaging, decay per training step,
            :class:`torch.optim.swa_utils.AveragedModel`); validation, the best-epoch checkpoint and the resume
            state use the average. 0 disables it (the paper's plain weights).
        aux_parameters_weight: training only, not the paper's: weight of an auxiliary loss, the mean squared
            error of a linear head on the embedding regressing each training stroke's material parameters
            (``aux_targets_train`` of :func:`train`, z-scored on the training strokes). The parameters are
            privileged information, known in simulation and not in real recordings; the head is dropped after
            training, so the checkpoint and inference are the model's own. 0 disables it.
        sam_rho: sharpness-aware minimisation (:mod:`perception.sam`): each step takes the gradient at the
            weights moved by this l2 distance up the batch's gradient, so training seeks flat minima (two forward
            and backward passes a step). 0 disables it (the paper's plain AdamW step).
        batch_per_class: training only, not the paper's: each batch is drawn as ``batch_size // batch_per_class``
            chunks of ``batch_per_class`` strokes of one label each (P x K sampling, :func:`class_balanced_batches`),
            so that every anchor of CER's contrastive loss has positives in its batch. With plain batches of 32 and
            the fine-grained task's 42 instances, about 4 anchors in 10 have none and add nothing to the loss.
            Every stroke is still seen once per epoch. 0 (the default) draws batches without regard to labels.
        init_checkpoint: checkpoint folder to fine-tune from ("" trains from scratch); its norm stats and
            class names are kept.
        feature_config: the front end.
    """

    model: str = "touchformer"
    task: str = "ssmc"
    epochs: int = 50
    batch_size: int = 32
    lr: float = 3e-3
    weight_decay: float = 0.01
    optimizer: str = "adamw"
    schedule: str = "cosine"
    warmup_epochs: int = 0
    label_smoothing: float = 0.0
    grad_clip: float = 1.0
    seed: int = 0
    device: str = "auto"
    feature_noise_std: float = 0.05
    corruption_ratio: float = 0.0
    corruption_std: float = 1.0
    val_fraction: float = 0.15
    train_fraction: float = 1.0
    split_by_object: bool = False
    val_by_instance: bool = False
    num_threads: int = 0
    group_by_length: bool = False
    modality_dropout: float = 0.0
    time_crop: float = 1.0
    ema_decay: float = 0.0
    feature_mask: float = 0.0
    mixup_alpha: float = 0.0
    aux_parameters_weight: float = 0.0
    sam_rho: float = 0.0
    batch_per_class: int = 0
    model_overrides: tuple[tuple[str, Any], ...] = ()
    init_checkpoint: str = ""
    feature_config: FeatureConfig = field(default_factory=FeatureConfig)

    def __post_init__(self) -> None:
        if self.model not in MODEL_REGISTRY:
            raise ValueError(f"unknown model {self.model!r}; known: {sorted(MODEL_REGISTRY)}")
        if self.task not in TASKS:
            raise ValueError(f"unknown task {self.task!r}; expected one of {TASKS}")
        if self.optimizer not in ("adam", "adamw"):
            raise ValueError(f"optimizer must be 'adam' or 'adamw', got {self.optimizer!r}")
        if self.schedule not in ("cosine", "constant"):
            raise ValueError(f"schedule must be 'cosine' or 'constant', got {self.schedule!r}")
        if self.epochs < 1 or self.batch_size < 1:
            raise ValueError(f"epochs and batch_size must be >= 1, got {self.epochs} and {self.batch_size}")
        if not 0 <= self.warmup_epochs < self.epochs:
            raise ValueError(f"warmup_epochs must lie in [0, epochs), got {self.warmup_epochs}")
        if not (math.isfinite(self.lr) and self.lr > 0):
            raise ValueError(f"lr must be a positive number, got {self.lr}")
        if not (math.isfinite(self.weight_decay) and self.weight_decay >= 0):
            raise ValueError(f"weight_decay must be a number >= 0, got {self.weight_decay}")
        if not (math.isfinite(self.feature_noise_std) and self.feature_noise_std >= 0):
            raise ValueError(f"feature_noise_std must be a number >= 0, got {self.feature_noise_std}")
        for key, value in self.model_overrides:
            if key in ("in_dims", "n_classes", "frame_clock_s"):
                raise ValueError(f"model option {key} comes from the data and its features, not from an option")
            if isinstance(value, float) and not math.isfinite(value):
                raise ValueError(f"model option {key} must be finite, got {value}")
            if key.endswith("dropout") and not (isinstance(value, (int, float)) and 0.0 <= value < 1.0):
                raise ValueError(f"model option {key} must lie in [0, 1), got {value!r}")
        if not 0.0 <= self.label_smoothing < 1.0:
            raise ValueError(f"label_smoothing must lie in [0, 1), got {self.label_smoothing}")
        if self.device not in ("auto", "cpu", "cuda"):
            raise ValueError(f"device must be 'auto', 'cpu' or 'cuda', got {self.device!r}")
        if not 0.0 <= self.corruption_ratio <= 1.0:
            raise ValueError(f"corruption_ratio must lie in [0, 1], got {self.corruption_ratio}")
        if not self.corruption_std >= 0.0:
            raise ValueError(f"corruption_std must be >= 0, got {self.corruption_std}")
        if not 0.0 <= self.modality_dropout < 1.0:
            raise ValueError(f"modality_dropout must lie in [0, 1), got {self.modality_dropout}")
        if not 0.0 < self.time_crop <= 1.0:
            raise ValueError(f"time_crop must lie in (0, 1], got {self.time_crop}")
        if not 0.0 <= self.feature_mask < 1.0:
            raise ValueError(f"feature_mask must lie in [0, 1), got {self.feature_mask}")
        if not (self.mixup_alpha >= 0.0 and math.isfinite(self.mixup_alpha)):
            raise ValueError(f"mixup_alpha must be a finite number >= 0, got {self.mixup_alpha}")
        if not (self.aux_parameters_weight >= 0.0 and math.isfinite(self.aux_parameters_weight)):
            raise ValueError(f"aux_parameters_weight must be a finite number >= 0, got {self.aux_parameters_weight}")
        if self.aux_parameters_weight > 0 and self.mixup_alpha > 0:
            raise ValueError("aux_parameters_weight and mixup_alpha cannot both be on: a mixed stroke has no one "
                             "object's parameters")
        if not (self.sam_rho >= 0.0 and math.isfinite(self.sam_rho)):
            raise ValueError(f"sam_rho must be a finite number >= 0, got {self.sam_rho}")
        if not (isinstance(self.batch_per_class, int) and not isinstance(self.batch_per_class, bool)
                and 0 <= self.batch_per_class <= self.batch_size):
            raise ValueError(f"batch_per_class must be a whole number in [0, batch_size {self.batch_size}], "
                             f"got {self.batch_per_class!r}")
        if not 0.0 <= self.ema_decay < 1.0:
            raise ValueError(f"ema_decay must lie in [0, 1), got {self.ema_decay}")
        if not math.isfinite(self.corruption_std):
            raise ValueError(f"corruption_std must be finite, got {self.corruption_std}")
        if not 0.0 <= self.val_fraction < 1.0:
            raise ValueError(f"val_fraction must lie in [0, 1), got {self.val_fraction}")
        if not 0.0 < self.train_fraction <= 1.0:
            raise ValueError(f"train_fraction must lie in (0, 1], got {self.train_fraction}")

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON data (tuples become lists)."""
        return json.loads(json.dumps(config_to_dict(self)))

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> TrainConfig:
        data = dict(data)
        data["model_overrides"] = tuple((str(k), tuplify(v)) for k, v in data.get("model_overrides", ()))
        fc = data.pop("feature_config", None)
        config = config_from_dict(cls, {k: v for k, v in data.items() if k != "model_overrides"})
        return dataclasses.replace(config, model_overrides=data["model_overrides"],
                                   feature_config=FeatureConfig() if fc is None else config_from_dict(FeatureConfig, fc))


def with_frame_clock(options: Mapping[str, Any], feature_config: FeatureConfig) -> dict[str, Any]:
    """Model options plus, with TouchFormer's ``time_bias`` on, ``frame_clock_s`` from the front ends
    (:func:`perception.features.frame_clock_s`), which is what the data gives, not an option."""
    options = dict(options)
    if options.get("time_bias"):
        options["frame_clock_s"] = frame_clock_s(feature_config)
    return options


def model_overrides(config: TrainConfig) -> dict[str, Any]:
    """The model config's fields that ``config`` sets: its ``model_overrides``, with the frames' clock
    (:func:`with_frame_clock`)."""
    return with_frame_clock({k: tuplify(v) for k, v in config.model_overrides}, config.feature_config)


@dataclass(frozen=True)
class TrainResult:
    """What a training run produced.

    Attributes:
        checkpoint_dir: folder of the best-epoch checkpoint.
        class_names: class index -> label.
        best_epoch: 1-based epoch of the best validation accuracy.
        best_val_accuracy: its validation accuracy in [0, 1] (nan without a validation part).
        history: one dict per finished epoch (epoch, lr, train_loss, train_ce, train_contrastive,
            train_accuracy, val_accuracy, seconds).
        resumed_from_epoch: epochs already finished when this call started (0 for a fresh run).
        device: the torch device used.
    """

    checkpoint_dir: Path
    class_names: tuple[str, ...]
    best_epoch: int
    best_val_accuracy: float
    history: tuple[Mapping[str, float], ...]
    resumed_from_epoch: int
    device: str

    def to_dict(self) -> dict[str, Any]:
        return {"checkpoint_dir": str(self.checkpoint_dir), "class_names": list(self.class_names),
                "best_epoch": self.best_epoch, "best_val_accuracy": self.best_val_accuracy,
                "history": [dict(h) for h in self.history], "resumed_from_epoch": self.resumed_from_epoch,
                "device": self.device}


# ----------------------------------------------------------------------------------------------------------
# features, augmentation, prediction


def cuda_available() -> bool:
    """Whether this machine has a CUDA GPU torch can use, asked without initialising CUDA in this process.

    :func:`torch.cuda.device_count` counts the GPUs through NVML where the driver has it (it falls back to the
    CUDA runtime otherwise); :func:`torch.cuda.is_available` would always ask the CUDA runtime, after which a
    forked process can no longer use CUDA ("Cannot re-initialize CUDA in forked subprocess"), and the
    evaluation forks its training workers (``perception.evaluate._pretrain``) after resolving the device.
    """
    return torch.cuda.device_count() > 0


def resolve_device(device: str) -> torch.device:
    """"auto" -> CUDA when available, else CPU (:func:`cuda_available`)."""
    if device == "auto":
        return torch.device("cuda" if cuda_available() else "cpu")
    if device == "cuda" and not cuda_available():
        raise TrainError("device 'cuda' asked for but CUDA is not available")
    return torch.device(device)


def featurize_records(records: Sequence[StrokeRecord], config: FeatureConfig, progress: bool = False,
                      desc: str = "featurize") -> list[dict[str, np.ndarray | None]]:
    """:func:`perception.features.featurize` of every record (call once per run and reuse)."""
    return [featurize(r, config) for r in tqdm(records, desc=desc, disable=not progress, leave=False)]


def corrupt_batch(batch: FeatureBatch, ratio: float, std: float, generator: torch.Generator) -> FeatureBatch:
    """Gaussian noise on randomly chosen modalities (robustness experiment, paper sec. 5.3).

    Each present modality of each sample is corrupted with probability ``ratio``: N(0, std^2) is added to its
    normalised features at the valid steps (std in units of the per-channel training std). Padding stays 0.
    """
    if ratio <= 0 or std <= 0:
        return batch
    x = {}
    for m in MODALITIES:
        xm = batch.x[m]  # (B, T, C)
        hit = (torch.rand(xm.shape[0], generator=generator) < ratio) & batch.present[m]  # (B,)
        noise = torch.randn(xm.shape, generator=generator) * std  # (B, T, C)
        weight = (hit[:, None] & ~batch.padding[m]).to(xm.dtype).unsqueeze(-1)  # (B, T, 1)
        x[m] = xm + noise * weight
    return dataclasses.replace(batch, x=x)


def add_feature_noise(batch: FeatureBatch, std: float, generator: torch.Generator) -> FeatureBatch:
    """Training augmentation: N(0, std^2) on every valid step of every present modality."""
    if std <= 0:
        return batch
    x = {m: batch.x[m] + torch.randn(batch.x[m].shape, generator=generator) * std
         * (~batch.padding[m]).to(batch.x[m].dtype).unsqueeze(-1) for m in MODALITIES}
    return dataclasses.replace(batch, x=x)


def crop_in_time(features: StrokeFeatures, min_share: float, generator: torch.Generator) -> StrokeFeatures:
    """Training augmentation: the stroke cut to one random window of its duration.

    The window covers a share ``u ~ U(min_share, 1)`` of the stroke, starting at ``a ~ U(0, 1 - u)``; each
    stream keeps its frames ``[floor(a T), ceil((a + u) T))`` (at least one), so the streams keep the same span of
    the stroke whatever their rates. Missing streams stay missing; ``min_share`` 1 returns the features as they are.
    """
    if min_share >= 1.0:
        return features
    share, start = torch.rand(2, generator=generator, dtype=torch.float64).tolist()
    share = min_share + (1.0 - min_share) * share
    start *= 1.0 - share
    out: dict[str, np.ndarray | None] = {}
    for m, f in features.items():
        if f is None:
            out[m] = None
            continue
        lo = min(int(math.floor(start * len(f))), len(f) - 1)
        hi = max(int(math.ceil((start + share) * len(f))), lo + 1)
        out[m] = f[lo:hi]
    return out


def _random_band(lengths: torch.Tensor, size: int, max_share: float, generator: torch.Generator) -> torch.Tensor:
    """Per sample, a band [start, start + width) inside [0, length) as a (B, size) bool mask: width ~ floor(U(0,
    max_share) * length), start uniform over the positions where it fits. ``lengths`` (B,) int64, each <= size."""
    u_width, u_start = torch.rand(2, lengths.shape[0], generator=generator, dtype=torch.float64)
    width = torch.floor(u_width * max_share * lengths).long()
    start = torch.floor(u_start * (lengths - width + 1)).long()
    index = torch.arange(size)[None, :]  # (1, size)
    return (index >= start[:, None]) & (index < (start + width)[:, None])


def mask_features(batch: FeatureBatch, max_share: float, generator: torch.Generator) -> FeatureBatch:
    """Training augmentation in the manner of SpecAugment (Park et al. 2019): in each present modality of each
    sample one band of consecutive channels and one span of consecutive valid steps are set to 0 (the training
    mean in normalised units). Each is a uniform share in [0, ``max_share``] of the channels or of that sample's
    valid steps. Padding and missing modalities are left as they are; ``max_share`` 0 returns the batch unchanged
    without drawing from ``generator``."""
    if max_share <= 0:
        return batch
    x = {}
    for m in MODALITIES:
        xm = batch.x[m]  # (B, T, C)
        n_batch, n_steps, n_channels = xm.shape
        in_channels = _random_band(torch.full((n_batch,), n_channels), n_channels, max_share, generator)  # (B, C)
        in_steps = _random_band((~batch.padding[m]).sum(dim=1), n_steps, max_share, generator)  # (B, T)
        keep = ~(in_channels[:, None, :] | in_steps[:, :, None])  # (B, T, C)
        x[m] = xm * keep.to(xm.dtype)
    return dataclasses.replace(batch, x=x)


@dataclass(frozen=True)
class MixedBatch:
    """A batch blended by :func:`mixup_batch`: ``batch.labels`` holds the label of the larger share.

    Attributes:
        batch: the blended features; a step is padding only where it is in both strokes, a modality present
            where it is in either.
        partner_labels: (B,) the label of the stroke each one was blended with.
        share: weight of ``batch.labels`` in the blend, in [0.5, 1]; 1 is no blend.
    """

    batch: FeatureBatch
    partner_labels: torch.Tensor
    share: float


def mixup_batch(batch: FeatureBatch, alpha: float, generator: torch.Generator) -> MixedBatch:
    """Training augmentation: mixup (Zhang et al. 2018) on the normalised features.

    One weight per batch, ``share = max(w, 1 - w)`` with ``w ~ Beta(alpha, alpha)`` (drawn from ``generator``
    by inverting the Beta CDF with :func:`scipy.stats.beta.ppf`), and one random partner per stroke: every
    modality becomes ``share * x + (1 - share) * x[partner]``. Padding and missing streams are 0, so a step one
    stroke lacks takes the other's scaled values. ``alpha`` 0 returns the batch unblended (share 1, each stroke
    its own partner) without drawing from ``generator``.
    """
    if batch.labels is None:
        raise ValueError("mixup needs a labelled batch")
    if alpha <= 0:
        return MixedBatch(batch=batch, partner_labels=batch.labels, share=1.0)
    u = float(torch.rand(1, generator=generator, dtype=torch.float64))
    weight = float(scipy.stats.beta.ppf(u, alpha, alpha))
    share = max(weight, 1.0 - weight)
    partner = torch.randperm(batch.batch_size, generator=generator)  # (B,)
    x = {m: share * batch.x[m] + (1.0 - share) * batch.x[m][partner] for m in MODALITIES}
    padding = {m: batch.padding[m] & batch.padding[m][partner] for m in MODALITIES}
    present = {m: batch.present[m] | batch.present[m][partner] for m in MODALITIES}
    return MixedBatch(batch=dataclasses.replace(batch, x=x, padding=padding, present=present),
                      partner_labels=batch.labels[partner], share=share)


def drop_modalities(batch: FeatureBatch, prob: float, generator: torch.Generator) -> FeatureBatch:
    """Training augmentation: each present modality of each sample is removed with probability ``prob``
    (features zeroed, every step padding, ``present`` False: exactly what :func:`collate` gives for a missing
    stream). A sample keeps at least one modality: if all of its present ones were drawn, the one with the
    largest draw survives."""
    if prob <= 0:
        return batch
    present = batch.present_matrix()  # (B, M)
    draw = torch.rand(present.shape, generator=generator)  # (B, M)
    drop = (draw < prob) & present
    survivor = draw.masked_fill(~present, -1.0).argmax(dim=1)  # (B,)
    all_gone = (present & ~drop).sum(dim=1) == 0  # (B,)
    drop[all_gone, survivor[all_gone]] = False
    x, padding, kept = {}, {}, {}
    for i, m in enumerate(MODALITIES):
        d = drop[:, i]  # (B,)
        x[m] = batch.x[m] * (~d).to(batch.x[m].dtype)[:, None, None]
        padding[m] = batch.padding[m] | d[:, None]
        kept[m] = batch.present[m] & ~d
    return dataclasses.replace(batch, x=x, padding=padding, present=kept)


@dataclass(frozen=True)
class Predictions:
    """Model outputs over a set of strokes: logits (N, K), embedding (N, E), alphas (N, 4), pred (N,)."""

    logits: np.ndarray
    embedding: np.ndarray
    alphas: np.ndarray

    @property
    def pred(self) -> np.ndarray:
        return self.logits.argmax(axis=1) if len(self.logits) else np.zeros(0, dtype=np.int64)


@torch.no_grad()
def predict(model: nn.Module, features: Sequence[StrokeFeatures], dims: Mapping[str, int],
            stats: NormStats | None = None, batch_size: int = 64, device: torch.device | str = "cpu",
            corruption_ratio: float = 0.0, corruption_std: float = 1.0, seed: int = 0,
            drop: Sequence[str] = ()) -> Predictions:
    """Run a model over featurized strokes in eval mode.

    Args:
        model: any registered model.
        features: per-stroke features; raw if ``stats`` is given, else already normalised.
        dims: feature channels per modality.
        stats: normalisation to apply first (None: the features are already normalised).
        batch_size: strokes per forward pass.
        device: torch device.
        corruption_ratio, corruption_std: test-time corruption (see :func:`corrupt_batch`), seeded by ``seed``.
        drop: modalities removed at test time (set missing, as a dropped-out sensor).
    """
    model.eval()
    gen = torch.Generator().manual_seed(int(seed))
    feats = [{m: (None if m in drop else f.get(m)) for m in MODALITIES} for f in features]
    logits, emb, alphas = [], [], []
    for start in range(0, len(feats), batch_size):
        batch = collate(feats[start:start + batch_size], dims, stats=stats)
        batch = corrupt_batch(batch, corruption_ratio, corruption_std, gen).to(device)
        out = model(batch)
        logits.append(out.logits.float().cpu().numpy())
        emb.append(out.embedding.float().cpu().numpy())
        alphas.append(out.alphas.float().cpu().numpy())
    if not logits:
        return Predictions(np.zeros((0, 0), np.float32), np.zeros((0, 0), np.float32), np.zeros((0, 4), np.float32))
    return Predictions(np.concatenate(logits), np.concatenate(emb), np.concatenate(alphas))


def length_grouped_batches(order: np.ndarray, lengths: np.ndarray, batch_size: int, generator: torch.Generator,
                           pool_batches: int = 8) -> list[np.ndarray]:
    """Mini-batches of strokes of similar length, still random: the shuffled ``order`` is cut into pools of
    ``pool_batches`` batches, each pool sorted by length (frames summed over the modalities) and cut into
    batches, and the batches shuffled with ``generator``. Every stroke appears once and the number of batches
    is ``ceil(len(order) / batch_size)``, as with plain shuffling (only the last pool can end short).

    Why: a batch is padded to its longest stroke, and stroke lengths spread widely (sound frames: 10th
    percentile 47, median 60, 90th 122, longest 243 on ``data/clean30``), so a uniformly drawn batch of 32 is
    padded to about 2.5x the mean length and attention cost grows with the square of it.
    """
    pool = batch_size * pool_batches
    batches: list[np.ndarray] = []
    for start in range(0, len(order), pool):
        chunk = order[start:start + pool]
        chunk = chunk[np.argsort(-lengths[chunk], kind="stable")]
        batches += [chunk[i:i + batch_size] for i in range(0, len(chunk), batch_size)]
    perm = torch.randperm(len(batches), generator=generator).numpy()
    return [batches[i] for i in perm]


def class_balanced_batches(order: np.ndarray, labels: np.ndarray, batch_size: int, per_class: int,
                           generator: torch.Generator, lengths: np.ndarray | None = None,
                           pool_batches: int = 8) -> list[np.ndarray]:
    """P x K mini-batches: each label's strokes, in the shuffled ``order``, are cut into chunks of ``per_class``
    (the last one of a label may be shorter), the chunks are shuffled with ``generator`` and ``batch_size //
    per_class`` chunks make a batch, so a stroke has up to ``per_class - 1`` strokes of its own label beside it.
    Every stroke appears once; the number of batches depends on the labels only (:func:`class_balanced_steps`).
    With ``lengths`` the chunks are also grouped by length, as :func:`length_grouped_batches` groups strokes:
    pools of ``pool_batches`` batches' chunks are sorted by their longest stroke and the batches shuffled."""
    chunks = []
    ordered = labels[order]  # (n,) each stroke's label, in the shuffled order
    for label in np.unique(labels):
        members = order[ordered == label]  # (n_label,) in the shuffled order
        chunks += [members[i:i + per_class] for i in range(0, len(members), per_class)]
    chunks = [chunks[i] for i in torch.randperm(len(chunks), generator=generator).numpy()]
    per_batch = max(1, batch_size // per_class)
    if lengths is not None:
        pool = per_batch * pool_batches
        chunks = [chunk for start in range(0, len(chunks), pool)
                  for chunk in sorted(chunks[start:start + pool], key=lambda c: -int(lengths[c].max()))]
    batches = [np.concatenate(chunks[i:i + per_batch]) for i in range(0, len(chunks), per_batch)]
    if lengths is not None:
        batches = [batches[i] for i in torch.randperm(len(batches), generator=generator).numpy()]
    return batches


def class_balanced_steps(labels: np.ndarray, batch_size: int, per_class: int) -> int:
    """How many batches :func:`class_balanced_batches` makes of strokes with these labels."""
    chunks = sum(math.ceil(count / per_class) for count in np.unique(labels, return_counts=True)[1])
    return math.ceil(chunks / max(1, batch_size // per_class))


def cosine_lr(base_lr: float, step: int, total_steps: int) -> float:
    """lr at ``step`` (0-based) of a cosine decay from ``base_lr`` to 0 at ``total_steps``."""
    return 0.5 * base_lr * (1.0 + math.cos(math.pi * min(step, total_steps) / max(total_steps, 1)))


def scheduled_lr(config: TrainConfig, step: int, steps_per_epoch: int) -> float:
    """The learning rate of training step ``step`` (0-based): a linear rise from 0 over ``config.warmup_epochs``,
    then ``config.schedule`` (the cosine decays to 0 over the steps after the warmup)."""
    warmup_steps = config.warmup_epochs * steps_per_epoch
    if step < warmup_steps:
        return config.lr * (step + 1) / warmup_steps
    if config.schedule == "constant":
        return config.lr
    return cosine_lr(config.lr, step - warmup_steps, config.epochs * steps_per_epoch - warmup_steps)


# ----------------------------------------------------------------------------------------------------------
# resume state


def strokes_fingerprint(records: Sequence[StrokeRecord]) -> str:
    """sha256 of the strokes' labels and metadata and of a strided sample of every stream (shape, rate, clock
    offset and about 64 samples each). Cheap, and it tells apart two data sets of the same size, so a run folder
    is not reused for other strokes; a change that falls between the sampled points goes unnoticed."""
    digest = hashlib.sha256()
    for record in records:
        digest.update(json.dumps([record.category, record.instance, bool(record.combustible), record.meta],
                                 sort_keys=True, default=str).encode())
        for key in MODALITIES:
            stream = record.streams.get(key)
            if stream is None:
                digest.update(f"{key}:missing".encode())
                continue
            digest.update(f"{key}:{stream.data.shape}:{stream.rate_hz!r}:{stream.t0_s!r}".encode())
            step = max(1, len(stream.data) // 64)
            digest.update(np.ascontiguousarray(stream.data[::step], dtype=np.float32).tobytes())
    return digest.hexdigest()


def _save_resume(folder: Path, model: nn.Module, optimizer: torch.optim.Optimizer, record: dict[str, Any],
                 ema: AveragedModel | None = None, aux_head: nn.Module | None = None) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    tensors = {f"model.{k}": v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    if ema is not None:
        tensors.update({f"ema.{k}": v.detach().cpu().contiguous() for k, v in ema.state_dict().items()})
    if aux_head is not None:
        tensors.update({f"aux_head.{k}": v.detach().cpu().contiguous() for k, v in aux_head.state_dict().items()})
    opt = optimizer.state_dict()
    state_keys: dict[str, list[str]] = {}
    for pid, state in opt["state"].items():
        state_keys[str(pid)] = sorted(state)
        for name, value in state.items():
            tensors[f"optim.{pid}.{name}"] = torch.as_tensor(value).detach().cpu().contiguous()
    record = {**record, "optimizer_param_groups": opt["param_groups"], "optimizer_state_keys": state_keys}
    atomic_write(folder / "state.safetensors", lambda tmp: safetensors.torch.save_file(tensors, tmp))
    text = json.dumps(record, indent=2, sort_keys=True)
    atomic_write(folder / "state.json", lambda tmp: Path(tmp).write_text(text, encoding="utf-8"))


def _model_config_json(cls: type, data: Mapping[str, Any]) -> dict[str, Any]:
    """A model config as the resume record keeps it: every field of ``cls`` (fields missing from ``data``, which
    was saved before they existed, at their defaults), as JSON data."""
    return json.loads(json.dumps(config_to_dict(config_from_dict(cls, data))))


def _checkpoint_model_config(checkpoint_dir: Path, cls: type) -> dict[str, Any]:
    """``{"model_config": ...}`` from a run's checkpoint, for a resume record written before records kept the
    model's config (so that a changed model default is not resumed as if it were the same run); empty when the
    checkpoint holds none that ``cls`` reads."""
    try:
        data = json.loads((checkpoint_dir / "config.json").read_text(encoding="utf-8"))
        return {"model_config": _model_config_json(cls, data["model_config"])}
    except (OSError, ValueError, KeyError, TypeError):
        return {}


def _resume_record(out_dir: Path, model: nn.Module, optimizer: torch.optim.Optimizer, device: torch.device,
                   identity: Mapping[str, Any], model_config_cls: type, ema: AveragedModel | None = None,
                   aux_head: nn.Module | None = None) -> dict[str, Any] | None:
    """The resume record of the run folder ``out_dir`` (its state loaded into ``model`` and ``optimizer``), or
    None for a fresh folder.

    Raises:
        StaleRunError: the folder holds a run of another config, model, class list or data.
    """
    resume_dir = out_dir / RESUME_DIR
    record = _load_resume(resume_dir, model, optimizer, device, ema, aux_head)
    if record is None:
        return None
    if isinstance(record.get("config"), dict):
        try:  # a run saved before a field existed has that field at its default
            record = {**record, "config": _trained_config(TrainConfig.from_dict(record["config"]))}
        except (TypeError, ValueError, KeyError):
            pass  # not a config of this version: the identity check below says so
    if "model_config" not in record:  # saved before runs recorded their model's config
        record = {**record, **_checkpoint_model_config(out_dir / CHECKPOINT_DIR, model_config_cls)}
    else:  # saved before a model field existed: that field at the value such configs had (its default)
        try:
            record = {**record, "model_config": _model_config_json(model_config_cls, record["model_config"])}
        except (TypeError, ValueError, KeyError):
            pass  # not a config of this model: the identity check below says so
    # a run saved before the data fingerprint (or the model config) was recorded is checked on the rest
    checked = {k: v for k, v in identity.items() if k in record or k not in ("data_sha256", "model_config")}
    if {k: record.get(k) for k in checked} != checked:
        raise StaleRunError(f"{resume_dir}: holds a run with another config, class list or data; "
                            f"use a fresh output folder")
    return record


def _trained_config(config: TrainConfig) -> dict[str, Any]:
    """``config`` as plain JSON without its :data:`PLACEMENT_FIELDS` (and the :data:`TRAIN_IDENTITY_OMITS` and,
    in its spectral front ends, the :data:`SPECTRAL_IDENTITY_OMITS` at their given values): what a run folder's
    identity holds."""
    trained = _without_omitted({k: v for k, v in config.to_dict().items() if k not in PLACEMENT_FIELDS},
                               TRAIN_IDENTITY_OMITS)
    features = trained["feature_config"]
    for front_end in ("sound", "accel"):
        features[front_end] = _without_omitted(features[front_end], SPECTRAL_IDENTITY_OMITS)
    return trained


def run_identity(config: TrainConfig, n_classes: int) -> dict[str, Any]:
    """What a run of ``config`` is, apart from its strokes: the trained settings (:func:`_trained_config`) and
    the model config it builds (the registry's defaults with the run's overrides, so a changed model default
    tells two runs apart; fields in the config class's ``IDENTITY_OMITS`` left out at the value given there),
    as JSON data. The evaluation's run store names outcomes by it
    (:mod:`perception.run_store`)."""
    config_cls = MODEL_REGISTRY[config.model][0]
    in_dims = tuple(feature_dims(config.feature_config)[m] for m in MODALITIES)
    model_config = config_cls(in_dims=in_dims, n_classes=n_classes, **model_overrides(config))
    model_json = _model_config_json(config_cls, config_to_dict(model_config))
    # fields added since the runs were stored, left out at what those runs did
    model_json = _without_omitted(model_json, getattr(config_cls, "IDENTITY_OMITS", {}))
    return {"config": _trained_config(config), "model_config": model_json}


def _set_aside(out_dir: Path) -> Path:
    """Rename a run folder that cannot be resumed to ``<name>.stale-<n>`` (the first n free) and return it."""
    n = 1
    while (aside := out_dir.with_name(f"{out_dir.name}.stale-{n}")).exists():
        n += 1
    out_dir.rename(aside)
    return aside


def _load_resume(folder: Path, model: nn.Module, optimizer: torch.optim.Optimizer, device: torch.device,
                 ema: AveragedModel | None = None, aux_head: nn.Module | None = None) -> dict[str, Any] | None:
    json_path, tensor_path = folder / "state.json", folder / "state.safetensors"
    if not json_path.is_file():
        return None
    try:
        record = json.loads(json_path.read_text(encoding="utf-8"))
        tensors = safetensors.torch.load_file(str(tensor_path), device=str(device))
    except Exception as exc:  # corrupt JSON, missing/corrupt safetensors
        raise TrainError(f"{folder}: unreadable resume state ({exc.__class__.__name__}: "
                         f"{(str(exc).splitlines() or [''])[0]}); delete the folder to start afresh") from None
    try:
        model.load_state_dict({k[len("model."):]: v for k, v in tensors.items() if k.startswith("model.")})
    except RuntimeError as exc:  # missing, unexpected or reshaped weights
        detail = " ".join(line.strip() for line in str(exc).splitlines()[1:] if line.strip())
        raise StaleRunError(f"{folder}: holds a model of another architecture "
                            f"({detail[:160] or exc}); use a fresh output folder") from None
    if ema is not None:
        ema_state = {k[len("ema."):]: v for k, v in tensors.items() if k.startswith("ema.")}
        if not ema_state:  # the identity check that follows tells this run apart too; say it plainly here
            raise StaleRunError(f"{folder}: holds a run without the weight average this config keeps; use a fresh "
                                f"output folder")
        try:
            ema.load_state_dict(ema_state)
        except RuntimeError as exc:
            raise StaleRunError(f"{folder}: its weight average does not fit this model ({exc.__class__.__name__}); "
                                f"use a fresh output folder") from None
    if aux_head is not None:
        try:
            aux_head.load_state_dict({k[len("aux_head."):]: v for k, v in tensors.items() if k.startswith("aux_head.")})
        except RuntimeError:
            raise StaleRunError(f"{folder}: holds a run without the auxiliary parameter head this config trains, or "
                                f"one of another size; use a fresh output folder") from None
    try:
        state = {int(pid): {name: tensors[f"optim.{pid}.{name}"] for name in names}
                 for pid, names in record["optimizer_state_keys"].items()}
        for group in record["optimizer_param_groups"]:
            if isinstance(group.get("betas"), list):
                group["betas"] = tuple(group["betas"])
        optimizer.load_state_dict({"state": state, "param_groups": record["optimizer_param_groups"]})
        missing = [key for key in ("epoch", "history", "best_epoch", "best_val_accuracy") if key not in record]
        if missing:  # what resuming reads next
            raise KeyError(", ".join(missing))
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise TrainError(f"{folder}: malformed resume state ({exc.__class__.__name__}: {exc}); delete the folder "
                         f"to start afresh") from None
    return record


# ----------------------------------------------------------------------------------------------------------
# training


def _accuracy(pred: np.ndarray, labels: np.ndarray) -> float:
    return float(np.mean(pred == labels)) if len(labels) else float("nan")


def _aux_parameter_head(config: TrainConfig, model_config: Any, targets: np.ndarray | None, n_train: int
                        ) -> tuple[nn.Linear | None, torch.Tensor | None]:
    """The auxiliary head of ``config.aux_parameters_weight`` (a linear map from the embedding to the P
    parameters, drawn from torch's seeded generator right after the model) and its z-scored targets, or
    (None, None) when it is off.

    Raises:
        TrainError: it is on and ``targets`` is missing, not one finite row per training stroke, or the model
            has no embedding size.
    """
    if config.aux_parameters_weight == 0.0:
        return None, None
    if targets is None:
        raise TrainError("aux_parameters_weight > 0 needs each training stroke's material parameters "
                         "(aux_targets_train)")
    targets = np.asarray(targets, dtype=np.float64)
    if targets.ndim != 2 or targets.shape[0] != n_train or targets.shape[1] == 0:
        raise TrainError(f"aux_targets_train must hold one row of material parameters per training stroke "
                         f"({n_train}), got shape {targets.shape}")
    if not np.all(np.isfinite(targets)):
        raise TrainError("aux_targets_train holds NaN or infinite values")
    emb_dim = getattr(model_config, "emb_dim", None)
    if not isinstance(emb_dim, int):
        raise TrainError(f"model {config.model!r} has no embedding size (emb_dim) for the auxiliary head")
    std = targets.std(axis=0)
    z = (targets - targets.mean(axis=0)) / np.where(std > 0, std, 1.0)
    return nn.Linear(emb_dim, targets.shape[1]), torch.as_tensor(z, dtype=torch.float32)


def _batch_loss(model: nn.Module, model_config: Any, config: TrainConfig, batch: FeatureBatch, mixed: MixedBatch,
                aux_head: nn.Module | None, aux_rows: torch.Tensor | None
                ) -> tuple[ModelOutput, LossTerms, torch.Tensor, torch.Tensor | None]:
    """One training batch's forward pass and loss: the model's output, eq. 14's loss terms, the loss trained on
    (with the auxiliary parameter and per-modality terms where they are on) and the parameter MSE (None
    without ``aux_head``)."""
    out, unimodal = (model.forward_with_unimodal(batch) if getattr(model, "unimodal_heads", None) is not None
                     else (model(batch), None))
    terms = total_loss(out.logits, out.embedding, batch.labels, model_config.cer_lambda, model_config.cer_tau,
                       label_smoothing=config.label_smoothing, partner_labels=mixed.partner_labels.to(batch.labels.device),
                       share=mixed.share)
    loss = terms.total
    aux = None
    if aux_head is not None:
        aux = nn.functional.mse_loss(aux_head(out.embedding), aux_rows)
        loss = loss + config.aux_parameters_weight * aux
    if unimodal is not None:
        loss = loss + model_config.unimodal_lambda * unimodal_cross_entropy(unimodal, batch.labels,
                                                                            batch.present_matrix())
    return out, terms, loss, aux


def train(records_train: Sequence[StrokeRecord], records_val: Sequence[StrokeRecord], config: TrainConfig,
          out_dir: str | os.PathLike, progress: bool = True, *, class_names: Sequence[str] | None = None,
          features_train: Sequence[StrokeFeatures] | None = None,
          features_val: Sequence[StrokeFeatures] | None = None,
          provenance: Mapping[str, Any] | None = None,
          on_epoch_end: Callable[[Mapping[str, float]], None] | None = None,
          replace_stale: bool = False, aux_targets_train: np.ndarray | None = None) -> TrainResult:
    """Train ``config.model`` on ``records_train``, choosing the best epoch on ``records_val``.

    Args:
        records_train: training strokes.
        records_val: validation strokes (from the training part of the split; may be empty, then the last
            epoch is kept).
        config: the run's settings.
        out_dir: run folder: ``checkpoint/`` (best epoch), ``resume/`` (last epoch), ``train_result.json``.
            A folder holding an unfinished run with the same config and strokes is resumed.
        progress: tqdm bars.
        class_names: label order (default: sorted labels of the training strokes). Fine-tuning keeps the
            init checkpoint's.
        features_train, features_val: precomputed raw features of the records (see :func:`featurize_records`).
        provenance: extra JSON data stored in the checkpoint's meta (command, data manifest hash, ...).
        on_epoch_end: called with each epoch's history row after its state is saved.
        replace_stale: a folder holding a run of another config, model or data is renamed to
            ``<name>.stale-<n>`` (nothing is deleted) and the run trained afresh, instead of raising
            :class:`StaleRunError` (the evaluation's run cache, after a setting or a model default changed).
        aux_targets_train: (len(records_train), P) material parameters of each training stroke's object, for
            ``config.aux_parameters_weight`` > 0 (read only then).

    Returns:
        The :class:`TrainResult`.

    Raises:
        TrainError: unknown validation labels, CUDA missing, auxiliary targets missing or malformed.
        StaleRunError: (a TrainError) resume state from another config, model or other strokes, unless
            ``replace_stale``.
    """
    out_dir = Path(out_dir)
    if config.num_threads > 0:
        torch.set_num_threads(config.num_threads)
    device = resolve_device(config.device)
    fc = config.feature_config
    dims = feature_dims(fc)
    in_dims = tuple(dims[m] for m in MODALITIES)

    init = load_checkpoint(config.init_checkpoint) if config.init_checkpoint else None
    if init is not None:
        if init.model_name != config.model:
            raise TrainError(f"{config.init_checkpoint}: holds a {init.model_name!r} model, config asks {config.model!r}")
        class_names = init.class_names
    train_labels = labels_of(records_train, config.task)
    names = tuple(class_names) if class_names is not None else tuple(sorted(set(train_labels)))
    index = {n: i for i, n in enumerate(names)}
    unknown = sorted(set(train_labels + labels_of(records_val, config.task)) - set(index))
    if unknown:
        raise TrainError(f"labels {unknown[:5]} are not among the {len(names)} class names")
    y_train = np.array([index[l] for l in train_labels], dtype=np.int64)
    y_val = np.array([index[l] for l in labels_of(records_val, config.task)], dtype=np.int64)

    if features_train is None:
        features_train = featurize_records(records_train, fc, progress, "featurize train")
    if features_val is None:
        features_val = featurize_records(records_val, fc, progress, "featurize val")
    if fc.modalities != MODALITIES:  # precomputed features may hold the other sensors too
        features_train = [keep_modalities(f, fc.modalities) for f in features_train]
        features_val = [keep_modalities(f, fc.modalities) for f in features_val]
    stats = init.norm_stats if init is not None else fit_norm_stats(features_train, dims)
    norm_train = [normalize(f, stats) for f in features_train]
    norm_val = [normalize(f, stats) for f in features_val]

    torch.manual_seed(config.seed)
    model_config, model = build_model(config.model, in_dims, len(names), **model_overrides(config))
    if init is not None:
        model.load_state_dict(init.model.state_dict())
    aux_head, aux_targets = _aux_parameter_head(config, model_config, aux_targets_train, len(records_train))
    model.to(device)
    opt_cls = torch.optim.AdamW if config.optimizer == "adamw" else torch.optim.Adam
    trained = list(model.parameters())
    if aux_head is not None:
        aux_head.to(device)
        aux_targets = aux_targets.to(device)
        trained += list(aux_head.parameters())
    optimizer = opt_cls(trained, lr=config.lr, weight_decay=config.weight_decay)
    ema = (AveragedModel(model, multi_avg_fn=get_ema_multi_avg_fn(config.ema_decay), use_buffers=True)
           if config.ema_decay > 0 else None)
    evaluated = model if ema is None else ema.module  # what validation scores and the checkpoint keeps

    n = len(norm_train)
    if n == 0:
        raise TrainError("no training strokes")
    steps_per_epoch = max(1, math.ceil(n / config.batch_size) if config.batch_per_class == 0
                          else class_balanced_steps(y_train, config.batch_size, config.batch_per_class))
    lengths = np.array([sum(0 if f.get(m) is None else len(f[m]) for m in MODALITIES) for f in norm_train])
    identity = {"config": _trained_config(config), "class_names": list(names), "n_train": n, "n_val": len(norm_val),
                "data_sha256": f"{strokes_fingerprint(records_train)}:{strokes_fingerprint(records_val)}",
                "model_config": _model_config_json(type(model_config), config_to_dict(model_config))}
    if config.init_checkpoint:  # the weights fine-tuned from, not only their folder's name
        identity["init_sha256"] = sha256_file(Path(config.init_checkpoint) / WEIGHTS_FILE)
    if aux_targets is not None:  # the targets regressed, not only their weight
        identity["aux_targets_sha256"] = hashlib.sha256(aux_targets.cpu().numpy().tobytes()).hexdigest()

    resume_dir = out_dir / RESUME_DIR
    try:
        record = _resume_record(out_dir, model, optimizer, device, identity, type(model_config), ema, aux_head)
    except StaleRunError as exc:
        if not replace_stale:
            raise
        aside = _set_aside(out_dir)
        tqdm.write(f"{out_dir}: {str(exc).split(': ', 1)[-1].split(';')[0]}; kept as {aside.name}, training afresh",
                   file=sys.stderr)
        return train(records_train, records_val, config, out_dir, progress, class_names=class_names,
                     features_train=features_train, features_val=features_val, provenance=provenance,
                     on_epoch_end=on_epoch_end, aux_targets_train=aux_targets_train)
    start_epoch = 0 if record is None else int(record["epoch"])
    history: list[dict[str, float]] = [] if record is None else list(record["history"])
    best_epoch = 0 if record is None else int(record["best_epoch"])
    best_val = -1.0 if record is None else float(record["best_val_accuracy"])
    meta = {"train_config": config.to_dict(), "seed": config.seed, "task": config.task,
            "deviations": DEVIATIONS, **dict(provenance or {})}

    bar = tqdm(range(start_epoch, config.epochs), desc=f"train {config.model}/{config.task}", disable=not progress,
               initial=start_epoch, total=config.epochs, leave=False)
    for epoch in bar:
        t0 = time.perf_counter()
        torch.manual_seed(config.seed * 1_000_003 + epoch)  # dropout
        gen = torch.Generator().manual_seed(config.seed * 1_000_003 + epoch)  # order and noise
        order = torch.randperm(n, generator=gen).numpy()
        if config.batch_per_class > 0:
            batches = class_balanced_batches(order, y_train, config.batch_size, config.batch_per_class, gen,
                                             lengths if config.group_by_length else None)
        elif config.group_by_length:
            batches = length_grouped_batches(order, lengths, config.batch_size, gen)
        else:
            batches = [order[b * config.batch_size:(b + 1) * config.batch_size] for b in range(steps_per_epoch)]
        model.train()
        sums = {"loss": 0.0, "ce": 0.0, "contrastive": 0.0, "correct": 0.0, "aux": 0.0}
        for b, idx in enumerate(batches):
            if idx.size == 0:
                continue
            step = epoch * steps_per_epoch + b
            lr = scheduled_lr(config, step, steps_per_epoch)
            for group in optimizer.param_groups:
                group["lr"] = lr
            batch = collate([crop_in_time(norm_train[i], config.time_crop, gen) for i in idx], dims,
                            labels=y_train[idx].tolist())
            batch = mask_features(batch, config.feature_mask, gen)
            batch = add_feature_noise(batch, config.feature_noise_std, gen)
            batch = drop_modalities(batch, config.modality_dropout, gen)
            batch = corrupt_batch(batch, config.corruption_ratio, config.corruption_std, gen)
            mixed = mixup_batch(batch, config.mixup_alpha, gen)
            batch = mixed.batch.to(device)
            aux_rows = None if aux_head is None else aux_targets[torch.as_tensor(idx, device=device)]
            out, terms, loss, aux = _batch_loss(model, model_config, config, batch, mixed, aux_head, aux_rows)
            if aux is not None:
                sums["aux"] += float(aux.detach()) * len(idx)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            if config.sam_rho > 0:  # SAM: the gradient at the ascent point, applied from the weights themselves
                steps = sam.ascend(trained, config.sam_rho)
                optimizer.zero_grad(set_to_none=True)
                _batch_loss(model, model_config, config, batch, mixed, aux_head, aux_rows)[2].backward()
                sam.descend_back(trained, steps)
            if config.grad_clip > 0:
                nn.utils.clip_grad_norm_(model.parameters(), config.grad_clip)
            optimizer.step()
            if ema is not None:
                ema.update_parameters(model)
            k = len(idx)
            sums["loss"] += float(loss.detach()) * k
            sums["ce"] += float(terms.ce.detach()) * k
            sums["contrastive"] += float(terms.contrastive.detach()) * k
            sums["correct"] += float((out.logits.argmax(dim=1) == batch.labels).sum())
        val_pred = predict(evaluated, norm_val, dims, batch_size=max(64, config.batch_size), device=device,
                           corruption_ratio=config.corruption_ratio, corruption_std=config.corruption_std,
                           seed=config.seed + 1).pred if norm_val else np.zeros(0, np.int64)
        val_acc = _accuracy(val_pred, y_val)
        row = {"epoch": epoch + 1, "lr": lr, "train_loss": sums["loss"] / n, "train_ce": sums["ce"] / n,
               "train_contrastive": sums["contrastive"] / n, "train_accuracy": sums["correct"] / n,
               "val_accuracy": val_acc, "seconds": time.perf_counter() - t0}
        if aux_head is not None:
            row["train_aux_mse"] = sums["aux"] / n
        history.append(row)
        improved = (val_acc > best_val) if norm_val else True
        if improved:
            best_epoch, best_val = epoch + 1, (val_acc if norm_val else float("nan"))
            save_checkpoint(out_dir / CHECKPOINT_DIR, config.model, evaluated, model_config, fc, stats, names,
                            meta={**meta, "best_epoch": best_epoch, "val_accuracy": val_acc})
        _save_resume(resume_dir, model, optimizer, {**identity, "epoch": epoch + 1, "history": history,
                                                    "best_epoch": best_epoch, "best_val_accuracy": best_val}, ema,
                     aux_head)
        bar.set_postfix(loss=f"{row['train_loss']:.3f}", val=f"{val_acc:.3f}")
        if on_epoch_end is not None:
            on_epoch_end(row)

    result = TrainResult(checkpoint_dir=out_dir / CHECKPOINT_DIR, class_names=names, best_epoch=best_epoch,
                         best_val_accuracy=best_val, history=tuple(history), resumed_from_epoch=start_epoch,
                         device=str(device))
    (out_dir / RESULT_FILE).write_text(json.dumps(result.to_dict(), indent=2), encoding="utf-8")
    return result


# ----------------------------------------------------------------------------------------------------------
# CLI entry


def task_split(records: Sequence[StrokeRecord], config: TrainConfig, fold: int = 0, n_folds: int = 5
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(train, validation, test) indices of ``records`` for ``config.task``: SSMC and fine-grained use the 7:3
    split seeded by ``config.seed`` (by object with ``config.split_by_object``), USMC fold ``fold`` of
    ``n_folds``; the validation part is carved from the training part."""
    from perception.dataset import fine_split, ssmc_split, usmc_folds, validation_split

    by_object = config.split_by_object
    if config.task == "ssmc":
        train_idx, test_idx = ssmc_split(records, config.seed, group_by_object=by_object)
    elif config.task == "fine":
        train_idx, test_idx = fine_split(records, config.seed, group_by_object=by_object)
    else:
        folds = usmc_folds(records, k=n_folds, seed=config.seed)
        if not 0 <= fold < len(folds):
            raise TrainError(f"fold {fold} out of range for {len(folds)} folds")
        train_idx, test_idx = folds[fold]
    train_idx, val_idx = validation_split(records, train_idx, config.task, config.seed, config.val_fraction,
                                          group_by_object=by_object or None,
                                          group_by_instance=config.val_by_instance)
    if config.train_fraction < 1.0:
        train_idx = _subsample(records, train_idx, config)
    return train_idx, val_idx, test_idx


def _subsample(records: Sequence[StrokeRecord], train_idx: np.ndarray, config: TrainConfig) -> np.ndarray:
    """``config.train_fraction`` of ``train_idx``, stratified by the task's label, seeded (sorted indices)."""
    from sklearn.model_selection import train_test_split

    labels = labels_of([records[i] for i in train_idx], config.task)
    try:
        kept, _ = train_test_split(train_idx, train_size=config.train_fraction, stratify=labels,
                                   random_state=config.seed)
    except ValueError as exc:  # too few strokes to keep every label
        raise TrainError(f"train_fraction {config.train_fraction} of {len(train_idx)} training strokes: {exc}")
    return np.sort(kept)


def train_command(data_dir: str | os.PathLike, out_dir: str | os.PathLike, config: TrainConfig, fold: int = 0,
                  n_folds: int = 5, command: str = "", progress: bool = True,
                  aux_targets_of: Callable[[Sequence[StrokeRecord]], np.ndarray] | None = None) -> dict[str, Any]:
    """``robotdemo train``: load a data set, split it for ``config.task``, train, test the best epoch.

    The split is :func:`task_split`'s. Writes ``out_dir/metrics.json``. With ``config.aux_parameters_weight``
    > 0, ``aux_targets_of`` gives the material parameters of the training strokes (one row per stroke).

    Returns:
        {"test_accuracy", "test_g_mean", "n_train", "n_val", "n_test", "best_epoch", "checkpoint_dir",
        "val_sensor_use" (per sensor: the best epoch's mean MAG weight and dropped share on the validation strokes,
        :func:`perception.sensor_use.sensor_use`), ...}.
    """
    from perception.dataset import load_dataset
    from perception.evaluate import g_mean

    data = load_dataset(data_dir)
    records = data.records
    train_idx, val_idx, test_idx = task_split(records, config, fold, n_folds)
    pick = lambda idx: [records[i] for i in idx]  # noqa: E731
    names = tuple(sorted(set(labels_of(records, config.task))))
    aux_targets = None
    if config.aux_parameters_weight > 0:
        if aux_targets_of is None:
            raise TrainError("aux_parameters_weight > 0 needs a source of the strokes' material parameters")
        aux_targets = aux_targets_of(pick(train_idx))
    result = train(pick(train_idx), pick(val_idx), config, out_dir, progress, class_names=names,
                   provenance={"command": command, "data_dir": str(data_dir),
                               "data_manifest_sha256": data.manifest_sha256, "fold": fold},
                   aux_targets_train=aux_targets)
    ckpt = load_checkpoint(result.checkpoint_dir, device=resolve_device(config.device))
    # Temperature scaling on the validation strokes: the robot's confidence threshold then means what it says.
    corruption = {"corruption_ratio": config.corruption_ratio, "corruption_std": config.corruption_std,
                  "seed": config.seed + TEST_CORRUPTION_SEED_OFFSET}
    val_feats = featurize_records(pick(val_idx), ckpt.feature_config, progress, "featurize val")
    val_preds = predict(ckpt.model, val_feats, feature_dims(ckpt.feature_config), stats=ckpt.norm_stats,
                        device=resolve_device(config.device), **corruption)
    # How much the best epoch used each sensor on the validation strokes (a sensor the gate shut out shows here).
    val_use = sensor_use(val_preds.alphas, presence_matrix(val_feats))
    y_val = np.array([names.index(l) for l in labels_of(pick(val_idx), config.task)])
    temperature = fit_temperature(val_preds.logits, y_val)
    set_temperature(result.checkpoint_dir, temperature)
    feats = featurize_records(pick(test_idx), ckpt.feature_config, progress, "featurize test")
    preds = predict(ckpt.model, feats, feature_dims(ckpt.feature_config), stats=ckpt.norm_stats,
                    device=resolve_device(config.device), **corruption)
    y = np.array([names.index(l) for l in labels_of(pick(test_idx), config.task)])
    metrics = {"task": config.task, "model": config.model, "fold": fold, "seed": config.seed,
               "test_accuracy": _accuracy(preds.pred, y), "test_g_mean": g_mean(y, preds.pred, range(len(names))),
               "n_train": len(train_idx), "n_val": len(val_idx), "n_test": len(test_idx),
               "split_by_object": config.split_by_object, "val_by_instance": config.val_by_instance,
               "corruption_ratio": config.corruption_ratio, "corruption_std": config.corruption_std,
               "best_epoch": result.best_epoch, "best_val_accuracy": result.best_val_accuracy,
               "temperature": temperature, "val_nll": nll(val_preds.logits, y_val),
               "val_nll_calibrated": nll(val_preds.logits, y_val, temperature),
               "val_sensor_use": {name: use.to_dict() for name, use in val_use.items()},
               "checkpoint_dir": str(result.checkpoint_dir), "data_manifest_sha256": data.manifest_sha256}
    Path(out_dir, "metrics.json").write_text(json.dumps(metrics, indent=2), encoding="utf-8")
    return metrics
