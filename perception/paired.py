"""Paired comparison of two classifiers on the same test strokes.

Table 1 gives each model's accuracy as mean ± std over seeds (or folds), which measures how much a model moves
when it is trained again on another split. It does not say whether two models that were tested on the same
strokes differ by more than which strokes happened to be drawn for testing. This module answers that for a pair
of models scored on the same runs (the same seed's or fold's test strokes for both):

- the difference of their accuracies, the mean over runs of each run's difference (as Table 1 averages);
- a 95 % bootstrap interval of that difference over the test strokes, each run's strokes resampled on their own
  (``scipy.stats.bootstrap`` with one sample per run, which resamples each sample independently), so it holds
  the test split's sampling noise for these trained networks, not the training seed's;
- the discordant strokes (right for one model only) pooled over the runs, and McNemar's exact test on them
  (``scipy.stats.binomtest``: under "the two are equally good" each discordant stroke is a fair coin).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Sequence

import numpy as np
from scipy import stats


@dataclass(frozen=True)
class PairedComparison:
    """One model against another on the same test strokes.

    Attributes:
        model: the model compared.
        baseline: the model it is compared against.
        n_runs: runs (seeds or folds) pooled.
        n_strokes: test strokes over all runs.
        difference_points: mean over runs of (model accuracy - baseline accuracy), in percentage points.
        ci95_points: 95 % bootstrap interval (BCa; percentile where BCa is undefined) of ``difference_points``
            over the test strokes, in points.
        model_only_right: test strokes the model classifies right and the baseline wrong, over all runs.
        baseline_only_right: test strokes the baseline classifies right and the model wrong, over all runs.
        mcnemar_p: two-sided exact McNemar p-value on the discordant strokes (1.0 when there are none).
    """

    model: str
    baseline: str
    n_runs: int
    n_strokes: int
    difference_points: float
    ci95_points: tuple[float, float]
    model_only_right: int
    baseline_only_right: int
    mcnemar_p: float

    def to_dict(self) -> dict[str, Any]:
        return {**asdict(self), "ci95_points": list(self.ci95_points)}


def _as_labels(values: Any, what: str) -> np.ndarray:
    array = np.asarray(values)
    if array.ndim != 1 or array.size == 0:
        raise ValueError(f"{what} must be a non-empty 1-D array of class indices, got shape {array.shape}")
    if not np.issubdtype(array.dtype, np.integer):
        if not np.all(np.isfinite(array)) or np.any(array != np.round(array)):
            raise ValueError(f"{what} holds values that are not class indices (NaN, inf or fractions)")
        array = array.astype(np.int64)
    return array


def _mean_of_run_means(*samples: np.ndarray, axis: int = -1) -> np.ndarray:
    return np.mean([np.mean(s, axis=axis) for s in samples], axis=0)


def paired_comparison(y_true: Sequence[Any], model_pred: Sequence[Any], baseline_pred: Sequence[Any],
                      model: str = "model", baseline: str = "baseline", n_resamples: int = 9999,
                      seed: int = 0) -> PairedComparison:
    """Compare ``model`` with ``baseline`` run by run on the same test strokes.

    Args:
        y_true: per run, the test strokes' true class indices.
        model_pred: per run, the model's predicted class indices for the same strokes, in the same order.
        baseline_pred: per run, the baseline's, likewise.
        model, baseline: names for the record.
        n_resamples: bootstrap resamples.
        seed: the bootstrap's random seed.

    Raises:
        ValueError: no runs, runs of different counts, a run whose arrays differ in length, or values that are
            not class indices.
    """
    if not (len(y_true) == len(model_pred) == len(baseline_pred)) or len(y_true) == 0:
        raise ValueError(f"paired comparison needs the same non-zero number of runs for the truth and both models, "
                         f"got {len(y_true)}, {len(model_pred)} and {len(baseline_pred)}")
    diffs, only_model, only_base = [], 0, 0
    for k, (y, a, b) in enumerate(zip(y_true, model_pred, baseline_pred)):
        y, a, b = (_as_labels(v, f"run {k}'s {w}") for v, w in
                   ((y, "true labels"), (a, f"{model} predictions"), (b, f"{baseline} predictions")))
        if not (y.shape == a.shape == b.shape):
            raise ValueError(f"run {k}: {len(y)} true labels, {len(a)} {model} predictions and {len(b)} "
                             f"{baseline} predictions; a paired comparison needs the same strokes for all three")
        right_a, right_b = a == y, b == y
        only_model += int(np.sum(right_a & ~right_b))
        only_base += int(np.sum(right_b & ~right_a))
        diffs.append(right_a.astype(np.float64) - right_b.astype(np.float64))
    difference = float(_mean_of_run_means(*diffs))
    if all(np.all(d == d[0]) for d in diffs):  # no spread to resample (e.g. both models always agree)
        low = high = difference
    else:
        for method in ("BCa", "percentile"):  # BCa is undefined for some degenerate samples (NaN): fall back
            res = stats.bootstrap(tuple(diffs), _mean_of_run_means, n_resamples=n_resamples, confidence_level=0.95,
                                  method=method, vectorized=True, rng=np.random.default_rng(seed))
            low, high = float(res.confidence_interval.low), float(res.confidence_interval.high)
            if np.isfinite(low) and np.isfinite(high):
                break
    discordant = only_model + only_base
    p = float(stats.binomtest(only_model, discordant, 0.5).pvalue) if discordant else 1.0
    return PairedComparison(model=model, baseline=baseline, n_runs=len(diffs),
                            n_strokes=int(sum(len(d) for d in diffs)), difference_points=100.0 * difference,
                            ci95_points=(100.0 * low, 100.0 * high), model_only_right=only_model,
                            baseline_only_right=only_base, mcnemar_p=p)
