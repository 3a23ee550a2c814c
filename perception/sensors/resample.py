"""Uniform-rate signal helpers: linear interpolation onto another grid, and what a sensor's causal decimation
filter records of a signal (:func:`sensor_samples`)."""

from __future__ import annotations

import numpy as np

DECIMATION_ORDER = 3
"""Cascaded boxcars in the sensors' decimation filter (sinc^3, the usual sigma-delta decimator)."""


def interpolate_uniform(x: np.ndarray, rate_hz: float, t_s: np.ndarray) -> np.ndarray:
    """Linear interpolation of a uniformly sampled signal at arbitrary times (held at the ends).

    Args:
        x: (T, ...) samples, sample k at time k / rate_hz.
        rate_hz: sampling rate of ``x``, Hz.
        t_s: (M,) query times, s, on the same clock.

    Returns:
        (M, ...) interpolated samples.
    """
    t_s = np.asarray(t_s, dtype=float)
    if x.shape[0] == 1:
        return np.repeat(x, t_s.shape[0], axis=0)
    pos = np.clip(t_s * rate_hz, 0.0, x.shape[0] - 1.0)
    i0 = np.minimum(np.floor(pos).astype(np.int64), x.shape[0] - 2)
    frac = (pos - i0).reshape((-1,) + (1,) * (x.ndim - 1))
    return x[i0] * (1.0 - frac) + x[i0 + 1] * frac


def _causal_moving_mean(x: np.ndarray, length: int) -> np.ndarray:
    """Mean of the ``length`` samples ending at each sample (the signal held at ``x[0]`` before it starts).

    A running sum (``np.cumsum``) makes this O(T) whatever ``length``; ``scipy.signal.lfilter`` with a boxcar
    would be O(T * length), 441 multiplies per sample for 44.1 kHz -> 100 Hz.
    """
    if length <= 1:
        return np.array(x, dtype=float)
    padded = np.concatenate([np.repeat(x[:1], length, axis=0), x], axis=0).astype(float)
    total = np.cumsum(padded, axis=0)
    return (total[length:] - total[:-length]) / length


def _filter_rate_hz(rate_in_hz: float, rate_out_hz: float) -> float:
    """Rate the decimation filter runs at: the input's, or 20 x the output's for an input under 10 x finer."""
    return float(rate_in_hz) if rate_in_hz >= 10.0 * rate_out_hz else 20.0 * rate_out_hz


def decimation_delay_s(rate_in_hz: float, rate_out_hz: float, order: int = DECIMATION_ORDER) -> float:
    """Group delay of :func:`sensor_samples`' sinc^order filter, s (about ``order`` / (2 ``rate_out_hz``))."""
    rate = _filter_rate_hz(rate_in_hz, rate_out_hz)
    return 0.5 * order * (max(int(round(rate / rate_out_hz)), 1) - 1) / rate


def sensor_samples(x: np.ndarray, rate_in_hz: float, rate_out_hz: float, t0_s: float, duration_s: float,
                   order: int = DECIMATION_ORDER) -> np.ndarray:
    """What a sensor clocked at ``rate_out_hz`` records of a signal, starting ``t0_s`` after its start.

    The sensor's converter filters causally, then samples: ``order`` cascaded boxcars one output period long
    (a sinc^order / CIC decimator, as in sigma-delta and Hall-sensor front ends). Each output sample is thus a
    weighted mean of the signal over the last ``order`` periods: its step response rises monotonically, with no
    ringing and nothing before the step (a zero-phase resampler such as ``scipy.signal.resample_poly`` rings
    before a press begins), and it lags by :func:`decimation_delay_s`, about ``order`` / (2 ``rate_out_hz``).
    Order 3 passes 82 % of a tone at 0.2 x the output rate and 44 % at 0.4 x (the droop of a sinc^3), and
    rejects a tone at 1.5 x the output rate by about 37 dB.

    Args:
        x: (T, ...) signal at ``rate_in_hz`` starting at time 0. An input less than 10 times finer than the
            output is first interpolated linearly onto a grid 20 times finer than the output.
        rate_in_hz: input rate, Hz.
        rate_out_hz: sensor rate, Hz.
        t0_s: time of the sensor's first sample, s (>= 0).
        duration_s: length of the signal, s; the sensor records samples at t0 + n / rate_out < duration.
        order: number of cascaded boxcars (>= 1).

    Returns:
        (n, ...) sensor samples, n = floor((duration - t0) * rate_out); sample n is the filter's output at
        t0 + n / rate_out. A sample time past the input's last sample gets the filter's output there (the
        input's duration is expected to cover ``duration_s``).
    """
    if order < 1:
        raise ValueError(f"decimation order must be >= 1, got {order}")
    if np.shape(x)[0] == 0:
        raise ValueError("sensor_samples needs at least one input sample")
    n_out = max(int(np.floor((duration_s - t0_s) * rate_out_hz)), 1)
    x = np.asarray(x, dtype=float)
    rate = _filter_rate_hz(rate_in_hz, rate_out_hz)
    if rate != rate_in_hz:
        x = interpolate_uniform(x, rate_in_hz, np.arange(int(np.floor(duration_s * rate)) + 1) / rate)
    length = max(int(round(rate / rate_out_hz)), 1)
    filtered = x
    for _ in range(order):
        filtered = _causal_moving_mean(filtered, length)
    index = np.round((t0_s + np.arange(n_out) / rate_out_hz) * rate).astype(np.int64)
    return filtered[np.clip(index, 0, filtered.shape[0] - 1)]
