"""Temperature scaling (perception.calibration): fitted on held-out strokes, it recovers how overconfident
logits are, keeps the predicted class, and refuses malformed input."""

from __future__ import annotations

import numpy as np
import pytest

from perception.calibration import fit_temperature, nll


def _calibrated(n: int = 4000, k: int = 5, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Logits whose softmax is the true label distribution (labels drawn from it): calibrated at T = 1."""
    rng = np.random.default_rng(seed)
    logits = rng.normal(0.0, 1.5, size=(n, k))
    p = np.exp(logits - logits.max(1, keepdims=True))
    p /= p.sum(1, keepdims=True)
    labels = np.array([rng.choice(k, p=row) for row in p])
    return logits, labels


def test_recovers_the_scale_of_overconfident_logits():
    logits, labels = _calibrated()
    assert fit_temperature(logits, labels) == pytest.approx(1.0, abs=0.1)
    assert fit_temperature(3.0 * logits, labels) == pytest.approx(3.0, rel=0.1)  # overconfident
    assert fit_temperature(0.5 * logits, labels) == pytest.approx(0.5, rel=0.1)  # underconfident
    t = fit_temperature(3.0 * logits, labels)
    assert nll(3.0 * logits, labels, t) < nll(3.0 * logits, labels) - 0.1
    assert np.array_equal(np.argmax(3.0 * logits / t, axis=1), np.argmax(logits, axis=1))


def test_bad_input_is_refused():
    logits, labels = _calibrated(n=10)
    with pytest.raises(ValueError, match="NaN or inf"):
        fit_temperature(np.where(np.eye(10, 5, dtype=bool), np.nan, logits), labels)
    with pytest.raises(ValueError, match="labels must lie"):
        fit_temperature(logits, labels + 5)
    with pytest.raises(ValueError, match="N > 0"):
        fit_temperature(logits[:0], labels[:0])
    with pytest.raises(ValueError, match="N > 0"):
        fit_temperature(logits, labels[:3])
