"""Adaptive anti-outlier UKF on the 3-DOF Magic-Formula vehicle model (paper 002).

Liu, Cui, Peng 2023, "Vehicle state and parameter estimation based on adaptive anti-outlier
unscented Kalman filter and GA-BPNN method", J. Vibroengineering, doi 10.21595/jve.2023.23441.

Contents
--------
* :class:`AOUKFConfig`: the tuning (ROS parameters ``aoukf.*`` of the state node).
* :class:`VehicleStateAOUKF`: the node-facing estimator
  (:class:`~vehicle_estimation.estimators.interfaces.StateEstimator`, as
  :class:`~vehicle_estimation.estimators.state.ckf.VehicleStateCKF`), with the optional GA-BPNN
  output correction of Eq. 5 (:class:`~vehicle_estimation.estimators.state.gabpnn.BPCorrection`).

The filters (UKF, anti-outlier UKF, EKF) are in :mod:`.aoukf_filters`, the 3-DOF model in
:mod:`.three_dof_model`.

Choices where the paper is not explicit (all in :class:`AOUKFConfig`)
-------------------------------------------------------------------
* Tyre: the paper gives ``B = 0.237, C = 1.65, D = 3610.5, E = 0.707`` (Sec. 2.2, for its
  Table-1 car, slip angle in degrees, ``D`` in N per tyre). ``D`` follows the axle load of
  Eq. 3 as ``D = mf_d F_z / mf_reference_load`` (the linear term ``a2 F_z`` of the paper's
  ``D = a1 F_z^2 + a2 F_z``; the reference load is the mean tyre load of the paper's Table-1
  car, ``1522 g / 4``), a friction coefficient of 0.97. With ``mf_peak_from_road_friction``
  (default) ``D = road_friction F_z`` instead: a model whose tyres cannot reach the measured
  lateral acceleration has no slip angle that explains the measurement, and past the Magic
  Formula's peak its force falls as the slip grows, so the filter chases ay with ever more
  slip (the real Stanford drive, 1.2 g on a dry track: vy 2.7 m/s off). With
  ``mf_match_cornering_stiffness`` (default) ``B`` is set per axle
  so that the cornering stiffness ``B C D`` equals ``VehicleParams.cornering_stiffness_*``:
  the paper's numbers describe the paper's car, the vehicle file describes ours. ``False``
  uses the paper's ``B`` as is.
* Innovation standard deviation (Sec. 3.3): ``sigma_ii`` is the larger of the UKF's
  ``sqrt(P_zz,ii)`` (the paper's formula) and a robust running estimate over the last
  ``innovation_window`` innovations, each clipped at ``C sigma`` before it enters the window.
  The running estimate lets ``sigma`` follow a time-varying noise level (a fixed ``R`` would
  flag a whole noisy segment as outliers); the clipping keeps outliers out of it and still
  lets ``sigma`` grow by up to ``C`` per window when the noise really rises.
* Gain factor ``m`` (Sec. 3.3, "depends on the size of the innovation"): ``m = 1`` for
  ``|e_i| <= C sigma_ii``, ``m = C sigma_ii / |e_i|`` up to ``zero_gain_ratio C sigma_ii``,
  and ``m = 0`` beyond (the "very high innovation" case).
* Isolated vs speckled (Steps 1-5): online, the first flagged sample of a channel is an
  isolated outlier (gain scaling); from the ``speckle_min_run``-th consecutive flagged
  sample on it is part of a speckled outlier and is replaced by the prediction
  ``(Z)_i <- (Z_hat)_i`` (innovation 0, no information: its gain column is zeroed). A run
  longer than ``max_outlier_run_s`` is taken as a real change of the signal, not an outlier:
  the channel's window is restarted and the channel is accepted until its innovation passes
  Eq. 7 again (``resyncs``).

Extension beyond the paper: the undriven wheels' mean speed times the wheel radius observes
``vx`` when the wheel speeds are finite (``wheel_speed_update``, default on); without it ``vx``
is the integral of the measured ``ax`` and drifts with its bias. The start value of ``vx``
comes from the same wheels when they are available, as in ``VehicleStateCKF``.
"""

from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING, Optional

import numpy as np

from vehicle_estimation.contract.settings import check_settings, setting
from vehicle_estimation.contract.vehicle import VehicleParams
from vehicle_estimation.estimators.common.sigma_points import AdditiveNoiseFilter
from vehicle_estimation.estimators.state.aoukf_filters import (
    AntiOutlierUKF,
    ExtendedKalmanFilter,
    OutlierDecision,
    UnscentedKalmanFilter,
)
from vehicle_estimation.estimators.state.core import VehicleStateCore
from vehicle_estimation.estimators.state.three_dof_model import PAPER_REFERENCE_LOAD, ThreeDofModel
from vehicle_estimation.estimators.state.vehicle_model import VehicleInputs

if TYPE_CHECKING:   # gabpnn imports nothing from here at run time either; no cycle
    from vehicle_estimation.estimators.state.gabpnn import BPCorrection

__all__ = ["AOUKFConfig", "VehicleStateAOUKF", "FILTER_KINDS", "OBSERVATIONS"]

#: Observation channels of the vehicle model, in the order of :meth:`ThreeDofModel.measurement`.
OBSERVATIONS = ("ay", "r", "vx_wheels")
#: Filters :class:`VehicleStateAOUKF` can run on the model (paper Table 2 contrasts).
FILTER_KINDS = ("aoukf", "ukf", "ekf")


def _positive(default: float, doc: str) -> float:
    return setting(default, doc, low=0.0, low_open=True)


@dataclasses.dataclass(frozen=True)
class AOUKFConfig:
    """Tuning of :class:`VehicleStateAOUKF`. Noise values refer to ``nominal_dt``."""

    filter: str = setting("aoukf", "'aoukf' (paper Sec. 3.3), 'ukf' (plain UKF) or 'ekf' (the contrast)",
                          choices=FILTER_KINDS)
    mf_b: float = _positive(0.237, "Magic-Formula B of Sec. 2.2 [1/deg] (0.237)")
    mf_c: float = _positive(1.65, "Magic-Formula C of Sec. 2.2 [-] (1.65)")
    mf_d: float = _positive(3610.5, "Magic-Formula D of Sec. 2.2 [N per tyre at mf_reference_load] (3610.5)")
    mf_e: float = setting(0.707, "Magic-Formula E of Sec. 2.2 [-] (0.707); below 1 (a curvature factor "
                          ">= 1 folds the curve)", high=1.0, high_open=True)
    mf_reference_load: float = _positive(
        PAPER_REFERENCE_LOAD, "Tyre load at which the tyre has peak mf_d; D scales with the Eq.-3 load "
        "(default: mean tyre load of the paper's 1522 kg car) [N]")
    mf_peak_from_road_friction: bool = setting(
        True, "Peak D = the vehicle's road_friction x the Eq.-3 tyre load (false: the paper's mf_d, "
        "scaled by the load; its mu of 0.97 caps the model's ay below what a car on a dry track reaches). "
        "With the GA-BPNN correction the paper's tyre runs: the correction learnt its residuals")
    mf_match_cornering_stiffness: bool = setting(
        True, "Set B per axle so that B C D equals the vehicle's cornering_stiffness_front/rear "
        "(false: the paper's B for both axles)")
    q_diag: tuple[float, float, float] = setting(
        (2e-4, 2e-4, 1e-5), "Process noise of [vx, vy, r] per nominal_dt [(m/s)^2, (m/s)^2, (rad/s)^2]",
        low=0.0, low_open=True, each=True)
    r_ay: float = _positive(0.04, "Measurement variance of ay [(m/s^2)^2]")
    r_yaw_rate: float = _positive(1e-4, "Measurement variance of the yaw rate [(rad/s)^2]")
    r_wheel_speed: float = _positive(4e-3, "Measurement variance of the wheel-speed vx [(m/s)^2]")
    p0_diag: tuple[float, float, float] = setting(
        (1.0, 0.25, 0.01), "Initial covariance diagonal of [vx, vy, r] [(m/s)^2, (m/s)^2, (rad/s)^2]",
        low=0.0, low_open=True, each=True)
    initial_vx: float = setting(0.0, "Start speed without wheel speeds [m/s]")
    wheel_speed_update: bool = setting(
        True, "Observe vx by the undriven wheels' mean speed x radius (extension beyond the paper)")
    init_vx_from_wheel_speeds: bool = setting(True, "Start vx from the undriven wheels when they report")
    outlier_c: float = _positive(3.0, "C of Eq. 7: a component is an outlier when |e_i| > C sigma_ii [-]")
    zero_gain_ratio: float = setting(2.0, "The gain factor m is 0 above this multiple of C sigma [-]", low=1.0)
    innovation_window_s: float = setting(
        1.0, "Length of the running innovation std (0: P_zz only) [s]", low=0.0)
    speckle_min_run: int = setting(2, "Consecutive outliers from which they are speckled (replaced)", low=1)
    max_outlier_run_s: float = setting(
        0.5, "A run of outliers longer than this is accepted as a real change [s]", low=0.0)
    max_abs_accel: float = _positive(
        15.0, "An |ax| input above this is clipped (an ax spike goes straight into vx) [m/s^2]")
    ukf_alpha: float = _positive(1.0, "Sigma-point spread alpha [-]")
    ukf_beta: float = setting(2.0, "Sigma-point prior-distribution weight beta (2: Gaussian) [-]")
    ukf_kappa: float = setting(0.0, "Sigma-point secondary scaling kappa [-]")
    nominal_dt: float = _positive(0.01, "Step the noise values refer to; Q scales with dt / nominal_dt [s]")
    max_gap_s: float = _positive(0.5, "A stamp gap above this re-initialises [s]")
    max_substep: float = _positive(0.01, "Euler sub-step of Eq. 1 [s]")
    min_speed: float = _positive(1.0, "vx floor in the slip angles [m/s]")

    def validate(self) -> None:
        """Raise ``ValueError`` naming the first invalid field."""
        check_settings(self)
        for name in ("q_diag", "p0_diag"):
            value = tuple(getattr(self, name))
            if len(value) != 3:
                raise ValueError(f"{name} must be 3 finite positive numbers, got {value!r}")
        lam = self.ukf_alpha ** 2 * (3 + self.ukf_kappa) - 3
        if not 3 + lam > 0:
            raise ValueError(f"ukf_kappa must give n + lambda > 0, got {self.ukf_kappa!r}")


# ========================================================================================
class VehicleStateAOUKF(VehicleStateCore):
    """Vehicle state ``[vx, vy, r]`` by the anti-outlier UKF (+ GA-BPNN) of paper 002.

    API of :class:`~vehicle_estimation.estimators.state.ckf.VehicleStateCKF`: one :meth:`step` per IMU
    sample with ``z = [ax, ay, r]`` (bias-compensated IMU in base_link); ``ax`` is the model's
    input, ``[ay, r]`` the observation; ``inputs`` carries the road-wheel steer angle, the wheel
    speeds (vx observation), the slope (removes gravity from ``ax``) and the mass (model mass;
    ``None``: ``VehicleParams.mass``).

    With a ``correction`` (:class:`~vehicle_estimation.estimators.state.gabpnn.BPCorrection`) :attr:`x`
    is the corrected output of Eq. 5, ``X' = X_k|k + B_perr``; the filter itself never sees
    the correction (:attr:`x_filter` is the UKF estimate).
    """

    _filter: AdditiveNoiseFilter
    #: Sec. 2.3's observation ``[ay, r]`` and the wheel-speed ``vx`` (:meth:`_h`).
    measurement_channels = ("ay", "r", "vx")

    def __init__(self, params: VehicleParams, config: Optional[AOUKFConfig] = None,
                 correction: Optional["BPCorrection"] = None):
        params.validate()
        cfg = AOUKFConfig() if config is None else config
        cfg.validate()
        # An all-wheel drive has no undriven axle: the rear wheels stand in (less drive slip).
        undriven = [2, 3] if params.driven_axle == "all" else list(params.undriven_wheels)
        super().__init__(params, cfg.initial_vx, np.diag(cfg.p0_diag), undriven, cfg.max_gap_s)
        self.rejected["accel_clipped"] = 0
        self.config = cfg
        self.correction = correction
        self.model = ThreeDofModel.from_params(params, cfg)
        self._models: dict[float, ThreeDofModel] = {params.mass: self.model}
        self._Q = np.diag(np.asarray(cfg.q_diag, dtype=float))
        R = np.diag([cfg.r_ay, cfg.r_yaw_rate, cfg.r_wheel_speed])
        x0 = self._x0(None)
        f, h = self._f, self._h
        if cfg.filter == "ekf":
            self._filter = ExtendedKalmanFilter(f, h, self._Q, R, x0, self._P0)
        elif cfg.filter == "ukf":
            self._filter = UnscentedKalmanFilter(f, h, self._Q, R, x0, self._P0, alpha=cfg.ukf_alpha,
                                                 beta=cfg.ukf_beta, kappa=cfg.ukf_kappa)
        else:
            window = int(round(cfg.innovation_window_s / cfg.nominal_dt))
            max_run = int(round(cfg.max_outlier_run_s / cfg.nominal_dt))
            self._filter = AntiOutlierUKF(f, h, self._Q, R, x0, self._P0, C=cfg.outlier_c,
                                          zero_gain_ratio=cfg.zero_gain_ratio, window=window,
                                          speckle_min_run=cfg.speckle_min_run, max_run=max_run,
                                          alpha=cfg.ukf_alpha, beta=cfg.ukf_beta, kappa=cfg.ukf_kappa)
        self._ax = 0.0
        self._correction_output = np.zeros(3)
        self.last_decision: Optional[OutlierDecision] = None

    # -- model closures ------------------------------------------------------------------
    def _model_for(self, mass: Optional[float]) -> ThreeDofModel:
        key = self.params.mass if mass is None else float(mass)
        model = self._models.get(key)
        if model is None:
            if len(self._models) > 16:
                self._models.clear()
            model = ThreeDofModel.from_params(self.params.with_mass(key), self.config)
            self._models[key] = model
        return model

    def _f(self, X, dt, model: ThreeDofModel, ax_kin: float, delta: float):
        return model.transition(X, dt, ax_kin, delta)

    def _h(self, X, model: ThreeDofModel, delta: float):
        return model.measurement(X, delta)

    # -- helpers -------------------------------------------------------------------------
    def reset(self, vx0: Optional[float] = None) -> None:
        """Back to ``[vx0, 0, 0]`` (``vx0`` default ``initial_vx``), ``P0``; forget the stamp,
        the outlier windows and the correction's feature history."""
        super().reset(vx0)
        if self.correction is not None:
            self.correction.reset()
        self._correction_output = np.zeros(3)

    def _vx_after_failure(self, inputs: VehicleInputs) -> Optional[float]:
        return self._vx_from_wheels(inputs) if self.config.init_vx_from_wheel_speeds else None

    def _vx_after_gap(self, inputs: VehicleInputs) -> Optional[float]:
        vx0 = self._vx_after_failure(inputs)
        return vx0 if vx0 is not None else self._vx_now()

    # -- main entry ----------------------------------------------------------------------
    def step(self, t: float, inputs: VehicleInputs, z) -> bool:
        """Predict to ``t`` with ``ax = z[0]`` and update with ``[ay, r] = z[1:]`` (+ wheels).

        Returns True if a measurement update was applied. Rejected (nothing changes, counted
        in :attr:`rejected`): non-finite ``t``, invalid ``inputs``, ``z`` not 3 values, stamp
        not increasing. A non-finite ``ax`` predicts with the last valid one; a non-finite
        ``ay``/``r`` is left out of the update (both non-finite and no wheels: no update). An
        ``|ax|`` above ``max_abs_accel`` is clipped. A gap above ``max_gap_s`` re-initialises.
        """
        sample = self._begin_step(t, inputs, z)
        if sample is None:
            return False
        t, z, dt = sample
        cfg = self.config
        if math.isfinite(z[0]):
            ax = float(z[0])
            if abs(ax) > cfg.max_abs_accel:
                ax = math.copysign(cfg.max_abs_accel, ax)
                self.rejected["accel_clipped"] += 1
            self._ax = ax
        model = self._model_for(inputs.mass)
        delta = float(inputs.steer_angle)
        if not self.initialised:
            vx0 = self._vx_from_wheels(inputs) if cfg.init_vx_from_wheel_speeds else None
            self._filter.reset(*self._initial_moments(vx0))
            self.initialised = True
        else:
            ax_kin = self._ax - self.params.gravity * math.sin(float(inputs.slope))
            Q = self._with_extra_vx_noise(self._Q * (dt / cfg.nominal_dt), dt)
            self._filter.predict(dt, model, ax_kin, delta, Q=Q)
        self.t = t
        x_prior = self._filter.x
        obs = np.array([z[1], z[2], np.nan])
        if cfg.wheel_speed_update:
            vx_wheels = self._vx_from_wheels(inputs)
            if vx_wheels is not None:
                obs[2] = vx_wheels
        select = np.nonzero(np.isfinite(obs))[0]
        if not np.isfinite(z).all():
            self.rejected["nonfinite_measurement"] += 1
            self.last_event = "non-finite measurement"
        if select.size == 0:
            if self._reinitialised_after_failure(inputs):
                return False
            self._after_update(x_prior, t)
            return False
        with np.errstate(all="ignore"):
            try:
                result = self._filter.update(obs[select], model, delta, select=select)
            except np.linalg.LinAlgError:
                result = None
        if result is None:
            self._filter._x[:] = np.nan        # handled as a numerical failure below
        if self._reinitialised_after_failure(inputs):
            return False
        self.last_decision = result if isinstance(result, OutlierDecision) else None
        self.updates += 1
        self._after_update(x_prior, t)
        return True

    def _after_update(self, x_prior: np.ndarray, t: float) -> None:
        if self.correction is None:
            return
        out = self.correction.step(t, self._filter.x - x_prior)
        self._correction_output = out if np.isfinite(out).all() else np.zeros(3)

    def _correct_speed(self, vx: float, variance: float) -> None:
        f = self._filter
        P = f._P
        K = P[:, 0] / (P[0, 0] + variance)
        f._x = f._x + K * (vx - f._x[0])
        P = P - np.outer(K, P[0, :])
        f._P = 0.5 * (P + P.T)

    # -- outputs -------------------------------------------------------------------------
    @property
    def x_filter(self) -> np.ndarray:
        """The UKF/EKF estimate ``X_k|k`` (no GA-BPNN correction)."""
        return self._filter.x

    @property
    def correction_output(self) -> np.ndarray:
        """The last ``B_perr`` of Eq. 5 (zeros without a correction)."""
        return self._correction_output.copy()

    @property
    def x(self) -> np.ndarray:
        """``[vx, vy, r]``: ``X_k|k + B_perr`` (Eq. 5) with a correction, else ``X_k|k``."""
        return self._filter.x + self._correction_output

    @property
    def outlier_counts(self) -> dict[str, int]:
        """Anti-outlier counters: isolated_downweighted, isolated_zero_gain, speckled_replaced,
        resyncs (all zero for the plain UKF/EKF)."""
        if isinstance(self._filter, AntiOutlierUKF):
            return dict(self._filter.counts)
        return {"isolated_downweighted": 0, "isolated_zero_gain": 0, "speckled_replaced": 0, "resyncs": 0}

    @property
    def counters(self) -> dict[str, int]:
        """Everything a diagnostics message needs: outliers, rejected inputs, updates."""
        out = {**self.outlier_counts, **{f"rejected_{k}": v for k, v in self.rejected.items()}}
        out.update(updates=self.updates, reinitialisations=self.reinitialisations,
                   speed_updates=self.speed_updates)
        return out

    def status(self) -> dict[str, str]:
        """The counters (measurements the anti-outlier step down-weighted, ignored or replaced,
        Sec. 3.3; rejected inputs) and whether the GA-BPNN correction is on."""
        out = {f"aoukf {k}": str(v) for k, v in self.counters.items()}
        out["GA-BPNN correction"] = "on" if self.correction is not None else "off"
        return out
