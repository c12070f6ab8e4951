"""The layout of the fusion's error state (paper 003 Eq. (32)), the filter's phases, and how the
error covariance moves with the estimate."""

from __future__ import annotations

import math

import numpy as np

from vehicle_estimation.estimators.common.rotations import skew

# Error-state layout, Eq. (32): z = [dp, dv, eps, dba, dbg], then the mounting pitch and
# yaw corrections dm (about base_link y, z; R_m,true = (I + S([0, dm])) R_m,hat), then the CAN
# speed's scale error dk (speed = (1 + k) v_x).
IP, IV, IA, IBA, IBG, IM, IK = 0, 3, 6, 9, 12, 15, 17
N_ERR = 18

# Phases of :attr:`FusionEKF.status`, in order: alignment (Sec. 7.1), then the free heading
# until GNSS motion fixes the yaw, then running.
STATUS_WAIT_STANDSTILL = "waiting_for_standstill"
STATUS_ALIGNING = "aligning"
STATUS_WAIT_HEADING = "waiting_for_heading"
STATUS_RUNNING = "running"


def invariant_reset(P, dz):
    """The error covariance after the estimate moved by ``dz``, for errors of the velocity and
    the position taken about the attitude's estimate (right-invariant: xi_v = dv - S(v) eps,
    xi_p = dp - S(p) eps): ``G P G^T`` with ``G = I + S(dv)`` at (v, eps) and ``S(dp)`` at
    (p, eps).

    Why: a rotation of the whole solution about the vertical (dp, dv, eps) = (S(e_z) p,
    S(e_z) v, -e_z) is what no sensor but GNSS sees. Each body-velocity update is blind to that
    direction at the estimate it is made at, and the propagation carries it along exactly, but
    the ES-EKF keeps P where the update left the estimate: the direction it was blind to moves
    with v and P does not, so update after update P learns the heading from nothing (FASTSim's
    car without GNSS, seed 3: the heading since alignment 87 % within 2 sigma, NEES 1.9, and
    4.7 deg in one pull-away). With G the blind direction follows the estimate, as the error of
    an invariant EKF does (Barrau & Bonnabel 2017): N^T P^-1 N stays what it was."""
    G = np.eye(P.shape[0])
    G[IV:IV + 3, IA:IA + 3] = skew(dz[IV:IV + 3])
    G[IP:IP + 3, IA:IA + 3] = skew(dz[IP:IP + 3])
    P = G @ P @ G.T
    return 0.5 * (P + P.T)


def scaled_speed_row(pred: np.ndarray, H: np.ndarray, scale_error: float,
                     held: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """The CAN speed's prediction ``(1 + k) v_x`` and its Jacobian, from the body speed's
    ``v_x`` and its row ``H``: the other columns scaled by ``1 + k``, the scale error's ``v_x``
    (0 when ``held``: then k is taken as known in the filter, its variance a consider term of the
    published covariances, :class:`.lasting_speed_offset.LastingSpeedOffset`)."""
    scale = 1.0 + scale_error
    H = H * scale
    H[0, IK] = 0.0 if held else pred[0]
    return pred * scale, H


def innovation_inverse(S: np.ndarray) -> np.ndarray | None:
    """Inverse of a small innovation covariance, or None (1x1, the CAN speed's, in closed form)."""
    if S.shape[0] == 1:
        s = S[0, 0]
        return np.array([[1.0 / s]]) if s > 0.0 and math.isfinite(s) else None
    try:
        inv = np.linalg.inv(S)
    except np.linalg.LinAlgError:
        return None
    return inv if math.isfinite(float(inv.sum())) else None
