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


def test_successive_differences_read_a_sensors_white_noise():
    """A slowly turning rate (a yaw rate ramping 0.02 rad/s^2) with white noise of 0.002 / 0.004 /
    0.001 rad/s at 100 Hz: half the mean square of the differences is the noise variance (a
    rate that moves by as much as its noise per sample reads high: the cautious side); an
    IMU's stated figure is the floor, raised axis by axis where the samples show more."""
    from vehicle_estimation.estimators.common.noise import SuccessiveDifferenceNoise, with_floor

    rng = np.random.default_rng(4)
    std = np.array([0.002, 0.004, 0.001])
    t = np.arange(3000) / 100.0
    rate = np.column_stack([np.zeros_like(t), 0.1 * t, 0.02 * t]) + rng.normal(0.0, std, (t.size, 3))
    noise = SuccessiveDifferenceNoise(memory_samples=1000.0)
    assert noise.variance is None
    for sample in rate[:10]:
        noise.add(sample)
    assert noise.variance is None                      # too few differences yet
    for sample in rate[10:]:
        noise.add(sample)
    np.testing.assert_allclose(np.sqrt(noise.variance[[0, 2]]), std[[0, 2]], rtol=0.1)
    # y ramps 0.001 rad/s per sample on 0.004 of noise: a little high, never low
    assert 1.0 < np.sqrt(noise.variance[1]) / std[1] < 1.1
    stated = np.diag([0.003 ** 2, 0.003 ** 2, 0.003 ** 2])
    floor = with_floor(stated, noise.variance)
    assert floor[0, 0] == stated[0, 0] and floor[2, 2] == stated[2, 2]
    assert floor[1, 1] == pytest.approx(noise.variance[1])
    np.testing.assert_array_equal(with_floor(None, None), np.zeros((3, 3)))
    noise.reset()
    assert noise.variance is None
