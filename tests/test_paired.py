"""Paired comparison of two classifiers on the same test strokes (perception/paired.py)."""

import numpy as np
import pytest
from scipy import stats

from perception.paired import paired_comparison


def _runs(rng, accuracies, sizes, n_classes=7):
    """Per run: true labels, and one prediction array per accuracy (each right with that probability)."""
    ys, preds = [], [[] for _ in accuracies]
    for n in sizes:
        y = rng.integers(0, n_classes, n)
        ys.append(y)
        for p, acc in zip(preds, accuracies):
            p.append(np.where(rng.random(n) < acc, y, (y + 1) % n_classes))
    return ys, preds


def test_hand_example_counts_discordant_strokes_and_averages_runs():
    y = [np.array([0, 1, 2, 3]), np.array([0, 0])]
    a = [np.array([0, 1, 2, 0]), np.array([0, 1])]  # 3/4 and 1/2 right
    b = [np.array([0, 0, 0, 0]), np.array([0, 0])]  # 1/4 and 2/2 right
    c = paired_comparison(y, a, b, "a", "b", n_resamples=999)
    assert c.n_runs == 2 and c.n_strokes == 6
    assert c.difference_points == pytest.approx(100 * ((0.75 - 0.25) + (0.5 - 1.0)) / 2)  # mean of run means
    assert (c.model_only_right, c.baseline_only_right) == (2, 1)
    assert c.mcnemar_p == pytest.approx(stats.binomtest(2, 3, 0.5).pvalue)


def test_a_clearly_better_model_is_told_apart_and_a_copy_is_not():
    rng = np.random.default_rng(0)
    ys, (good, poor) = _runs(rng, (0.9, 0.7), (378, 378, 378))
    c = paired_comparison(ys, good, poor, "good", "poor")
    assert 10 < c.difference_points < 30
    low, high = c.ci95_points
    assert 0 < low < c.difference_points < high
    assert c.mcnemar_p < 1e-6 and c.model_only_right > c.baseline_only_right
    same = paired_comparison(ys, good, good)
    assert same.difference_points == 0.0 and same.ci95_points == (0.0, 0.0) and same.mcnemar_p == 1.0


def test_equally_good_models_get_an_interval_around_zero():
    rng = np.random.default_rng(1)
    ys, (a, b) = _runs(rng, (0.8, 0.8), (200, 260, 240, 250, 310))  # unequal folds, as USMC's
    c = paired_comparison(ys, a, b)
    low, high = c.ci95_points
    assert low < 0 < high and high - low < 10  # 1260 strokes: an interval a few points wide
    assert c.mcnemar_p > 0.05
    # the difference is the mean over runs of each run's difference, as Table 1 averages folds
    per_run = [np.mean(p == y) - np.mean(q == y) for y, p, q in zip(ys, a, b)]
    assert c.difference_points == pytest.approx(100 * np.mean(per_run))


def test_the_bootstrap_is_seeded():
    rng = np.random.default_rng(2)
    ys, (a, b) = _runs(rng, (0.8, 0.75), (120, 120))
    assert paired_comparison(ys, a, b, seed=3) == paired_comparison(ys, a, b, seed=3)


@pytest.mark.parametrize("y, a, b, message", [
    ([np.array([0, 1])], [np.array([0, 1])], [], "same non-zero number of runs"),
    ([], [], [], "same non-zero number of runs"),
    ([np.array([0, 1])], [np.array([0, 1, 1])], [np.array([0, 1])], "the same strokes"),
    ([np.array([0, 1])], [np.array([0.0, np.nan])], [np.array([0, 1])], "not class indices"),
    ([np.array([], dtype=int)], [np.array([], dtype=int)], [np.array([], dtype=int)], "non-empty"),
])
def test_bad_input_is_named(y, a, b, message):
    with pytest.raises(ValueError, match=message):
        paired_comparison(y, a, b)
