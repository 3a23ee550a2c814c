"""The simple reference classifier: logistic regression on per-stream summary statistics.

Every learned model must beat it. Per modality (raw stream, no framing):

- level: mean of the channel means, mean of the channel standard deviations, RMS, max |x| (stream units);
- spectrum (of the detrended samples, power summed over channels): spectral centroid as a fraction of the
  Nyquist frequency, and the log energy fraction in ``n_bands`` octave-spaced bands up to Nyquist;
- an indicator: 1 if the stream is present. A missing stream has all its statistics set to 0.

The features go through ``StandardScaler`` then ``LogisticRegression`` (one sklearn ``Pipeline``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
import scipy.signal
from sklearn.linear_model import LogisticRegression
from sklearn.pipeline import Pipeline
from sklearn.preprocessing import StandardScaler

from perception.streams import MODALITIES, Stream, StrokeRecord


@dataclass(frozen=True)
class ReferenceConfig:
    """Reference classifier settings.

    Attributes:
        n_bands: octave bands per stream (the lowest band reaches down to 0 Hz).
        label: which label to learn when none is passed: "category" or "instance".
        c: inverse L2 regularisation strength of the logistic regression.
        max_iter: solver iterations.
    """

    n_bands: int = 8
    label: str = "category"
    c: float = 1.0
    max_iter: int = 2000

    def __post_init__(self) -> None:
        if self.label not in ("category", "instance"):
            raise ValueError(f"label must be 'category' or 'instance', got {self.label!r}")


def stream_statistics(stream: Stream | None, n_bands: int) -> np.ndarray:
    """Summary statistics of one stream: (5 + n_bands + 1,) float64, zeros plus indicator 0 if missing."""
    n = 5 + n_bands
    if stream is None or stream.data.shape[0] == 0:
        return np.zeros(n + 1)
    x = stream.data.astype(np.float64)  # (T, C)
    level = [x.mean(axis=0).mean(), x.std(axis=0).mean(), np.sqrt(np.mean(x ** 2)), np.abs(x).max()]
    xd = scipy.signal.detrend(x, axis=0, type="linear") if x.shape[0] > 1 else x - x.mean(axis=0)
    freqs, psd = scipy.signal.periodogram(xd, fs=stream.rate_hz, window="hann", axis=0)  # (F,), (F, C)
    power = psd.sum(axis=1)  # (F,)
    total = power.sum() + 1e-20
    nyquist = stream.rate_hz / 2.0
    centroid = float((freqs * power).sum() / total / nyquist)
    edges = nyquist * 2.0 ** -np.arange(n_bands, -1, -1, dtype=np.float64)  # octaves up to Nyquist
    edges[0] = 0.0
    bands = [power[(freqs >= lo) & (freqs <= hi)].sum() / total for lo, hi in zip(edges[:-1], edges[1:])]
    return np.array(level + [centroid] + list(np.log(np.asarray(bands) + 1e-8)) + [1.0])


def summary_features(record: StrokeRecord, n_bands: int = 8) -> np.ndarray:
    """Concatenated :func:`stream_statistics` of the four modalities, :data:`MODALITIES` order."""
    return np.concatenate([stream_statistics(record.stream(m), n_bands) for m in MODALITIES])


class ReferenceClassifier:
    """StandardScaler + logistic regression on :func:`summary_features`."""

    def __init__(self, config: ReferenceConfig = ReferenceConfig()) -> None:
        self.config = config
        self.pipeline = Pipeline([
            ("scale", StandardScaler()),
            ("logreg", LogisticRegression(C=config.c, max_iter=config.max_iter)),
        ])

    def _features(self, records: Sequence[StrokeRecord]) -> np.ndarray:
        return np.stack([summary_features(r, self.config.n_bands) for r in records])  # (N, D)

    def _labels(self, records: Sequence[StrokeRecord], labels: Sequence[str] | None) -> list[str]:
        if labels is not None:
            if len(labels) != len(records):
                raise ValueError(f"{len(labels)} labels for {len(records)} records")
            return list(labels)
        return [r.category if self.config.label == "category" else r.instance for r in records]

    def fit(self, records: Sequence[StrokeRecord], labels: Sequence[str] | None = None) -> ReferenceClassifier:
        """Fit on ``records``; labels default to each record's category (or instance, see config)."""
        self.pipeline.fit(self._features(records), self._labels(records, labels))
        return self

    @property
    def classes(self) -> tuple[str, ...]:
        return tuple(str(c) for c in self.pipeline.classes_)

    def predict(self, records: Sequence[StrokeRecord]) -> list[str]:
        """Predicted label of each record."""
        return [str(p) for p in self.pipeline.predict(self._features(records))]

    def predict_proba(self, records: Sequence[StrokeRecord]) -> np.ndarray:
        """(N, K) class probabilities, columns in :attr:`classes` order."""
        return self.pipeline.predict_proba(self._features(records))

    def score(self, records: Sequence[StrokeRecord], labels: Sequence[str] | None = None) -> float:
        """Accuracy in [0, 1] on ``records``."""
        truth = self._labels(records, labels)
        pred = self.predict(records)
        return float(np.mean([p == t for p, t in zip(pred, truth)]))


def honesty_check(records: Sequence[StrokeRecord], seed: int = 0) -> dict:
    """The emulation's honesty check: the reference classifier's accuracy on a 7:3 split (SSMC), for the
    category and for the instance. Above 0.90 on categories the emulation is less varied than real materials.
    Also each stream's own category accuracy (:func:`stream_accuracies`). The summary features are computed once.
    """
    from perception.dataset import ssmc_split

    train_idx, test_idx = ssmc_split(records, seed)
    x = ReferenceClassifier()._features(records)  # (N, D), shared by every classifier below
    result = {"n_train": len(train_idx), "n_test": len(test_idx), "seed": seed}
    labels = {}
    for label in ("category", "instance"):
        clf = ReferenceClassifier(ReferenceConfig(label=label))
        y = labels[label] = np.array(clf._labels(records, None))
        clf.pipeline.fit(x[train_idx], y[train_idx])
        result[f"{label}_accuracy"] = round(float(np.mean(clf.pipeline.predict(x[test_idx]) == y[test_idx])), 4)
    result["too_easy"] = result["category_accuracy"] > 0.90
    y = labels["category"]
    result["category_accuracy_by_stream"] = _block_accuracies(x[train_idx], y[train_idx], x[test_idx], y[test_idx])
    return result


def stream_accuracies(train: Sequence[StrokeRecord], test: Sequence[StrokeRecord],
                      config: ReferenceConfig = ReferenceConfig()) -> dict[str, float]:
    """Accuracy in [0, 1] on ``test`` of one reference classifier per modality, each fitted on that modality's
    block of :func:`summary_features` of ``train`` alone: how much of the label each stream carries by itself."""
    clf = ReferenceClassifier(config)
    return _block_accuracies(clf._features(train), np.array(clf._labels(train, None)), clf._features(test),
                             np.array(clf._labels(test, None)), config)


def _block_accuracies(x_train: np.ndarray, y_train: np.ndarray, x_test: np.ndarray, y_test: np.ndarray,
                      config: ReferenceConfig = ReferenceConfig()) -> dict[str, float]:
    """:func:`stream_accuracies` on summary matrices (rows: strokes; one equal block per modality)."""
    clf = ReferenceClassifier(config)
    block = x_train.shape[1] // len(MODALITIES)
    result = {}
    for j, modality in enumerate(MODALITIES):
        cols = slice(j * block, (j + 1) * block)
        clf.pipeline.fit(x_train[:, cols], y_train)  # refits the same pipeline on this block
        result[modality] = round(float(np.mean(clf.pipeline.predict(x_test[:, cols]) == y_test)), 4)
    return result
