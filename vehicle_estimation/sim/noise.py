"""Sensor noise shared by every drive we make: our simulator's, the independent simulator's and
the vibration added to real logs."""

from __future__ import annotations

import numpy as np

#: Engine, road and wheel vibration seen by a body-mounted accelerometer [Hz].
VIBRATION_BAND_HZ = (10.0, 60.0)


def band_limited_noise(rng: np.random.Generator, n: int, fs: float, std: float,
                       band: tuple[float, float] = VIBRATION_BAND_HZ, axes: int = 3) -> np.ndarray:
    """``(n, axes)`` noise in ``band`` [Hz] at the sample rate ``fs``, scaled to ``std`` per axis.

    White noise through a 4th-order Butterworth band-pass, zero-phase, so the noise is vibration
    only: no drift an accelerometer bias estimate would absorb. A log sampled too slowly for the
    band's top (a 100 Hz IMU cannot carry 60 Hz) gets the band up to 0.9 x its Nyquist frequency.
    """
    from scipy import signal
    low, high = band[0], min(band[1], 0.45 * fs)
    if not 0.0 < low < high:
        raise ValueError(f"band {band} Hz leaves nothing below the Nyquist frequency of {fs:g} Hz")
    sos = signal.butter(4, (low, high), btype="bandpass", fs=fs, output="sos")
    w = signal.sosfiltfilt(sos, rng.standard_normal((n, axes)), axis=0)
    return std * w / np.std(w, axis=0)
