"""Temperature scaling (Guo et al., "On Calibration of Modern Neural Networks", ICML 2017): one scalar T > 0
divides a trained network's logits so that its softmax probabilities match how often it is right, fitted by
minimising the negative log-likelihood on held-out (validation) strokes. The predicted class is unchanged;
what changes is the confidence the sorting robot compares against its threshold before stroking again.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import minimize_scalar
from scipy.special import log_softmax

LOG_T_BOUNDS = (-4.0, 4.0)
"""Search range of log T (T from 0.018 to 55)."""


def nll(logits: np.ndarray, labels: np.ndarray, temperature: float = 1.0) -> float:
    """Mean negative log-likelihood of ``labels`` (N,) under softmax(``logits`` (N, K) / ``temperature``)."""
    logp = log_softmax(np.asarray(logits, dtype=float) / temperature, axis=1)
    return float(-logp[np.arange(len(labels)), labels].mean())


def fit_temperature(logits: np.ndarray, labels: np.ndarray) -> float:
    """The temperature minimising :func:`nll` on these strokes.

    Raises:
        ValueError: no strokes, shapes that do not match, labels out of range, or non-finite logits.
    """
    logits, labels = np.asarray(logits, dtype=float), np.asarray(labels)
    if logits.ndim != 2 or labels.shape != (len(logits),) or len(logits) == 0:
        raise ValueError(f"fit_temperature needs logits (N, K) and labels (N,) with N > 0, got {logits.shape} "
                         f"and {labels.shape}")
    if not np.all(np.isfinite(logits)):
        raise ValueError("fit_temperature: logits hold NaN or inf")
    if labels.min() < 0 or labels.max() >= logits.shape[1]:
        raise ValueError(f"fit_temperature: labels must lie in [0, {logits.shape[1]})")
    best = minimize_scalar(lambda log_t: nll(logits, labels, math.exp(log_t)), bounds=LOG_T_BOUNDS,
                           method="bounded", options={"xatol": 1e-4})
    return float(math.exp(best.x))
