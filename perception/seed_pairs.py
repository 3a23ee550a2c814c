"""Seed-paired comparison of training runs: does one recipe beat another over retrainings?

:mod:`perception.paired` asks whether two trained networks differ by more than the draw of the test strokes.
This module asks the other question, the one a probe of a recipe needs: trained again with other seeds (or on
other folds), is arm A's accuracy above arm B's by more than the seeds move it? It reads the ``metrics.json``
that ``robotdemo train`` writes, pairs A's run with B's run of the same seed and fold (the same split, so the
same validation and test strokes), and gives for each metric:

- the mean over pairs of A's accuracy minus B's, in points;
- its 95 % t-interval and the paired t-test's two-sided p (``scipy.stats.ttest_rel``), which treat the pairs'
  differences as draws from the recipes' training noise;
- how many pairs A won, lost and tied.

A runs folder holds one folder per arm, each with one folder per run, any depth below it:
``RUNS/ARM/.../metrics.json``. Runs of different data sets or tasks are not paired (a one-line error).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from scipy import stats

from perception.sensor_use import sensor_use_from_dict, shut_out

METRICS: tuple[str, ...] = ("val", "test")
"""What a pair is compared on: the best epoch's validation accuracy (what a recipe may be chosen on) and the
test accuracy of that epoch."""

_KEYS = {"val": "best_val_accuracy", "test": "test_accuracy"}


@dataclass(frozen=True)
class RunScore:
    """One ``robotdemo train`` run, as its ``metrics.json`` gives it.

    Attributes:
        arm: the arm's folder name under the runs folder.
        path: the ``metrics.json`` read.
        task: ssmc, usmc or fine.
        seed: training seed.
        fold: USMC fold (0 for the other tasks).
        val_accuracy: the best epoch's validation accuracy, in [0, 1].
        test_accuracy: that epoch's test accuracy, in [0, 1].
        data_manifest_sha256: the data set's manifest hash.
        shut_out: the sensors the gate dropped on more than half of the validation strokes that carry them
            (:func:`perception.sensor_use.shut_out`); None for a run whose ``metrics.json`` predates
            ``val_sensor_use``.
    """

    arm: str
    path: Path
    task: str
    seed: int
    fold: int
    val_accuracy: float
    test_accuracy: float
    data_manifest_sha256: str
    shut_out: tuple[str, ...] | None = None

    @property
    def key(self) -> tuple[int, int]:
        """What pairs a run with another arm's: (seed, fold)."""
        return self.seed, self.fold

    def accuracy(self, metric: str) -> float:
        return self.val_accuracy if metric == "val" else self.test_accuracy


@dataclass(frozen=True)
class SeedPairedDifference:
    """Arm ``arm`` against arm ``against`` on one metric, over the runs both have.

    Attributes:
        arm, against: the two arms.
        metric: "val" or "test".
        n_pairs: runs paired (same seed and fold in both arms).
        mean_points: mean over pairs of (arm - against) accuracy, in percentage points.
        ci95_points: 95 % t-interval of ``mean_points``.
        p_value: two-sided paired t-test p (1.0 when every difference is 0).
        won, lost, tied: pairs in which ``arm`` scored above, under, level with ``against``.
        differences_points: each pair's difference, in (seed, fold) order.
    """

    arm: str
    against: str
    metric: str
    n_pairs: int
    mean_points: float
    ci95_points: tuple[float, float]
    p_value: float
    won: int
    lost: int
    tied: int
    differences_points: tuple[float, ...]

    def to_dict(self) -> dict[str, Any]:
        return {**asdict(self), "ci95_points": list(self.ci95_points),
                "differences_points": list(self.differences_points)}


def _read_run(arm: str, path: Path) -> RunScore:
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON ({exc.msg} at line {exc.lineno})") from None
    if not isinstance(record, dict):
        raise ValueError(f"{path}: expected a JSON object as robotdemo train writes, got {type(record).__name__}")
    missing = [k for k in ("task", "seed", "fold", *_KEYS.values(), "data_manifest_sha256") if k not in record]
    if missing:
        raise ValueError(f"{path}: not a robotdemo train metrics.json (missing {', '.join(missing)})")
    scores = {}
    for metric, key in _KEYS.items():
        value = record[key]
        if not isinstance(value, (int, float)) or not math.isfinite(value) or not 0.0 <= value <= 1.0:
            raise ValueError(f"{path}: {key} must be an accuracy in [0, 1], got {value!r}")
        scores[metric] = float(value)
    return RunScore(arm=arm, path=path, task=str(record["task"]), seed=int(record["seed"]), fold=int(record["fold"]),
                    val_accuracy=scores["val"], test_accuracy=scores["test"],
                    data_manifest_sha256=str(record["data_manifest_sha256"]), shut_out=_read_shut_out(path, record))


def _read_shut_out(path: Path, record: dict[str, Any]) -> tuple[str, ...] | None:
    """The sensors ``record``'s ``val_sensor_use`` says the gate shut out; None when the run does not record it."""
    use = record.get("val_sensor_use")
    if use is None:
        return None
    try:
        parsed = sensor_use_from_dict(use)
    except ValueError as exc:
        raise ValueError(f"{path}: malformed val_sensor_use ({exc})") from None
    return tuple(shut_out(parsed))


def load_arm_runs(root: str | Path) -> dict[str, dict[tuple[int, int], RunScore]]:
    """Every run under ``root``, by arm and (seed, fold).

    Raises:
        ValueError: ``root`` is not a folder or holds no run; a ``metrics.json`` is malformed; an arm has two
            runs of one seed and fold.
    """
    root = Path(root)
    if not root.is_dir():
        raise ValueError(f"runs folder {root} does not exist or is not a folder")
    arms: dict[str, dict[tuple[int, int], RunScore]] = {}
    for path in sorted(root.glob("*/**/metrics.json")):
        arm = path.relative_to(root).parts[0]
        run = _read_run(arm, path)
        by_key = arms.setdefault(arm, {})
        if run.key in by_key:
            raise ValueError(f"arm {arm!r} has two runs of seed {run.seed} fold {run.fold}: "
                             f"{by_key[run.key].path} and {path}")
        by_key[run.key] = run
    if not arms:
        raise ValueError(f"runs folder {root} holds no ARM/.../metrics.json")
    return arms


def seed_paired_difference(runs: dict[str, dict[tuple[int, int], RunScore]], arm: str, against: str,
                           metric: str) -> SeedPairedDifference:
    """``arm`` minus ``against`` on ``metric`` over the (seed, fold) runs both arms have.

    Raises:
        ValueError: an arm is unknown, the metric is not one of :data:`METRICS`, fewer than two runs pair, or a
            pair's runs are of different data sets or tasks.
    """
    if metric not in METRICS:
        raise ValueError(f"metric must be one of {METRICS}, got {metric!r}")
    for name in (arm, against):
        if name not in runs:
            raise ValueError(f"no arm {name!r} in the runs folder (arms: {', '.join(sorted(runs))})")
    keys = sorted(set(runs[arm]) & set(runs[against]))
    if len(keys) < 2:
        raise ValueError(f"{arm!r} and {against!r} share {len(keys)} (seed, fold) run(s); a paired comparison "
                         "needs at least 2")
    for key in keys:
        a, b = runs[arm][key], runs[against][key]
        if (a.data_manifest_sha256, a.task) != (b.data_manifest_sha256, b.task):
            raise ValueError(f"seed {key[0]} fold {key[1]}: {a.path} and {b.path} are of different data sets or "
                             f"tasks ({a.task} {a.data_manifest_sha256[:12]} against {b.task} "
                             f"{b.data_manifest_sha256[:12]}); they do not pair")
    diffs = np.array([100.0 * (runs[arm][k].accuracy(metric) - runs[against][k].accuracy(metric)) for k in keys])
    mean = float(diffs.mean())
    if np.allclose(diffs, diffs[0]):  # no spread: the t-test is undefined
        ci, p = (mean, mean), (1.0 if diffs[0] == 0 else 0.0)
    else:
        result = stats.ttest_1samp(diffs, 0.0)
        interval = result.confidence_interval(0.95)
        ci, p = (float(interval.low), float(interval.high)), float(result.pvalue)
    return SeedPairedDifference(arm=arm, against=against, metric=metric, n_pairs=len(keys), mean_points=mean,
                                ci95_points=ci, p_value=p, won=int((diffs > 0).sum()), lost=int((diffs < 0).sum()),
                                tied=int((diffs == 0).sum()), differences_points=tuple(float(d) for d in diffs))


def arm_summary(runs: dict[tuple[int, int], RunScore]) -> dict[str, Any]:
    """Mean and sample std over an arm's runs, in percent, per metric, with its seeds and folds, and the runs in
    which the gate shut a sensor out (of those that record their sensor use)."""
    keys = sorted(runs)
    out: dict[str, Any] = {"runs": len(keys), "seeds": sorted({k[0] for k in keys}),
                           "folds": sorted({k[1] for k in keys})}
    for metric in METRICS:
        values = np.array([100.0 * runs[k].accuracy(metric) for k in keys])
        out[metric] = {"mean": float(values.mean()), "std": float(values.std(ddof=1)) if len(values) > 1 else 0.0}
    recorded = [runs[k] for k in keys if runs[k].shut_out is not None]
    out["sensor_use_recorded"] = len(recorded)
    out["sensor_shut_out"] = [{"seed": r.seed, "fold": r.fold, "sensors": list(r.shut_out)}
                              for r in recorded if r.shut_out]
    return out


def parse_pair(text: str) -> tuple[str, str]:
    """``"A:B"`` -> ("A", "B")."""
    parts = text.split(":")
    if len(parts) != 2 or not all(parts):
        raise ValueError(f"a pair must be ARM:AGAINST, got {text!r}")
    return parts[0], parts[1]


def compare_arms(root: str | Path, pairs: Sequence[tuple[str, str]]) -> dict[str, Any]:
    """Every arm's mean and std, and each pair's :class:`SeedPairedDifference` on validation and test."""
    runs = load_arm_runs(root)
    return {"runs_folder": str(root),
            "arms": {arm: arm_summary(by_key) for arm, by_key in sorted(runs.items())},
            "pairs": [{metric: seed_paired_difference(runs, a, b, metric).to_dict() for metric in METRICS}
                      | {"arm": a, "against": b} for a, b in pairs]}


def format_comparison(result: dict[str, Any]) -> str:
    """The comparison as text: a line per arm, a line per pair."""
    lines = []
    for arm, s in result["arms"].items():
        line = (f"{arm}: {s['runs']} runs, val {s['val']['mean']:.1f} ± {s['val']['std']:.1f} %, "
                f"test {s['test']['mean']:.1f} ± {s['test']['std']:.1f} %")
        if s.get("sensor_use_recorded"):
            shut = s["sensor_shut_out"]
            line += f"; a sensor shut out by the gate in {len(shut)} of {s['sensor_use_recorded']} runs"
            if shut:
                line += " (" + ", ".join(f"seed {r['seed']} fold {r['fold']}: {'+'.join(r['sensors'])}"
                                         for r in shut) + ")"
        lines.append(line)
    for pair in result["pairs"]:
        parts = [f"{m} {pair[m]['mean_points']:+.1f} ({pair[m]['ci95_points'][0]:+.1f} to "
                 f"{pair[m]['ci95_points'][1]:+.1f}, p {pair[m]['p_value']:.2g}, {pair[m]['won']}-{pair[m]['lost']})"
                 for m in METRICS]
        lines.append(f"{pair['arm']} - {pair['against']} ({pair['val']['n_pairs']} pairs): " + "; ".join(parts))
    return "\n".join(lines)


def plot_comparison(path: str | Path, result: dict[str, Any]) -> Path:
    """Each pair's per-run differences (dots) with their mean and 95 % interval (bar), validation and test."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pairs = result["pairs"]
    fig, axes = plt.subplots(1, len(METRICS), figsize=(5 * len(METRICS), 0.8 + 0.7 * max(len(pairs), 1)),
                             sharey=True, squeeze=False)
    labels = [f"{p['arm']} - {p['against']}" for p in pairs]
    rng = np.random.default_rng(0)  # vertical jitter of the dots only
    for ax, metric in zip(axes[0], METRICS):
        for row, pair in enumerate(pairs):
            d = pair[metric]
            ax.scatter(d["differences_points"], row + rng.uniform(-0.15, 0.15, len(d["differences_points"])),
                       s=12, color="0.5", zorder=2)
            lo, hi = d["ci95_points"]
            ax.errorbar(d["mean_points"], row, xerr=[[d["mean_points"] - lo], [hi - d["mean_points"]]], fmt="o",
                        color="C0", capsize=4, zorder=3)
        ax.axvline(0.0, color="k", lw=0.8)
        ax.set_title(f"{metric} accuracy")
        ax.set_xlabel("difference (points)")
        ax.set_yticks(range(len(pairs)), labels)
        ax.set_ylim(len(pairs) - 0.5, -0.5)  # the first pair on top
    fig.tight_layout()
    out = Path(path)
    fig.savefig(out, dpi=120)
    plt.close(fig)
    return out
