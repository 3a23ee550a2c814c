"""Per-modality front ends: raw sensor streams -> (T_m, C_m) float32 feature sequences, and batching.

Each modality keeps its own frame rate and length; nothing is aligned across modalities (TouchFormer's
cross-attention does that, section 3.2 of the paper).

=========  ===============================================================  ======================
modality   front end                                                        channels C_m (default)
=========  ===============================================================  ======================
sound      Hann STFT -> mel filterbank -> log energy -> DCT (MFCC-like)      24
normal     sliding window over the 16 taxels: per-taxel mean and std         32
friction   sliding window over the 32 shear channels: mean and std           64
accel      Hann STFT, power summed over the 3 axes -> linear bands -> log    16
           (or the pad-normal axis and the in-plane power side by side)      (32)
=========  ===============================================================  ======================

Windows and hops are given in seconds, so a stream recorded at another rate than the nominal one
(:data:`perception.streams.NOMINAL_RATE_HZ`) still yields frames of the same duration.

Typical use::

    feats = [featurize(rec, cfg) for rec in train_records]
    stats = fit_norm_stats(feats)
    batch = collate(feats, feature_dims(cfg), stats=stats, labels=[0, 1, ...])
"""

from __future__ import annotations

import dataclasses
import functools

from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np
import scipy.fft
import scipy.signal
import torch
from numpy.lib.stride_tricks import sliding_window_view

from perception.streams import MODALITIES, NUM_CHANNELS, Stream, StrokeRecord

StrokeFeatures = Mapping[str, "np.ndarray | None"]
"""modality key -> (T_m, C_m) float32 features, or ``None`` where the stream is missing."""

_LOG_FLOOR = 1e-10  # added to band energies before the log (arbitrary units squared)


@dataclass(frozen=True)
class SpectralConfig:
    """Short-time spectral front end (sound, acceleration).

    Attributes:
        window_s: STFT window length, seconds.
        hop_s: hop between frames, seconds.
        n_bands: number of triangular filterbank bands.
        fmin_hz: lower edge of the first band, Hz.
        fmax_hz: upper edge of the last band, Hz (clipped to the Nyquist frequency).
        mel: mel-spaced bands if True, linearly spaced otherwise.
        n_coeffs: DCT coefficients kept from the log band energies (MFCC-like); 0 keeps the log band
            energies themselves.
        channel_groups: which of the stream's channels are summed into one spectrum: each group (channel
            indices) gives its own log band energies, side by side in the order given. Empty (the default):
            the power of all channels is summed into one spectrum. :data:`ACCEL_NORMAL_TANGENTIAL` keeps the
            accelerometer's pad-normal vibration apart from its in-plane one.
    """

    window_s: float
    hop_s: float
    n_bands: int
    fmin_hz: float
    fmax_hz: float
    mel: bool
    n_coeffs: int = 0
    channel_groups: tuple[tuple[int, ...], ...] = ()

    def __post_init__(self) -> None:
        groups = self.channel_groups
        if any(not group or any(not isinstance(c, int) or isinstance(c, bool) or c < 0 for c in group)
               or len(set(group)) != len(group) for group in groups):
            raise ValueError(f"channel_groups must be non-empty groups of distinct channel indices >= 0, got {groups}")

    @property
    def n_channels(self) -> int:
        per_spectrum = self.n_coeffs if self.n_coeffs > 0 else self.n_bands
        return per_spectrum * max(1, len(self.channel_groups))


ACCEL_NORMAL_TANGENTIAL: tuple[tuple[int, ...], ...] = ((2,), (0, 1))
"""Accelerometer ``channel_groups`` (pad frame: x, y in the pad's plane, z along its normal): the normal
vibration's spectrum, then the in-plane power (x + y, which does not depend on the slide's direction). A surface's
heights push the pad along its normal while friction and stick-slip shake it along the slide, so summing the
three axes, as the default does, mixes the two (``robotdemo train --accel-axes normal-tangential``)."""

ACCEL_AXES: dict[str, tuple[tuple[int, ...], ...]] = {"sum": (), "normal-tangential": ACCEL_NORMAL_TANGENTIAL}
"""Named accelerometer channel groupings (``robotdemo train --accel-axes``)."""


@dataclass(frozen=True)
class TaxelConfig:
    """Window statistics of taxel channels (normal, friction).

    Attributes:
        window_s: window length, seconds.
        hop_s: hop between frames, seconds.
    """

    window_s: float = 0.2
    hop_s: float = 0.1


@dataclass(frozen=True)
class FeatureConfig:
    """Front-end settings for the four modalities (saved with every checkpoint).

    Attributes:
        sound, normal, friction, accel: each modality's front end.
        modalities: the sensors a model is trained on and fed (:data:`MODALITIES` order). Any other stream is
            treated as missing, in training and at inference alike, since the checkpoint carries this config: a
            model for a robot without a microphone, or one sensor on its own to see what it carries.
    """

    sound: SpectralConfig = field(default_factory=lambda: SpectralConfig(
        window_s=0.09288, hop_s=0.04644, n_bands=40, fmin_hz=50.0, fmax_hz=16_000.0, mel=True, n_coeffs=24))
    normal: TaxelConfig = field(default_factory=TaxelConfig)
    friction: TaxelConfig = field(default_factory=TaxelConfig)
    accel: SpectralConfig = field(default_factory=lambda: SpectralConfig(
        window_s=0.256, hop_s=0.128, n_bands=16, fmin_hz=2.0, fmax_hz=250.0, mel=False, n_coeffs=0))
    modalities: tuple[str, ...] = MODALITIES

    def __post_init__(self) -> None:
        unknown = sorted(set(self.modalities) - set(MODALITIES))
        if unknown or not self.modalities or len(set(self.modalities)) != len(self.modalities):
            raise ValueError(f"modalities must be distinct names among {MODALITIES}, at least one; "
                             f"got {list(self.modalities)}")
        object.__setattr__(self, "modalities", tuple(m for m in MODALITIES if m in self.modalities))


def with_accel_axes(config: FeatureConfig, accel_axes: str) -> FeatureConfig:
    """``config`` with its accelerometer spectra grouped as :data:`ACCEL_AXES` names (``--accel-axes``).

    Raises:
        ValueError: ``accel_axes`` is not a key of :data:`ACCEL_AXES`.
    """
    if accel_axes not in ACCEL_AXES:
        raise ValueError(f"accel_axes must be one of {sorted(ACCEL_AXES)}, got {accel_axes!r}")
    return dataclasses.replace(config, accel=dataclasses.replace(config.accel, channel_groups=ACCEL_AXES[accel_axes]))


def feature_dims(config: FeatureConfig) -> dict[str, int]:
    """Feature channels C_m per modality, in :data:`MODALITIES` order."""
    return {
        "sound": config.sound.n_channels,
        "normal": 2 * NUM_CHANNELS["normal"],
        "friction": 2 * NUM_CHANNELS["friction"],
        "accel": config.accel.n_channels,
    }


def frame_clock_s(config: FeatureConfig) -> tuple[tuple[float, float], ...]:
    """When each modality's frames lie on the stroke's clock, :data:`MODALITIES` order: (hop between frames,
    centre of the first frame) in seconds, frame i centred at centre + i hop. Nominal: the front end rounds
    window and hop to whole samples of the stream's rate, and a stream's first sample lies at its own ``t0_s``
    (tens of milliseconds at most on our strokes), neither of which is known without the stream."""
    spectral_or_taxel = {"sound": config.sound, "normal": config.normal, "friction": config.friction,
                         "accel": config.accel}
    return tuple((float(spectral_or_taxel[m].hop_s), float(spectral_or_taxel[m].window_s) / 2.0) for m in MODALITIES)


# ----------------------------------------------------------------------------------------------------------
# front ends


def _hz_to_mel(f: np.ndarray) -> np.ndarray:
    return 2595.0 * np.log10(1.0 + f / 700.0)


def _mel_to_hz(m: np.ndarray) -> np.ndarray:
    return 700.0 * (10.0 ** (m / 2595.0) - 1.0)


def filterbank(freqs_hz: np.ndarray, n_bands: int, fmin_hz: float, fmax_hz: float, mel: bool) -> np.ndarray:
    """Triangular filterbank.

    Args:
        freqs_hz: (F,) centre frequencies of the FFT bins, Hz.
        n_bands: number of bands.
        fmin_hz, fmax_hz: band range, Hz.
        mel: mel-spaced edges if True, linear otherwise.

    Returns:
        (n_bands, F) non-negative weights.
    """
    if mel:
        edges = _mel_to_hz(np.linspace(_hz_to_mel(np.asarray(fmin_hz)), _hz_to_mel(np.asarray(fmax_hz)), n_bands + 2))
    else:
        edges = np.linspace(fmin_hz, fmax_hz, n_bands + 2)
    lo, mid, hi = edges[:-2, None], edges[1:-1, None], edges[2:, None]
    rising = (freqs_hz[None, :] - lo) / (mid - lo)
    falling = (hi - freqs_hz[None, :]) / (hi - mid)
    return np.clip(np.minimum(rising, falling), 0.0, None)


@functools.lru_cache(maxsize=32)
def _cached_filterbank(n_win: int, rate_hz: float, n_bands: int, fmin_hz: float, fmax_hz: float, mel: bool) -> np.ndarray:
    """The filterbank for an STFT of ``n_win`` samples at ``rate_hz`` (built once per setting, read-only)."""
    weights = filterbank(np.fft.rfftfreq(n_win, 1.0 / rate_hz), n_bands, fmin_hz, fmax_hz, mel)
    weights.setflags(write=False)
    return weights


@functools.lru_cache(maxsize=32)
def _cached_hann(n_win: int) -> np.ndarray:
    """The periodic Hann window ``scipy.signal.stft`` would build for ``window="hann"`` (built once per length)."""
    window = scipy.signal.get_window("hann", n_win)
    window.flags.writeable = False
    return window


def _frame_params(window_s: float, hop_s: float, rate_hz: float) -> tuple[int, int]:
    n_win = max(2, int(round(window_s * rate_hz)))
    hop = max(1, int(round(hop_s * rate_hz)))
    return n_win, hop


def spectral_features(stream: Stream, config: SpectralConfig) -> np.ndarray:
    """Log filterbank energies (optionally DCT'd) of one stream, power summed over its channels (or over each of
    ``config.channel_groups``, the groups' features side by side).

    Args:
        stream: (T, C) samples at ``stream.rate_hz``.
        config: spectral settings.

    Returns:
        (T_frames, config.n_channels) float32, T_frames >= 1.

    Raises:
        ValueError: a channel group names a channel the stream does not have.
    """
    if config.channel_groups:
        n_channels = stream.data.shape[1]
        needed = max(max(group) for group in config.channel_groups) + 1
        if needed > n_channels:
            raise ValueError(f"the spectral front end's channel_groups {[list(g) for g in config.channel_groups]} "
                             f"need {needed} channels; the stream has {n_channels}")
        whole = dataclasses.replace(config, channel_groups=())
        return np.concatenate([spectral_features(Stream(stream.data[:, list(group)], stream.rate_hz, stream.t0_s), whole)
                               for group in config.channel_groups], axis=1)
    rate = stream.rate_hz
    n_win, hop = _frame_params(config.window_s, config.hop_s, rate)
    x = stream.data.astype(np.float64).T  # (C, T)
    x = x - x.mean(axis=1, keepdims=True)
    if x.shape[1] < n_win:
        x = np.pad(x, ((0, 0), (0, n_win - x.shape[1])))
    freqs, _, zxx = scipy.signal.stft(x, fs=rate, window=_cached_hann(n_win), nperseg=n_win, noverlap=n_win - hop,
                                      boundary=None, padded=False, axis=-1)  # zxx (C, F, N)
    power = (np.abs(zxx) ** 2).sum(axis=0)  # (F, N)
    weights = _cached_filterbank(n_win, rate, config.n_bands, config.fmin_hz, min(config.fmax_hz, rate / 2.0), config.mel)
    log_bands = np.log(weights @ power + _LOG_FLOOR)  # (n_bands, N)
    if config.n_coeffs > 0:
        log_bands = scipy.fft.dct(log_bands, type=2, norm="ortho", axis=0)[: config.n_coeffs]
    return np.ascontiguousarray(log_bands.T, dtype=np.float32)  # (N, C_feat)


def taxel_features(stream: Stream, config: TaxelConfig) -> np.ndarray:
    """Per-channel mean and standard deviation over sliding windows.

    Args:
        stream: (T, C) taxel samples (N) at ``stream.rate_hz``.
        config: window settings.

    Returns:
        (T_frames, 2 C) float32: [means of the C channels, stds of the C channels], T_frames >= 1.
    """
    n_win, hop = _frame_params(config.window_s, config.hop_s, stream.rate_hz)
    x = stream.data.astype(np.float64)  # (T, C)
    n_win = min(n_win, x.shape[0])  # a stream shorter than one window is one frame
    frames = sliding_window_view(x, n_win, axis=0)[::hop]  # (N, C, n_win)
    feats = np.concatenate([frames.mean(axis=-1), frames.std(axis=-1)], axis=1)  # (N, 2C)
    return np.ascontiguousarray(feats, dtype=np.float32)


def featurize(record: StrokeRecord, config: FeatureConfig) -> dict[str, np.ndarray | None]:
    """Feature sequences of one stroke.

    Returns:
        modality -> (T_m, C_m) float32 array, or ``None`` where the stream is missing or not among
        ``config.modalities``.
    """
    out: dict[str, np.ndarray | None] = {}
    for key in MODALITIES:
        stream = record.stream(key)
        if stream is None or stream.data.shape[0] == 0 or key not in config.modalities:
            out[key] = None
        elif key in ("sound", "accel"):
            out[key] = spectral_features(stream, config.sound if key == "sound" else config.accel)
        else:
            out[key] = taxel_features(stream, config.normal if key == "normal" else config.friction)
    return out


def keep_modalities(features: StrokeFeatures, modalities: Sequence[str]) -> dict[str, np.ndarray | None]:
    """``features`` with every modality outside ``modalities`` marked missing (``None``)."""
    return {key: features.get(key) if key in modalities else None for key in MODALITIES}


# ----------------------------------------------------------------------------------------------------------
# normalisation


@dataclass(frozen=True)
class NormStats:
    """Per-channel feature mean and standard deviation, fitted on training strokes only.

    Attributes:
        mean: modality -> C_m floats.
        std: modality -> C_m floats, all > 0.
    """

    mean: Mapping[str, tuple[float, ...]]
    std: Mapping[str, tuple[float, ...]]

    def to_dict(self) -> dict[str, dict[str, list[float]]]:
        return {"mean": {k: list(v) for k, v in self.mean.items()}, "std": {k: list(v) for k, v in self.std.items()}}

    @classmethod
    def from_dict(cls, data: Mapping[str, Mapping[str, Sequence[float]]]) -> NormStats:
        return cls(mean={k: tuple(float(x) for x in v) for k, v in data["mean"].items()},
                   std={k: tuple(float(x) for x in v) for k, v in data["std"].items()})


def fit_norm_stats(features: Sequence[StrokeFeatures], dims: Mapping[str, int]) -> NormStats:
    """Fit per-channel statistics over every frame of every stroke where the modality is present.

    Args:
        features: training strokes' features (see :func:`featurize`).
        dims: feature channels per modality (see :func:`feature_dims`); a modality absent from every
            training stroke gets mean 0, std 1.

    Returns:
        The fitted :class:`NormStats` (std floored at 1e-6).
    """
    mean: dict[str, tuple[float, ...]] = {}
    std: dict[str, tuple[float, ...]] = {}
    for key in MODALITIES:
        seqs = [f[key] for f in features if f.get(key) is not None]
        if not seqs:
            mean[key], std[key] = (0.0,) * dims[key], (1.0,) * dims[key]
            continue
        frames = np.concatenate(seqs, axis=0).astype(np.float64)  # (sum T, C)
        mean[key] = tuple(float(v) for v in frames.mean(axis=0))
        std[key] = tuple(float(v) for v in np.maximum(frames.std(axis=0), 1e-6))
    return NormStats(mean=mean, std=std)


def normalize(features: StrokeFeatures, stats: NormStats) -> dict[str, np.ndarray | None]:
    """(x - mean) / std per channel; missing modalities stay ``None``."""
    out: dict[str, np.ndarray | None] = {}
    for key in MODALITIES:
        x = features.get(key)
        if x is None:
            out[key] = None
            continue
        mu = np.asarray(stats.mean[key], dtype=np.float32)
        sd = np.asarray(stats.std[key], dtype=np.float32)
        out[key] = ((x - mu) / sd).astype(np.float32)
    return out


# ----------------------------------------------------------------------------------------------------------
# batching


@dataclass(frozen=True)
class FeatureBatch:
    """A padded batch; every modality keeps its own length.

    Attributes:
        x: modality -> (B, T_max_m, C_m) float32, zeros at padded steps and for missing modalities.
        padding: modality -> (B, T_max_m) bool, True at padded steps (all True where missing).
        present: modality -> (B,) bool, False where the stream is missing.
        labels: (B,) int64 class indices, or ``None``.
    """

    x: Mapping[str, torch.Tensor]
    padding: Mapping[str, torch.Tensor]
    present: Mapping[str, torch.Tensor]
    labels: torch.Tensor | None = None

    @property
    def batch_size(self) -> int:
        return int(self.present[MODALITIES[0]].shape[0])

    def present_matrix(self) -> torch.Tensor:
        """(B, 4) bool presence, columns in :data:`MODALITIES` order."""
        return torch.stack([self.present[m] for m in MODALITIES], dim=1)

    def to(self, device: torch.device | str) -> FeatureBatch:
        return FeatureBatch(
            x={k: v.to(device) for k, v in self.x.items()},
            padding={k: v.to(device) for k, v in self.padding.items()},
            present={k: v.to(device) for k, v in self.present.items()},
            labels=None if self.labels is None else self.labels.to(device),
        )


def collate(features: Sequence[StrokeFeatures], dims: Mapping[str, int], stats: NormStats | None = None,
            labels: Sequence[int] | None = None) -> FeatureBatch:
    """Pad feature sequences into a batch (padding at the end of each sequence, value 0).

    Args:
        features: per-stroke features (see :func:`featurize`).
        dims: feature channels per modality (see :func:`feature_dims`).
        stats: if given, features are normalised with it before padding (so padding stays exactly 0).
        labels: optional class index per stroke.

    Returns:
        A :class:`FeatureBatch`. A modality missing from the whole batch gets T_max = 1, all padded.
    """
    if len(features) == 0:
        raise ValueError("collate needs at least one stroke")
    if stats is not None:
        features = [normalize(f, stats) for f in features]
    b = len(features)
    x, padding, present = {}, {}, {}
    for key in MODALITIES:
        seqs = [f.get(key) for f in features]
        for s in seqs:
            if s is not None and (s.ndim != 2 or s.shape[1] != dims[key]):
                raise ValueError(f"{key} features have shape {s.shape}, expected (T, {dims[key]})")
        t_max = max([1] + [s.shape[0] for s in seqs if s is not None])
        xm = np.zeros((b, t_max, dims[key]), dtype=np.float32)
        pad = np.ones((b, t_max), dtype=bool)
        for i, s in enumerate(seqs):
            if s is not None:
                xm[i, : s.shape[0]] = s
                pad[i, : s.shape[0]] = False
        x[key] = torch.from_numpy(xm)  # (B, T_max, C)
        padding[key] = torch.from_numpy(pad)  # (B, T_max)
        present[key] = torch.tensor([s is not None for s in seqs], dtype=torch.bool)  # (B,)
    y = None if labels is None else torch.as_tensor(list(labels), dtype=torch.long)
    return FeatureBatch(x=x, padding=padding, present=present, labels=y)
