"""Figures people would rather look at than JSON: the four streams of a few strokes side by side."""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from perception.streams import MODALITIES, StrokeRecord  # noqa: E402

_TITLES = {"sound": "S: sound (44.1 kHz)", "normal": "N: taxel normal force, sum of 16 (100 Hz)",
           "friction": "F: taxel shear |x, y|, sum (100 Hz)", "accel": "A: fingertip acceleration |a - mean| (500 Hz)"}


def _series(record: StrokeRecord, key: str) -> tuple[np.ndarray, np.ndarray] | None:
    stream = record.streams.get(key)
    if stream is None:
        return None
    data = stream.data
    if key == "normal":
        y = data.sum(axis=1)
    elif key == "friction":
        xy = data.reshape(len(data), 16, 2).sum(axis=1)
        y = np.linalg.norm(xy, axis=1)
    elif key == "accel":
        y = np.linalg.norm(data - data.mean(axis=0), axis=1)
    else:
        y = data[:, 0]
    return stream.times_s(), y


def plot_strokes(records: Sequence[StrokeRecord], path: str | Path) -> Path:
    """One column per stroke, one row per modality; a missing modality is marked as such."""
    n = len(records)
    fig, axes = plt.subplots(4, n, figsize=(3.2 * n, 8), squeeze=False, sharex="col")
    for col, rec in enumerate(records):
        axes[0, col].set_title(f"{rec.category} / {rec.instance}\n"
                               f"{rec.meta.get('target_force_n', float('nan')):.1f} N, "
                               f"{1000 * rec.meta.get('speed_mps', float('nan')):.0f} mm/s", fontsize=9)
        for row, key in enumerate(MODALITIES):
            ax = axes[row, col]
            series = _series(rec, key)
            if series is None:
                ax.text(0.5, 0.5, "missing", ha="center", va="center", transform=ax.transAxes, color="red")
            else:
                t, y = series
                ax.plot(t, y, lw=0.5 if key == "sound" else 1.0)
            if col == 0:
                ax.set_ylabel(_TITLES[key], fontsize=7)
        axes[-1, col].set_xlabel("time (s)")
    fig.tight_layout()
    path = Path(path)
    if not path.suffix:  # what matplotlib would write: name it so
        path = path.with_name(path.name + ".png")
    if path.is_dir():
        plt.close(fig)
        raise ValueError(f"{path} is a folder; give a file name for the plot")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
