"""uSkin-style 4 x 4 array of three-axis taxels: the N (normal) and F (friction) streams.

Signal chain, per 100 Hz sample:

1. Elastomer spread. Each contact point's normal and shear force is spread over the pad by a Gaussian of
   width ``spread_sigma_m`` (the elastomer layer's Boussinesq-like spreading, approximated by a Gaussian
   of about its thickness) and integrated over each taxel's cell (pitch x pitch square): the erf-product
   below. Force that lands outside the 16 cells is not sensed.
2. Crosstalk between 4-neighbour taxels: each taxel passes ``neighbour_crosstalk`` of its force (per axis) to
   each 4-neighbour and keeps the rest, so the pad's total is conserved (a taxel pressed alone reads a little
   less, its neighbours a little more; the sum over the pad still reads the applied force). Also from the
   normal into the shear axes (small per-taxel coefficients of either sign).
3. Saturation: a soft limit at ``saturation_normal_n`` per taxel (uSkin overload ~3 N) and
   ``saturation_shear_n`` in shear.
4. Counts: per-device offset, per-taxel-axis gain variation, slow drift (linear rate plus random walk;
   heat adds a common drift in the ``fire`` environment), white noise, rounding to 16-bit counts, clipping
   at the ADC range.
5. Bias removal as users do it: the mean of a ``bias_window_s`` window recorded at rest just before the
   stroke is subtracted, and counts are divided by the nominal sensitivity. Output is in newtons; gain
   errors, crosstalk, drift since the bias and noise remain, as on the real sensor.

Taxel order: from the top-left, row by row (index = row * cols + col; row 0 at +y, column 0 at -x).
Shear channels are taxel-major [x1, y1, x2, y2, ...], the force the object exerts on the pad.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import scipy.special

from perception.contact_trace import ContactTrace


@dataclass(frozen=True)
class TaxelArrayConfig:
    """Geometry and electrical model of the taxel array (defaults: a 16 x 16 mm uSkin-like pad).

    Attributes:
        rows, cols: taxel grid.
        pitch_m: taxel pitch, m.
        spread_sigma_m: elastomer spread width, m.
        rate_hz: output rate, Hz.
        counts_per_newton_normal, counts_per_newton_shear: nominal sensitivity, counts/N.
        offset_counts_mean, offset_counts_spread: per-taxel-axis raw offset, counts.
        gain_spread: 1-sigma relative per-taxel-axis gain error.
        neighbour_crosstalk: fraction of a taxel's force seen by each of its 4-neighbours (and not by itself).
        axis_crosstalk_spread: 1-sigma fraction of the normal force leaking into each shear axis.
        saturation_normal_n, saturation_shear_n: soft per-taxel force limits, N.
        saturation_sharpness: exponent of the soft limit x / (1 + |x / S|^p)^(1/p).
        noise_counts: white noise, counts RMS.
        drift_counts_per_s: 1-sigma per-taxel-axis drift rate in a clean lab, counts/s.
        drift_walk_counts_per_sqrt_s: random-walk drift, counts/sqrt(s).
        adc_max_counts: ADC full scale (16 bit).
        bias_window_s: rest window averaged for the bias, s.
        device_seed: seeds the per-device constants (offsets, gains, crosstalk): one physical sensor.
    """

    rows: int = 4
    cols: int = 4
    pitch_m: float = 0.004
    spread_sigma_m: float = 1.5e-3
    rate_hz: float = 100.0
    counts_per_newton_normal: float = 2000.0
    counts_per_newton_shear: float = 1500.0
    offset_counts_mean: float = 32_768.0
    offset_counts_spread: float = 3000.0
    gain_spread: float = 0.06
    neighbour_crosstalk: float = 0.04
    axis_crosstalk_spread: float = 0.02
    saturation_normal_n: float = 3.0
    saturation_shear_n: float = 1.5
    saturation_sharpness: float = 6.0
    noise_counts: float = 4.0
    drift_counts_per_s: float = 5.0
    drift_walk_counts_per_sqrt_s: float = 3.0
    adc_max_counts: float = 65_535.0
    bias_window_s: float = 0.1
    device_seed: int = 20_240_611

    def __post_init__(self) -> None:
        if not 0.0 <= self.neighbour_crosstalk < 0.25:
            raise ValueError(f"neighbour_crosstalk must be in [0, 0.25) (a taxel keeps the rest of its force), "
                             f"got {self.neighbour_crosstalk}")

    @property
    def num_taxels(self) -> int:
        return self.rows * self.cols


def taxel_centres_m(cfg: TaxelArrayConfig) -> np.ndarray:
    """(rows * cols, 2) taxel centres, pad frame, m, in output order (top-left first, row by row)."""
    cols = (np.arange(cfg.cols) - 0.5 * (cfg.cols - 1)) * cfg.pitch_m
    rows = (0.5 * (cfg.rows - 1) - np.arange(cfg.rows)) * cfg.pitch_m
    yy, xx = np.meshgrid(rows, cols, indexing="ij")
    return np.column_stack([xx.ravel(), yy.ravel()])


def _cell_fractions(coord_m: np.ndarray, centres_m: np.ndarray, cfg: TaxelArrayConfig) -> np.ndarray:
    """Fraction of a Gaussian (centred at coord) falling in each cell interval along one axis, (..., K)."""
    scale = 1.0 / (math.sqrt(2.0) * cfg.spread_sigma_m)
    hi = (centres_m + 0.5 * cfg.pitch_m - coord_m[..., None]) * scale
    lo = (centres_m - 0.5 * cfg.pitch_m - coord_m[..., None]) * scale
    return 0.5 * (scipy.special.erf(hi) - scipy.special.erf(lo))


def taxel_forces(trace: ContactTrace, cfg: TaxelArrayConfig = TaxelArrayConfig()) -> np.ndarray:
    """Force on each taxel cell after elastomer spreading, at the physics rate.

    Args:
        trace: contact trace.
        cfg: array geometry.

    Returns:
        (T, rows * cols, 3) forces (shear x, shear y, normal), N.
    """
    col_x = (np.arange(cfg.cols) - 0.5 * (cfg.cols - 1)) * cfg.pitch_m
    row_y = (0.5 * (cfg.rows - 1) - np.arange(cfg.rows)) * cfg.pitch_m
    pos = trace.point_position_on_pad_m
    wx = _cell_fractions(pos[..., 0], col_x, cfg)  # (T, P, cols)
    wy = _cell_fractions(pos[..., 1], row_y, cfg)  # (T, P, rows)
    weights = (wy[..., :, None] * wx[..., None, :]).reshape(pos.shape[0], pos.shape[1], -1)  # (T, P, 16)
    valid = trace.point_valid.astype(float)
    point_forces = np.concatenate([trace.point_shear_force_n, trace.point_normal_force_n[..., None]], axis=-1)
    point_forces = point_forces * valid[..., None]  # (T, P, 3)
    return np.einsum("tpk,tpa->tka", weights, point_forces)


@dataclass(frozen=True)
class _DeviceConstants:
    offsets: np.ndarray  # (16, 3) counts
    gains: np.ndarray  # (16, 3)
    axis_crosstalk: np.ndarray  # (16, 2) normal -> shear fraction
    neighbours: np.ndarray  # (16, 16) crosstalk matrix, reading = M @ force; each column sums to 1


@functools.lru_cache(maxsize=8)
def _device_constants(cfg: TaxelArrayConfig) -> _DeviceConstants:
    rng = np.random.default_rng(cfg.device_seed)
    n = cfg.num_taxels
    offsets = cfg.offset_counts_mean + cfg.offset_counts_spread * rng.standard_normal((n, 3))
    gains = 1.0 + cfg.gain_spread * np.clip(rng.standard_normal((n, 3)), -3, 3)
    axis_crosstalk = cfg.axis_crosstalk_spread * np.clip(rng.standard_normal((n, 2)), -3, 3)
    neighbours = np.zeros((n, n))
    for j in range(n):  # column j: where taxel j's force is read
        r, c = divmod(j, cfg.cols)
        for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1)):
            if 0 <= r + dr < cfg.rows and 0 <= c + dc < cfg.cols:
                neighbours[(r + dr) * cfg.cols + c + dc, j] = cfg.neighbour_crosstalk
        neighbours[j, j] = 1.0 - neighbours[:, j].sum()
    return _DeviceConstants(offsets, gains, axis_crosstalk, neighbours)


def _soft_limit(x: np.ndarray, limit: float, sharpness: float) -> np.ndarray:
    return x / (1.0 + np.abs(x / limit) ** sharpness) ** (1.0 / sharpness)


def uskin_readout(forces_n: np.ndarray, rng: np.random.Generator, cfg: TaxelArrayConfig = TaxelArrayConfig(),
                  drift_scale: float = 1.0, common_drift_counts_per_s: float = 0.0) -> np.ndarray:
    """What the sensor reports, in newtons after bias removal, for forces sampled at ``cfg.rate_hz``.

    Args:
        forces_n: (n, taxels, 3) true cell forces (shear x, shear y, normal), N, at the sensor rate.
        rng: random generator (noise, drift of this stroke).
        cfg: sensor model.
        drift_scale: multiplies the per-taxel drift (heat makes it larger).
        common_drift_counts_per_s: 1-sigma rate of a drift shared by all taxels (heat), counts/s.

    Returns:
        (n, taxels, 3) reported forces, N.
    """
    dev = _device_constants(cfg)
    n_bias = max(int(round(cfg.bias_window_s * cfg.rate_hz)), 1)
    n_out = forces_n.shape[0]
    forces = np.concatenate([np.zeros((n_bias,) + forces_n.shape[1:]), forces_n], axis=0)
    forces = np.einsum("ij,tja->tia", dev.neighbours, forces)
    normal = _soft_limit(forces[..., 2], cfg.saturation_normal_n, cfg.saturation_sharpness)
    shear = _soft_limit(forces[..., :2], cfg.saturation_shear_n, cfg.saturation_sharpness)
    shear = shear + dev.axis_crosstalk[None] * normal[..., None]
    sensitivity = np.array([cfg.counts_per_newton_shear, cfg.counts_per_newton_shear, cfg.counts_per_newton_normal])
    signal = np.concatenate([shear, normal[..., None]], axis=-1) * (dev.gains * sensitivity)[None]

    n_total = forces.shape[0]
    t = np.arange(n_total) / cfg.rate_hz
    rate = drift_scale * cfg.drift_counts_per_s * rng.standard_normal(dev.offsets.shape)
    rate = rate + common_drift_counts_per_s * rng.standard_normal()
    walk_step = drift_scale * cfg.drift_walk_counts_per_sqrt_s / math.sqrt(cfg.rate_hz)
    walk = np.cumsum(walk_step * rng.standard_normal((n_total,) + dev.offsets.shape), axis=0)
    counts = dev.offsets[None] + signal + rate[None] * t[:, None, None] + walk
    counts = counts + cfg.noise_counts * rng.standard_normal(counts.shape)
    counts = np.clip(np.round(counts), 0.0, cfg.adc_max_counts)
    bias = counts[:n_bias].mean(axis=0)
    return ((counts[n_bias:] - bias) / sensitivity)[:n_out]
