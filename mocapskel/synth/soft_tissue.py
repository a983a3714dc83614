"""Pose-independent skin motion of generated takes: band-limited noise, partly shared by a segment's markers."""
from __future__ import annotations

import numpy as np

from .body import _S

_SOFT_TISSUE_BAND_HZ = (1.0, 5.0)
_SOFT_TISSUE_SHARED = 0.3  # fraction of soft-tissue variance shared by a segment's markers


def _band_noise(rng: np.random.Generator, n: int, channels: int, rate: float, band: tuple[float, float]) -> np.ndarray:
    """(n, channels) Gaussian noise limited to ``band`` Hz, unit variance per channel."""
    f = np.fft.rfftfreq(n, 1.0 / rate)
    keep = np.flatnonzero((f >= band[0]) & (f <= band[1]))
    if keep.size == 0:  # too short a take for the band: use its lowest frequencies
        keep = np.arange(1, min(4, f.size))
    # random Fourier coefficients in the band only (white noise, filtered, without the forward FFT)
    W = np.zeros((f.size, channels), dtype=complex)
    W[keep] = rng.standard_normal((keep.size, channels)) + 1j * rng.standard_normal((keep.size, channels))
    x = np.fft.irfft(W, n=n, axis=0)
    sd = x.std(axis=0)
    return x / np.where(sd > 0, sd, 1.0)


def _soft_tissue(rng: np.random.Generator, n: int, marker_segment: np.ndarray, rate: float, rms: float) -> np.ndarray:
    """(n, M, 3) smooth skin motion, RMS displacement length exactly ``rms`` per marker."""
    M = marker_segment.size
    own = _band_noise(rng, n, M * 3, rate, _SOFT_TISSUE_BAND_HZ).reshape(n, M, 3)
    shared = _band_noise(rng, n, _S * 3, rate, _SOFT_TISSUE_BAND_HZ).reshape(n, _S, 3)
    c = _SOFT_TISSUE_SHARED
    d = np.sqrt(1.0 - c) * own + np.sqrt(c) * shared[:, marker_segment]
    d -= d.mean(axis=0)
    cur = np.sqrt(np.mean(np.einsum("fmi,fmi->fm", d, d), axis=0))
    return d * (rms / np.where(cur > 0, cur, 1.0))[:, None]
