"""The recorded-stroke format shared by sensor emulation, real-data converters and the models.

A stroke is four asynchronous streams, each with its own rate and clock offset:

=========  =====  ==========  ==========================================================
modality   key    rate (Hz)   channels
=========  =====  ==========  ==========================================================
sound      ``S``  44 100      1: microphone pressure, arbitrary units (float32)
normal     ``N``  100         16: uSkin z channel per taxel, newtons after bias removal
friction   ``F``  100         32: uSkin (x, y) shear per taxel, taxel-major [x1, y1, ...]
accel      ``A``  500         3: fingertip IMU, m/s^2, pad frame
=========  =====  ==========  ==========================================================

Any stream may be absent (a sensor that dropped out, or a data set that lacks it): it is then ``None``
in :attr:`StrokeRecord.streams`, never an array of zeros.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

MODALITIES: tuple[str, ...] = ("sound", "normal", "friction", "accel")
"""Modality keys in the paper's order S, N, F, A."""

MODALITY_SYMBOL: dict[str, str] = {"sound": "S", "normal": "N", "friction": "F", "accel": "A"}

NOMINAL_RATE_HZ: dict[str, float] = {"sound": 44_100.0, "normal": 100.0, "friction": 100.0, "accel": 500.0}
NUM_CHANNELS: dict[str, int] = {"sound": 1, "normal": 16, "friction": 32, "accel": 3}


class StreamError(ValueError):
    """A stream or record is malformed (wrong shape, NaN, unknown modality)."""


@dataclass(frozen=True)
class Stream:
    """One sensor's samples.

    Attributes:
        data: (T, C) float32 samples.
        rate_hz: sampling rate in Hz.
        t0_s: time of the first sample relative to the stroke's start, seconds (clock offset).
    """

    data: np.ndarray
    rate_hz: float
    t0_s: float = 0.0

    def __post_init__(self) -> None:
        if self.data.ndim != 2:
            raise StreamError(f"stream data must be (T, C), got shape {self.data.shape}")
        if not (self.rate_hz > 0 and math.isfinite(self.rate_hz)):
            raise StreamError(f"stream rate must be a positive number, got {self.rate_hz}")
        if not np.all(np.isfinite(self.data)):
            raise StreamError("stream data contains NaN or inf")

    @property
    def duration_s(self) -> float:
        return self.data.shape[0] / self.rate_hz

    def times_s(self) -> np.ndarray:
        """Sample times in seconds, stroke clock."""
        return self.t0_s + np.arange(self.data.shape[0]) / self.rate_hz


@dataclass(frozen=True)
class StrokeRecord:
    """One stroke: its streams (``None`` where missing) and its labels.

    Attributes:
        streams: modality key -> :class:`Stream` or ``None`` (missing). All four keys are present.
        category: material category, e.g. ``"metal"``.
        instance: material instance, e.g. ``"aluminium"``.
        combustible: whether the category burns.
        meta: stroke parameters, seed, environment and anything else worth keeping (JSON-serialisable).
    """

    streams: Mapping[str, Stream | None]
    category: str
    instance: str
    combustible: bool
    meta: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        unknown = set(self.streams) - set(MODALITIES)
        if unknown:
            raise StreamError(f"unknown modality keys {sorted(unknown)}; expected {MODALITIES}")
        for key, stream in self.streams.items():
            if stream is not None and stream.data.shape[1] != NUM_CHANNELS[key]:
                raise StreamError(
                    f"{key} stream has {stream.data.shape[1]} channels, expected {NUM_CHANNELS[key]}"
                )

    def stream(self, key: str) -> Stream | None:
        return self.streams.get(key)

    @property
    def present(self) -> tuple[str, ...]:
        """Keys of the modalities that were recorded."""
        return tuple(m for m in MODALITIES if self.streams.get(m) is not None)
