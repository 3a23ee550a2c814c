"""How much a trained model used each sensor: its MAG weights over a set of strokes.

Modality-Adaptive Gating (:mod:`perception.touchformer`, step 2) gives each stroke a weight alpha_m per sensor and
drops a sensor whose gate falls under ``gate_th`` (alpha_m = 0). A dropped sensor gets no gradient through its
alpha (unless ``gate_straight_through``), so once the gate shuts a sensor out on most strokes it can stay shut,
and the model reads the remaining sensors alone (session 68 of ``docs/touchformer-findings.md``: 3 of 10 runs
read the sound alone and stalled). This module summarises the alphas of a model's predictions per sensor so that
every training run reports it (``metrics.json``'s ``val_sensor_use``) and warns when a sensor was shut out.

Only strokes that carry a sensor count for it: an absent sensor (alpha 0 because it is missing) is not "dropped".
Baselines without a gate report uniform alphas, so their dropped share is 0.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from perception.streams import MODALITIES

SHUT_OUT_SHARE: float = 0.5
"""A sensor dropped by the gate on more than this share of the strokes that carry it is reported as shut out."""


@dataclass(frozen=True)
class SensorUse:
    """One sensor's MAG weights over the strokes that carry it.

    Attributes:
        n_strokes: strokes that carry the sensor.
        mean_alpha: mean alpha_m over those strokes, in [0, 1] (None when no stroke carries the sensor).
        dropped_share: share of those strokes on which the gate dropped the sensor (alpha_m = 0), in [0, 1]
            (None when no stroke carries it).
    """

    n_strokes: int
    mean_alpha: float | None
    dropped_share: float | None

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def sensor_use(alphas: np.ndarray, present: np.ndarray, names: Sequence[str] = MODALITIES
               ) -> dict[str, SensorUse]:
    """Per-sensor MAG use over N strokes.

    Args:
        alphas: (N, M) modality weights, as :class:`perception.train.Predictions` holds them.
        present: (N, M) bool, True where the stroke carries the sensor.
        names: the M sensors' names, in the columns' order.

    Raises:
        ValueError: shapes disagree, or the alphas hold NaN, inf or values outside [0, 1].
    """
    alphas = np.asarray(alphas, dtype=float)
    present = np.asarray(present, dtype=bool)
    if alphas.ndim != 2 or alphas.shape != present.shape or alphas.shape[1] != len(names):
        raise ValueError(f"sensor_use needs alphas and present of shape (N, {len(names)}), got {alphas.shape} "
                         f"and {present.shape}")
    if not np.all(np.isfinite(alphas)):
        raise ValueError("sensor_use: the alphas hold NaN or inf")
    if np.any((alphas < 0.0) | (alphas > 1.0 + 1e-6)):
        raise ValueError("sensor_use: alphas must lie in [0, 1]")
    use = {}
    for j, name in enumerate(names):
        carried = alphas[present[:, j], j]
        n = int(carried.size)
        use[name] = SensorUse(n_strokes=n, mean_alpha=float(carried.mean()) if n else None,
                              dropped_share=float(np.mean(carried == 0.0)) if n else None)
    return use


def sensor_use_from_dict(data: Any) -> dict[str, SensorUse]:
    """``metrics.json``'s ``val_sensor_use`` ({sensor: :meth:`SensorUse.to_dict`}) back into records.

    Raises:
        ValueError: ``data`` is not such a mapping, or a record's fields are missing, extra or not numbers.
    """
    if not isinstance(data, Mapping):
        raise ValueError(f"expected a mapping of sensor names to records, got {type(data).__name__}")
    out = {}
    for name, record in data.items():
        try:
            use = SensorUse(**record)
        except TypeError as exc:
            raise ValueError(f"sensor {name!r}: {exc}") from None
        if not all(v is None or isinstance(v, (int, float)) for v in (use.mean_alpha, use.dropped_share)):
            raise ValueError(f"sensor {name!r}: mean_alpha and dropped_share must be numbers or null")
        out[str(name)] = use
    return out


def presence_matrix(features: Sequence[Mapping[str, Any]], names: Sequence[str] = MODALITIES) -> np.ndarray:
    """(N, M) bool: which of ``names`` each featurized stroke carries (a missing sensor is None or absent)."""
    return np.array([[f.get(m) is not None for m in names] for f in features], dtype=bool).reshape(-1, len(names))


def shut_out(use: Mapping[str, SensorUse], share: float = SHUT_OUT_SHARE) -> dict[str, float]:
    """The sensors the gate dropped on more than ``share`` of the strokes that carry them: {name: dropped share}."""
    return {name: u.dropped_share for name, u in use.items()
            if u.dropped_share is not None and u.dropped_share > share}


def shut_out_warning(use: Mapping[str, SensorUse], where: str = "validation", share: float = SHUT_OUT_SHARE
                     ) -> str | None:
    """One line naming the sensors the gate shut out, or None when it shut none out."""
    shut = shut_out(use, share)
    if not shut:
        return None
    listed = ", ".join(f"{name} on {100 * s:.0f} %" for name, s in shut.items())
    return (f"warning: the gate dropped {listed} of the {where} strokes that carry them; a dropped sensor gets no "
            f"gradient through its weight unless --model-option gate_straight_through=True")
