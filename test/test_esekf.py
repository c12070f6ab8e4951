"""Tests for vehicle_estimation.estimators.fusion (paper 003 ES-EKF), on a synthetic drive.

The generator below is self-contained: a car rests for 10 s, accelerates, turns,
climbs and descends a 4 % grade, loses GNSS for 30 s (including a U-turn) and
stops.  IMU 200 Hz (white noise + constant biases), GNSS 10 Hz (sigma 1.5 m
horizontal, 3 m vertical), CAN speed 100 Hz quantised to 1 km/h.
"""
import dataclasses
import math
import time

import numpy as np
import pytest

from vehicle_estimation.estimators.fusion.config import FusionConfig
from vehicle_estimation.estimators.fusion.esekf import FusionEKF
from vehicle_estimation.estimators.common.rotations import euler_from_rotmat, quat_from_euler, quat_to_rotmat

G = 9.80665
IMU_HZ = 200.0
T_END = 160.0
OUTAGE = (95.0, 125.0)
ACC_BIAS = np.array([0.04, -0.03, 0.05])      # [m/s^2]
GYR_BIAS = np.array([0.003, -0.002, 0.004])   # [rad/s] (0.11-0.23 deg/s, typical MEMS)
ACC_NOISE = 0.03                              # [m/s^2] per sample
GYR_NOISE = 2e-3                              # [rad/s] per sample
GNSS_SIGMA = np.array([1.5, 1.5, 3.0])
YAW0 = math.radians(30.0)                     # initial heading (ENU, from east)
GRADE = math.atan(0.04)


def _sstep(t, t0, dur):
    """Smooth step 0 -> 1 over [t0, t0 + dur] and its time derivative."""
    x = np.clip((t - t0) / dur, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x), 6.0 * x * (1.0 - x) / dur


def _profiles(t):
    """Speed v, dv/dt, yaw rate, grade theta (nose-up), dtheta/dt as functions of time."""
    v = np.zeros_like(t)
    vd = np.zeros_like(t)
    for t0, dur, dv in ((10.0, 10.0, 15.0), (70.0, 5.0, 5.0), (135.0, 12.0, -20.0)):
        s, sd = _sstep(t, t0, dur)
        v += dv * s
        vd += dv * sd
    r = np.zeros_like(t)
    for t0, dur, ang in ((30.0, 8.0, 90.0), (55.0, 7.0, -90.0), (100.0, 15.0, 180.0), (126.0, 6.0, -45.0)):
        r += math.radians(ang) * _sstep(t, t0, dur)[1]
    th = np.zeros_like(t)
    thd = np.zeros_like(t)
    for t0, dur, d in ((40.0, 5.0, GRADE), (60.0, 5.0, -2 * GRADE), (82.0, 5.0, GRADE),
                       (105.0, 5.0, GRADE), (118.0, 5.0, -GRADE)):
        s, sd = _sstep(t, t0, dur)
        th += d * s
        thd += d * sd
    return v, vd, r, th, thd


def simulate(seed=0, mounting_rpy=(0.0, 0.0, 0.0), mounting=None):
    """Return a dict of time series (true state + noisy sensor streams).

    ``mounting_rpy``: roll, pitch, yaw of imu_link in base_link [rad]; the IMU reads
    C^T f with C the imu_link -> base_link rotation (``mounting``, when given).
    """
    rng = np.random.default_rng(seed)
    # Truth on a 1 kHz grid, positions by trapezoidal integration.
    tf = np.arange(0.0, T_END + 1e-9, 1e-3)
    v, vd, r, th, thd = _profiles(tf)
    psi = YAW0 + np.concatenate([[0.0], np.cumsum(0.5 * (r[1:] + r[:-1]) * 1e-3)])
    b = np.stack([np.cos(psi) * np.cos(th), np.sin(psi) * np.cos(th), np.sin(th)], axis=1)
    vn = v[:, None] * b
    pos = np.concatenate([np.zeros((1, 3)), np.cumsum(0.5 * (vn[1:] + vn[:-1]) * 1e-3, axis=0)])
    # IMU samples at 200 Hz (every 5th fine sample), analytic kinematics:
    # R = Rz(psi) Ry(beta), beta = -theta (REP-103 pitch, nose up => negative);
    # w_b = [-sin(beta) psi_dot, beta_dot, cos(beta) psi_dot];
    # f_b = [v_dot, v w_z, -v w_y] + R^T [0, 0, g].
    k = np.arange(0, len(tf), 5)
    t = tf[k]
    beta = -th[k]
    wb = np.stack([-np.sin(beta) * r[k], -thd[k], np.cos(beta) * r[k]], axis=1)
    gb = G * np.stack([-np.sin(beta), np.zeros_like(beta), np.cos(beta)], axis=1)  # R^T e_z g
    fb = np.stack([vd[k], v[k] * wb[:, 2], -v[k] * wb[:, 1]], axis=1) + gb
    C = quat_to_rotmat(quat_from_euler(*mounting_rpy)) if mounting is None else mounting
    imu_f = fb @ C + ACC_BIAS + rng.normal(0, ACC_NOISE, fb.shape)
    imu_w = wb @ C + GYR_BIAS + rng.normal(0, GYR_NOISE, wb.shape)
    # GNSS 10 Hz (stamps offset 1 ms from the IMU grid), CAN speed 100 Hz (offset 2.5 ms)
    kg = np.arange(1, len(tf), 100)
    kg = kg[(tf[kg] < OUTAGE[0]) | (tf[kg] > OUTAGE[1])]
    gnss_t = tf[kg]
    gnss = pos[kg] + rng.normal(0, 1, (len(kg), 3)) * GNSS_SIGMA
    ks = np.arange(0, len(tf) - 3, 10) + 2
    speed_t = tf[ks] + 0.0005
    speed = np.round(v[ks] * 3.6) / 3.6
    return dict(t=t, imu_f=imu_f, imu_w=imu_w, v=v[k], grade=th[k], yaw=psi[k], pos=pos[k],
                vn=vn[k], gnss_t=gnss_t, gnss=gnss, speed_t=speed_t, speed=speed)


def run_filter(sim, ekf=None):
    ekf = ekf or FusionEKF()
    n = len(sim["t"])
    out = {key: np.full(n, np.nan) for key in ("vx", "grade", "yaw", "grade_var")}
    out["pos"] = np.full((n, 3), np.nan)
    out["running"] = np.zeros(n, bool)
    ig = js = 0
    gt, st = sim["gnss_t"], sim["speed_t"]
    imu_time = 0.0
    for i in range(n):
        t = sim["t"][i]
        t0 = time.perf_counter()
        assert ekf.process_imu(t, sim["imu_f"][i], sim["imu_w"][i])
        imu_time += time.perf_counter() - t0
        while js < len(st) and st[js] <= t:
            ekf.update_speed(st[js], sim["speed"][js])
            js += 1
        while ig < len(gt) and gt[ig] <= t:
            ekf.update_gnss(gt[ig], sim["gnss"][ig], np.diag(GNSS_SIGMA ** 2))
            ig += 1
        if ekf.initialized:
            out["running"][i] = True
            out["vx"][i] = ekf.velocity_body[0]
            out["grade"][i] = ekf.road_grade
            out["yaw"][i] = ekf.yaw
            out["pos"][i] = ekf.position_enu
            out["grade_var"][i] = ekf.road_grade_variance
    out["us_per_imu"] = 1e6 * imu_time / n
    return ekf, out


@pytest.fixture(scope="module")
def drive():
    sim = simulate(seed=0)
    ekf, out = run_filter(sim)
    return sim, ekf, out


def _rms(x):
    return float(np.sqrt(np.mean(np.square(x))))


def test_initialises_during_the_drive(drive):
    sim, ekf, out = drive
    assert ekf.initialized and ekf.status == "running"
    t_init = sim["t"][np.argmax(out["running"])]
    # 10 s standstill, then ~15 m of travel (about 4.5 s at the given acceleration)
    assert 10.0 < t_init < 17.0, t_init
    assert ekf.events["heading_initialised"] == 1


def test_speed_and_grade_accuracy(drive):
    sim, ekf, out = drive
    m = out["running"] & (sim["t"] > 20.0)
    speed_rmse = _rms(out["vx"][m] - sim["v"][m])
    grade_rmse = _rms(out["grade"][m] - sim["grade"][m])
    yaw_err = np.angle(np.exp(1j * (out["yaw"][m] - sim["yaw"][m])))
    print(f"speed RMSE {speed_rmse:.4f} m/s, grade RMSE {math.degrees(grade_rmse):.3f} deg, "
          f"yaw RMSE {math.degrees(_rms(yaw_err)):.3f} deg, {out['us_per_imu']:.1f} us/IMU step")
    assert speed_rmse < 0.1
    assert math.degrees(grade_rmse) < 0.5
    # The reported grade standard deviation is the right order of magnitude.
    assert math.sqrt(np.mean(out["grade_var"][m])) < math.radians(1.0)


MOUNTING = tuple(math.radians(a) for a in (0.4, -0.6, 0.5))


@pytest.mark.parametrize("estimate", [True, False])
def test_imu_mounting_estimated(estimate):
    """A 0.6 deg mounting pitch is 0.6 deg of grade error unless the mounting states
    take it out; the grade is then as good as with a perfectly mounted IMU."""
    sim = simulate(seed=1, mounting_rpy=MOUNTING)
    ekf, out = run_filter(sim, FusionEKF(FusionConfig(nh_sigma_z=0.1, estimate_mounting=estimate)))
    m = out["running"] & (sim["t"] > 60.0)
    grade_rmse = math.degrees(_rms(out["grade"][m] - sim["grade"][m]))
    mount_pitch_err = math.degrees(ekf.mounting_rpy[1] - MOUNTING[1])
    print(f"estimate_mounting={estimate}: grade RMSE {grade_rmse:.3f} deg, "
          f"mounting pitch error {mount_pitch_err:.3f} deg")
    if estimate:
        assert grade_rmse < 0.2
        assert abs(mount_pitch_err) < 0.15
        assert ekf.mounting_covariance[0, 0] < math.radians(0.3) ** 2
    else:
        assert grade_rmse > 0.4     # what the states are for


@pytest.mark.parametrize("nominal_deg", [(0.0, 0.0, 90.0), (90.0, 0.0, 0.0), (180.0, 0.0, -90.0)],
                         ids=["turned-left", "on-its-side", "upside-down-turned"])
def test_imu_mounting_refined_in_base_link_axes(nominal_deg):
    """An IMU turned or laid on its side: the nominal mounting is given, and what the states
    refine is still the vehicle's pitch and yaw of it (base_link y and z), not whichever
    vehicle axes the IMU's own y and z happen to point along. A 0.6 deg pitch error about
    base_link y, on a turned IMU, would otherwise fall on the unobservable roll."""
    nominal = quat_to_rotmat(quat_from_euler(*np.radians(nominal_deg)))
    error = quat_to_rotmat(quat_from_euler(0.0, math.radians(-0.6), math.radians(0.5)))
    sim = simulate(seed=1, mounting=error @ nominal)
    config = FusionConfig(nh_sigma_z=0.1, estimate_mounting=True, mounting_rpy=tuple(np.radians(nominal_deg)))
    ekf, out = run_filter(sim, FusionEKF(config))
    m = out["running"] & (sim["t"] > 60.0)
    grade_rmse = math.degrees(_rms(out["grade"][m] - sim["grade"][m]))
    residual = np.degrees(euler_from_rotmat(ekf.mounting_rotation @ (error @ nominal).T))
    print(f"{nominal_deg}: grade RMSE {grade_rmse:.3f} deg, mounting residual {np.round(residual, 3)} deg")
    assert grade_rmse < 0.2
    assert abs(residual[1]) < 0.15 and abs(residual[2]) < 0.3
    assert ekf.mounting_covariance[0, 0] < math.radians(0.3) ** 2


@pytest.mark.parametrize("nominal_deg", [(0.0, 0.0, 0.0), (90.0, 0.0, 90.0)], ids=["level", "turned"])
def test_in_motion_alignment_when_started_while_driving(nominal_deg):
    """A filter started at 25 s (15 m/s, no standstill ahead of it) levels itself on the
    specific force minus the CAN-speed kinematics (the car's, turned into the IMU's axes), takes
    the heading from GNSS, and then tracks speed and grade."""
    mounting_rpy = tuple(np.radians(nominal_deg))
    sim = simulate(seed=2, mounting_rpy=mounting_rpy)
    start = sim["t"] >= 25.0
    cut = dict(sim)
    for key in ("t", "imu_f", "imu_w", "v", "grade", "yaw", "pos", "vn"):
        cut[key] = sim[key][start]
    keep_g, keep_s = sim["gnss_t"] >= 25.0, sim["speed_t"] >= 25.0
    cut["gnss_t"], cut["gnss"] = sim["gnss_t"][keep_g], sim["gnss"][keep_g]
    cut["speed_t"], cut["speed"] = sim["speed_t"][keep_s], sim["speed"][keep_s]
    ekf, out = run_filter(cut, FusionEKF(FusionConfig(mounting_rpy=mounting_rpy)))
    assert ekf.events["aligned_in_motion"] == 1 and ekf.initialized
    t_init = cut["t"][np.argmax(out["running"])]
    assert t_init < 25.0 + 5.0 + 3.0, t_init
    # aligned, and before any GNSS heading: already moving forward, along base_link x
    aligned = FusionEKF(FusionConfig(mounting_rpy=mounting_rpy))
    js = 0
    for t, f, w, v in zip(cut["t"], cut["imu_f"], cut["imu_w"], cut["v"]):
        aligned.process_imu(t, f, w)
        while js < len(cut["speed_t"]) and cut["speed_t"][js] <= t:
            aligned.update_speed(cut["speed_t"][js], cut["speed"][js])
            js += 1
        if aligned.events["aligned_in_motion"]:
            np.testing.assert_allclose(aligned.velocity_body, [v, 0.0, 0.0], atol=0.3)
            assert aligned.yaw == pytest.approx(0.0, abs=1e-9)     # odom = the car's start pose
            break
    m = out["running"] & (cut["t"] > 60.0)
    assert _rms(out["vx"][m] - cut["v"][m]) < 0.1
    assert math.degrees(_rms(out["grade"][m] - cut["grade"][m])) < 0.5
    # without it the filter waits for a standstill that only comes at the end of the drive
    ekf_off, out_off = run_filter(cut, FusionEKF(FusionConfig(in_motion_alignment=False, mounting_rpy=mounting_rpy)))
    assert not out_off["running"][cut["t"] < 130.0].any()


@pytest.mark.parametrize("nominal_deg", [(0.0, 0.0, 0.0), (90.0, 0.0, 0.0)], ids=["level", "on-its-side"])
def test_without_gnss_the_yaw_rate_bias_is_held(nominal_deg):
    """Without GNSS nothing observes the heading, so the gyro bias about base_link z is a
    consider state: it keeps what the standstill alignment gave it, while the constraints still
    move the other two. On an IMU on its side that is the IMU's own y axis, not its z."""
    mounting_rpy = tuple(np.radians(nominal_deg))
    sim = simulate(seed=3, mounting_rpy=mounting_rpy)
    ekf = FusionEKF(FusionConfig(mounting_rpy=mounting_rpy))
    C = quat_to_rotmat(quat_from_euler(*mounting_rpy))
    js, aligned = 0, None
    for t, f, w in zip(sim["t"], sim["imu_f"], sim["imu_w"]):
        ekf.process_imu(t, f, w)
        while js < len(sim["speed_t"]) and sim["speed_t"][js] <= t:
            ekf.update_speed(sim["speed_t"][js], sim["speed"][js])
            js += 1
        if aligned is None and ekf.status != "waiting_for_standstill" and ekf.status != "aligning":
            aligned = C @ ekf.gyro_bias                       # about base_link's axes
    assert not ekf.gnss_aided and aligned is not None
    final = C @ ekf.gyro_bias
    assert final[2] == pytest.approx(aligned[2], abs=1e-12)
    assert abs(final[0] - aligned[0]) > 1e-6 and abs(final[1] - aligned[1]) > 1e-6


def test_gyro_bias_recovered(drive):
    """Tolerance 5e-4 rad/s (0.03 deg/s) per axis: the 200-sample standstill average alone
    has sigma = 2e-3 / sqrt(200) = 1.4e-4 rad/s, so this is ~3.5 sigma of the initial error,
    while the bias itself is 2e-3..4e-3 rad/s (i.e. a >= 4x reduction)."""
    sim, ekf, out = drive
    err = ekf.gyro_bias - GYR_BIAS
    print("gyro bias error [rad/s]", err, "accel bias error", ekf.accel_bias - ACC_BIAS)
    assert np.all(np.abs(err) < 5e-4), err


def test_position_bounded_through_gnss_outage(drive):
    sim, ekf, out = drive
    err = np.linalg.norm(out["pos"][:, :2] - sim["pos"][:, :2], axis=1)
    m_out = (sim["t"] >= OUTAGE[0]) & (sim["t"] <= OUTAGE[1])
    m_before = out["running"] & (sim["t"] > 30.0) & (sim["t"] < OUTAGE[0])
    m_after = sim["t"] > OUTAGE[1] + 10.0
    print(f"horizontal error: before {err[m_before].mean():.2f} m, max in 30 s outage "
          f"{err[m_out].max():.2f} m (~{sim['v'][m_out].mean() * 30:.0f} m driven), "
          f"after {err[m_after].mean():.2f} m")
    assert err[m_before].mean() < 1.5
    assert err[m_out].max() < 15.0          # 30 s dead reckoning on IMU + CAN speed + NH, ~1.5 % of distance
    assert err[m_after].mean() < 1.5        # GNSS accepted again (gate did not lock out)
    assert ekf.rejected["gnss_gate"] < 5


def test_covariance_symmetric_psd_after_drive(drive):
    _, ekf, _ = drive
    P = ekf.covariance
    assert P.shape == (18, 18)
    np.testing.assert_array_equal(P, P.T)
    assert np.linalg.eigvalsh(P).min() > -1e-12
    for block in (ekf.position_covariance, ekf.velocity_covariance, ekf.attitude_covariance,
                  ekf.velocity_body_covariance):
        assert block.shape == (3, 3)
        assert np.linalg.eigvalsh(0.5 * (block + block.T)).min() >= -1e-12
    assert ekf.pitch_variance == ekf.road_grade_variance > 0


def test_paper_sensor_rates_gnss_1hz_can_4hz():
    """The paper's rates (Sec. 7.1): GNSS 1 Hz, CAN 4 Hz.  Low-rate, quantised CAN keeps
    reading 0 km/h for up to 0.25 s after the car starts rolling; the IMU cross-check on
    the stationary update must stop that from corrupting the accelerometer bias/tilt."""
    sim = simulate(seed=5)
    sel = np.isclose((sim["gnss_t"] - 0.001) % 1.0, 0.0, atol=1e-6)
    sim["gnss_t"], sim["gnss"] = sim["gnss_t"][sel], sim["gnss"][sel]
    sel = np.arange(len(sim["speed_t"])) % 25 == 0
    sim["speed_t"], sim["speed"] = sim["speed_t"][sel], sim["speed"][sel]
    ekf, out = run_filter(sim)
    assert ekf.initialized
    m = out["running"] & (sim["t"] > 20.0)
    speed_rmse = _rms(out["vx"][m] - sim["v"][m])
    grade_rmse = math.degrees(_rms(out["grade"][m] - sim["grade"][m]))
    print(f"1 Hz GNSS / 4 Hz CAN: speed RMSE {speed_rmse:.3f} m/s, grade RMSE {grade_rmse:.3f} deg")
    assert speed_rmse < 0.1 and grade_rmse < 0.5
    assert ekf.rejected["speed_gate"] == 0


def test_without_can_speed_imu_alignment_fallback():
    """No speed topic and no hint: alignment falls back on the IMU variance test and
    the heading still initialises from GNSS; the run stays sane (looser bounds)."""
    sim = simulate(seed=4)
    n = int(60.0 * IMU_HZ)
    sim = {k: (v[:n] if len(v) == len(sim["t"]) else v) for k, v in sim.items()}
    sel = sim["gnss_t"] < 60.0
    sim["gnss_t"], sim["gnss"] = sim["gnss_t"][sel], sim["gnss"][sel]
    sim["speed_t"], sim["speed"] = sim["speed_t"][:0], sim["speed"][:0]
    ekf, out = run_filter(sim)
    assert ekf.initialized
    m = out["running"] & (sim["t"] > 30.0)
    assert _rms(out["vx"][m] - sim["v"][m]) < 0.3
    assert math.degrees(_rms(out["grade"][m] - sim["grade"][m])) < 0.5


# --------------------------------------------------------------------------- unit tests

def _static_imu(grade=0.0, roll=0.0, yaw=0.0):
    R = quat_to_rotmat(quat_from_euler(roll, -grade, yaw))
    return R.T @ np.array([0.0, 0.0, G]), np.zeros(3)


def _aligned_filter(grade=0.0, **cfg):
    ekf = FusionEKF(FusionConfig(**cfg))
    f, w = _static_imu(grade)
    t = 0.0
    for i in range(250):
        t = i * 0.005
        ekf.update_speed(t, 0.0)
        ekf.process_imu(t, f, w + 0.001)
    return ekf, t


def test_alignment_on_a_slope_sign_conventions():
    ekf, _ = _aligned_filter(grade=GRADE)
    assert ekf.status == "waiting_for_heading" and not ekf.initialized
    assert ekf.road_grade == pytest.approx(GRADE, abs=1e-9)     # uphill positive
    assert ekf.pitch == pytest.approx(-GRADE, abs=1e-9)         # REP-103: nose up = negative pitch
    assert ekf.roll == pytest.approx(0.0, abs=1e-9)
    np.testing.assert_allclose(ekf.gyro_bias, 0.001, atol=1e-12)
    np.testing.assert_allclose(ekf.accel_bias, 0.0, atol=1e-12)
    q = ekf.quaternion
    assert q.shape == (4,) and q[3] > 0 and abs(np.linalg.norm(q) - 1) < 1e-12
    f, w = ekf.compensated_imu(*_static_imu(GRADE))
    np.testing.assert_allclose(w, -0.001)


def test_a_correlated_speed_error_weighs_2_tau_over_the_spacing():
    """speed_error_correlation_s: a CAN speed sample 10 ms after the last one counts as
    2 tau / 10 ms = 200 times its variance; after a gap longer than 2 tau, as itself."""
    variance = (1.0 / 3.6) ** 2 / 12.0                      # 1 km/h quantisation
    correlated, _ = _aligned_filter()                       # the same filter until now
    correlated.config = dataclasses.replace(correlated.config, speed_error_correlation_s=1.0)
    white, t = _aligned_filter()
    assert correlated.update_speed(t + 0.01, 0.3, variance)
    assert white.update_speed(t + 0.01, 0.3, 200.0 * variance)
    np.testing.assert_allclose(correlated.covariance, white.covariance, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(correlated.velocity_body, white.velocity_body, rtol=1e-12, atol=1e-15)
    assert correlated.update_speed(t + 5.0, 0.0, variance)   # 5 s later: white again
    assert white.update_speed(t + 5.0, 0.0, variance)
    np.testing.assert_allclose(correlated.covariance, white.covariance, rtol=1e-12, atol=1e-15)


def test_without_gnss_the_forward_velocity_is_not_published_below_the_can_speeds_own_error():
    """A 1 km/h quantisation offset lasts while the speed stays in one step: without GNSS no
    averaging of the CAN speed removes it, so the published forward variance keeps the speed's
    stated variance as its floor; with a fix in the last seconds the filter's own holds."""
    variance = (1.0 / 3.6) ** 2 / 12.0
    ekf, t = _aligned_filter(speed_error_correlation_s=1.0)
    f, w = _static_imu()
    for i in range(1, 2001):                                  # 10 s of IMU at 200 Hz, speed at 100 Hz
        ekf.process_imu(t + i * 0.005, f, w + 0.001)
        if i % 2 == 0:
            ekf.update_speed(t + i * 0.005, 0.0, variance)
    _, H = ekf._body_speed_rows([0, 1, 2])
    own = float((H @ ekf.covariance @ H.T)[0, 0])
    assert own < 0.5 * variance                               # the filter alone: too sure
    assert not ekf.gnss_aided and ekf.velocity_body_covariance[0, 0] == pytest.approx(variance)
    t += 10.0
    ekf.update_gnss(t, np.zeros(3))
    assert ekf.gnss_aided and ekf.velocity_body_covariance[0, 0] < 0.5 * variance


def test_alignment_needs_standstill_and_hint_works():
    ekf = FusionEKF()
    f, w = _static_imu()
    for i in range(300):                      # moving according to CAN speed
        ekf.update_speed(i * 0.005, 5.0)
        ekf.process_imu(i * 0.005, f, w)
    assert ekf.status == "waiting_for_standstill"
    ekf.set_stationary_hint(True)
    for i in range(300, 510):
        ekf.process_imu(i * 0.005, f, w)
    assert ekf.status == "waiting_for_heading"


def test_rejects_nonfinite_and_out_of_order():
    ekf, t = _aligned_filter()
    P0, p0, q0 = ekf.covariance, ekf.position_enu, ekf.quaternion
    f, w = _static_imu()
    assert not ekf.process_imu(t + 0.005, [np.nan, 0, 9.8], w)
    assert not ekf.process_imu(t + 0.005, f, [0, np.inf, 0])
    assert not ekf.process_imu(float("nan"), f, w)
    assert not ekf.process_imu(t, f, w)                 # same stamp
    assert not ekf.process_imu(t - 0.1, f, w)           # older stamp
    assert not ekf.process_imu(t + 0.005, [1.0, 2.0], w)  # wrong shape
    assert ekf.rejected["imu_nonfinite"] == 4
    assert ekf.rejected["imu_out_of_order"] == 2
    np.testing.assert_array_equal(ekf.covariance, P0)
    np.testing.assert_array_equal(ekf.position_enu, p0)
    np.testing.assert_array_equal(ekf.quaternion, q0)
    assert ekf.time == t
    assert not ekf.update_speed(t, float("nan"))
    assert not ekf.update_speed(t - 1.0, 0.0)            # older than the last speed stamp
    assert not ekf.update_speed(t + 0.01, 1.0, variance=-1.0)
    assert not ekf.update_gnss(t, [np.nan, 0, 0])
    assert not ekf.update_gnss(t, [0, 0, 0], covariance=np.full((3, 3), np.nan))
    assert ekf.update_gnss(t, [0, 0, 0])
    assert not ekf.update_gnss(t, [0, 0, 0])             # duplicate stamp
    assert ekf.rejected["speed_nonfinite"] == 2 and ekf.rejected["speed_out_of_order"] == 1
    assert ekf.rejected["gnss_nonfinite"] == 2 and ekf.rejected["gnss_out_of_order"] == 1
    # still works afterwards
    assert ekf.process_imu(t + 0.005, f, w)


def test_imu_samples_beyond_the_sensor_range_are_rejected():
    ekf, t = _aligned_filter()
    P0, p0 = ekf.covariance, ekf.position_enu
    f, w = _static_imu()
    assert not ekf.process_imu(t + 0.005, [0.0, 1000.0, G], w)          # 100 g: a scaling fault
    assert not ekf.process_imu(t + 0.005, f, [0.0, 0.0, -50.0])        # 2900 deg/s
    assert ekf.rejected["imu_range"] == 2
    np.testing.assert_array_equal(ekf.covariance, P0)
    np.testing.assert_array_equal(ekf.position_enu, p0)
    assert ekf.process_imu(t + 0.005, [0.0, 150.0, G], w)              # within 16 g: a real crash
    assert ekf.rejected["imu_range"] == 2


def test_a_gnss_jump_restarts_the_heading_initialisation():
    """A fix from elsewhere while the heading is being fixed: the GNSS track is no longer the
    INS track rotated, so the initialisation starts again instead of taking its rotation."""
    sim = simulate(seed=1)
    jumped = dict(sim)
    jumped["gnss"] = sim["gnss"].copy()
    i_jump = int(np.searchsorted(sim["gnss_t"], 12.0))
    jumped["gnss"][i_jump] += np.array([900.0, -700.0, 0.0])
    ekf, out = run_filter(jumped)
    assert ekf.events["heading_restarted"] >= 1
    assert ekf.events["heading_initialised"] == 1
    m = out["running"]
    yaw_err = np.angle(np.exp(1j * (out["yaw"][m] - sim["yaw"][m])))
    assert math.degrees(_rms(yaw_err)) < 2.0
    assert np.linalg.norm(out["pos"][-1, :2] - sim["pos"][-1, :2]) < 10.0


def test_gnss_gating_rejects_outlier():
    sim = simulate(seed=3)
    n = int(40.0 * IMU_HZ)                   # run the first 40 s
    short = {k: (v[:n] if len(v) == len(sim["t"]) else v) for k, v in sim.items()}
    short["gnss"] = sim["gnss"][sim["gnss_t"] < 40.0].copy()
    short["gnss_t"] = sim["gnss_t"][sim["gnss_t"] < 40.0]
    short["speed"] = sim["speed"][sim["speed_t"] < 40.0]
    short["speed_t"] = sim["speed_t"][sim["speed_t"] < 40.0]
    i_out = int(np.searchsorted(short["gnss_t"], 36.0))
    short["gnss"][i_out] += np.array([60.0, -40.0, 0.0])  # a 72 m multipath jump
    ekf, out = run_filter(short)
    assert ekf.rejected["gnss_gate"] >= 1
    k = int(np.searchsorted(short["t"], short["gnss_t"][i_out])) + 1
    assert np.linalg.norm(out["pos"][k, :2] - short["pos"][k, :2]) < 3.0


def test_covariance_stays_symmetric_psd_random_inputs():
    """Abuse the filter with random IMU/measurements; P must stay symmetric PSD and finite."""
    rng = np.random.default_rng(7)
    ekf, t = _aligned_filter()
    ekf.status = "running"                  # skip the heading phase for this stress test
    for i in range(3000):
        t += 0.005
        ekf.process_imu(t, rng.normal(0, 3, 3) + [0, 0, G], rng.normal(0, 0.3, 3))
        if i % 2 == 0:
            ekf.update_speed(t, abs(rng.normal(10, 5)))
        if i % 20 == 0:
            ekf.update_gnss(t, rng.normal(0, 50, 3), np.diag(rng.uniform(0.5, 10, 3)))
        if i % 500 == 0:
            P = ekf.covariance
            np.testing.assert_array_equal(P, P.T)
            assert np.all(np.isfinite(P)) and np.linalg.eigvalsh(P).min() > -1e-9
    P = ekf.covariance
    np.testing.assert_array_equal(P, P.T)
    assert np.linalg.eigvalsh(P).min() > -1e-9


def test_config_validation_names_field():
    FusionConfig().validate()
    with pytest.raises(ValueError, match="speed_sigma"):
        FusionConfig(speed_sigma=-1.0).validate()
    with pytest.raises(ValueError, match="gnss_sigma"):
        FusionConfig(gnss_sigma=(1.0, 2.0)).validate()
    with pytest.raises(ValueError, match="init_stationary_samples"):
        FusionConfig(init_stationary_samples=0).validate()
    with pytest.raises(ValueError, match="nh_update_rate_hz"):
        FusionEKF(FusionConfig(nh_update_rate_hz=float("nan")))
    with pytest.raises(ValueError, match="unknown"):
        FusionConfig.from_dict({"not_a_field": 1})
    assert FusionConfig.from_dict({"gnss_sigma": [1.0, 1.0, 2.0]}).gnss_sigma == (1.0, 1.0, 2.0)


def test_reset():
    ekf, t = _aligned_filter()
    ekf.reset()
    assert ekf.status == "waiting_for_standstill" and ekf.time is None
    assert sum(ekf.rejected.values()) == 0


def test_rotation_helpers_round_trip():
    from vehicle_estimation.estimators.common.rotations import euler_from_quat, rotmat_to_quat
    rng = np.random.default_rng(11)
    for _ in range(200):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q2 = rotmat_to_quat(quat_to_rotmat(q))        # exercises all Shepperd branches
        assert min(np.abs(q2 - q).max(), np.abs(q2 + q).max()) < 1e-12
        r, p, y = rng.uniform(-3, 3), rng.uniform(-1.5, 1.5), rng.uniform(-3, 3)
        np.testing.assert_allclose(euler_from_quat(quat_from_euler(r, p, y)), (r, p, y), atol=1e-9)
    # REP-103: positive pitch tips the nose (body x) down
    assert quat_to_rotmat(quat_from_euler(0.0, 0.1, 0.0))[2, 0] < 0


def test_without_gnss_the_filter_navigates_with_a_free_heading():
    """No GNSS at all: the filter aligns at the standstill and then navigates, heading free.

    Speed and grade need no heading, so they are as good as with GNSS; the yaw is relative to
    the heading at alignment (taken as 0), so the ENU heading is off by the true initial one,
    and the track is the true one rotated by it: its shape (distances) is dead-reckoned."""
    sim = simulate(seed=3)
    no_gnss = dict(sim, gnss_t=np.zeros(0), gnss=np.zeros((0, 3)))
    ekf = FusionEKF()
    vx, grade, yaw, pos, pos_var, t_nav = [], [], [], [], [], []
    js = 0
    aligned_z_bias = None
    for i, t in enumerate(no_gnss["t"]):
        ekf.process_imu(t, no_gnss["imu_f"][i], no_gnss["imu_w"][i])
        while js < len(no_gnss["speed_t"]) and no_gnss["speed_t"][js] <= t:
            ekf.update_speed(no_gnss["speed_t"][js], no_gnss["speed"][js])
            js += 1
        if ekf.navigating:
            if aligned_z_bias is None:
                aligned_z_bias = float(ekf.gyro_bias[2])
            t_nav.append(i)
            vx.append(ekf.velocity_body[0])
            grade.append(ekf.road_grade)
            yaw.append(ekf.yaw)
            pos.append(ekf.position_enu)
            pos_var.append(np.trace(ekf.position_covariance[:2, :2]))
    assert not ekf.initialized and ekf.navigating and ekf.status == "waiting_for_heading"
    k = np.array(t_nav)
    assert sim["t"][k[0]] < 10.0                      # aligned at the standstill
    later = sim["t"][k] > 30.0
    assert _rms(np.array(vx)[later] - sim["v"][k][later]) < 0.1
    assert math.degrees(_rms(np.array(grade)[later] - sim["grade"][k][later])) < 1.0
    heading_offset = np.unwrap(sim["yaw"][k] - np.array(yaw))
    assert abs(heading_offset[-1] - YAW0) < math.radians(5.0)   # free heading: relative to the start
    # the track, rotated by the true initial heading, is the true track within a few % of the
    # distance travelled, and the position covariance grows with it
    rot = np.array([[math.cos(YAW0), -math.sin(YAW0)], [math.sin(YAW0), math.cos(YAW0)]])
    est = (np.array(pos)[:, :2] - np.array(pos)[0, :2]) @ rot.T
    true = sim["pos"][k][:, :2] - sim["pos"][k][0, :2]
    travelled = float(np.sum(np.linalg.norm(np.diff(true, axis=0), axis=1)))
    assert np.linalg.norm(est[-1] - true[-1]) < 0.05 * travelled
    assert pos_var[-1] > 10.0 * pos_var[0]
    # nothing observes the z gyro bias without GNSS: it keeps the alignment's standstill mean,
    # within its (kept) sigma of the truth, instead of trading it for the lateral accel bias
    # (with the update's gain it ended 1.9 sigma off, its sigma shrunk 4x by the coupling)
    assert ekf.gyro_bias[2] == pytest.approx(aligned_z_bias, abs=1e-12)
    err_z = ekf.gyro_bias[2] - GYR_BIAS[2]
    assert abs(err_z) < 2.0 * math.sqrt(ekf.gyro_bias_covariance[2, 2]) and abs(err_z) < 5e-4, err_z


def _grade_without_gnss(sim, ekf, *others):
    """Run ``ekf`` (and ``others`` beside it) on the IMU and the speed of ``sim``, no GNSS; the
    grade errors and published sigmas of ``ekf`` once it navigates, after 30 s."""
    errors, sigmas = [], []
    js = 0
    for i, t in enumerate(sim["t"]):
        for each in (ekf, *others):
            each.process_imu(t, sim["imu_f"][i], sim["imu_w"][i])
        while js < len(sim["speed_t"]) and sim["speed_t"][js] <= t:
            for each in (ekf, *others):
                each.update_speed(sim["speed_t"][js], sim["speed"][js])
            js += 1
        if ekf.navigating and t > 30.0:
            errors.append(ekf.road_grade - sim["grade"][i])
            sigmas.append(math.sqrt(ekf.road_grade_variance))
    return np.array(errors), np.array(sigmas)


def test_without_gnss_the_accelerometer_bias_is_held_and_its_prior_is_in_the_grade():
    """Without GNSS the along-track bias and the grade are one unobservable sum: the bias must
    not random-walk (on FASTSim's 600 s hilly drive the paper's walk took it to +2 m/s^2 and the
    grade to -10 deg), and the grade's variance must carry the bias prior it cannot shed."""
    sim = simulate(seed=3)
    cfg = FusionConfig()
    held, walking = FusionEKF(cfg), FusionEKF(FusionConfig(accel_bias_walk_without_gnss=True))
    errors, sigmas = _grade_without_gnss(sim, held, walking)
    assert not held.accel_bias_observed and not held.gnss_aided
    p_held = held.covariance[9:12, 9:12]
    assert np.all(np.diag(p_held) <= cfg.p0_accel_bias_sigma ** 2 * (1.0 + 1e-9))   # no walk
    assert walking.covariance[9, 9] > 10.0 * p_held[0, 0]                           # the paper's walk
    # the published bias covariance and the grade variance carry the unaided prior
    assert held.accel_bias_covariance[0, 0] >= cfg.unaided_accel_bias_sigma ** 2
    assert min(sigmas) >= cfg.unaided_accel_bias_sigma / G * 0.99
    # ... and so do the odometry's pitch and roll (about base_link y and x; a lateral bias is a
    # roll no vehicle constraint tells apart); its yaw, and the attitude that goes with the
    # compensated IMU, keep P's (their errors cancel in a - g)
    tilt = (cfg.unaided_accel_bias_sigma / G) ** 2
    added = held.pose_attitude_covariance - held.attitude_covariance
    x_axis, y_axis, z_axis = held.rotation_matrix.T
    for axis in (x_axis, y_axis):
        assert axis @ added @ axis == pytest.approx(tilt, rel=1e-9)
    assert z_axis @ added @ z_axis == pytest.approx(0.0, abs=1e-15)
    assert x_axis @ added @ y_axis == pytest.approx(0.0, abs=1e-15)
    assert math.degrees(_rms(errors)) < 0.3
    assert np.mean(np.abs(errors) < 2.0 * sigmas) > 0.95


def test_without_gnss_the_vertical_bias_variance_covers_what_the_held_bias_misses():
    """Held, the vertical bias's P settles ever more surely (2e-4 m/s^2 on our demo without GNSS,
    where the bias it had learnt was 0.007 off: the filter's g against the simulator's, NEES
    840). Until GNSS has observed the bias, the published covariance carries the unaided term on
    every axis: a g 0.01 m/s^2 off (local gravity spans 9.78 to 9.83) reads as bias, within it."""
    sim = simulate(seed=3)
    for gravity_error in (0.0, 0.01):
        cfg = FusionConfig(gravity=G + gravity_error)
        ekf = FusionEKF(cfg)
        _grade_without_gnss(sim, ekf)
        assert not ekf.accel_bias_observed
        assert math.sqrt(ekf.covariance[11, 11]) < 0.001                 # P alone: too sure
        sigma = math.sqrt(ekf.accel_bias_covariance[2, 2])
        assert sigma >= cfg.unaided_accel_bias_sigma
        assert abs(ekf.accel_bias[2] - (ACC_BIAS[2] - gravity_error)) < 2.0 * sigma


def test_without_gnss_the_shipped_bias_prior_is_counted_once():
    """params/estimation.yaml puts the MEMS bias prior into P itself (p0), which then learns the
    bias in motion; only what its model misplaces between bias and tilt is added on top
    (``unaided_accel_bias_sigma``). The grade variance is then honest: errors within 2 sigma,
    and not the prior counted twice (with the whole 0.05 m/s^2 added again the grade sigma was
    0.30 deg for a 0.05 deg error on this drive, NEES 0.02; now 0.13 deg, NEES 0.09)."""
    import yaml
    from vehicle_estimation.contract.vehicle import merge_ros_parameters
    from vehicle_estimation.paths import params_file
    shipped = merge_ros_parameters(yaml.safe_load(params_file("estimation").read_text()), node="fusion")
    ekf = FusionEKF(FusionConfig(p0_accel_bias_sigma=shipped["fusion.p0_accel_bias_sigma"],
                                 unaided_accel_bias_sigma=shipped["fusion.unaided_accel_bias_sigma"]))
    errors, sigmas = _grade_without_gnss(simulate(seed=3), ekf)
    assert not ekf.accel_bias_observed
    assert np.mean(np.abs(errors) < 2.0 * sigmas) > 0.9        # not too small
    assert np.mean((errors / sigmas) ** 2) > 0.05               # nor the prior twice (0.02)


def test_gnss_makes_the_bias_observable_and_drops_the_unaided_prior(drive):
    sim, ekf, out = drive
    assert ekf.accel_bias_observed
    cfg = ekf.config
    assert ekf.accel_bias_covariance[0, 0] < cfg.unaided_accel_bias_sigma ** 2
    np.testing.assert_array_equal(ekf.pose_attitude_covariance, ekf.attitude_covariance)
    # a mounting roll the constraints cannot refine is the roll's alone, with GNSS too
    sigma, shipped = math.radians(1.0), cfg.mounting_roll_sigma
    cfg.mounting_roll_sigma = sigma
    try:
        added = ekf.pose_attitude_covariance - ekf.attitude_covariance
    finally:
        cfg.mounting_roll_sigma = shipped
    np.testing.assert_allclose(added, sigma ** 2 * np.outer(ekf.rotation_matrix[:, 0], ekf.rotation_matrix[:, 0]),
                               atol=1e-15)
    running = out["running"]
    # shortly after the heading is fixed the GNSS-aided grade is tighter than the unaided prior
    assert np.nanmin(out["grade_var"][running]) < (cfg.unaided_accel_bias_sigma / G) ** 2


def _pull_away(top_speed, seconds=20.0, pitch=math.radians(0.5), yaw_rate=0.0, nominal_rpy=(0.0, 0.0, 0.0),
               straight_after_s=0.0, **cfg):
    """A filter aligned on level ground whose IMU sits ``pitch`` nose-up in the body (the nominal
    mounting ``nominal_rpy`` says no more), pulled away at 0.5 m/s^2 to ``top_speed`` on a level
    road, turning at ``yaw_rate`` [rad/s] all the while but the last ``straight_after_s``, without
    GNSS: the vertical constraint sees the body velocity times the mounting error."""
    ekf = FusionEKF(FusionConfig(nh_sigma_z=0.1, estimate_mounting=True, mounting_rpy=nominal_rpy, **cfg))
    to_nominal = quat_to_rotmat(quat_from_euler(*nominal_rpy)).T
    f_level, w = (to_nominal @ x for x in _static_imu(grade=pitch))
    t = 0.0
    for i in range(250):
        t = i * 0.005
        ekf.update_speed(t, 0.0)
        ekf.process_imu(t, f_level, w)
    to_imu = to_nominal @ quat_to_rotmat(quat_from_euler(0.0, -pitch, 0.0)).T
    for i in range(1, int(seconds / 0.005) + 1):
        t_i = t + i * 0.005
        accel = 0.5 if 0.5 * i * 0.005 < top_speed else 0.0
        speed = min(top_speed, 0.5 * i * 0.005)
        r = yaw_rate if i * 0.005 <= seconds - straight_after_s else 0.0
        f = f_level + to_imu @ np.array([accel, r * speed, 0.0])
        ekf.process_imu(t_i, f, w + to_imu @ np.array([0.0, 0.0, r]))
        if i % 2 == 0:
            ekf.update_speed(t_i, speed)
    return ekf


def _heading_information(ekf) -> float:
    """N^T P^-1 N for the direction no sensor but GNSS sees, a rotation of the whole solution
    about the vertical: (dp, dv, eps) = (S(e_z) p, S(e_z) v, -e_z) at the estimate."""
    from vehicle_estimation.estimators.fusion.error_state import IA, IP, IV, N_ERR
    n = np.zeros(N_ERR)
    n[IP:IP + 3] = np.cross([0.0, 0.0, 1.0], ekf._p)
    n[IV:IV + 3] = np.cross([0.0, 0.0, 1.0], ekf._v)
    n[IA + 2] = -1.0
    kept = np.flatnonzero(np.diag(ekf._P) > 0.0)     # a state that is off has no variance
    return float(n[kept] @ np.linalg.solve(ekf._P[np.ix_(kept, kept)], n[kept]))


@pytest.mark.parametrize("hold", [False, True], ids=["yaw-rate bias estimated", "yaw-rate bias held"])
def test_without_gnss_an_update_does_not_inform_the_heading(hold):
    """Without GNSS a speed update, blind to the heading at the estimate it is made at, leaves
    the information about the heading as it was when P moves with the estimate
    (``invariant_reset_without_gnss``); the ES-EKF's P, left where the update moved the
    velocity, gains some with every update (a turning car pulling away)."""
    gains = {}
    for invariant in (False, True):
        ekf = _pull_away(5.0, seconds=15.0, yaw_rate=0.05, invariant_reset_without_gnss=invariant,
                         hold_yaw_rate_bias_without_gnss=hold)
        before = _heading_information(ekf)
        assert ekf.update_speed(ekf.time + 0.001, 5.2)
        gains[invariant] = _heading_information(ekf) / before - 1.0
    assert gains[False] > 1e-5
    if hold:     # a Schmidt update is not the optimal one: it may only lose information
        assert -1e-5 < gains[True] <= 1e-12
    else:
        assert abs(gains[True]) < 1e-12


@pytest.mark.parametrize("zero_rate_update", [False, True], ids=["velocity update only", "zero-rate update"])
def test_standing_without_gnss_the_gyro_reads_its_bias(zero_rate_update):
    """A gyro whose bias moved after the alignment (a warm-up drift), standing 10 s without GNSS:
    the zero-rate update reads the new bias off the gyro on every axis, also the yaw-rate bias
    that is held without GNSS (FASTSim's car, whose three stops refresh it: heading 3.7 -> 0.7 deg
    RMSE). The velocity update alone sees only what the bias tilts, and nothing of the yaw. (The
    tilt axes' sigma is too small here, 4e-5 rad/s: Table 3's gyro noise, 1e-5 rad/s, is far below
    this gyro's 0.003, so P takes every tilt for the bias's.)"""
    rng = np.random.default_rng(5)
    ekf = FusionEKF(FusionConfig(stationary_rate_update=zero_rate_update))
    f, w = _static_imu()
    aligned, drifted = np.array([0.001, -0.001, 0.002]), np.array([0.0015, -0.0015, 0.003])
    for i in range(int(11.25 / 0.005)):
        t = i * 0.005
        if i % 2 == 0:
            ekf.update_speed(t, 0.0)
        bias = aligned if t < 1.25 else drifted
        ekf.process_imu(t, f + rng.normal(0.0, 0.05, 3), w + bias + rng.normal(0.0, 0.003, 3))
    assert ekf.stationary and not ekf.gnss_aided
    error, sigma = ekf.gyro_bias - drifted, np.sqrt(np.diag(ekf.gyro_bias_covariance))
    if zero_rate_update:
        assert np.all(np.abs(error) < 2e-4) and abs(error[2]) < 2.0 * sigma[2]
    else:                               # the yaw-rate bias held where the alignment put it
        assert abs(error[2]) > 0.9e-3 and abs(ekf.gyro_bias[2] - aligned[2]) < 1e-4


def test_gnss_observes_the_speeds_scale_error(drive):
    """Wheels on a tyre 3 % larger than the nominal radius: the CAN speed reads 3 % high. Taken
    as exact it pulls the velocity off GNSS's by that share; as a state (``estimate_speed_scale``)
    GNSS observes it, and the velocity follows the true speed."""
    sim, _, _ = drive
    scaled = dict(sim, speed=sim["speed"] * 1.03)
    learnt, learnt_out = run_filter(scaled, FusionEKF(FusionConfig(estimate_speed_scale=True)))
    taken, taken_out = run_filter(scaled)
    assert taken.speed_scale == 1.0 and taken.speed_scale_variance == 0.0
    error, sigma = learnt.speed_scale - 1.03, math.sqrt(learnt.speed_scale_variance)
    assert abs(error) < 0.003 and abs(error) < 2.0 * sigma < 0.01, (error, sigma)   # sigma with its floor
    m = learnt_out["running"] & taken_out["running"] & (sim["t"] > 60.0)
    learnt_rmse, taken_rmse = (_rms(out["vx"][m] - sim["v"][m]) for out in (learnt_out, taken_out))
    assert learnt_rmse < 0.1 and taken_rmse > 0.25, (learnt_rmse, taken_rmse)


def _pull_away_on_speeds_3_percent_high(ekf: FusionEKF) -> float:
    """40 s without GNSS: standstill, 1 m/s^2 to 20 m/s, cruise; the CAN speed 3 % high and the
    accelerometer 0.05 m/s^2 off. The true final speed."""
    f_level, w = _static_imu()
    step, speed = 0.005, 0.0
    for i in range(int(40.0 / step)):
        t = i * step
        accel = 1.0 if 1.5 <= t and speed < 20.0 else 0.0
        if i % 2 == 0:
            ekf.update_speed(t, 1.03 * speed, 0.01)
        ekf.process_imu(t, f_level + np.array([accel + 0.05, 0.0, 0.0]), w)
        speed = min(20.0, speed + accel * step)
    return speed


def test_without_gnss_the_speeds_scale_is_held_and_its_prior_is_in_the_velocity():
    """Without GNSS only the accelerometer would tell the scale, through its own bias: a pull-away
    with an unknown 0.05 m/s^2 bias reads as a scale error (a 36 t truck learnt 1.18). The scale
    is a consider state then: it keeps its value, and its prior reaches the published velocity,
    which a speed 3 % high then lies within 2 sigma of."""
    ekf = FusionEKF(FusionConfig(estimate_speed_scale=True, p0_accel_bias_sigma=0.05))
    speed = _pull_away_on_speeds_3_percent_high(ekf)
    assert ekf.navigating and not ekf.gnss_aided
    assert ekf.speed_scale == 1.0
    assert ekf.speed_scale_variance == pytest.approx(0.02 ** 2 + 0.004 ** 2, rel=1e-3)   # and its walk
    error, sigma = ekf.velocity_body[0] - speed, math.sqrt(ekf.velocity_body_covariance[0, 0])
    assert 0.5 < error < 2.0 * sigma, (error, sigma)


def test_a_scale_resumed_from_an_earlier_drive_corrects_the_speed_without_gnss():
    """The same drive as above, started from the scale an earlier drive with GNSS learnt
    (``resume_speed_scale``; a fusion node persists it): held as before, but at 1.03 with the
    earlier sigma plus ``speed_scale_resume_sigma``, so the speed no longer reads 3 % high; a
    reset (a bag loop) starts from it again. Bad values are refused, and only before the first
    sample."""
    config = FusionConfig(estimate_speed_scale=True, p0_accel_bias_sigma=0.05)
    ekf = FusionEKF(config)
    resumed = ekf.resume_speed_scale(1.03, 0.002 ** 2)
    assert resumed == pytest.approx(0.002 ** 2 + config.speed_scale_resume_sigma ** 2)
    assert ekf.speed_scale == pytest.approx(1.03) and ekf.speed_scale_filter_variance == pytest.approx(resumed)
    speed = _pull_away_on_speeds_3_percent_high(ekf)
    assert ekf.navigating and not ekf.gnss_aided and ekf.speed_scale == pytest.approx(1.03)
    error, sigma = ekf.velocity_body[0] - speed, math.sqrt(ekf.velocity_body_covariance[0, 0])
    assert abs(error) < 0.1 and abs(error) < 2.0 * sigma, (error, sigma)     # 0.6 m/s high when not resumed
    with pytest.raises(ValueError, match="before the first sample"):
        ekf.resume_speed_scale(1.0, 0.0)
    ekf.reset()
    assert ekf.speed_scale == pytest.approx(1.03) and ekf.speed_scale_filter_variance == pytest.approx(resumed)
    fresh = FusionEKF(config)
    assert fresh.resume_speed_scale(1.03, 1.0) == pytest.approx(0.02 ** 2)      # never above the prior
    for scale, variance in ((float("nan"), 0.0), (1.5, 0.0), (1.0, -1.0)):
        with pytest.raises(ValueError, match="not a speed scale"):
            FusionEKF(config).resume_speed_scale(scale, variance)
    with pytest.raises(ValueError, match="estimate_speed_scale"):
        FusionEKF(FusionConfig()).resume_speed_scale(1.03, 0.0)


def test_without_gnss_the_position_carries_the_speed_offset_that_lasts_while_its_value_does():
    """A bus speed in 1 km/h steps at a steady 24 m/s reads 86 km/h, 0.11 m/s low, for as long
    as the cruise lasts (FASTSim's cycles hold integer speeds). Without GNSS the position along
    the track is off by that offset times the cruise's time; counted as correlated over 1 s only,
    the published sigma says a few metres. With ``lasting_speed_offset`` the covariance carries
    each span of one reported value as its own offset, and the estimates are the same."""
    config = dict(speed_error_correlation_s=1.0, q_accel_sigma=0.05)
    filters = {flag: FusionEKF(FusionConfig(lasting_speed_offset=flag, **config)) for flag in (False, True)}
    f_level, w = _static_imu()
    step, stated = 0.005, (1.0 / 3.6) ** 2 / 12.0
    x = speed = 0.0
    for i in range(int(75.0 / step)):
        t = i * step
        accel = 1.2 if 1.5 <= t and speed < 24.0 else 0.0
        f = f_level + np.array([accel, 0.0, 0.0])
        for ekf in filters.values():
            if i % 2 == 0:
                ekf.update_speed(t, round(3.6 * speed) / 3.6, stated)
            ekf.process_imu(t, f, w)
        speed = min(24.0, speed + accel * step)
        x += speed * step
    lasting, correlated = filters[True], filters[False]
    assert not lasting.gnss_aided and lasting.initialized is False
    np.testing.assert_array_equal(lasting.position_enu, correlated.position_enu)
    error = lasting.position_enu[0] - x
    assert error < -5.0                         # 0.11 m/s low for 55 s of cruise
    assert abs(error) > 2.0 * math.sqrt(correlated.position_covariance[0, 0])
    assert abs(error) < 2.0 * math.sqrt(lasting.position_covariance[0, 0])
    # the cruise's offset lies along the track: across it nothing is added
    np.testing.assert_allclose(lasting.position_covariance[1:, 1:], correlated.position_covariance[1:, 1:],
                               rtol=1e-4, atol=0)


def test_a_speed_that_changes_every_sample_adds_almost_no_lasting_offset():
    """Spans of one reported value: a quantised cruise is one span (its offset times its time,
    along the track); a noisy speed closes a span every sample, and 60 s of it add what white
    noise would, sigma^2 dt T, not sigma^2 T^2."""
    from vehicle_estimation.estimators.fusion.lasting_speed_offset import LastingSpeedOffset

    east, north, variance = np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]), 0.0064
    held, noisy = LastingSpeedOffset(), LastingSpeedOffset()
    rng = np.random.default_rng(1)
    for i in range(6001):
        t = 0.01 * i
        held.add(t, 23.89, variance, east if t < 30.0 else north)
        noisy.add(t, 24.0 + rng.normal(0.0, 0.08), variance, east)
    D = np.array([29.99, 30.01])    # each interval along the axis of the sample that ends it
    np.testing.assert_allclose(held.covariance[:2, :2], variance * np.outer(D, D), rtol=1e-9)
    assert noisy.covariance[0, 0] == pytest.approx(variance * 0.01 * 60.0, rel=1e-6)
    held.add(60.01, 23.61, variance, north)         # the next step: the cruise's span is closed
    assert held.covariance[0, 0] == pytest.approx(variance * D[0] ** 2, rel=1e-9)
    held.reset()
    assert not held.covariance.any()


def test_without_gnss_a_crawl_does_not_move_the_mounting():
    """Below ``mounting_min_speed_without_gnss`` the constraints carry no mounting columns: a
    crawl leaves the mounting where the alignment put it (its errors go to the attitude, which
    GNSS or faster driving corrects later); from that speed up the mounting is learnt."""
    crawl = _pull_away(0.8)
    assert not crawl.gnss_aided and crawl.mounting_columns() == (False, False)
    np.testing.assert_array_equal(crawl.mounting_rpy, 0.0)
    ungated = _pull_away(0.8, mounting_min_speed_without_gnss=0.0)
    assert ungated.mounting_columns() == (True, True)
    assert abs(math.degrees(ungated.mounting_rpy[1])) > 0.01          # without the gate it moves
    driving = _pull_away(3.0)
    assert driving.mounting_columns() == (True, True)
    assert abs(math.degrees(driving.mounting_rpy[1])) > 0.01
    # what the crawl did not learn stays in the mounting's variance
    assert crawl.mounting_covariance[0, 0] == pytest.approx(crawl.config.p0_mounting_sigma ** 2)


@pytest.mark.parametrize("nominal_rpy", [(0.0, 0.0, 0.0), (math.pi / 2, 0.0, 0.0)], ids=["level", "on-its-side"])
def test_without_gnss_a_corner_holds_the_mounting_pitch_and_refines_its_yaw(nominal_rpy):
    """In a corner the constraints miss the sideslip and the roll, which nothing pins without
    GNSS: above ``mounting_max_yaw_rate_without_gnss`` the mounting pitch keeps its value and its
    variance (its column is out of the constraints), while its yaw is still learnt; with the
    gate opened the same corner moves the pitch. The gate reads the vehicle's yaw rate, about
    base_link z, also from an IMU on its side (whose own z axis then turns with the roll)."""
    cornering = _pull_away(5.0, yaw_rate=0.1, nominal_rpy=nominal_rpy)
    prior = cornering.config.p0_mounting_sigma ** 2
    assert cornering.mounting_columns() == (False, True)
    assert cornering.mounting_rpy[1] == pytest.approx(0.0, abs=1e-12)
    assert cornering.mounting_covariance[0, 0] == pytest.approx(prior)
    assert cornering.mounting_covariance[1, 1] < 0.8 * prior                # the yaw is learnt
    ungated = _pull_away(5.0, yaw_rate=0.1, nominal_rpy=nominal_rpy, mounting_max_yaw_rate_without_gnss=1.0)
    assert ungated.mounting_columns() == (True, True)
    assert abs(math.degrees(ungated.mounting_rpy[1])) > 0.01
    straight = _pull_away(5.0, yaw_rate=0.01, nominal_rpy=nominal_rpy)    # below the gate
    assert straight.mounting_columns() == (True, True)
    assert abs(math.degrees(straight.mounting_rpy[1])) > 0.01


def test_without_gnss_a_corner_loosens_the_vertical_constraint_for_a_while():
    """In a corner the vertical constraint sees the roll error times the filter's lateral
    velocity, which the sideslip and the body's roll sway put off: without GNSS it reads that
    as a roll and becomes sure of it. So in a corner, and ``nh_cornering_hold_s`` after it (a
    lane change's yaw rate passes through zero), it is at ``nh_sigma_z_cornering_without_gnss``;
    a straight brings the tight one back. (What it does to the roll: test_validation_commonroad.)"""
    cornering = _pull_away(5.0, yaw_rate=0.1)
    loose = cornering.config.nh_sigma_z_cornering_without_gnss
    assert cornering.vertical_constraint_sigma == pytest.approx(loose)
    tight = _pull_away(5.0, yaw_rate=0.1, nh_sigma_z_cornering_without_gnss=0.1)
    assert tight.vertical_constraint_sigma == pytest.approx(0.1)
    assert _pull_away(5.0, yaw_rate=0.01).vertical_constraint_sigma == pytest.approx(0.1)     # below the gate
    hold = cornering.config.nh_cornering_hold_s
    for straight_s, sigma in ((hold - 1.0, loose), (hold + 1.0, 0.1)):
        after = _pull_away(5.0, yaw_rate=0.1, straight_after_s=straight_s)
        assert after.vertical_constraint_sigma == pytest.approx(sigma)
