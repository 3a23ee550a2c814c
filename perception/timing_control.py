"""Can a model relate when something happens in one sensor to when it happens in another? A positive control
for the evaluation's "find out why" (`robotdemo bench timing`).

The probes of `REPORT.md` ("What the networks use") found that TouchFormer's accuracy on our strokes barely
moves when each sensor is shifted in time by its own amount. That can mean two things: the strokes carry
nothing in the timing of one sensor against another, or the model cannot read it. This module separates them
with strokes where the class is *only* in that timing.

Each synthetic stroke is a set of front-end feature sequences laid out as :func:`perception.features.featurize`
lays out the real ones (the same channels per modality, the same frame hops, :func:`perception.features.
frame_clock_s`), with a duration drawn per stroke, so the four sequences have different lengths and rates.
Every channel is N(0, 1) noise (the scale of normalised features). The sound and the friction each carry one
event, a Gaussian bump in time on their first :data:`EVENT_CHANNELS` channels; class 0 has both events at the
same instant, class 1 has the friction's event a random share of the stroke later, wrapped around its end. Both
events' times are uniform over the stroke in both classes, so each sensor on its own, and any statistic of it,
says nothing about the class; the normal force and the acceleration carry an event at an unrelated time.

Every model is trained with ``robotdemo train``'s optimiser and defaults (AdamW, cosine learning rate, the CER
loss at the model's own lambda, batch 32), without its feature-noise augmentation or validation part, for a
fixed number of epochs, and scored on held-out strokes of the same kind.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
import torch
from tqdm import tqdm

from perception.baselines import MODEL_REGISTRY, build_model
from perception.features import FeatureConfig, StrokeFeatures, collate, feature_dims, frame_clock_s
from perception.losses import total_loss
from perception.streams import MODALITIES
from perception.train import cosine_lr, with_frame_clock

EVENT_CHANNELS = 4
"""Feature channels each event raises."""

DEFAULT_MODELS: tuple[tuple[str, str, tuple[tuple[str, Any], ...]], ...] = (
    ("touchformer", "touchformer", ()),
    ("touchformer, time_bias", "touchformer", (("time_bias", True),)),
    ("touchformer_soft", "touchformer_soft", ()),
    ("lstm", "lstm", ()),
    ("mtcnn", "mtcnn", ()),
)
"""(label, registered model, model options): each model with its defaults, the paper's TouchFormer also with
``time_bias``."""


@dataclass(frozen=True)
class TimingControlConfig:
    """The synthetic strokes, the models and their training.

    Attributes:
        n_train: training strokes per seed (half of each class).
        n_test: held-out strokes per seed.
        seeds: one data draw and one model initialisation per seed.
        epochs: training epochs.
        batch_size: strokes per step.
        lr: AdamW's initial learning rate (cosine decay to 0), as ``robotdemo train``'s default.
        weight_decay: AdamW's weight decay, as ``robotdemo train``'s default.
        duration_s: (shortest, longest) stroke, seconds; the real strokes' median is about 2.4 s.
        event_amplitude: height of an event's bump, in units of the noise std.
        event_width_s: std of an event's bump in time, seconds.
        offset_share: class 1's friction event lies this share of the stroke after the sound's, drawn uniform
            in (low, high), wrapped around the stroke's end.
        models: (label, registered model name, model options) per model.
        model_overrides: options applied to every model whose config has them (e.g. a small ``d_model`` for a
            quick run), before each model's own.
    """

    n_train: int = 1000
    n_test: int = 400
    seeds: tuple[int, ...] = (0, 1, 2)
    epochs: int = 30
    batch_size: int = 32
    lr: float = 3e-3
    weight_decay: float = 0.01
    duration_s: tuple[float, float] = (1.8, 3.2)
    event_amplitude: float = 3.0
    event_width_s: float = 0.08
    offset_share: tuple[float, float] = (0.3, 0.7)
    models: tuple[tuple[str, str, tuple[tuple[str, Any], ...]], ...] = DEFAULT_MODELS
    model_overrides: tuple[tuple[str, Any], ...] = ()
    feature_config: FeatureConfig = field(default_factory=FeatureConfig)

    def __post_init__(self) -> None:
        if min(self.n_train, self.n_test, self.epochs, self.batch_size) < 2 or not self.seeds:
            raise ValueError("n_train, n_test, epochs and batch_size must be >= 2, and seeds not empty")
        if not 0 < self.duration_s[0] <= self.duration_s[1]:
            raise ValueError(f"duration_s must be (shortest, longest) > 0, got {self.duration_s}")
        if not 0 < self.offset_share[0] <= self.offset_share[1] < 1:
            raise ValueError(f"offset_share must lie in (0, 1), low <= high, got {self.offset_share}")


def timing_strokes(n: int, seed: int, config: TimingControlConfig) -> tuple[list[StrokeFeatures], np.ndarray]:
    """``n`` synthetic strokes' features and their classes (0: sound and friction events at one instant, 1: the
    friction's later); the classes alternate before a seeded shuffle, so each holds half."""
    rng = np.random.default_rng(seed)
    dims = feature_dims(config.feature_config)
    clock = dict(zip(MODALITIES, frame_clock_s(config.feature_config)))
    labels = np.arange(n) % 2
    rng.shuffle(labels)
    strokes = []
    for label in labels:
        duration_s = rng.uniform(*config.duration_s)
        sound_share = rng.uniform()
        friction_share = (sound_share + (rng.uniform(*config.offset_share) if label else 0.0)) % 1.0
        shares = {"sound": sound_share, "friction": friction_share, "normal": rng.uniform(), "accel": rng.uniform()}
        stroke = {}
        for m in MODALITIES:
            hop_s, first_s = clock[m]
            n_frames = max(1, int((duration_s - 2.0 * first_s) // hop_s) + 1)
            centres_s = first_s + hop_s * np.arange(n_frames)  # (T,)
            event_s = duration_s * (0.1 + 0.8 * shares[m])  # events kept off the stroke's first and last tenth
            bump = config.event_amplitude * np.exp(-0.5 * ((centres_s - event_s) / config.event_width_s) ** 2)
            x = rng.normal(size=(n_frames, dims[m]))  # (T, C)
            x[:, :EVENT_CHANNELS] += bump[:, None]
            stroke[m] = x.astype(np.float32)
        strokes.append(stroke)
    return strokes, labels


def _accuracy(model: torch.nn.Module, strokes: Sequence[StrokeFeatures], labels: np.ndarray,
              dims: dict[str, int]) -> float:
    model.eval()
    with torch.no_grad():
        pred = model(collate(strokes, dims)).logits.argmax(dim=1).numpy()
    return float((pred == labels).mean())


def train_and_test(name: str, options: dict[str, Any], seed: int, config: TimingControlConfig
                   ) -> dict[str, float]:
    """Train one model on one seed's strokes; its accuracy on its training strokes and on held-out ones."""
    dims = feature_dims(config.feature_config)
    train, y_train = timing_strokes(config.n_train, 2 * seed, config)
    test, y_test = timing_strokes(config.n_test, 2 * seed + 1, config)
    torch.manual_seed(seed)
    model_config, model = build_model(name, tuple(dims[m] for m in MODALITIES), 2,
                                      **with_frame_clock(options, config.feature_config))
    cer_lambda, cer_tau = getattr(model_config, "cer_lambda", 0.0), getattr(model_config, "cer_tau", 0.2)
    optimizer = torch.optim.AdamW(model.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    order_rng = np.random.default_rng(seed)
    steps_per_epoch = math.ceil(config.n_train / config.batch_size)
    total = config.epochs * steps_per_epoch
    for step in range(total):
        if step % steps_per_epoch == 0:
            model.train()
            order = order_rng.permutation(config.n_train)
        pick = order[(step % steps_per_epoch) * config.batch_size:][:config.batch_size]
        batch = collate([train[i] for i in pick], dims, labels=y_train[pick])
        for group in optimizer.param_groups:
            group["lr"] = cosine_lr(config.lr, step, total)
        out = model(batch)
        loss = total_loss(out.logits, out.embedding, batch.labels, cer_lambda, cer_tau).total
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    return {"train_accuracy": _accuracy(model, train[:config.n_test], y_train[:config.n_test], dims),
            "test_accuracy": _accuracy(model, test, y_test, dims)}


def run_timing_control(config: TimingControlConfig = TimingControlConfig(), progress: bool = False
                       ) -> dict[str, Any]:
    """Every model of ``config`` on every seed: held-out accuracy per seed, its mean, and the training strokes'
    accuracy (chance is 0.5)."""
    results: dict[str, Any] = {}
    jobs = [(label, name, opts, seed) for label, name, opts in config.models for seed in config.seeds]
    for label, name, opts, seed in tqdm(jobs, desc="timing control", disable=not progress):
        fields = {f.name for f in dataclasses.fields(MODEL_REGISTRY[name][0])}
        options = {k: v for k, v in config.model_overrides if k in fields} | dict(opts)
        scores = train_and_test(name, options, seed, config)
        row = results.setdefault(label, {"model": name, "options": dict(opts), "test_accuracy": [],
                                         "train_accuracy": []})
        row["test_accuracy"].append(scores["test_accuracy"])
        row["train_accuracy"].append(scores["train_accuracy"])
    for row in results.values():
        row["test_accuracy_mean"] = float(np.mean(row["test_accuracy"]))
        row["train_accuracy_mean"] = float(np.mean(row["train_accuracy"]))
    return {"chance": 0.5, "n_train": config.n_train, "n_test": config.n_test, "epochs": config.epochs,
            "seeds": list(config.seeds), "models": results}
