"""The evaluation's figures (PNG, matplotlib): confusion matrices, the probes, the robustness curve, t-SNE of
embeddings and training curves, each drawn from what :func:`perception.evaluate.evaluate` collected."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
from sklearn.metrics import confusion_matrix

from perception.report import MODEL_LABEL, PROBE_LABEL, TASK_LABEL


def plot_confusion(path: Path, y_true: np.ndarray, y_pred: np.ndarray, names: Sequence[str], title: str) -> None:
    import matplotlib.pyplot as plt

    cm = confusion_matrix(y_true, y_pred, labels=range(len(names))).astype(np.float64)
    cm = cm / np.maximum(cm.sum(axis=1, keepdims=True), 1)
    k = len(names)
    fig, ax = plt.subplots(figsize=(min(2 + 0.45 * k, 14), min(1.6 + 0.45 * k, 13)))
    im = ax.imshow(cm, vmin=0, vmax=1, cmap="Blues")
    if k <= 30:
        ax.set_xticks(range(k), names, rotation=60, ha="right", fontsize=7)
        ax.set_yticks(range(k), names, fontsize=7)
    if k <= 12:
        for i in range(k):
            for j in range(k):
                ax.text(j, i, f"{cm[i, j]:.2f}", ha="center", va="center", fontsize=7,
                        color="white" if cm[i, j] > 0.5 else "black")
    ax.set_xlabel("predicted")
    ax.set_ylabel("true")
    ax.set_title(title, fontsize=9)
    fig.colorbar(im, ax=ax, fraction=0.046, label="recall")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_probes(path: Path, probes: Mapping[str, Mapping[str, Mapping[str, Mapping[str, float]]]]) -> None:
    """One panel per task: each model's mean test accuracy on its test strokes as recorded and under each
    alteration (grouped bars, error bars ± one std over the seeds or folds)."""
    import matplotlib.pyplot as plt

    kinds = list(PROBE_LABEL)
    fig, axes = plt.subplots(1, len(probes), figsize=(5.2 * len(probes), 3.8), sharey=True, squeeze=False)
    for ax, (task, per_model) in zip(axes[0], probes.items()):
        models = list(per_model)
        width = 0.8 / len(kinds)
        for j, kind in enumerate(kinds):
            xs = [i + (j - (len(kinds) - 1) / 2) * width for i, m in enumerate(models) if kind in per_model[m]]
            stats = [per_model[m][kind] for m in models if kind in per_model[m]]
            ax.bar(xs, [100 * st["mean"] for st in stats], width, yerr=[100 * st["std"] for st in stats],
                   label=PROBE_LABEL[kind], capsize=2)
        ax.set_xticks(range(len(models)), [MODEL_LABEL.get(m, m) for m in models], rotation=20, ha="right",
                      fontsize=7)
        ax.set_title(TASK_LABEL[task], fontsize=9)
        ax.grid(axis="y", alpha=0.3)
    axes[0][0].set_ylabel("test accuracy [%]")
    axes[0][-1].legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_robustness(path: Path, levels: Sequence[Mapping[str, Any]], ylabel: str = "SSMC test accuracy [%]",
                     title: str = "Gaussian noise of std {std} on random modalities") -> None:
    """One panel per noise intensity: mean accuracy against p, one line per model, with a band of ± one std
    over the seeds."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(levels), figsize=(5.0 * len(levels), 3.8), sharey=True, squeeze=False)
    for ax, level in zip(axes[0], levels):
        for model, curve in level["curves"].items():
            ps = sorted(curve, key=float)
            x, mean = np.array([float(p) for p in ps]), np.array([100 * curve[p] for p in ps])
            std = np.array([100 * level["curves_std"][model][p] for p in ps])
            line, = ax.plot(x, mean, marker="o", label=MODEL_LABEL.get(model, model))
            ax.fill_between(x, mean - std, mean + std, color=line.get_color(), alpha=0.12, linewidth=0)
        ax.set_xlabel("corruption ratio p")
        ax.set_title(title.format(std=f"{level['corruption_std']:g}"), fontsize=9)
        ax.grid(alpha=0.3)
    axes[0][0].set_ylabel(ylabel)
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_tsne(path: Path, panels: Sequence[tuple[str, np.ndarray, np.ndarray]], seed: int) -> None:
    import matplotlib.pyplot as plt
    from sklearn.manifold import TSNE

    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 4.0), squeeze=False)
    for ax, (title, emb, y) in zip(axes[0], panels):
        n = emb.shape[0]
        if n >= 5:
            xy = TSNE(n_components=2, perplexity=float(max(2.0, min(30.0, (n - 1) / 3.0))), init="pca",
                      random_state=seed).fit_transform(emb)
            ax.scatter(xy[:, 0], xy[:, 1], c=y, cmap="tab20" if y.max() >= 10 else "tab10", s=10)
        ax.set_title(title, fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_training_curves(path: Path, runs: Mapping[str, Mapping[str, Any]]) -> None:
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.0, 3.8))
    for i, (model, run) in enumerate(runs.items()):
        epochs = np.arange(1, len(run["val_accuracy_curve"]) + 1)
        color = f"C{i}"
        label = MODEL_LABEL.get(model, model)
        ax.plot(epochs, 100 * np.asarray(run["train_accuracy_curve"]), "--", color=color, label=f"{label} train")
        ax.plot(epochs, 100 * np.asarray(run["val_accuracy_curve"]), "-", color=color, label=f"{label} validation")
        ax.axvline(run["best_epoch"], color=color, alpha=0.3, lw=1)
    ax.set_xlabel("epoch")
    ax.set_ylabel("accuracy [%]")
    ax.set_title(f"SSMC {next(iter(runs.values()))['split']}: training vs validation (vertical: chosen epoch)",
                 fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
