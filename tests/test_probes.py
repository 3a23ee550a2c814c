"""Alterations of test strokes that take one kind of structure out (perception.probes)."""

from __future__ import annotations

import numpy as np
import pytest

from perception.probes import ALTERATIONS, alter, swap_summaries
from perception.streams import MODALITIES


def _strokes(n: int = 6, seed: int = 0) -> tuple[list[dict], np.ndarray]:
    """``n`` strokes of two classes; stroke i's frames of modality j are all distinct and encode (i, j, t);
    stroke 0 has no acceleration stream."""
    rng = np.random.default_rng(seed)
    strokes = []
    for i in range(n):
        stroke = {}
        for j, m in enumerate(MODALITIES):
            t = int(rng.integers(5, 12))
            stroke[m] = np.stack([np.full(3, 1000.0 * i + 100.0 * j + k) for k in range(t)])  # (T, 3)
        strokes.append(stroke)
    strokes[0]["accel"] = None
    return strokes, np.array([0, 1] * (n // 2))


@pytest.mark.parametrize("kind", ["time_shuffled", "time_reversed", "desync"])
def test_time_alterations_keep_each_streams_frames_and_change_their_order(kind):
    strokes, labels = _strokes()
    altered = alter(strokes, labels, kind, np.random.default_rng(1))
    assert len(altered.features) == len(strokes)
    moved = 0
    for i, (before, after) in enumerate(zip(strokes, altered.features)):
        assert altered.sources[i] == {m: i for m in MODALITIES}  # nothing taken from another stroke
        for m in MODALITIES:
            if before[m] is None:
                assert after[m] is None  # a missing stream stays missing
                continue
            assert after[m].shape == before[m].shape
            assert sorted(after[m][:, 0]) == sorted(before[m][:, 0])  # the same frames
            moved += not np.array_equal(after[m], before[m])
            t = len(before[m])
            if kind == "time_reversed":
                assert np.array_equal(after[m], before[m][::-1])
            if kind == "desync":  # a circular shift: consecutive frames stay consecutive but at one seam
                assert any(np.array_equal(after[m], np.roll(before[m], k, axis=0)) for k in range(t))
    assert moved >= 15  # of 23 streams of 5-11 frames: a shift leaves one as it was with chance 1 / T


def test_desync_shifts_the_sensors_of_one_stroke_by_different_amounts():
    strokes, labels = _strokes(n=40)
    altered = alter(strokes, labels, "desync", np.random.default_rng(2))
    differing = 0
    for before, after in zip(strokes[1:], altered.features[1:]):
        shifts = {m: next(k for k in range(len(before[m])) if np.array_equal(after[m], np.roll(before[m], k, axis=0)))
                  / len(before[m]) for m in MODALITIES}
        differing += len(set(np.round(list(shifts.values()), 6))) > 1
    assert differing >= 35


def test_swap_takes_each_stream_from_another_stroke_of_the_same_class():
    strokes, labels = _strokes(n=10)
    altered = alter(strokes, labels, "swap", np.random.default_rng(3))
    donors_per_stroke = []
    for i, (after, source) in enumerate(zip(altered.features, altered.sources)):
        for m in MODALITIES:
            k = source[m]
            if strokes[i][m] is None:  # a missing sensor stays missing
                assert after[m] is None and k == i
                continue
            assert k != i and labels[k] == labels[i]
            assert strokes[k][m] is not None and after[m] is strokes[k][m]  # the donor's stream, unchanged
        donors_per_stroke.append(len(set(source.values())))
    assert max(donors_per_stroke) > 1  # the four sensors of a stroke come from different strokes


def test_swap_keeps_a_stream_whose_class_has_no_other_stroke():
    strokes, _ = _strokes(n=3)
    labels = np.array([0, 1, 1])
    altered = alter(strokes, labels, "swap", np.random.default_rng(4))
    assert altered.sources[0] == {m: 0 for m in MODALITIES}
    assert all(altered.sources[1][m] == 2 and altered.sources[2][m] == 1 for m in MODALITIES)


def test_swap_summaries_assembles_each_block_from_its_source():
    summaries = np.arange(3 * 8, dtype=float).reshape(3, 8)  # two statistics per modality
    sources = [{"sound": 1, "normal": 2, "friction": 0, "accel": 0}]
    assert swap_summaries(summaries, sources).tolist() == [[8, 9, 18, 19, 4, 5, 6, 7]]


def test_alter_is_seeded_and_rejects_bad_input():
    strokes, labels = _strokes()
    for kind in ALTERATIONS:
        a = alter(strokes, labels, kind, np.random.default_rng(5))
        b = alter(strokes, labels, kind, np.random.default_rng(5))
        assert a.sources == b.sources
        assert all(np.array_equal(x[m], y[m]) for x, y in zip(a.features, b.features) for m in MODALITIES
                   if x[m] is not None)
    with pytest.raises(ValueError, match="unknown alteration 'mirror'"):
        alter(strokes, labels, "mirror", np.random.default_rng(0))
    with pytest.raises(ValueError, match="6 strokes but 5 labels"):
        alter(strokes, labels[:5], "swap", np.random.default_rng(0))
