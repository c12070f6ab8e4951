"""Tuning of the IMU / GNSS / CAN-speed fusion (:class:`FusionConfig`), paper 003 Tables 2-3."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

from vehicle_estimation.contract.settings import check_settings, setting
from vehicle_estimation.contract.vehicle import GRAVITY, dataclass_from_mapping

__all__ = ["FusionConfig"]

#: Fields where None is valid and means "off" (see their docs).
OPTIONAL_FIELDS = ("nh_update_rate_hz", "gnss_gate_chi2", "speed_gate_chi2")


@dataclass
class FusionConfig:
    """Filter tuning.  Defaults are paper 003 Tables 2-3 (SI units) where the paper
    gives a value; the remaining fields are implementation choices documented here.

    The paper's process noise is in discrete "per IMU sample" form, Eq. (34): velocity
    and attitude noise enter as ``Ts * R * w`` (variance ``Ts^2 sigma^2`` per step) and
    the bias random walks as ``I * w`` (variance ``sigma^2`` per step).  The bias terms
    are scaled by ``dt * imu_rate_hz`` so that they equal the paper at the nominal rate
    and stay consistent under timing jitter.

    A CAN speed of 0 is only trusted while the IMU agrees (quantised or low-rate CAN reads 0
    for a while after the car starts to roll): the low-passed gravity-free acceleration and
    angular rate must be below ``stationary_max_accel`` and ``stationary_max_rate``.

    In-motion alignment (not in the paper, which starts at standstill): a filter started while
    the car drives (a node restart, a bag cut mid-drive) levels itself on the mean specific
    force minus the CAN-speed kinematics over ``in_motion_window_s``, with the ``in_motion_*``
    priors.

    Without GNSS (not in the paper, which always has it) the along-track (and lateral)
    accelerometer bias and the pitch (roll) enter every measurement only as the sum
    ``g tilt + bias``: one direction of the error state is unobservable. The paper's bias
    random walk then lets the split wander with whatever the model gets wrong (on FASTSim's
    hilly drive the x bias reached +2 m/s^2 and the grade -10 deg in 600 s; the true bias is
    0.05). So the accelerometer bias is held while no valid fix has come for
    ``gnss_aiding_timeout_s``, and every correction of the sum goes into the tilt, which the
    gyro carries between corrections. Its vertical part the vertical constraint observes, but
    letting it walk there costs the pitch what the constraint told it (FASTSim's truck without
    GNSS: slope 0.10 -> 0.59 deg), so it is held too, and the unaided term below covers it in
    the published bias covariance. A bias that no fix has ever observed is only known to
    its prior; ``unaided_accel_bias_sigma`` enters the grade variance, and the published bias
    covariance, as a 'consider' term on top of P. With Table 2's p0 (0.005) it is the typical
    turn-on bias of a MEMS accelerometer (0.05), which P does not hold. Where P starts at that
    prior (``p0_accel_bias_sigma`` 0.05, as params/estimation.yaml ships it), P learns the bias
    in motion (the vertical constraint and the speed separate it from the tilt) but is too sure
    of the split its model gets partly wrong, and the term is only that part (shipped 0.02).

    Without GNSS nothing observes the heading, so nothing observes the z gyro bias either (the
    alignment's standstill mean set it), yet the non-holonomic constraint couples it to the
    lateral accelerometer bias (``v_y' = a_y - r v_x``: a yaw-rate error looks like
    ``b_y / v_x``) and the filter trades one for the other (on FASTSim's drive the z bias went
    from -2 to +2 mrad/s). ``hold_yaw_rate_bias_without_gnss`` makes it a 'consider' state while
    no fix aids (a Schmidt update: its gain is zero, its covariance and cross-covariances are
    kept, Joseph form), corrected by GNSS. The bias held is the one about base_link z (the
    IMU's own z on a level IMU; another of its axes, or a mix, on a turned one).

    Nor does anything observe a rotation of the whole solution about the vertical, but the ES-EKF
    learns one: each body-velocity update is blind to it at the velocity it is made at, while P
    stays where the update moved the velocity. ``invariant_reset_without_gnss`` moves P with the
    estimate (:func:`.error_state.invariant_reset`), as an invariant EKF's error would, while no
    fix aids; with GNSS the fixes observe the heading and nothing changes.

    The IMU mounting (``estimate_mounting``) enters the body-velocity constraints as the
    velocity times its angle. Without GNSS it is refined there only from
    ``mounting_min_speed_without_gnss`` up, and its pitch only while the yaw rate stays below
    ``mounting_max_yaw_rate_without_gnss`` (:meth:`FusionEKF.mounting_columns`): pulling away,
    the product is smaller than what the constraints' model misses (the body pitching under the
    first acceleration, the CAN speed's quantisation); in a corner the constraints miss the
    sideslip and the roll, which no fix pins without GNSS; and no fix takes back what the
    mounting learnt from either.
    """

    gravity: float = setting(GRAVITY, "Gravitational acceleration [m/s^2] (paper uses 9.81, Eq. (27))",
                             low=0.0, low_open=True)
    imu_rate_hz: float = setting(200.0, "Nominal IMU rate the per-sample process noise refers to [Hz]",
                                 low=0.0, low_open=True)
    # --- Table 2: initial state standard deviations (P0) ---
    p0_position_sigma: float = setting(2.0, "Initial position std [m] (Table 2)", low=0.0, low_open=True)
    p0_velocity_sigma: float = setting(0.5, "Initial velocity std [m/s] (Table 2)", low=0.0, low_open=True)
    p0_attitude_sigma: tuple = setting((5e-3, 5e-3, 10e-3), "Initial attitude std about world x, y, z [rad] "
                                       "(Table 2)", each=True, low=0.0, low_open=True)
    p0_accel_bias_sigma: float = setting(0.005, "Initial accelerometer bias std [m/s^2] (Table 2)",
                                         low=0.0, low_open=True)
    p0_gyro_bias_sigma: float = setting(0.0008, "Initial gyro bias std [rad/s] (Table 2)", low=0.0, low_open=True)
    # --- Table 3 (left): process noise Q ---
    q_accel_sigma: float = setting(0.03, "Accelerometer noise [m/s^2] (Table 3)", low=0.0, low_open=True)
    q_gyro_sigma: float = setting(1e-5, "Gyro noise [rad/s] (Table 3)", low=0.0, low_open=True)
    q_accel_bias_sigma: float = setting(1e-3, "Accelerometer bias random walk per sample [m/s^2] (Table 3)",
                                        low=0.0, low_open=True)
    q_gyro_bias_sigma: float = setting(1e-6, "Gyro bias random walk per sample [rad/s] (Table 3)",
                                       low=0.0, low_open=True)
    # --- Table 3 (right): measurement noise W ---
    gnss_sigma: tuple = setting((2.0, 2.0, 5.0), "GNSS position std E, N, U where a fix gives no covariance [m] "
                                "(Table 3)", each=True, low=0.0, low_open=True)
    speed_sigma: float = setting(0.5, "CAN speed std [m/s] (Table 3)", low=0.0, low_open=True)
    speed_error_correlation_s: float = setting(
        0.0, "Correlation time of the CAN speed's error [s]: a speed quantised to 1 km/h is off by the "
        "same amount for as long as the speed stays in one step, which as white noise at the bus rate "
        "would count as known to mm/s; its variance is weighed 2 tau / (sample spacing) times "
        "(0: white, Table 3)", low=0.0)
    nh_sigma_y: float = setting(5.0, "Lateral non-holonomic constraint std [m/s] (Table 3)",
                                low=0.0, low_open=True)
    nh_sigma_z: float = setting(15.0, "Vertical non-holonomic constraint std [m/s] (Table 3)",
                                low=0.0, low_open=True)
    # --- stationary updates (paper: "greatly reduced" NH variances; value not given) ---
    stationary_sigma: float = setting(0.02, "Non-holonomic std while stationary [m/s]", low=0.0, low_open=True)
    stationary_update_longitudinal: bool = setting(True, "Also pseudo-measure body-x speed 0 at standstill")
    stationary_rate_update: bool = setting(False, "Also pseudo-measure the angular rate 0 at standstill (a "
                                           "zero-rate update of the gyro bias; not in the paper)")
    stationary_rate_sigma: float = setting(0.005, "Std of one zero-rate update [rad/s]: the gyro's white noise "
                                           "per sample and what a parked car's rocking adds", low=0.0, low_open=True)
    stationary_speed_threshold: float = setting(0.05, "|CAN speed| at or below this is stationary [m/s]", low=0.0)
    stationary_max_accel: float = setting(0.15, "Stationary only while the low-passed gravity-free acceleration "
                                          "is below this [m/s^2]", low=0.0, low_open=True)
    stationary_max_rate: float = setting(0.03, "Stationary only while the low-passed angular rate is below this "
                                         "[rad/s]", low=0.0, low_open=True)
    stationary_imu_tau_s: float = setting(0.1, "Time constant of the low-pass of the stationarity test [s]",
                                          low=0.0, low_open=True)
    speed_timeout_s: float = setting(0.5, "A CAN speed older than this leaves stationarity unknown [s]",
                                     low=0.0, low_open=True)
    speed_unsigned: bool = setting(False, "The CAN speed is |v_x| (its sign taken from the estimate)")
    nh_update_rate_hz: float | None = setting(None, "Rate of the non-holonomic updates [Hz]; None: every IMU "
                                              "sample, as in the paper", low=0.0, low_open=True)
    full_velocity_jacobian: bool = setting(True, "Include the attitude term -R^T S(v) in the body-speed Jacobian")
    # --- initialisation (Sec. 7.1) ---
    init_stationary_samples: int = setting(200, "Stationary IMU samples averaged by the alignment (Sec. 7.1)",
                                           low=1)
    init_max_accel_std: float = setting(0.3, "Largest per-axis accelerometer std over the alignment window "
                                        "[m/s^2]", low=0.0, low_open=True)
    init_max_gyro_std: float = setting(0.02, "Largest per-axis gyro std over the alignment window [rad/s]",
                                       low=0.0, low_open=True)
    heading_min_baseline_m: float = setting(15.0, "GNSS travel before the yaw is fixed [m]",
                                            low=0.0, low_open=True)
    in_motion_alignment: bool = setting(True, "Align while driving when the filter starts in motion")
    in_motion_window_s: float = setting(5.0, "Continuous motion the in-motion alignment averages [s]",
                                        low=0.0, low_open=True)
    in_motion_tilt_sigma: float = setting(0.0175, "Tilt prior after the in-motion alignment [rad]",
                                          low=0.0, low_open=True)
    in_motion_gyro_bias_sigma: float = setting(0.005, "Gyro bias prior after the in-motion alignment (no "
                                               "standstill mean) [rad/s]", low=0.0, low_open=True)
    heading_max_fixes: int = setting(600, "Most GNSS fixes kept for the heading initialisation", low=2)
    # --- robustness ---
    gnss_gate_chi2: float | None = setting(16.27, "Chi-square gate of a GNSS update (chi2(3) 99.9 %); None "
                                           "disables", low=0.0, low_open=True)
    speed_gate_chi2: float | None = setting(10.83, "Chi-square gate of a CAN speed update (chi2(1) 99.9 %); None "
                                            "disables", low=0.0, low_open=True)
    max_consecutive_rejections: int = setting(10, "Gate rejections in a row after which the covariance block is "
                                              "re-opened", low=1)
    max_measurement_delay_s: float = setting(0.5, "Measurements older than the filter by more are rejected [s]",
                                             low=0.0, low_open=True)
    max_imu_dt_s: float = setting(0.5, "Larger IMU gaps are propagated but counted [s]", low=0.0, low_open=True)
    imu_max_specific_force: float = setting(160.0, "IMU samples with a specific-force axis beyond this are "
                                            "rejected: an automotive IMU's range is 16 g [m/s^2]",
                                            low=0.0, low_open=True)
    imu_max_angular_rate: float = setting(35.0, "IMU samples with a rate axis beyond this are rejected: "
                                          "2000 deg/s, a MEMS gyro's widest range [rad/s]", low=0.0, low_open=True)
    heading_max_scale_error: float = setting(0.5, "The GNSS track and the INS track may differ in length by this "
                                             "share before the heading initialisation restarts", low=0.0,
                                             low_open=True)
    # --- IMU mounting (imu_link in base_link; not in the paper, see the esekf module docstring) ---
    mounting_rpy: tuple = setting((0.0, 0.0, 0.0), "Nominal roll, pitch, yaw of imu_link in base_link [rad]",
                                  low=-math.pi, high=math.pi, each=True)
    estimate_mounting: bool = setting(False, "Refine the mounting pitch and yaw online (needs nh_sigma_z <= 1)")
    p0_mounting_sigma: float = setting(0.035, "Prior std of the mounting pitch and yaw refinement [rad]", low=0.0)
    mounting_roll_sigma: float = setting(0.0, "Std of the nominal mounting roll, which no constraint refines: it "
                                         "enters the published roll's variance (estimation/odometry); 0 = the "
                                         "IMU calibrated to the body, as in the paper [rad]", low=0.0)
    q_mounting_sigma: float = setting(1e-7, "Mounting random walk per sample [rad]: a mounting does not move",
                                      low=0.0)
    # --- the CAN speed's scale (not in the paper; see the esekf module docstring) ---
    estimate_speed_scale: bool = setting(False, "Estimate the CAN speed's scale error (the effective rolling "
                                         "radius: tyre wear, pressure, a speed calibrated for another tyre) "
                                         "as a filter state, speed = (1 + k) v_x; GNSS positions observe it, "
                                         "without them it is held (a consider state)")
    p0_speed_scale_sigma: float = setting(0.02, "Prior std of that scale error k [-]", low=0.0)
    q_speed_scale_sigma: float = setting(4e-6, "Random walk of k per sample [-]: tyres wear and warm up "
                                         "slowly (1e-3 over 10 min at 100 Hz)", low=0.0)
    speed_scale_after_s: float = setting(
        10.0, "The scale is held this long after GNSS fixed the heading [s]: the first fixes settle "
        "the velocity and the attitude, which a freed scale would trade against (CommonRoad's 14 s "
        "lane change: slope within 2 sigma 90 -> 86 % with it freed at once)", low=0.0)
    speed_scale_resume_sigma: float = setting(
        0.003, "Added to the std of a scale resumed from an earlier drive (resume_speed_scale) [-]: "
        "between drives the tyres' pressure and temperature move the rolling radius by a few tenths "
        "of a percent", low=0.0)
    speed_scale_floor_sigma: float = setting(
        0.004, "Added to the published scale's std [-]: a speed in 1 km/h steps is off by one amount "
        "for as long as it keeps a value, 0.4 % at 70 km/h, and the filter, which takes that offset "
        "as correlated over speed_error_correlation_s, cannot tell it from a scale", low=0.0)
    # --- without GNSS (not in the paper, which always has it; see the class docstring) ---
    accel_bias_walk_without_gnss: bool = setting(False, "Let the accelerometer bias random-walk without GNSS too "
                                                 "(the paper's Q)")
    gnss_aiding_timeout_s: float = setting(5.0, "No valid fix for this long: the accelerometer bias is held [s]",
                                           low=0.0, low_open=True)
    lasting_speed_offset: bool = setting(
        False, "Without GNSS the published position covariance also carries the CAN speed's offset as "
        "lasting while its reported value does not change (a 1 km/h step at a steady speed): per such "
        "span its stated variance times D D^T, D the forward axis integrated over the span's time; the "
        "estimates do not change")
    unaided_accel_bias_sigma: float = setting(0.05, "Accelerometer-bias error added to P in the grade variance "
                                              "until GNSS observes the bias: the prior P lacks, or what P "
                                              "misplaces when p0 holds the prior [m/s^2]", low=0.0)
    hold_yaw_rate_bias_without_gnss: bool = setting(True, "Hold the yaw-rate gyro bias (about base_link z) "
                                                    "while no GNSS fix aids (a consider state)")
    invariant_reset_without_gnss: bool = setting(False, "While no GNSS fix aids, move the velocity's and the "
                                                 "position's covariance with the estimate at each update (errors "
                                                 "about the attitude's estimate), so that no update informs the "
                                                 "heading, which nothing observes")
    mounting_min_speed_without_gnss: float = setting(1.0, "Without GNSS the vehicle constraints refine the "
                                                     "mounting only from this speed up [m/s]", low=0.0)
    mounting_max_yaw_rate_without_gnss: float = setting(
        0.02, "Without GNSS the vehicle constraints refine the mounting pitch only while the low-passed yaw "
        "rate stays below this [rad/s]: in a corner the sideslip and the roll that they do not model "
        "reach them as a mounting pitch", low=0.0, low_open=True)
    nh_sigma_z_cornering_without_gnss: float = setting(
        1.0, "Without GNSS, the vertical non-holonomic constraint's std in a corner and for "
        "nh_cornering_hold_s after it [m/s] (a corner: the low-passed yaw rate above "
        "mounting_max_yaw_rate_without_gnss; never tighter than nh_sigma_z): there the tight constraint "
        "reads the sideslip and the body roll that neither constraint models as a roll, and the "
        "filter becomes sure of it", low=0.0, low_open=True)
    nh_cornering_hold_s: float = setting(
        3.0, "How long after a corner the vertical constraint stays at nh_sigma_z_cornering_without_gnss "
        "[s]: a lane change's yaw rate passes through zero between its turns, and the lateral "
        "velocity a corner leaves wrong takes seconds to settle", low=0.0)

    def validate(self) -> None:
        """Raise ValueError naming the first bad field."""
        check_settings(self, skip=[name for name in OPTIONAL_FIELDS if getattr(self, name) is None])
        for name in ("p0_attitude_sigma", "gnss_sigma", "mounting_rpy"):
            if len(getattr(self, name)) != 3:
                raise ValueError(f"{name} must be 3 numbers, got {getattr(self, name)!r}")
        if self.estimate_mounting and self.nh_sigma_z > 1.0:
            raise ValueError(
                "estimate_mounting needs nh_sigma_z <= 1 m/s: the "
                f"mounting pitch is observed through the vertical constraint (nh_sigma_z={self.nh_sigma_z!r})")

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "FusionConfig":
        """Build from a (ROS parameter) dict; unknown keys raise ValueError."""
        return dataclass_from_mapping(cls, d, "unknown FusionConfig field {key!r}")
