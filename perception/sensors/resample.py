"""Uniform-rate signal helpers: linear interpolation onto another grid, anti-aliased rational resampling."""

from __future__ import annotations

from fractions import Fraction

import numpy as np
import scipy.signal


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


def resample_rational(x: np.ndarray, rate_in_hz: float, rate_out_hz: float, max_denominator: int = 1000) -> np.ndarray:
    """Anti-aliased resampling along axis 0 with a polyphase FIR (``scipy.signal.resample_poly``).

    Args:
        x: (T, ...) samples at ``rate_in_hz``.
        rate_in_hz: input rate, Hz.
        rate_out_hz: output rate, Hz (approximated by a ratio with denominator <= ``max_denominator``).

    Returns:
        (T', ...) samples at ``rate_out_hz``, same start time.
    """
    ratio = Fraction(rate_out_hz / rate_in_hz).limit_denominator(max_denominator)
    if ratio == 1:
        return np.array(x, dtype=float)
    return scipy.signal.resample_poly(x, ratio.numerator, ratio.denominator, axis=0, padtype="line")


def sensor_samples(x: np.ndarray, rate_in_hz: float, rate_out_hz: float, t0_s: float, duration_s: float) -> np.ndarray:
    """What a sensor clocked at ``rate_out_hz`` records of a signal, starting ``t0_s`` after its start.

    The signal is shifted by the clock offset on its own (finer) grid, then resampled with anti-aliasing.

    Args:
        x: (T, ...) signal at ``rate_in_hz`` starting at time 0 (shifted by whole samples when the input
            is at least 10 times finer than the output, by linear interpolation otherwise).
        rate_in_hz: input rate, Hz.
        rate_out_hz: sensor rate, Hz.
        t0_s: time of the sensor's first sample, s (>= 0).
        duration_s: length of the signal, s; the sensor records samples at t0 + n / rate_out < duration.

    Returns:
        (n, ...) sensor samples, n = floor((duration - t0) * rate_out).
    """
    n_out = max(int(np.floor((duration_s - t0_s) * rate_out_hz)), 1)
    n_in = x.shape[0]
    if rate_in_hz >= 10.0 * rate_out_hz:
        # Fine input: a whole-sample shift is accurate to 1 / rate_in, far below the output period.
        shifted = x[min(int(round(t0_s * rate_in_hz)), n_in - 1):]
    else:
        shifted = interpolate_uniform(x, rate_in_hz, t0_s + np.arange(n_in) / rate_in_hz)
    out = resample_rational(shifted, rate_in_hz, rate_out_hz)
    if out.shape[0] < n_out:
        pad = np.repeat(out[-1:], n_out - out.shape[0], axis=0)
        out = np.concatenate([out, pad], axis=0)
    return out[:n_out]
