"""Band-limited vibration noise (sim/noise.py), as added to simulated and real drives."""

import numpy as np
import pytest

from vehicle_estimation.sim.noise import band_limited_noise


@pytest.mark.parametrize("fs, top", [(200.0, 60.0), (100.0, 45.0)])
def test_vibration_has_its_std_and_stays_in_its_band(fs, top):
    noise = band_limited_noise(np.random.default_rng(1), 20000, fs, 4.0)
    assert noise.shape == (20000, 3)
    np.testing.assert_allclose(noise.std(axis=0), 4.0, rtol=1e-12)
    power = np.abs(np.fft.rfft(noise[:, 1])) ** 2
    freq = np.fft.rfftfreq(noise.shape[0], 1.0 / fs)
    in_band = (freq >= 10.0) & (freq <= top)
    assert power[in_band].sum() > 0.95 * power.sum()
    assert power[freq < 5.0].sum() < 1e-3 * power.sum()      # no drift a bias estimate would absorb


def test_a_band_above_nyquist_is_refused():
    with pytest.raises(ValueError, match="Nyquist"):
        band_limited_noise(np.random.default_rng(1), 100, 15.0, 1.0)
