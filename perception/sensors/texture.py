"""An object's random surface height field, drawn from its material's roughness spectrum.

The 1-D profile spectrum is self-affine with a roll-off at the correlation length xi:

    S(k) ~ (1 + (k xi)^2) ^ -(H + 1/2),        k = 2 pi / wavelength,

normalised to the material's RMS height. The 2-D field is built by the turning-bands method: the sum of
a few such 1-D profiles laid along directions spread over 180 degrees (divided by sqrt of their number),
which is cheap to evaluate anywhere and approximately isotropic. Each band is periodic (FFT synthesis)
with a period longer than the object, so the pad never sees the repeat within a stroke.

Two versions of the same field are kept: the full-resolution one and one smoothed at the pad's
asperity-contact scale (``probe_radius_m``), which is what modulates the quasi-static contact force.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.fft

from perception.materials import MaterialSample


@dataclass(frozen=True)
class TextureConfig:
    """Surface synthesis settings.

    Attributes:
        spacing_m: profile sample spacing, m (sets the finest wavelength: 2 x spacing).
        probe_radius_m: Gaussian smoothing radius of the pad's asperity contact, m.
        num_bands: turning bands (directions).
        min_period_m, max_period_m: band period limits, m (object diagonal + 20 mm, clipped to these).
    """

    spacing_m: float = 5e-6
    probe_radius_m: float = 50e-6
    num_bands: int = 3
    min_period_m: float = 0.05
    max_period_m: float = 0.25


@dataclass(frozen=True)
class SurfaceTexture:
    """A periodic turning-bands height field.

    Attributes:
        directions: (J, 2) unit vectors of the bands, object frame.
        spacing_m: sample spacing along each band, m.
        heights_m: (J, L) full-resolution band profiles, m (already divided by sqrt(J)).
        smoothed_heights_m: (J, L) the same profiles smoothed at the probe radius, m.
    """

    directions: np.ndarray
    spacing_m: float
    heights_m: np.ndarray
    smoothed_heights_m: np.ndarray

    def sample(self, xy_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Heights at points of the top face.

        Args:
            xy_m: (M, 2) positions, object frame, m.

        Returns:
            (full, smoothed): two (M,) height arrays, m.
        """
        length = self.heights_m.shape[1]
        full = np.zeros(xy_m.shape[0])
        smooth = np.zeros(xy_m.shape[0])
        for band in range(self.directions.shape[0]):
            pos = (xy_m @ self.directions[band]) / self.spacing_m  # (M,) in samples
            base = np.floor(pos)
            frac = pos - base
            i0 = base.astype(np.int64) % length
            i1 = (i0 + 1) % length
            full += self.heights_m[band, i0] * (1.0 - frac) + self.heights_m[band, i1] * frac
            smooth += self.smoothed_heights_m[band, i0] * (1.0 - frac) + self.smoothed_heights_m[band, i1] * frac
        return full, smooth


def profile_spectrum(k_rad_per_m: np.ndarray, correlation_length_m: float, hurst_exponent: float) -> np.ndarray:
    """Unnormalised 1-D power spectrum of a self-affine profile with roll-off (see module docstring)."""
    return (1.0 + (k_rad_per_m * correlation_length_m) ** 2) ** (-(hurst_exponent + 0.5))


def make_surface_texture(material: MaterialSample, size_m: tuple[float, float, float], seed: int,
                         config: TextureConfig = TextureConfig()) -> SurfaceTexture:
    """Draw an object's surface height field.

    Args:
        material: the object's material (roughness RMS, correlation length, Hurst exponent).
        size_m: object size (x, y, z), m; the band period covers the top face's diagonal.
        seed: the object's surface seed (same seed, same surface).
        config: synthesis settings.

    Returns:
        The :class:`SurfaceTexture`.
    """
    rng = np.random.default_rng(seed)
    diagonal = math.hypot(size_m[0], size_m[1])
    period = float(np.clip(diagonal + 0.02, config.min_period_m, config.max_period_m))
    length = scipy.fft.next_fast_len(int(math.ceil(period / config.spacing_m)), real=True)
    k = 2.0 * np.pi * scipy.fft.rfftfreq(length, d=config.spacing_m)
    amplitude = np.sqrt(profile_spectrum(k, material.correlation_length_m, material.hurst_exponent))
    amplitude[0] = 0.0
    smoothing = np.exp(-0.5 * (k * config.probe_radius_m) ** 2)
    n_bands = config.num_bands
    theta0 = rng.uniform(0.0, np.pi / n_bands)
    angles = theta0 + np.pi * np.arange(n_bands) / n_bands
    directions = np.column_stack([np.cos(angles), np.sin(angles)])
    white = rng.standard_normal((n_bands, k.shape[0])) + 1j * rng.standard_normal((n_bands, k.shape[0]))
    full = scipy.fft.irfft(white * amplitude, n=length, axis=1)
    smooth = scipy.fft.irfft(white * (amplitude * smoothing), n=length, axis=1)
    scale = material.roughness_rms_m / (np.std(full, axis=1, keepdims=True) + 1e-300) / math.sqrt(n_bands)
    return SurfaceTexture(directions=directions, spacing_m=config.spacing_m,
                          heights_m=full * scale, smoothed_heights_m=smooth * scale)
