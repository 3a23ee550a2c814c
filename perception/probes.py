"""What a trained classifier uses: its test strokes altered at inference, one kind of structure at a time.

TouchFormer's case rests on two kinds of structure: the temporal dynamics within a sensor (intra-modal
attention, positional embeddings) and the relations between sensors (inter-modal attention, fused "without
alignment"). Each alteration below removes one of them from the test strokes of a trained network, and nothing
else, so the accuracy it costs says how much the network's predictions rest on it:

- ``time_shuffled``: each stream's frames in a random order (the stream's set of frames kept; its temporal
  order and the timing between sensors gone);
- ``time_reversed``: each stream's frames backwards (order within a sensor reversed, local frame content kept);
- ``desync``: each stream circularly shifted by its own random number of frames (the order within a sensor kept
  but for one seam; when things happen in one sensor against another gone);
- ``swap``: each stream taken from another test stroke of the same class, a different stroke per stream
  (what each sensor says about the class kept; everything the four sensors share within one stroke gone, such
  as the pressing force and sliding speed that shape all of them at once).

Nothing is trained or selected on these: they are read on the test strokes of runs already chosen.
"""

from __future__ import annotations

from typing import Mapping, NamedTuple, Sequence

import numpy as np

from perception.features import StrokeFeatures
from perception.streams import MODALITIES

ALTERATIONS: tuple[str, ...] = ("time_shuffled", "time_reversed", "desync", "swap")


class AlteredStrokes(NamedTuple):
    """Altered per-stroke features and, per stroke and modality, the index (into the inputs) of the stroke
    the stream came from (itself except under ``swap``)."""

    features: list[dict[str, np.ndarray | None]]
    sources: list[dict[str, int]]


def alter(features: Sequence[StrokeFeatures], labels: Sequence[int], kind: str,
          rng: np.random.Generator) -> AlteredStrokes:
    """``features`` (one mapping modality -> (T_m, C_m) frames or None per stroke) altered by ``kind``.

    Args:
        features: the test strokes' features.
        labels: their class labels (used by ``swap`` only: a stream is taken from a stroke of the same class).
        kind: one of :data:`ALTERATIONS`.
        rng: draws the permutations, shifts and donor strokes.

    A missing stream stays missing. Under ``swap`` a stream whose class has no other stroke with that stream
    keeps its own.
    """
    if kind not in ALTERATIONS:
        raise ValueError(f"unknown alteration {kind!r}; expected one of {ALTERATIONS}")
    if len(labels) != len(features):
        raise ValueError(f"{len(features)} strokes but {len(labels)} labels")
    labels = np.asarray(labels)
    out: list[dict[str, np.ndarray | None]] = []
    sources: list[dict[str, int]] = []
    for i, stroke in enumerate(features):
        altered: dict[str, np.ndarray | None] = {}
        source: dict[str, int] = {}
        for m in MODALITIES:
            frames, source[m] = stroke.get(m), i
            if frames is not None:
                if kind == "time_shuffled":
                    frames = frames[rng.permutation(len(frames))]
                elif kind == "time_reversed":
                    frames = frames[::-1].copy()
                elif kind == "desync":
                    frames = np.roll(frames, int(rng.integers(len(frames))), axis=0)
                else:  # swap
                    donors = [k for k in np.flatnonzero(labels == labels[i])
                              if k != i and features[k].get(m) is not None]
                    if donors:
                        source[m] = int(donors[rng.integers(len(donors))])
                        frames = features[source[m]][m]
            altered[m] = frames
        out.append(altered)
        sources.append(source)
    return AlteredStrokes(out, sources)


def swap_summaries(summaries: np.ndarray, sources: Sequence[Mapping[str, int]]) -> np.ndarray:
    """Per-stroke stream statistics (N, 4 B: one block of B per modality, :data:`MODALITIES` order, as
    :func:`perception.reference_classifier.summary_features` lays them out) assembled from the strokes
    ``sources`` names: the ``swap`` alteration for a classifier that reads statistics instead of frames."""
    block = summaries.shape[1] // len(MODALITIES)
    return np.stack([np.concatenate([summaries[src[m], j * block:(j + 1) * block] for j, m in enumerate(MODALITIES)])
                     for src in sources]) if len(sources) else summaries[:0]
